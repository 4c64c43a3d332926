//! The public ops and the choice each makes of where it runs, by the thread's kernels
//! switch ([`crate::Kernels`]) and its operands: the fused CPU node (`crate::cpu`) where
//! the switch is `fused` and the operands are f32 on the CPU; the node built from tensor
//! ops (`crate::graph`) on the device graph (a GPU, or `device` anywhere); else candle's
//! composed ops, the reference. The ops with CUDA kernels too (LayerNorm, softmax, bias
//! with activation) run their one node on either device.

pub(crate) mod attention;
pub(crate) mod block;
pub(crate) mod conv;
pub(crate) mod linear;
pub(crate) mod mix;
pub(crate) mod mlp;
pub(crate) mod pointwise;

use crate::cpu::usable_with_cuda_any;
use crate::{Kernels, enabled, kernels};
use candle_core::Tensor;

/// Whether the fused CPU nodes take `ts`: the `fused` kernels, f32 on the CPU.
fn usable(ts: &[&Tensor]) -> bool {
    kernels() == Kernels::Fused
        && ts
            .iter()
            .all(|t| t.dtype() == candle_core::DType::F32 && t.device().is_cpu() && t.rank() >= 1)
}

/// [`usable`] for the ops that have CUDA kernels too (LayerNorm, softmax, bias with
/// activation): with the one-node ops on, f32 on the CPU or, in a `cuda` build, on a CUDA
/// device.
fn usable_with_cuda(ts: &[&Tensor]) -> bool {
    enabled() && usable_with_cuda_any(ts)
}

// The products' precision across the ops.
#[cfg(test)]
mod tests {
    use crate::testing::randn;
    use crate::{
        Kernels, MlpAct, MlpLayer, Precision, attention, attention_composed, linear, linear_low,
        matmul, matmul_low, mlp_cat, on_device_pool, precision, softmax, with_fused, with_kernels,
        with_precision,
    };
    use candle_core::{Device, Tensor, Var};

    #[test]
    fn bf16_products_track_f32_and_keep_f32_gradients() {
        let rel = |a: &Tensor, b: &Tensor| -> f32 {
            let d = (a - b).unwrap().sqr().unwrap().sum_all().unwrap();
            let n = b.sqr().unwrap().sum_all().unwrap();
            let (d, n) = (d.to_scalar::<f32>().unwrap(), n.to_scalar::<f32>().unwrap());
            // Inputs of 1e17 saturate the softmax: both gradients are exactly 0 there.
            if n == 0.0 { d.sqrt() } else { (d / n).sqrt() }
        };
        for scale in [1.0f32, 1e-18, 1e17] {
            let x = randn(&[2, 9, 24], scale, 1);
            let w = Var::from_tensor(&randn(&[16, 24], 0.2, 2)).unwrap();
            let b = Var::from_tensor(&randn(&[16], 0.2, 3)).unwrap();
            let k = randn(&[2, 5, 16], 1.0, 4);
            let run = |p: Precision| {
                with_fused(false, || {
                    with_precision(p, || {
                        let h = linear(&x, w.as_tensor(), Some(b.as_tensor())).unwrap();
                        let a = attention_composed(&h, &k, &k, 2, 0.25).unwrap();
                        let g = a.sqr().unwrap().sum_all().unwrap().backward().unwrap();
                        (h, g.get(w.as_tensor()).unwrap().clone())
                    })
                })
            };
            let (h32, g32) = run(Precision::F32);
            let (h16, g16) = run(Precision::Bf16);
            assert_eq!(g16.dtype(), candle_core::DType::F32);
            assert!(rel(&h16, &h32) < 1e-2, "scale {scale}: {}", rel(&h16, &h32));
            assert!(rel(&g16, &g32) < 5e-2, "scale {scale}: {}", rel(&g16, &g32));
            let finite = g16.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(finite.iter().all(|v| v.is_finite()), "scale {scale}");
        }
        let seen = with_precision(Precision::Bf16, || on_device_pool(&Device::Cpu, precision));
        assert_eq!(seen, Precision::Bf16);
        assert_eq!(precision(), Precision::F32, "restored after the closure");
    }

