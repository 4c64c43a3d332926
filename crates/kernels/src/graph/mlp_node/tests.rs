//! Tests of the MLP node: against the layer-by-layer graph, the node of two inputs, parts
//! stored in bf16, what it keeps, finite differences and a second backward pass.

use super::*;
use crate::dispatch::linear::linear_act;
use crate::testing::{assert_second_backward_agrees, finite_difference_check, randn};
use crate::{Kernels, Precision, with_kernels, with_precision};
use candle_core::Var;

/// The layers one by one as a GPU ran them before this node: `linear_act` each.
fn layer_by_layer(x: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let mut h = x.clone();
    for (i, (w, b)) in layers.iter().enumerate() {
        let hidden = i + 1 < layers.len();
        h = linear_act(&h, w, *b, hidden.then_some(act))?;
    }
    Ok(h)
}

/// Weights `[out, in]` and biases of layers of widths `dims`, as variables, seeded
/// from `seed` (weights) and `seed + 10` (biases).
fn biased_layers(dims: &[usize], seed: u64) -> Vec<(Var, Var)> {
    dims.windows(2)
        .enumerate()
        .map(|(i, d)| {
            let w = randn(&[d[1], d[0]], 0.4, seed + i as u64);
            let b = randn(&[d[1]], 0.2, seed + 10 + i as u64);
            (Var::from_tensor(&w).unwrap(), Var::from_tensor(&b).unwrap())
        })
        .collect()
}

fn layers_of(params: &[(Var, Var)]) -> Vec<MlpLayer<'_>> {
    params
        .iter()
        .map(|(w, b)| (w.as_tensor(), Some(b.as_tensor())))
        .collect()
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

/// Value and gradients (input, then each weight and bias) of `Σ mlp(x) ⊙ w`, on the
/// device graph (the layer-by-layer products are then candle's, as the node's).
fn run(
    node: bool,
    p: Precision,
    act: MlpAct,
    x: &Var,
    params: &[(Var, Var)],
) -> (Vec<f32>, Vec<Vec<f32>>) {
    with_kernels(Kernels::Device, || {
        with_precision(p, || {
            let layers: Vec<MlpLayer> = params
                .iter()
                .map(|(w, b)| (w.as_tensor(), Some(b.as_tensor())))
                .collect();
            let y = match node {
                true => mlp_node(x.as_tensor(), &layers, act, p == Precision::Bf16)
                    .unwrap()
                    .unwrap(),
                false => layer_by_layer(x.as_tensor(), &layers, act).unwrap(),
            };
            let w = randn(y.dims(), 1.0, 77);
            let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let mut grads = vec![values(g.get(x.as_tensor()).unwrap())];
            for (w, b) in params {
                grads.push(values(g.get(w.as_tensor()).unwrap()));
                grads.push(values(g.get(b.as_tensor()).unwrap()));
            }
            (values(&y), grads)
        })
    })
}

/// The node computes what the layer-by-layer graph computes, in f32 and in bf16
/// (bf16 products on the CPU's gemm), for each activation and for ordinary and
/// extreme inputs: the same values and gradients (zeros may differ in sign, as
/// candle's accumulation adds +0), all finite.
#[test]
fn the_node_computes_the_layer_by_layer_graph() {
    for p in [Precision::F32, Precision::Bf16] {
        for act in [MlpAct::Relu, MlpAct::LeakyRelu(0.01), MlpAct::Gelu] {
            for scale in [1.0f32, 1e-20, 1e12] {
                let x = Var::from_tensor(&randn(&[2, 7, 12], scale, 1)).unwrap();
                let dims = [12, 20, 16, 5];
                let params: Vec<(Var, Var)> = dims
                    .windows(2)
                    .enumerate()
                    .map(|(i, d)| {
                        let w = randn(&[d[1], d[0]], 0.4, 10 + i as u64);
                        let b = randn(&[d[1]], 0.2, 20 + i as u64);
                        (Var::from_tensor(&w).unwrap(), Var::from_tensor(&b).unwrap())
                    })
                    .collect();
                let (y1, g1) = run(true, p, act, &x, &params);
                let (y0, g0) = run(false, p, act, &x, &params);
                let case = format!("{p} {act:?} scale {scale:e}");
                assert_eq!(y1, y0, "values, {case}");
                for (k, (a, b)) in g1.iter().zip(&g0).enumerate() {
                    assert_eq!(a, b, "gradient {k}, {case}");
                    assert!(a.iter().all(|v| v.is_finite()), "gradient {k}, {case}");
                }
            }
        }
    }
}

