//! The choice of the Slot Mixer's mixing block (attention with one head over the slots):
//! one fused CPU node where it applies, else `None` (the caller composes the block from
//! candle's ops).

use super::usable;
use crate::graph::mix::slot_mix_node;
use crate::profile;
use candle_core::{Result, Tensor};
use std::sync::Arc;

/// The mixing block as one node: `x: [b, r, dx]` ray queries, `slots: [b, k, ds]`,
/// `w_q: [ds, dx]`, `w_k: [ds, ds]` → the mixed slots `[b, r, ds]` and the weights
/// `[b, r, k]` (softmax over the slots, without a gradient). `None` where it does not
/// apply (composed kernels, other devices or dtypes, shapes that do not fit): the caller
/// then composes the block from candle's ops (`osrt_model::decoder::slot_mixer`).
pub fn slot_mix(
    x: &Tensor,
    slots: &Tensor,
    w_q: &Tensor,
    w_k: &Tensor,
    scale: f64,
) -> Result<Option<(Tensor, Tensor)>> {
    let here = || crate::ledger::within("slot_mix", || slot_mix_here(x, slots, w_q, w_k, scale));
    let Some(rec) = profile::current() else {
        return here();
    };
    let y = profile::nested(here)?;
    if y.is_some() {
        let rerun = move |t: &[Tensor]| -> Result<Vec<Tensor>> {
            match slot_mix_here(&t[0], &t[1], &t[2], &t[3], scale)? {
                Some((mixed, weights)) => Ok(vec![mixed, weights]),
                None => candle_core::bail!("profile: the recorded slot mix no longer fits"),
            }
        };
        profile::record(&rec, "slot_mix", &[x, slots, w_q, w_k], Arc::new(rerun));
    }
    Ok(y)
}

fn slot_mix_here(
    x: &Tensor,
    slots: &Tensor,
    w_q: &Tensor,
    w_k: &Tensor,
    scale: f64,
) -> Result<Option<(Tensor, Tensor)>> {
    if !usable(&[x, slots, w_q, w_k]) {
        return Ok(None);
    }
    slot_mix_node(x, slots, w_q, w_k, scale)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{
        assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
    };
    use crate::with_fused;
    use candle_core::Var;

    /// `[x, slots, W_q, W_k]`: `b` elements, `r` rays of width `dx`, `k` slots of `ds`.
    fn args((b, r, k): (usize, usize, usize), scale: f32, seed: u64) -> Vec<Tensor> {
        let (dx, ds) = (6, 5);
        vec![
            randn(&[b, r, dx], scale, seed),
            randn(&[b, k, ds], 1.0, seed + 1),
            randn(&[ds, dx], 0.5, seed + 2),
            randn(&[ds, ds], 0.5, seed + 3),
        ]
    }

    /// The block from candle's ops (the decoder's composed path): the reference.
    fn composed(t: &[Tensor], scale: f64) -> Result<(Tensor, Tensor)> {
        let q = crate::linear(&t[0], &t[2], None)?; // [b, r, ds]
        let k = crate::linear(&t[1], &t[3], None)?; // [b, k, ds]
        let logits = (crate::matmul(&q, &k.t()?)? * scale)?; // [b, r, k]
        let weights = crate::softmax(&logits, candle_core::D::Minus1)?;
        Ok((crate::matmul(&weights, &t[1])?, weights))
    }

    /// The one node where it applies, else the composed block (as the decoder calls it).
    fn mix(t: &[Tensor]) -> Result<(Tensor, Tensor)> {
        match slot_mix(&t[0], &t[1], &t[2], &t[3], 0.4)? {
            Some(out) => Ok(out),
            None => composed(t, 0.4),
        }
    }

    fn mixed(t: &[Tensor]) -> Result<Tensor> {
        Ok(mix(t)?.0)
    }

    /// The one-node mix against the composed block (projections, batched `q kᵀ`, softmax,
    /// `w S`) and f64 finite differences, for every input; its weights are the composed
    /// weights and carry no gradient.
    #[test]
    fn slot_mix_matches_the_composed_version_and_finite_differences() {
        let a = args((3, 40, 4), 1.0, 1);
        assert_matches_composed(&a, mixed, 1e-5);
        finite_difference_check(&args((2, 3, 3), 1.0, 2), mixed);
        let [wf, wc] = [true, false].map(|on| with_fused(on, || mix(&a).unwrap().1));
        assert_eq!(wf.dims(), [3, 40, 4]);
        assert!(max_diff(&wf, &wc) <= 1e-6);
        let sums = wf.sum(candle_core::D::Minus1).unwrap();
        assert!(max_diff(&sums, &sums.ones_like().unwrap()) <= 1e-5);
        assert!(!wf.track_op(), "the fused weights carry no gradient");
    }

    /// Queries and slots that start inside a larger buffer (contiguous views with an
    /// offset) give the bits of fresh copies, forward and backward.
    #[test]
    fn inputs_with_a_storage_offset_give_the_bits_of_copies() {
        let a = args((2, 6, 3), 1.0, 5);
        let shifted = |t: &Tensor| {
            Tensor::cat(&[&t.narrow(0, 0, 1).unwrap(), t], 0)
                .unwrap()
                .narrow(0, 1, t.dim(0).unwrap())
                .unwrap()
        };
        let offset = vec![shifted(&a[0]), shifted(&a[1]), a[2].clone(), a[3].clone()];
        assert!(offset[1].storage_and_layout().1.start_offset() > 0);
        let run = |t: &[Tensor]| {
            let w = [
                Var::from_tensor(&t[2]).unwrap(),
                Var::from_tensor(&t[3]).unwrap(),
            ];
            let (y, weights) = with_fused(true, || {
                slot_mix(&t[0], &t[1], w[0].as_tensor(), w[1].as_tensor(), 0.4)
            })
            .unwrap()
            .expect("the one-node mix applies");
            let g = y.sum_all().unwrap().backward().unwrap();
            let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let dw: Vec<_> = w
                .iter()
                .map(|v| flat(g.get(v.as_tensor()).unwrap()))
                .collect();
            (flat(&y), flat(&weights), dw)
        };
        assert_eq!(run(&offset), run(&a));
    }

    /// Saturated logits (one slot takes all the weight) stay finite and agree with the
    /// composed version.
    #[test]
    fn slot_mix_is_finite_on_extreme_inputs() {
        let a = args((2, 9, 3), 1e6, 3);
        let [(y, g), (yc, _)] = both(&a, mixed);
        assert!(max_diff(&y, &yc) <= 1e-5 * (1.0 + max_abs(&yc)));
        for t in std::iter::once(&y).chain(&g) {
            assert!(max_abs(t).is_finite());
        }
    }

    /// Shapes that do not fit are left to the composed ops (which report the error), as
    /// is everything when the kernels are switched off.
    #[test]
    fn shapes_that_do_not_fit_and_composed_kernels_are_left_to_the_caller() {
        let a = args((1, 4, 2), 1.0, 4);
        let bad = [a[0].clone(), a[1].clone(), a[3].clone(), a[3].clone()];
        let left = with_fused(true, || slot_mix(&bad[0], &bad[1], &bad[2], &bad[3], 0.4));
        assert!(left.unwrap().is_none());
        assert!(with_fused(true, || mix(&bad)).is_err());
        let off = with_fused(false, || slot_mix(&a[0], &a[1], &a[2], &a[3], 0.4));
        assert!(off.unwrap().is_none());
        assert!(
            with_fused(true, || slot_mix(&a[0], &a[1], &a[2], &a[3], 0.4))
                .unwrap()
                .is_some()
        );
    }
}
