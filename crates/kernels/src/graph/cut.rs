//! The backward pass in segments, so that each segment's activations are freed before the
//! segment before it runs its backward pass; optionally with the segments' activations
//! not kept at all but made again in the backward pass ([`recompute`]).
//!
//! Why: candle frees a graph only as a whole, when its output is dropped, so every
//! activation of the step stays until the whole backward pass has ended, when the step
//! also holds all its gradients (PyTorch frees each saved tensor once its node is done).
//! The model marks a few boundaries with [`cut`] (the encoder's CNN and transformer, the
//! slot attention, the decoder): inside [`with_cuts`], the tensor that crosses one is
//! copied into a fresh variable, and the later segments are built on that copy.
//! [`Cuts::backward`] then runs, last segment first, the backward pass of
//! `Σ upstream ⊙ ∂loss/∂copy`, whose gradient at `upstream` is `1 · ∂loss/∂copy`:
//! the gradient the uncut graph carries there, to the bit. Where the boundary is the only
//! way from `upstream` to the loss (as at each of the model's), every gradient is the
//! uncut graph's to the bit; where `upstream` also reaches the loss another way, its two
//! gradients are summed after its segment's backward pass instead of before (the same up
//! to rounding). Outside [`with_cuts`] (evaluation, tests of the model) [`cut`] returns its
//! operand itself.
//!
//! [`recompute`] marks a segment by the function that makes it (a transformer block, a
//! convolution): with recomputation on, the forward pass keeps only the segment's inputs
//! and a copy of its output, and drops its graph; the backward pass runs the function
//! again on the same inputs and takes the gradients from that graph (activation
//! checkpointing, as `torch.utils.checkpoint`). The forward pass is then paid twice
//! (1.13–1.38× the step's time on the CPU, docs/performance.md), for a peak of one
//! segment's activations instead of all of them. The ops are deterministic, so the graph
//! made again is the one the forward pass made and the gradients are those of a [`cut`]
//! at the same places, to the bit, except where a tensor read by two segments sums more
//! than two gradient parts: the sum is then taken in another order (to rounding).

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};
use std::cell::RefCell;

thread_local! {
    static CUTS: RefCell<Option<Boundaries>> = const { RefCell::new(None) };
}

/// The boundaries a forward pass inside [`with_cuts`] has crossed so far.
struct Boundaries {
    cuts: Vec<Cut>,
    /// Whether [`recompute`] drops its segment's graph (else its function runs as it is).
    recompute: bool,
}

/// A segment's forward pass, run again by the backward pass.
type Forward = Box<dyn Fn(&[Tensor]) -> Result<Tensor>>;

/// Where the backward pass finds a segment's graph.
enum Upstream {
    /// The segment's output, which holds its graph.
    Kept(Tensor),
    /// The segment's inputs (leaves: earlier boundaries' copies, parameters, data), the
    /// function that makes its output from them, and the ops and precision it ran with
    /// (it runs again with them, whatever the backward pass's caller has set).
    Recomputed {
        inputs: Vec<Tensor>,
        forward: Forward,
        ops: (crate::Kernels, crate::Precision),
    },
}

/// One boundary: the segment before it and the variable the later segments were built
/// on.
struct Cut {
    upstream: Upstream,
    copy: Var,
}

/// The boundaries a forward pass crossed, in order.
#[derive(Default)]
pub struct Cuts(Vec<Cut>);

/// A segment boundary: inside [`with_cuts`] a tracked `t` is copied into a fresh variable
/// (the same shape and values), which is returned; otherwise, and where `t` is a variable
/// already (a parameter, a recomputed segment's output), `t` itself.
pub fn cut(t: &Tensor) -> Result<Tensor> {
    if !t.track_op() || t.is_variable() {
        return Ok(t.clone());
    }
    CUTS.with(|c| match c.borrow_mut().as_mut() {
        Some(b) => {
            let copy = Var::from_tensor(&t.detach())?;
            let out = copy.as_tensor().clone();
            b.cuts.push(Cut {
                upstream: Upstream::Kept(t.clone()),
                copy,
            });
            Ok(out)
        }
        None => Ok(t.clone()),
    })
}

