//! Whether a device's one-node ops compute what the CPU's do: each op with a CUDA kernel
//! (`crate::cuda`) or a node of its own there (attention, convolution, MLP), on the same
//! seeded inputs (ordinary and extreme) on the CPU and on the device, values and input
//! gradients of `Σ op(args) ⊙ w` compared. `osrt check-device` reports it beside the whole
//! train step; on the CPU it compares the CPU with itself.

use crate::MlpAct;
use candle_core::{Device, Result, Tensor, Var};
use rand::{Rng, SeedableRng};
use serde::Serialize;

/// Largest relative difference accepted: f32 with other summation orders and other
/// `exp`/`erf` implementations, nothing more.
pub const OP_TOLERANCE: f64 = 1e-4;

#[derive(Debug, Clone, Serialize)]
pub struct OpCheck {
    pub op: String,
    /// `max |y_dev − y_cpu| / max(max |y_cpu|, 1e-30)` over finite values.
    pub value_rel_max: f64,
    /// The same over every input's gradient (the worst input).
    pub gradient_rel_max: f64,
    /// Whether every value and gradient on the device is finite where the CPU's is.
    pub finite: bool,
    pub pass: bool,
}

fn normal(shape: &[usize], scale: f32, seed: u64) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let v: Vec<f32> = (0..n)
        .map(|_| {
            let u1: f64 = rng.random::<f64>().max(1e-300);
            let u2: f64 = rng.random::<f64>();
            ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32 * scale
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu)
}

type Op = Box<dyn Fn(&[Tensor]) -> Result<Tensor>>;

/// The bias-with-activation variants the checks run.
const BIAS_ACTS: [(&str, Option<MlpAct>); 4] = [
    ("bias", None),
    ("bias+relu", Some(MlpAct::Relu)),
    ("bias+leaky_relu", Some(MlpAct::LeakyRelu(0.01))),
    ("bias+gelu", Some(MlpAct::Gelu)),
];