/// The node over two inputs side by side gives the values and gradients of the node
/// over their concatenation (`Tensor::cat`) bit for bit, in f32 and bf16, where either
/// part or both carry a gradient; it matches finite differences.
#[test]
fn the_two_input_node_is_the_node_of_the_concatenation() {
    let params = biased_layers(&[12, 20, 5], 30);
    let layers = layers_of(&params);
    for (p, tracked) in [
        (Precision::F32, [true, true]),
        (Precision::Bf16, [true, true]),
        (Precision::F32, [false, true]),
        (Precision::Bf16, [true, false]),
    ] {
        let a = randn(&[2, 3, 7], 1.0, 50);
        let b = randn(&[2, 3, 5], 1.0, 51);
        let (va, vb) = (Var::from_tensor(&a).unwrap(), Var::from_tensor(&b).unwrap());
        let ta = if tracked[0] {
            va.as_tensor().clone()
        } else {
            a.clone()
        };
        let tb = if tracked[1] {
            vb.as_tensor().clone()
        } else {
            b.clone()
        };
        let bf16 = p == Precision::Bf16;
        let [(y1, g1), (y0, g0)] = [true, false].map(|two| {
            let y = match two {
                true => mlp_cat_node(&ta, &tb, &layers, MlpAct::Gelu, bf16),
                false => mlp_node(
                    &Tensor::cat(&[&ta, &tb], 2).unwrap(),
                    &layers,
                    MlpAct::Gelu,
                    bf16,
                ),
            };
            let y = y.unwrap().unwrap();
            let w = randn(y.dims(), 1.0, 52);
            let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let mut grads: Vec<Option<Vec<f32>>> = [&va, &vb]
                .iter()
                .map(|v| g.get(v.as_tensor()).map(values))
                .collect();
            for (w, b) in &params {
                grads.push(Some(values(g.get(w.as_tensor()).unwrap())));
                grads.push(Some(values(g.get(b.as_tensor()).unwrap())));
            }
            (values(&y), grads)
        });
        assert_eq!(y1, y0, "{p} {tracked:?}");
        assert_eq!(g1, g0, "{p} {tracked:?}");
        assert_eq!(g1[0].is_some(), tracked[0]);
        assert_eq!(g1[1].is_some(), tracked[1]);
    }
    let args = [
        randn(&[3, 4], 1.0, 60),
        randn(&[3, 2], 1.0, 61),
        randn(&[5, 6], 0.5, 62),
        randn(&[5], 0.2, 63),
    ];
    finite_difference_check(&args, |t| {
        let layers = [(&t[2], Some(&t[3]))];
        match crate::enabled() && t[0].dtype() == DType::F32 {
            true => Ok(mlp_cat_node(&t[0], &t[1], &layers, MlpAct::Gelu, false)?.expect("fits")),
            false => {
                crate::mlp_layer_by_layer(&Tensor::cat(&[&t[0], &t[1]], 1)?, &layers, MlpAct::Gelu)
            }
        }
    });
}

