//! The backward pass in segments, so that each segment's activations are freed before the
//! segment before it runs its backward pass.
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

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};
use std::cell::RefCell;

thread_local! {
    static CUTS: RefCell<Option<Vec<Cut>>> = const { RefCell::new(None) };
}

/// One boundary: the tensor before it (with its graph) and the variable the later
/// segments were built on.
struct Cut {
    upstream: Tensor,
    copy: Var,
}

/// The boundaries a forward pass crossed, in order.
#[derive(Default)]
pub struct Cuts(Vec<Cut>);

/// A segment boundary: inside [`with_cuts`] a tracked `t` is copied into a fresh variable
/// (the same shape and values), which is returned; otherwise `t` itself.
pub fn cut(t: &Tensor) -> Result<Tensor> {
    if !t.track_op() {
        return Ok(t.clone());
    }
    CUTS.with(|c| match c.borrow_mut().as_mut() {
        Some(cuts) => {
            let copy = Var::from_tensor(&t.detach())?;
            let out = copy.as_tensor().clone();
            cuts.push(Cut {
                upstream: t.clone(),
                copy,
            });
            Ok(out)
        }
        None => Ok(t.clone()),
    })
}

/// Runs `f` (a forward pass) with [`cut`] active on this thread, and returns the
/// boundaries it crossed.
pub fn with_cuts<T>(f: impl FnOnce() -> T) -> (T, Cuts) {
    let before = CUTS.with(|c| c.replace(Some(Vec::new())));
    let out = f();
    let cuts = CUTS.with(|c| c.replace(before)).unwrap_or_default();
    (out, Cuts(cuts))
}

impl Cuts {
    /// The earlier segments' backward passes, last first, after the last segment's
    /// (`grads`, from the loss): each boundary's gradient taken from `grads` (the copy is
    /// then freed) and carried into its upstream segment, whose gradients are added to
    /// `grads`; each segment's graph is freed before the next one's backward pass. The
    /// caller drops the last segment's graph (the loss) before calling this.
    pub fn backward(self, grads: &mut GradStore) -> Result<()> {
        detach_all(grads);
        let mut cuts = self.0;
        while let Some(Cut { upstream, copy }) = cuts.pop() {
            let Some(d) = grads.remove(copy.as_tensor()) else {
                continue; // the loss did not reach this boundary
            };
            drop(copy);
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
            grads.extend(more)?;
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
            let (loss, cuts) = with_cuts(|| forward(bypass));
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
        let (_, cuts) = with_cuts(|| cut(&x).unwrap());
        assert!(cuts.0.is_empty());
    }
}