/// `f(inputs)` as a segment of its own. Inside [`with_cuts`] with recomputation on, the
/// tracked inputs that are not leaves get a [`cut`] first (so that the segment's graph
/// ends at leaves and is made again alone), `f` runs without boundaries of its own, its
/// output is copied into a fresh variable, which is returned, and its graph is dropped;
/// [`Cuts::backward`] runs `f` again on the same inputs. Otherwise (recomputation off,
/// or outside [`with_cuts`]) it is `f(inputs)`, the graph kept as it is.
///
/// `f` must give the same values on the same inputs each time (no randomness of its
/// own): its second graph is then its first, and the gradients are those of the cuts.
pub fn recompute(
    inputs: &[&Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor> + 'static,
) -> Result<Tensor> {
    let recompute = CUTS.with(|c| c.borrow().as_ref().map(|b| b.recompute));
    let owned = |t: &[&Tensor]| t.iter().map(|&t| t.clone()).collect::<Vec<_>>();
    match recompute {
        None | Some(false) => f(&owned(inputs)),
        Some(true) => {
            let inputs = inputs
                .iter()
                .map(|&t| match t.track_op() && !t.is_variable() {
                    true => boundary(t),
                    false => Ok(t.clone()),
                })
                .collect::<Result<Vec<_>>>()?;
            let out = without_cuts(|| f(&inputs))?;
            if !out.track_op() {
                return Ok(out); // nothing of the segment to differentiate
            }
            // The copy, then the output and with it the segment's graph go.
            let copy = Var::from_tensor(&out.detach())?;
            drop(out);
            let t = copy.as_tensor().clone();
            CUTS.with(|c| {
                if let Some(b) = c.borrow_mut().as_mut() {
                    b.cuts.push(Cut {
                        upstream: Upstream::Recomputed {
                            inputs,
                            forward: Box::new(f),
                            ops: (crate::kernels(), crate::precision()),
                        },
                        copy,
                    })
                }
            });
            Ok(t)
        }
    }
}

/// The copy of `t`'s boundary: the one made already if `t` crossed one (a tensor read by
/// two recomputed segments gets one copy, whose gradient sums both), else a new [`cut`].
fn boundary(t: &Tensor) -> Result<Tensor> {
    let made = CUTS.with(|c| {
        let c = c.borrow();
        let cuts = c.as_ref().map_or(&[][..], |b| &b.cuts[..]);
        cuts.iter().find_map(|cut| match &cut.upstream {
            Upstream::Kept(u) if u.id() == t.id() => Some(cut.copy.as_tensor().clone()),
            _ => None,
        })
    });
    match made {
        Some(copy) => Ok(copy),
        None => cut(t),
    }
}

/// `f` with no boundaries active on this thread (they are restored after).
fn without_cuts<T>(f: impl FnOnce() -> T) -> T {
    let saved = CUTS.with(|c| c.replace(None));
    let out = f();
    CUTS.with(|c| c.replace(saved));
    out
}

/// Runs `f` (a forward pass) with [`cut`] and [`recompute`] active on this thread, and
/// returns the boundaries it crossed; with `recompute`, the segments [`recompute`] marks
/// keep no activations.
pub fn with_cuts<T>(recompute: bool, f: impl FnOnce() -> T) -> (T, Cuts) {
    let before = CUTS.with(|c| {
        c.replace(Some(Boundaries {
            cuts: Vec::new(),
            recompute,
        }))
    });
    let out = f();
    let cuts = CUTS
        .with(|c| c.replace(before))
        .map_or_else(Vec::new, |b| b.cuts);
    (out, Cuts(cuts))
}

impl Cuts {
    /// The earlier segments' backward passes, last first, after the last segment's
    /// (`grads`, from the loss): each boundary's gradient taken from `grads` (the copy is
    /// then freed) and carried into its upstream segment (made again first where it was
    /// recomputed), whose gradients are added to `grads`; each segment's graph is freed
    /// before the next one's backward pass. The caller drops the last segment's graph
    /// (the loss) before calling this.
    pub fn backward(self, grads: &mut GradStore) -> Result<()> {
        self.backward_flushing(grads, |_| Ok(()))
    }

    /// [`Cuts::backward`], handing `grads` to `flush` once the last segment's gradients
    /// are in (before the first boundary's backward pass) and again after each segment's
    /// backward pass, its graph freed: a caller that takes the gradients it has finished
    /// with out of the store there (a running sum over micro-batches) holds no more than a
    /// segment's at a time beside them. `flush` must leave the boundaries' gradients (the
    /// copies' variables) in the store: the segments before them need them.
    pub fn backward_flushing(
        self,
        grads: &mut GradStore,
        mut flush: impl FnMut(&mut GradStore) -> Result<()>,
    ) -> Result<()> {
        detach_all(grads);
        flush(grads)?;
        let mut cuts = self.0;
        while let Some(Cut { upstream, copy }) = cuts.pop() {
            let Some(d) = grads.remove(copy.as_tensor()) else {
                continue; // the loss did not reach this boundary
            };
            drop(copy);
            let upstream = match upstream {
                Upstream::Kept(t) => t,
                Upstream::Recomputed {
                    inputs,
                    forward,
                    ops: (kernels, precision),
                } => crate::with_kernels(kernels, || {
                    crate::with_precision(precision, || {
                        let again = || without_cuts(|| forward(&inputs));
                        crate::ledger::in_phase(crate::ledger::Phase::Recompute, again)
                    })
                })?,
            };
            // Detached: a variable's gradient is candle's sum of its parts, which may still
            // carry their own graph (a product with a weight), and that graph is not part
            // of this segment.
            let d = d.detach();
            let segment = (upstream * &d)?.sum_all()?;
            let mut more = segment.backward()?;
            // candle's backward pass of a product also writes the gradient of its constant
            // factor (`upstream` times one): it would hold this segment's graph.
            more.remove(&d);
            detach_all(&mut more);
            drop((segment, d));
            grads.extend(more)?;
            flush(grads)?;
        }
        Ok(())
    }
}

/// Every gradient in `grads` detached: candle's backward pass leaves a variable's gradient
/// as the sum of its parts, and a part computed from a tracked operand (a weight's
/// gradient from the layer's input) holds that operand's graph, the segment's
/// activations, as long as the store holds it.
fn detach_all(grads: &mut GradStore) {
    let ids: Vec<_> = grads.get_ids().copied().collect();
    for id in ids {
        if let Some(g) = grads
            .get_id(id)
            .filter(|g| g.track_op())
            .map(Tensor::detach)
        {
            grads.insert_id(id, g);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;

    /// A chain of three segments (two boundaries, one of them used twice after it) gives
    /// the uncut graph's gradients to the bit; where a value also reaches the loss past
    /// its boundary, its two gradients are summed after (not before) the segment's
    /// backward pass: the same gradients up to rounding.
    #[test]
    fn the_cut_graph_gives_the_uncut_gradients() {
        let w1 = Var::from_tensor(&randn(&[5, 4], 0.5, 1)).unwrap();
        let w2 = Var::from_tensor(&randn(&[4, 3], 0.5, 2)).unwrap();
        let w3 = Var::from_tensor(&randn(&[3, 2], 0.5, 3)).unwrap();
        let x = randn(&[6, 5], 1.0, 4);
        let forward = |bypass: bool| -> Result<Tensor> {
            let h1 = x.matmul(w1.as_tensor())?.tanh()?;
            let a = cut(&h1)?;
            let h2 = a.matmul(w2.as_tensor())?.gelu_erf()?;
            let b = cut(&h2)?;
            let h3 = (b.matmul(w3.as_tensor())? * b.narrow(1, 0, 2)?)?;
            let loss = h3.sqr()?.sum_all()?;
            match bypass {
                true => (loss + h2.sum_all()?)?.mean_all(),
                false => loss.mean_all(),
            }
        };
        let values = |g: &GradStore, w: &Var| {
            let v = g.get(w.as_tensor()).unwrap().flatten_all().unwrap();
            v.to_vec1::<f32>().unwrap()
        };
        for bypass in [false, true] {
            let plain = forward(bypass).unwrap().backward().unwrap();
            let (loss, cuts) = with_cuts(false, || forward(bypass));
            assert_eq!(cuts.0.len(), 2);
            let mut grads = loss.unwrap().backward().unwrap();
            cuts.backward(&mut grads).unwrap();
            // Nothing beside what the uncut pass leaves (no copy's gradient, no gradient of
            // a boundary's constant factor holding a segment's graph), and no gradient
            // holding a graph.
            assert_eq!(grads.get_ids().count(), plain.get_ids().count());
            assert!(
                grads
                    .get_ids()
                    .all(|id| !grads.get_id(*id).unwrap().track_op())
            );
            for w in [&w1, &w2, &w3] {
                let (got, want) = (values(&grads, w), values(&plain, w));
                match bypass {
                    false => assert_eq!(
                        got.iter().map(|f| f.to_bits()).collect::<Vec<_>>(),
                        want.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
                    ),
                    true => {
                        for (a, b) in got.iter().zip(&want) {
                            assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{a} vs {b}");
                        }
                    }
                }
            }
        }
        assert_eq!(cut(&x).unwrap().id(), x.id());
        let tracked = x.matmul(w1.as_tensor()).unwrap();
        assert_eq!(cut(&tracked).unwrap().id(), tracked.id());
        let (_, cuts) = with_cuts(false, || cut(&x).unwrap());
        assert!(cuts.0.is_empty());
    }

    /// The flushing backward pass hands the store over once per segment, last segment
    /// first, each time with that segment's parameter gradients in it: taken out there,
    /// they are the uncut graph's to the bit, and the segments before still get their
    /// boundaries' gradients.
    #[test]
    fn each_segments_gradients_can_be_taken_as_it_ends() {
        let w = [[5, 4], [4, 3], [3, 2]]
            .iter()
            .enumerate()
            .map(|(i, s)| Var::from_tensor(&randn(s, 0.5, i as u64 + 1)).unwrap())
            .collect::<Vec<_>>();
        let x = randn(&[6, 5], 1.0, 4);
        let forward = || -> Result<Tensor> {
            let h1 = cut(&x.matmul(w[0].as_tensor())?.tanh()?)?;
            let h2 = cut(&h1.matmul(w[1].as_tensor())?.gelu_erf()?)?;
            h2.matmul(w[2].as_tensor())?.sqr()?.sum_all()
        };
        let bits = |g: &Tensor| {
            let v = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            v.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
        };
        let plain = forward().unwrap().backward().unwrap();
        let (loss, cuts) = with_cuts(false, forward);
        let mut grads = loss.unwrap().backward().unwrap();
        let mut taken = Vec::new();
        let mut calls = 0;
        cuts.backward_flushing(&mut grads, |g| {
            for (i, w) in w.iter().enumerate() {
                if let Some(t) = g.remove(w.as_tensor()) {
                    taken.push((calls, i, bits(&t)));
                }
            }
            calls += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(calls, 3);
        let order = taken.iter().map(|(c, i, _)| (*c, *i)).collect::<Vec<_>>();
        assert_eq!(order, [(0, 2), (1, 1), (2, 0)]);
        for (_, i, got) in &taken {
            assert_eq!(got, &bits(plain.get(w[*i].as_tensor()).unwrap()));
        }
    }

    /// Recomputed segments give the gradients of cuts at the same places to the bit; the
    /// forward pass runs each once more, in the backward pass, and only where the loss
    /// reaches it; a non-leaf input gets a boundary first (one for two segments that read
    /// it); inside a segment's function recomputation is off; without it, or outside
    /// [`with_cuts`], the function runs once and the graph is whole.
    #[test]
    fn recomputed_segments_give_the_cut_gradients() {
        use std::cell::Cell;
        use std::rc::Rc;
        let w1 = Var::from_tensor(&randn(&[5, 4], 0.5, 1)).unwrap();
        let w2 = Var::from_tensor(&randn(&[4, 4], 0.5, 2)).unwrap();
        let w3 = Var::from_tensor(&randn(&[4, 3], 0.5, 3)).unwrap();
        let x = randn(&[6, 5], 1.0, 4);
        let calls = Rc::new(Cell::new(0));
        let nested = Rc::new(Cell::new(0));
        // recompute: whether the two middle layers are recomputed segments (else cuts).
        let forward = |recompute: bool| -> Result<(Tensor, Tensor)> {
            let h1 = x.matmul(w1.as_tensor())?.tanh()?; // not a leaf: gets a boundary
            let layer = |w: &Var| {
                let (w, calls, nested) = (w.as_tensor().clone(), calls.clone(), nested.clone());
                move |t: &[Tensor]| {
                    calls.set(calls.get() + 1);
                    // A recomputation inside one runs as a plain function.
                    let inner = recompute_count(&nested, &t[0])?;
                    (inner.matmul(&w)?.gelu_erf()? + &t[1])?.sin()
                }
            };
            let (h2, h3) = match recompute {
                true => {
                    let h2 = super::recompute(&[&h1, &h1], layer(&w2))?;
                    let h3 = super::recompute(&[&h2, &h1], layer(&w2))?;
                    (h2, h3)
                }
                false => {
                    let c1 = cut(&h1)?;
                    let h2 = cut(&layer(&w2)(&[c1.clone(), c1.clone()])?)?;
                    let h3 = cut(&layer(&w2)(&[h2.clone(), c1])?)?;
                    (h2, h3)
                }
            };
            // A segment the loss does not reach is not made again.
            let unused = super::recompute(&[&h3, &h1], layer(&w2))?;
            let loss = (h3.matmul(w3.as_tensor())?.sqr()?.sum_all()? + h2.sum_all()?)?;
            Ok((loss, unused))
        };
        let grads = |recompute: bool| {
            calls.set(0);
            let (out, cuts) = with_cuts(recompute, || forward(recompute));
            let (loss, unused) = out.unwrap();
            let forward_calls = calls.get();
            let mut grads = loss.backward().unwrap();
            drop((loss, unused));
            cuts.backward(&mut grads).unwrap();
            let g = [&w1, &w2, &w3].map(|w| {
                let g = grads.get(w.as_tensor()).unwrap();
                let v = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                v.iter().map(|f| f.to_bits()).collect::<Vec<_>>()
            });
            (g, forward_calls, calls.get())
        };
        let (cut_grads, forward_calls, all_calls) = grads(false);
        assert_eq!((forward_calls, all_calls), (3, 3));
        let (recomputed, forward_calls, all_calls) = grads(true);
        assert_eq!((forward_calls, all_calls), (3, 5));
        assert_eq!(recomputed, cut_grads);
        assert!(nested.get() > 0);
        // Outside `with_cuts` it is the function, its graph kept.
        calls.set(0);
        let (loss, _) = forward(true).unwrap();
        assert_eq!(calls.get(), 3);
        let whole = loss.backward().unwrap();
        assert!(whole.get(w1.as_tensor()).is_some());
        assert_eq!(cut(w1.as_tensor()).unwrap().id(), w1.as_tensor().id());
    }

    /// A recomputed segment runs again with the ops and precision of its first run, where
    /// the backward pass runs outside them.
    #[test]
    fn a_segment_is_made_again_with_its_first_runs_ops() {
        use crate::{Kernels, Precision};
        use std::cell::RefCell;
        use std::rc::Rc;
        let w = Var::from_tensor(&randn(&[4, 4], 0.5, 1)).unwrap();
        let x = randn(&[3, 4], 1.0, 2);
        let seen = Rc::new(RefCell::new(Vec::new()));
        let (out, cuts) = with_cuts(true, || {
            crate::with_kernels(Kernels::Composed, || {
                crate::with_precision(Precision::Bf16, || {
                    let (w, seen) = (w.as_tensor().clone(), seen.clone());
                    recompute(&[&x], move |t| {
                        seen.borrow_mut()
                            .push((crate::kernels(), crate::precision()));
                        t[0].matmul(&w)?.tanh()
                    })
                })
            })
        });
        let loss = out.unwrap().sqr().unwrap().sum_all().unwrap();
        let mut grads = loss.backward().unwrap();
        cuts.backward(&mut grads).unwrap();
        assert!(grads.get(w.as_tensor()).is_some());
        let first = (Kernels::Composed, Precision::Bf16);
        assert_eq!(*seen.borrow(), [first, first]);
    }

    /// `t` through a [`recompute`] made inside another one's function: there, recomputation
    /// is off and the function runs as it is (counted in `runs`).
    fn recompute_count(runs: &std::rc::Rc<std::cell::Cell<usize>>, t: &Tensor) -> Result<Tensor> {
        let runs = runs.clone();
        let out = recompute(&[t], move |t| {
            runs.set(runs.get() + 1);
            t[0].affine(1.0, 0.0)
        })?;
        assert!(!out.is_variable(), "a nested segment is not a boundary");
        Ok(out)
    }
}
