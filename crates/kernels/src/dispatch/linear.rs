//! The choice of the linear layer: the fused CPU node where it applies, on the device
//! graph a layer with a bias as the one-layer MLP node, else candle's product followed by
//! the bias with its activation ([`linear_act`], every linear layer's path on a GPU); and
//! [`linear_low`], the bias-free layer whose output stays in bf16 where the products are
//! bf16 on the device graph.

use super::pointwise::bias_act;
use super::usable;
use crate::cpu::{self, MlpAct, usable_with_cuda_any};
use crate::graph::matmul::{matmul, matmul_low, stores_low};
use crate::graph::mlp_node::mlp_node;
use crate::{Precision, device_graph, enabled, precision, profile};
use candle_core::{Result, Tensor};

/// `x: [.., in]`, `weight: [out, in]`, `bias: [out]` → `x·weightᵀ + bias: [.., out]`, one
/// 2-D product over all leading dims (candle's broadcast matmul is slower).
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let mut all = vec![x, weight];
    all.extend(bias);
    profile::op("linear", &all, |t| linear_here(&t[0], &t[1], t.get(2)))
}

fn linear_here(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let fits = weight.rank() == 2 && bias.is_none_or(|b| b.rank() == 1);
    let mut all = vec![x, weight];
    all.extend(bias);
    if fits && usable(&all) {
        return cpu::linear::linear(x, weight, bias);
    }
    // On the device graph a layer with a bias is the one-layer MLP node: the same ops (the
    // product, then the bias added in f32), without the product kept beside the output
    // for the backward pass (a bias add's needs neither).
    if let Some(b) = bias
        && fits
        && enabled()
        && usable_with_cuda_any(&all)
        && device_graph(x)
    {
        let bf16 = precision() == Precision::Bf16;
        // The activation is never applied: the one layer is the last.
        let layer = [(weight, Some(b))];
        if let Some(y) = mlp_node(x, &layer, MlpAct::Relu, bf16)? {
            return Ok(y);
        }
    }
    linear_act(x, weight, bias, None)
}

/// [`linear`] without a bias, the output stored as the bf16 product returns it where the
/// products run in bf16 on the device graph ([`crate::matmul_low`]: for an output whose
/// one reader is another product or an op that reads it in f32, such as attention's
/// projections); elsewhere [`linear`].
///
/// # Shapes
/// `x: [.., in]`, `weight: [out, in]` → `[.., out]`
pub fn linear_low(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    profile::op("linear", &[x, weight], |t| {
        let (x, w) = (&t[0], &t[1]);
        if !(w.rank() == 2 && stores_low(&[x, w])) {
            return linear_here(x, w, None);
        }
        let Some((&k, lead)) = x.dims().split_last() else {
            candle_core::bail!("linear: a scalar input")
        };
        let mut out = lead.to_vec();
        out.push(w.dim(0)?);
        matmul_low(&x.reshape(((), k))?, &w.t()?)?.reshape(out)
    })
}