/// Value and input gradients of `Σ f(args) ⊙ w` on `device` (the fused ops on).
fn run(args: &[Tensor], w: &Tensor, f: &Op, device: &Device) -> Result<(Vec<f32>, Vec<Vec<f32>>)> {
    crate::with_fused(true, || {
        let vars = args
            .iter()
            .map(|a| Var::from_tensor(&a.to_device(device)?))
            .collect::<Result<Vec<_>>>()?;
        let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let y = f(&ts)?;
        let loss = (&y * w.to_device(device)?)?.sum_all()?;
        let grads = loss.backward()?;
        let g = vars
            .iter()
            .map(|v| match grads.get(v.as_tensor()) {
                Some(g) => g.flatten_all()?.to_vec1::<f32>(),
                None => Ok(vec![0.0; v.elem_count()]),
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((y.flatten_all()?.to_vec1::<f32>()?, g))
    })
}

/// `(max |a − b| / max |a|` over the elements finite on both sides, whether `b` is finite
/// wherever `a` is`)`.
fn compare(a: &[f32], b: &[f32]) -> (f64, bool) {
    let scale = a
        .iter()
        .filter(|x| x.is_finite())
        .fold(0f32, |m, x| m.max(x.abs()))
        .max(1e-30) as f64;
    let mut worst = 0f64;
    let mut finite = a.len() == b.len();
    for (&x, &y) in a.iter().zip(b) {
        if x.is_finite() && !y.is_finite() {
            finite = false;
        }
        if x.is_finite() && y.is_finite() {
            worst = worst.max((x as f64 - y as f64).abs() / scale);
        }
    }
    (worst, finite)
}

/// Every op with a device kernel, each on ordinary and on extreme inputs.
fn cases() -> Result<Vec<(String, Vec<Tensor>, Op)>> {
    let mut out: Vec<(String, Vec<Tensor>, Op)> = Vec::new();
    let extreme = |rows: usize, d: usize| -> Result<Tensor> {
        // Large magnitudes, a constant row, tiny values, then ordinary rows.
        let mut v = vec![0f32; rows * d];
        for (i, x) in v.iter_mut().enumerate() {
            let (r, c) = (i / d, i % d);
            *x = match r {
                0 => [1e6f32, -3e6, 2e6, 5e5][c % 4],
                1 => 7.0,
                2 => [1e-20f32, -1e-20, 0.0, 2e-20][c % 4],
                _ => ((i * 7919) % 23) as f32 / 3.0 - 3.5,
            };
        }
        Tensor::from_vec(v, (rows, d), &Device::Cpu)
    };
    for (name, x) in [
        ("layer_norm [300, 180]", normal(&[300, 180], 1.0, 1)?),
        ("layer_norm extreme [8, 64]", extreme(8, 64)?),
    ] {
        let d = x.dim(1)?;
        out.push((
            name.into(),
            vec![x, normal(&[d], 1.0, 2)?, normal(&[d], 1.0, 3)?],
            Box::new(|t| crate::layer_norm(&t[0], &t[1], &t[2], 1e-5)),
        ));
    }
    for (name, x) in [
        ("softmax [4, 50, 32]", normal(&[4, 50, 32], 2.0, 4)?),
        ("softmax [3, 1300]", normal(&[3, 1300], 3.0, 5)?),
        (
            "softmax extreme [3, 4]",
            Tensor::new(
                &[
                    [1e30f32, -1e30, 0.0, 5.0],
                    [7.0, 7.0, 7.0, 7.0],
                    [-1e30, -1e30, -1e30, -2e30],
                ],
                &Device::Cpu,
            )?,
        ),
    ] {
        out.push((
            name.into(),
            vec![x],
            Box::new(|t| crate::softmax(&t[0], candle_core::D::Minus1)),
        ));
    }
    for (name, (b, n, m), heads) in [
        ("attention self [2, 40, 4×32]", (2, 40, 40), 4),
        ("attention cross [3, 300, 7] 2×16", (3, 300, 7), 2),
    ] {
        let inner = if heads == 4 { 128 } else { 32 };
        out.push((
            name.into(),
            vec![
                normal(&[b, n, inner], 1.0, 9)?,
                normal(&[b, m, inner], 1.0, 10)?,
                normal(&[b, m, inner], 1.0, 11)?,
            ],
            Box::new(move |t| {
                let scale = 1.0 / ((inner / heads) as f64).sqrt();
                crate::attention(&t[0], &t[1], &t[2], heads, scale)
            }),
        ));
    }
    node_cases(&mut out)?;
    own_buffer_cases(&mut out)?;
    for (name, act) in BIAS_ACTS {
        out.push((
            format!("{name} [500, 96]"),
            vec![normal(&[500, 96], 2.0, 6)?, normal(&[96], 1.0, 7)?],
            Box::new(move |t| crate::bias_act(&t[0], &t[1], act)),
        ));
        out.push((
            format!("{name} extreme [8, 64]"),
            vec![(extreme(8, 64)? * 1e3)?, normal(&[64], 1.0, 8)?],
            Box::new(move |t| crate::bias_act(&t[0], &t[1], act)),
        ));
    }
    Ok(out)
}

/// The ops the nodes run outside the graph on buffers of their own (the attention node's
/// scaled softmax backward over the weights' gradient, the MLP node's bias and activation
/// in place and from bf16 to bf16): values only.
fn own_buffer_cases(out: &mut Vec<(String, Vec<Tensor>, Op)>) -> Result<()> {
    out.push((
        "softmax backward scaled in place [64, 40]".into(),
        vec![normal(&[64, 40], 3.0, 22)?, normal(&[64, 40], 1.0, 23)?],
        Box::new(|t| {
            let y = crate::cpu::softmax::softmax_no_grad(&t[0].detach())?;
            crate::cpu::softmax::softmax_grad_scaled(&y, t[1].detach().copy()?, 0.125)
        }),
    ));
    for (name, act) in BIAS_ACTS {
        // Written over a copy of x (the bf16 MLP node's way): values only.
        out.push((
            format!("{name} in place [500, 96]"),
            vec![normal(&[500, 96], 2.0, 6)?, normal(&[96], 1.0, 7)?],
            Box::new(move |t| {
                let h = t[0].detach().copy()?;
                crate::cpu::bias_act::bias_act_in_place(&h, &t[1].detach(), act)?;
                Ok(h)
            }),
        ));
        // From a bf16 product to the bf16 input of the next (the bf16 MLP node's way):
        // values only, compared in f32.
        out.push((
            format!("{name} bf16 to bf16 [500, 96]"),
            vec![normal(&[500, 96], 2.0, 6)?, normal(&[96], 1.0, 7)?],
            Box::new(move |t| {
                let z = t[0].detach().to_dtype(candle_core::DType::BF16)?;
                crate::cpu::bias_act::bias_act_low(&z, &t[1].detach(), act)?
                    .to_dtype(candle_core::DType::F32)
            }),
        ));
        if let Some(a) = act {
            out.push((
                format!("{name} backward in place [500, 96]"),
                vec![
                    normal(&[500, 96], 2.0, 6)?,
                    normal(&[96], 1.0, 7)?,
                    normal(&[500, 96], 1.0, 21)?,
                ],
                Box::new(move |t| {
                    let h = t[0].detach().copy()?;
                    crate::cpu::bias_act::bias_act_bwd_in_place(
                        &h,
                        &t[1].detach(),
                        &t[2].detach(),
                        a,
                    )?;
                    Ok(h)
                }),
            ));
            // From a bf16 product and a bf16 gradient (the bf16 MLP node's hidden layers).
            out.push((
                format!("{name} backward from bf16 [500, 96]"),
                vec![
                    normal(&[500, 96], 2.0, 6)?,
                    normal(&[96], 1.0, 7)?,
                    normal(&[500, 96], 1.0, 21)?,
                ],
                Box::new(move |t| {
                    let low = |t: &Tensor| t.detach().to_dtype(candle_core::DType::BF16);
                    crate::cpu::bias_act::bias_act_bwd_low(
                        &low(&t[0])?,
                        &t[1].detach(),
                        &low(&t[2])?,
                        a,
                    )
                }),
            ));
        }
    }
    Ok(())
}

/// The convolution (on a GPU `conv_node.rs`: osrt's unfolding and col2im kernels around
/// cuBLAS products in one node; on the CPU the fused im2col kernel), square and not, and
/// the MLP.
fn node_cases(out: &mut Vec<(String, Vec<Tensor>, Op)>) -> Result<()> {
    for (name, x, stride) in [
        (
            "conv2d [4, 12, 12, 8] 3×3",
            normal(&[4, 12, 12, 8], 1.0, 12)?,
            1,
        ),
        (
            "conv2d [3, 16, 16, 6] 3×3 stride 2",
            normal(&[3, 16, 16, 6], 1.0, 13)?,
            2,
        ),
        (
            "conv2d [2, 9, 6, 5] 3×3 stride 2",
            normal(&[2, 9, 6, 5], 1.0, 20)?,
            2,
        ),
    ] {
        let c = x.dim(3)?;
        out.push((
            name.into(),
            vec![x, normal(&[10, c, 3, 3], 0.3, 14)?],
            Box::new(move |t| crate::conv2d_nhwc(&t[0], &t[1], stride, 1)),
        ));
    }
    // The MLP: on a GPU `mlp_node.rs`, on the CPU the fused MLP.
    for (name, act) in [
        ("mlp gelu [2, 50, 24]", MlpAct::Gelu),
        ("mlp leaky_relu [2, 50, 24]", MlpAct::LeakyRelu(0.01)),
    ] {
        out.push((
            name.into(),
            vec![
                normal(&[2, 50, 24], 1.0, 15)?,
                normal(&[40, 24], 0.3, 16)?,
                normal(&[40], 0.1, 17)?,
                normal(&[7, 40], 0.3, 18)?,
                normal(&[7], 0.1, 19)?,
            ],
            Box::new(move |t| {
                crate::mlp(&t[0], &[(&t[1], Some(&t[2])), (&t[3], Some(&t[4]))], act)
            }),
        ));
    }
    Ok(())
}

/// Each op on the CPU and on `device`, compared.
pub fn compare_ops_with_cpu(device: &Device) -> Result<Vec<OpCheck>> {
    let mut out = Vec::new();
    for (i, (op, args, f)) in cases()?.into_iter().enumerate() {
        let y = crate::with_fused(true, || f(&args))?;
        let w = normal(y.dims(), 1.0, 100 + i as u64)?;
        let (y_cpu, g_cpu) = run(&args, &w, &f, &Device::Cpu)?;
        let (y_dev, g_dev) = run(&args, &w, &f, device)?;
        let (value_rel_max, mut finite) = compare(&y_cpu, &y_dev);
        let mut gradient_rel_max = 0f64;
        for (a, b) in g_cpu.iter().zip(&g_dev) {
            let (e, fin) = compare(a, b);
            gradient_rel_max = gradient_rel_max.max(e);
            finite &= fin;
        }
        out.push(OpCheck {
            op,
            value_rel_max,
            gradient_rel_max,
            finite,
            pass: finite && value_rel_max <= OP_TOLERANCE && gradient_rel_max <= OP_TOLERANCE,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cpu_agrees_with_itself_and_a_wrong_value_is_caught() {
        let checks = compare_ops_with_cpu(&Device::Cpu).unwrap();
        assert!(checks.len() >= 15);
        for c in &checks {
            assert!(c.pass && c.value_rel_max == 0.0, "{c:?}");
        }
        let (e, finite) = compare(&[1.0, 2.0, f32::INFINITY], &[1.0, 2.1, 0.0]);
        assert!((e - 0.05).abs() < 1e-6 && finite);
        let (_, finite) = compare(&[1.0, 2.0], &[1.0, f32::NAN]);
        assert!(!finite);
    }
}
