use super::*;
use crate::testing::{f32_bits, finite_difference_check, max_abs, max_diff, randn};
use crate::{Kernels, Precision, with_kernels, with_precision};
use candle_core::Var;

/// Values and the three gradients of `Σ attention(q, k, v) · w` on the device graph in
/// `p`, through this node or the split-heads node.
fn run(args: &[Tensor], heads: usize, p: Precision, few: bool) -> Vec<Tensor> {
    let vars: Vec<Var> = args.iter().map(|a| Var::from_tensor(a).unwrap()).collect();
    with_kernels(Kernels::Device, || {
        with_precision(p, || {
            let (q, k, v) = (
                vars[0].as_tensor(),
                vars[1].as_tensor(),
                vars[2].as_tensor(),
            );
            let y = match few {
                true => attention(q, k, v, heads, 0.35).unwrap(),
                false => crate::graph::attention_node::attention(q, k, v, heads, 0.35).unwrap(),
            };
            let w = randn(y.dims(), 1.0, 94).to_dtype(y.dtype()).unwrap();
            let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let mut out = vec![y.to_dtype(DType::F32).unwrap()];
            for (var, a) in vars.iter().zip(args) {
                let d = g.get(var.as_tensor()).unwrap();
                assert_eq!(d.dtype(), a.dtype(), "each gradient in its operand's type");
                out.push(d.to_dtype(DType::F32).unwrap());
            }
            out
        })
    })
}

fn args(b: usize, n: usize, m: usize, width: usize, scale: f32) -> Vec<Tensor> {
    vec![
        randn(&[b, n, width], scale, 81),
        randn(&[b, m, width], scale, 82),
        randn(&[b, m, width], scale, 83),
    ]
}

/// The block-diagonal products give the split heads' values and gradients: in f32 to
/// rounding, in bf16 within the rounding of bf16 operands (the same operands, summed in
/// another order), also at extreme scales; and the f32 node matches f64 finite
/// differences.
#[test]
fn the_node_gives_the_split_heads_values_and_gradients() {
    for (b, n, m, heads, dh) in [(2, 9, 3, 4, 5), (1, 40, 6, 3, 8), (2, 5, 2, 2, 3)] {
        for scale in [1.0f32, 1e-20, 30.0] {
            let a = args(b, n, m, heads * dh, scale);
            // Saturated softmaxes (scale 30: logits in the hundreds) amplify the order of
            // a sum's terms; bf16 operands' roundings flip where their inputs differ.
            let wide = if scale > 1.0 { 100.0 } else { 1.0 };
            for (p, tol) in [(Precision::F32, 2e-6 * wide), (Precision::Bf16, 2e-2)] {
                let few = run(&a, heads, p, true);
                let split = run(&a, heads, p, false);
                for (i, (x, y)) in few.iter().zip(&split).enumerate() {
                    assert_eq!(x.dims(), y.dims());
                    let d = max_diff(x, y);
                    assert!(d.is_finite(), "{p} scale {scale:e}: output/gradient {i}");
                    assert!(
                        d <= tol * max_abs(y).max(f32::MIN_POSITIVE),
                        "{p} {b}×{n}×{m} h{heads} scale {scale:e}: output/gradient {i} off by {d:e} \
                         (largest {:e})",
                        max_abs(y)
                    );
                }
            }
        }
        let a = args(b, n, m, heads * dh, 1.0);
        finite_difference_check(&a, |t| {
            with_kernels(Kernels::Device, || {
                attention(&t[0], &t[1], &t[2], heads, 0.35)
            })
        });
    }
}

/// `q`, `k`, `v` stored in bf16 give the values and gradients of the same values stored
/// in f32, to the bit, each gradient in its operand's type.
#[test]
fn bf16_operands_give_their_f32_values_bits() {
    let a: Vec<Tensor> = args(2, 12, 3, 8, 1.0)
        .iter()
        .map(|t| t.to_dtype(DType::BF16).unwrap())
        .collect();
    let high: Vec<Tensor> = a.iter().map(|t| t.to_dtype(DType::F32).unwrap()).collect();
    let low = run(&a, 2, Precision::Bf16, true);
    let f32s = run(&high, 2, Precision::Bf16, true);
    for (i, (x, y)) in low.iter().zip(&f32s).enumerate() {
        assert_eq!(f32_bits(x), f32_bits(y), "output/gradient {i}");
    }
}

/// The ledger: one copy of a query-side tensor (`[b, n, h·dh]`), the output handed to
/// the graph, where the split heads also copy `q`, the output and their gradients into
/// and out of head-major order; every product on bf16 operands.
#[test]
fn nothing_of_the_query_side_is_copied() {
    let (b, n, m, heads, dh) = (2, 64, 3, 4, 8);
    let a = args(b, n, m, heads * dh, 1.0);
    let query_side = (b * n * heads * dh * 2) as u64; // bf16 bytes
    for few in [true, false] {
        let book = ledger::Ledger::default();
        ledger::recording(Some(book.clone()), || run(&a, heads, Precision::Bf16, few));
        let e = book.take();
        let copies: usize = e
            .movements
            .iter()
            .filter(|(mv, _)| mv.moved == ledger::Moved::Copy && mv.read >= query_side)
            .map(|(_, c)| c)
            .sum();
        match few {
            true => assert_eq!(copies, 1, "{:#?}", e.movements),
            false => assert!(copies >= 5, "the split heads copy {copies} times"),
        }
        assert!(e.products.iter().all(|(p, _)| p.precision() == "bf16"));
    }
}