/// [`linear`] followed by `act`, from candle's matrix product, with the bias and the
/// activation as one node where [`crate::bias_act`] applies (f32 on a GPU): the path of
/// every linear layer on a GPU.
pub(crate) fn linear_act(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    act: Option<MlpAct>,
) -> Result<Tensor> {
    let composed = |x: &Tensor| -> Result<Tensor> {
        let y = matmul(x, &weight.t()?)?;
        match (bias, act) {
            (Some(b), _) => bias_act(&y, b, act),
            (None, Some(a)) => a.apply(&y),
            (None, None) => Ok(y),
        }
    };
    if x.rank() == 2 {
        return composed(x);
    }
    let Some((&k, lead)) = x.dims().split_last() else {
        candle_core::bail!("linear: a scalar input")
    };
    let mut out = lead.to_vec();
    out.push(weight.dim(0)?);
    composed(&x.reshape(((), k))?)?.reshape(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::linear::{WGRAD_BLOCK_ROWS, WeightGrad};
    use crate::dispatch::mlp::mlp;
    use crate::testing::{
        assert_matches_composed, both, f32_bits, finite_difference_check, max_abs, max_diff, randn,
    };
    use crate::with_fused;
    use candle_core::{Device, Var};

    /// On the device graph a layer with a bias (the one-layer MLP node) gives the bits of
    /// the product followed by the bias node, values and the gradients of input, weight
    /// and bias, in f32 and in bf16 (with an f32 input and with a bf16-stored one).
    #[test]
    fn the_device_graph_biased_layer_gives_the_product_and_bias_bits() {
        use crate::{Kernels, with_kernels, with_precision};
        use candle_core::DType;
        for (p, dtype) in [
            (Precision::F32, DType::F32),
            (Precision::Bf16, DType::F32),
            (Precision::Bf16, DType::BF16),
        ] {
            let x =
                Var::from_tensor(&randn(&[2, 9, 11], 1.0, 41).to_dtype(dtype).unwrap()).unwrap();
            let w = Var::from_tensor(&randn(&[6, 11], 0.5, 42)).unwrap();
            let b = Var::from_tensor(&randn(&[6], 0.5, 43)).unwrap();
            let run = |node: bool| -> Vec<Vec<u32>> {
                with_kernels(Kernels::Device, || {
                    with_precision(p, || {
                        let (xt, wt, bt) = (x.as_tensor(), w.as_tensor(), b.as_tensor());
                        let y = match node {
                            true => linear(xt, wt, Some(bt)),
                            false => linear_act(xt, wt, Some(bt), None),
                        }
                        .unwrap();
                        let r = randn(y.dims(), 1.0, 44);
                        let g = (&y * &r).unwrap().sum_all().unwrap().backward().unwrap();
                        let dx = g.get(xt).unwrap();
                        assert_eq!(dx.dtype(), dtype);
                        vec![
                            f32_bits(&y),
                            f32_bits(dx),
                            f32_bits(g.get(wt).unwrap()),
                            f32_bits(g.get(bt).unwrap()),
                        ]
                    })
                })
            };
            assert_eq!(run(true), run(false), "{p} {dtype:?}");
        }
    }

    #[test]
    fn linear_matches_the_composed_version_and_finite_differences() {
        let (x, w, b) = (
            randn(&[37, 11], 1.0, 31),
            randn(&[6, 11], 1.0, 32),
            randn(&[6], 1.0, 33),
        );
        let with_bias = [x.clone(), w.clone(), b];
        assert_matches_composed(&with_bias, |t| linear(&t[0], &t[1], Some(&t[2])), 1e-5);
        assert_matches_composed(&with_bias[..2], |t| linear(&t[0], &t[1], None), 1e-5);
        let small = [
            randn(&[4, 5], 1.0, 34),
            randn(&[3, 5], 1.0, 35),
            randn(&[3], 1.0, 36),
        ];
        finite_difference_check(&small, |t| linear(&t[0], &t[1], Some(&t[2])));
        finite_difference_check(&small[..2], |t| linear(&t[0], &t[1], None));
        // Extremes: huge and constant rows give the composed op's values and finite
        // gradients where the composed op's are finite.
        let big = [
            Tensor::new(&[[1e18f32, -1e18, 3.0], [2.0, 2.0, 2.0]], &Device::Cpu).unwrap(),
            randn(&[4, 3], 1.0, 37),
            randn(&[4], 1.0, 38),
        ];
        let [(yf, gf), (yc, gc)] = both(&big, |t| linear(&t[0], &t[1], Some(&t[2])));
        let rel = |a: &Tensor, b: &Tensor| max_diff(a, b) / (1.0 + max_abs(b));
        assert!(rel(&yf, &yc) <= 1e-6, "forward differs");
        for (a, b) in gf.iter().zip(&gc) {
            assert!(rel(a, b) <= 1e-6, "gradient differs");
        }
    }

    /// The weight gradient summed over row blocks (here three, the last one short) agrees
    /// with candle's single product `gradᵀ·x` to float tolerance, both through the linear
    /// op's backward and directly, and its bits do not depend on the thread count.
    #[test]
    fn blocked_weight_gradient_matches_one_product_at_any_thread_count() {
        let rows = 2 * WGRAD_BLOCK_ROWS + 37;
        let (g, x) = (randn(&[rows, 5], 1.0, 61), randn(&[rows, 7], 1.0, 62));
        let want = g.t().unwrap().matmul(&x).unwrap();
        let blocked = |threads: usize| -> Vec<f32> {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                g.apply_op2_no_bwd(&x, &WeightGrad(crate::Precision::F32))
                    .unwrap()
            })
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
        };
        let one = blocked(1);
        assert_eq!(one, blocked(2), "bits depend on the thread count");
        assert_eq!(one, blocked(3), "bits depend on the thread count");
        let got = Tensor::from_vec(one, (5, 7), &Device::Cpu).unwrap();
        assert!(max_diff(&got, &want) <= 1e-4 * (1.0 + max_abs(&want)));
        // And as the gradient of a linear layer's weight.
        let w = Var::from_tensor(&randn(&[5, 7], 1.0, 63)).unwrap();
        let y = linear(&x, w.as_tensor(), None).unwrap();
        let grads = (y * &g).unwrap().sum_all().unwrap().backward().unwrap();
        let dw = grads.get(w.as_tensor()).unwrap();
        assert!(max_diff(dw, &want) <= 1e-4 * (1.0 + max_abs(&want)));
    }

    /// Inputs with several leading dims (or none) give the bits of the same rows as one
    /// `[rows, in]` matrix, forward and backward, fused (the ops flatten the leading dims
    /// themselves, with no reshape nodes around them) and composed; so does the MLP.
    #[test]
    fn linear_and_mlp_take_any_leading_dims() {
        let (w, b) = (randn(&[6, 11], 1.0, 52), randn(&[6], 1.0, 53));
        let (w2, b2) = (randn(&[4, 6], 1.0, 54), randn(&[4], 1.0, 55));
        let lin = |t: &[Tensor]| linear(&t[0], &t[1], Some(&t[2]));
        let lin_nb = |t: &[Tensor]| linear(&t[0], &t[1], None);
        let two = |t: &[Tensor]| {
            mlp(
                &t[0],
                &[(&t[1], Some(&t[2])), (&t[3], Some(&t[4]))],
                MlpAct::Gelu,
            )
        };
        // Each with the number of arguments it takes (each gets a gradient).
        type Case<'a> = (&'a dyn Fn(&[Tensor]) -> Result<Tensor>, usize);
        let fs: [Case; 3] = [(&lin, 3), (&lin_nb, 2), (&two, 5)];
        for shape in [vec![3, 5, 11], vec![2, 3, 4, 11], vec![11]] {
            let x = randn(&shape, 1.0, 51);
            let all = [x, w.clone(), b.clone(), w2.clone(), b2.clone()];
            for (f, n) in fs {
                let args = &all[..n];
                let nd = both(args, f);
                let as_rows = both(args, |t: &[Tensor]| {
                    let mut t = t.to_vec();
                    t[0] = t[0].reshape(((), 11))?;
                    let y = f(&t)?;
                    let mut out = shape[..shape.len() - 1].to_vec();
                    out.push(y.dim(1)?);
                    y.reshape(out)
                });
                for ((y, g), (y2, g2)) in nd.iter().zip(&as_rows) {
                    assert_eq!(y.dims(), y2.dims());
                    assert_eq!(max_diff(y, y2), 0.0, "{shape:?}: forward");
                    for (a, b) in g.iter().zip(g2) {
                        assert_eq!(a.dims(), b.dims());
                        assert_eq!(max_diff(a, b), 0.0, "{shape:?}: gradient");
                    }
                }
                // The point of taking N-D inputs: the fused graph has as many nodes as for
                // a 2-D input (no reshape nodes around the op, each of which would cost a
                // zero tensor and an add in backward).
                let nodes = |x: Tensor| {
                    with_fused(true, || {
                        let x = Var::from_tensor(&x).unwrap().as_tensor().clone();
                        let mut t = args.to_vec();
                        t[0] = x;
                        f(&t).unwrap().sorted_nodes().len()
                    })
                };
                let flat = randn(&[shape.iter().product::<usize>() / 11, 11], 1.0, 56);
                let nd_input = flat.reshape(shape.as_slice()).unwrap();
                assert_eq!(nodes(nd_input), nodes(flat), "{shape:?}: extra graph nodes");
                // And fused agrees with composed for these shapes.
                assert!(
                    max_diff(&nd[0].0, &nd[1].0) <= 1e-5,
                    "{shape:?}: fused vs composed"
                );
            }
        }
    }

    /// Backward computes no gradient for a data input (and so skips that matmul), and the
    /// weight and bias gradients are those of the composed ops.
    #[test]
    fn linear_skips_the_gradient_of_data_inputs() {
        let x = randn(&[9, 4], 1.0, 41);
        let w = Var::from_tensor(&randn(&[3, 4], 1.0, 42)).unwrap();
        let b = Var::from_tensor(&randn(&[3], 1.0, 43)).unwrap();
        let grads = |on: bool| {
            with_fused(on, || {
                let y = linear(&x, w.as_tensor(), Some(b.as_tensor())).unwrap();
                y.sqr().unwrap().sum_all().unwrap().backward().unwrap()
            })
        };
        let (fused, composed) = (grads(true), grads(false));
        assert!(fused.get(&x).is_none(), "a data input got a gradient");
        assert!(composed.get(&x).is_some(), "candle's matmul computes it");
        for v in [w.as_tensor(), b.as_tensor()] {
            let d = max_diff(fused.get(v).unwrap(), composed.get(v).unwrap());
            assert!(d <= 1e-5, "parameter gradient differs by {d}");
        }
    }
}