    /// Every fused CPU op in bf16 against its f32 twin and f64 finite differences
    /// (`bf16_twin_check`: 1e-2 relative L2 for values, 4e-2 for gradients), at unit and
    /// extreme input scales: the linear layer with and without a bias, the MLP and the
    /// MLP of a concatenation, attention, the convolution, the batched product and the
    /// Slot Mixer's mixing block. (The transformer block's check is in its own tests.)
    #[test]
    fn fused_bf16_ops_track_their_f32_twins() {
        use crate::testing::bf16_twin_check;
        let tol = 1e-2;
        for scale in [1.0f32, 1e-18, 1e17] {
            let differs = scale == 1.0;
            let x = randn(&[2, 9, 24], scale, 1);
            let (w, b) = (randn(&[16, 24], 0.2, 2), randn(&[16], 0.2, 3));
            let args = [x.clone(), w.clone(), b.clone()];
            bf16_twin_check(
                &format!("linear at {scale:e}"),
                &args,
                |t| linear(&t[0], &t[1], Some(&t[2])),
                tol,
                differs,
            );
            bf16_twin_check(
                &format!("linear without bias at {scale:e}"),
                &args[..2],
                |t| linear(&t[0], &t[1], None),
                tol,
                differs,
            );
            let mlp_args = [
                randn(&[2, 7, 12], scale, 4),
                randn(&[20, 12], 0.3, 5),
                randn(&[20], 0.3, 6),
                randn(&[5, 20], 0.3, 7),
                randn(&[5], 0.3, 8),
            ];
            let layers = |t: &[Tensor]| -> Vec<(Tensor, Tensor)> {
                vec![(t[0].clone(), t[1].clone()), (t[2].clone(), t[3].clone())]
            };
            bf16_twin_check(
                &format!("mlp at {scale:e}"),
                &mlp_args,
                |t| {
                    let l = layers(&t[1..]);
                    let l: Vec<MlpLayer> = l.iter().map(|(w, b)| (w, Some(b))).collect();
                    crate::mlp(&t[0], &l, MlpAct::Gelu)
                },
                tol,
                differs,
            );
            let mut cat_args = vec![randn(&[2, 7, 8], scale, 9), randn(&[2, 7, 4], 1.0, 10)];
            cat_args.extend(mlp_args[1..].iter().cloned());
            bf16_twin_check(
                &format!("mlp_cat at {scale:e}"),
                &cat_args,
                |t| {
                    let l = layers(&t[2..]);
                    let l: Vec<MlpLayer> = l.iter().map(|(w, b)| (w, Some(b))).collect();
                    mlp_cat(&t[0], &t[1], &l, MlpAct::Relu)
                },
                tol,
                differs,
            );
            let qkv = [
                randn(&[2, 9, 16], scale, 11),
                randn(&[2, 5, 16], 1.0, 12),
                randn(&[2, 5, 16], 1.0, 13),
            ];
            bf16_twin_check(
                &format!("attention at {scale:e}"),
                &qkv,
                |t| attention(&t[0], &t[1], &t[2], 2, 0.25),
                tol,
                differs,
            );
            let conv = [
                randn(&[2, 6, 7, 3], scale, 14),
                randn(&[5, 3, 3, 3], 0.3, 15),
            ];
            bf16_twin_check(
                &format!("conv2d at {scale:e}"),
                &conv,
                |t| crate::conv2d_nhwc(&t[0], &t[1], 2, 1),
                tol,
                differs,
            );
            let mm = [randn(&[2, 7, 5], scale, 16), randn(&[2, 5, 6], 1.0, 17)];
            bf16_twin_check(
                &format!("matmul at {scale:e}"),
                &mm,
                |t| matmul(&t[0], &t[1]),
                tol,
                differs,
            );
            let mix = [
                randn(&[2, 9, 6], scale, 18),
                randn(&[2, 4, 5], 1.0, 19),
                randn(&[5, 6], 0.4, 20),
                randn(&[5, 5], 0.4, 21),
            ];
            bf16_twin_check(
                &format!("slot_mix at {scale:e}"),
                &mix,
                |t| match crate::slot_mix(&t[0], &t[1], &t[2], &t[3], 0.5)? {
                    Some((mixed, _)) => Ok(mixed),
                    // The composed block (the finite differences' f64 function).
                    None => {
                        let q = t[0].broadcast_matmul(&t[2].t()?)?;
                        let k = t[1].broadcast_matmul(&t[3].t()?)?;
                        let logits = (q.matmul(&k.t()?)? * 0.5)?;
                        candle_nn::ops::softmax(&logits, candle_core::D::Minus1)?.matmul(&t[1])
                    }
                },
                tol,
                differs,
            );
        }
    }