/// With bf16 products, a part stored in bf16 (`crate::matmul_low`, the Slot Mixer's
/// mixed slot) is taken by the node, not left to the layer-by-layer graph of its
/// concatenation: the values and gradients are those of the node over the
/// concatenation of its f32 values, its gradient comes back in bf16.
#[test]
fn a_part_stored_in_bf16_is_taken() {
    let params = biased_layers(&[12, 20, 5], 70);
    let layers = layers_of(&params);
    let a = Var::from_tensor(&randn(&[2, 3, 7], 1.0, 90).to_dtype(DType::BF16).unwrap()).unwrap();
    let b = Var::from_tensor(&randn(&[2, 3, 5], 1.0, 91)).unwrap();
    // Not where the products are f32: the part would round the node's operand.
    assert!(
        mlp_cat_node(a.as_tensor(), b.as_tensor(), &layers, MlpAct::Gelu, false)
            .unwrap()
            .is_none()
    );
    let [(y1, g1), (y0, g0)] = [true, false].map(|two| {
        let (ta, tb) = (a.as_tensor(), b.as_tensor());
        let y = match two {
            true => mlp_cat_node(ta, tb, &layers, MlpAct::Gelu, true),
            false => {
                let cat = Tensor::cat(&[&ta.to_dtype(DType::F32).unwrap(), tb], 2).unwrap();
                mlp_node(&cat, &layers, MlpAct::Gelu, true)
            }
        };
        let y = y.unwrap().expect("the node takes a bf16 part");
        let w = randn(y.dims(), 1.0, 92);
        let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
        let da = g.get(ta).unwrap();
        assert_eq!(da.dtype(), DType::BF16);
        let mut grads = vec![values(&da.to_dtype(DType::F32).unwrap())];
        grads.push(values(g.get(tb).unwrap()));
        for (w, b) in &params {
            grads.push(values(g.get(w.as_tensor()).unwrap()));
            grads.push(values(g.get(b.as_tensor()).unwrap()));
        }
        (values(&y), grads)
    });
    assert_eq!(y1, y0);
    assert_eq!(g1, g0);
}

/// What the node keeps for the backward pass: each hidden layer's product output
/// (in the products' precision), nothing of the last layer, no layer's input.
#[test]
fn the_node_keeps_one_tensor_per_hidden_layer() {
    let x = randn(&[6, 12], 1.0, 1);
    let dims = [12, 20, 16, 5];
    let params: Vec<(Tensor, Tensor)> = dims
        .windows(2)
        .map(|d| (randn(&[d[1], d[0]], 0.4, 2), randn(&[d[1]], 0.2, 3)))
        .collect();
    for (bf16, dtype) in [(false, DType::F32), (true, DType::BF16)] {
        let plan = Plan {
            act: MlpAct::Gelu,
            bf16,
            params: params.clone(),
        };
        let saved = plan.forward(x.clone(), true).unwrap().1.unwrap();
        let shapes: Vec<_> = saved
            .iter()
            .map(|t| (t.dims().to_vec(), t.dtype()))
            .collect();
        assert_eq!(shapes, [(vec![6, 20], dtype), (vec![6, 16], dtype)]);
        assert!(plan.forward(x.clone(), false).unwrap().1.is_none());
    }
}

/// The f32 node against finite differences in f64 (where `f` takes the composed
/// layers), and a second backward pass through the same graph (the kept tensors
/// taken by the first) gives the same gradients.
#[test]
fn the_f32_node_matches_finite_differences_and_a_second_backward() {
    let args = [
        randn(&[3, 4, 6], 1.0, 1),
        randn(&[8, 6], 0.5, 2),
        randn(&[8], 0.2, 3),
        randn(&[3, 8], 0.5, 4),
        randn(&[3], 0.2, 5),
    ];
    let f = |t: &[Tensor]| -> Result<Tensor> {
        let layers = [(&t[1], Some(&t[2])), (&t[3], Some(&t[4]))];
        // The f64 evaluations of the finite differences take the composed layers.
        match crate::enabled() && t[0].dtype() == DType::F32 {
            true => Ok(mlp_node(&t[0], &layers, MlpAct::Gelu, false)?.expect("fits")),
            false => crate::mlp_layer_by_layer(&t[0], &layers, MlpAct::Gelu),
        }
    };
    finite_difference_check(&args, f);
    assert_second_backward_agrees(&args, f);
    // A layer without a bias is not the node's: the caller goes layer by layer.
    let no_bias = [(&args[1], None)];
    assert!(
        mlp_node(&args[0], &no_bias, MlpAct::Relu, false)
            .unwrap()
            .is_none()
    );
}