    /// On the device graph in bf16, attention with its projections stored in bf16
    /// (`linear_low`), and a mixed slot stored in bf16 (`matmul_low`) read by an MLP of a
    /// concatenation, give the bits (values and every gradient) of the same graph stored in
    /// f32, and store half the bytes; elsewhere the `_low` ops are the plain ones.
    #[test]
    fn products_stored_in_bf16_change_no_bits() {
        let x = Var::from_tensor(&randn(&[2, 5, 6], 1.0, 1)).unwrap();
        let ctx = Var::from_tensor(&randn(&[2, 3, 4], 1.0, 2)).unwrap();
        let w: Vec<Var> = [[8, 6], [8, 4], [8, 4], [6, 8], [8, 6], [4, 10], [3, 4]]
            .iter()
            .enumerate()
            .map(|(i, s)| Var::from_tensor(&randn(s, 0.4, 10 + i as u64)).unwrap())
            .collect();
        let b: Vec<Var> = [6, 4, 3]
            .iter()
            .enumerate()
            .map(|(i, &n)| Var::from_tensor(&randn(&[n], 0.2, 20 + i as u64)).unwrap())
            .collect();
        let run = |k: Kernels, p: Precision, stored_low: bool| {
            with_kernels(k, || {
                with_precision(p, || {
                    let proj = |t: &Tensor, w: &Var| match stored_low {
                        true => linear_low(t, w.as_tensor()),
                        false => linear(t, w.as_tensor(), None),
                    };
                    let (xt, ct) = (x.as_tensor(), ctx.as_tensor());
                    let (q, kk, v) = (
                        proj(xt, &w[0]).unwrap(),
                        proj(ct, &w[1]).unwrap(),
                        proj(ct, &w[2]).unwrap(),
                    );
                    let o = attention(&q, &kk, &v, 2, 0.5).unwrap();
                    let h = linear(&o, w[3].as_tensor(), Some(b[0].as_tensor())).unwrap();
                    let logits = linear(&h, w[4].as_tensor(), None).unwrap();
                    let wts = softmax(&logits.narrow(2, 0, 3).unwrap(), 2).unwrap();
                    let slots = ct.to_dtype(candle_core::DType::F32).unwrap();
                    let mixed = match stored_low {
                        true => matmul_low(&wts, &slots).unwrap(),
                        false => matmul(&wts, &slots).unwrap(),
                    };
                    let layers: Vec<MlpLayer> = vec![
                        (w[5].as_tensor(), Some(b[1].as_tensor())),
                        (w[6].as_tensor(), Some(b[2].as_tensor())),
                    ];
                    let y = mlp_cat(&mixed, &h, &layers, MlpAct::Relu).unwrap();
                    let low = [&q, &kk, &v, &o, &mixed]
                        .iter()
                        .filter(|t| t.dtype() == candle_core::DType::BF16)
                        .count();
                    let g = (&y * randn(y.dims(), 1.0, 30))
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .backward()
                        .unwrap();
                    let mut out = vec![y.flatten_all().unwrap().to_vec1::<f32>().unwrap()];
                    for v in [&x, &ctx].into_iter().chain(&w).chain(&b) {
                        out.push(
                            g.get(v.as_tensor())
                                .unwrap()
                                .flatten_all()
                                .unwrap()
                                .to_vec1()
                                .unwrap(),
                        );
                    }
                    (out, low)
                })
            })
        };
        let bits = |v: Vec<Vec<f32>>| -> Vec<Vec<u32>> {
            v.iter()
                .map(|x| x.iter().map(|f| f.to_bits()).collect())
                .collect()
        };
        for k in [Kernels::Device, Kernels::Composed, Kernels::Fused] {
            for p in [Precision::F32, Precision::Bf16] {
                if k == Kernels::Fused && p == Precision::Bf16 {
                    continue;
                }
                let (low, n_low) = run(k, p, true);
                let (plain, n_plain) = run(k, p, false);
                assert_eq!(bits(low), bits(plain), "{k} {p}");
                let stored = k == Kernels::Device && p == Precision::Bf16;
                assert_eq!((n_low, n_plain), (if stored { 5 } else { 0 }, 0), "{k} {p}");
            }
        }
    }
}
