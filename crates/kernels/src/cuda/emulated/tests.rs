//! Each kernel of `device_kernels.cu` under the emulator against the CPU op (bit for bit
//! where the two are meant to agree bit for bit) or an f64 reference.

use super::*;
use crate::cpu::bias_act::act_code;
use crate::cpu::conv::{self, ConvGeom};
use crate::testing::randn;
use crate::{MlpAct, with_fused};
use candle_core::{Device, Tensor, Var};

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

fn seeded(n: usize, scale: f32, seed: u64) -> Vec<f32> {
    values(&randn(&[n], scale, seed))
}

/// Largest `|a − r| / (1 + |r|)` (r the reference), and every value finite.
fn worst(a: &[f32], r: &[f64]) -> f64 {
    assert_eq!(a.len(), r.len());
    a.iter()
        .zip(r)
        .map(|(&a, &r)| {
            assert!(
                a.is_finite(),
                "non-finite value {a} where the reference is {r}"
            );
            (a as f64 - r).abs() / (1.0 + r.abs())
        })
        .fold(0.0, f64::max)
}

fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

/// LayerNorm forward and backward of rows of `d` in f64: `(y, dx, dγ, dβ)`.
fn layer_norm_reference(
    x: &[f32],
    g: &[f32],
    b: &[f32],
    dy: &[f32],
    eps: f64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let d = g.len();
    let (mut y, mut dx) = (vec![], vec![]);
    let (mut dg, mut db) = (vec![0f64; d], vec![0f64; d]);
    for (xr, dyr) in x.chunks(d).zip(dy.chunks(d)) {
        let xr = f64s(xr);
        let mean = xr.iter().sum::<f64>() / d as f64;
        let var = xr.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d as f64;
        let rstd = 1.0 / (var + eps).sqrt();
        let xhat: Vec<f64> = xr.iter().map(|v| (v - mean) * rstd).collect();
        let gy: Vec<f64> = (0..d).map(|i| dyr[i] as f64 * g[i] as f64).collect();
        let m1 = gy.iter().sum::<f64>() / d as f64;
        let m2 = gy.iter().zip(&xhat).map(|(a, b)| a * b).sum::<f64>() / d as f64;
        for i in 0..d {
            y.push(xhat[i] * g[i] as f64 + b[i] as f64);
            dx.push(rstd * (gy[i] - m1 - xhat[i] * m2));
            dg[i] += dyr[i] as f64 * xhat[i];
            db[i] += dyr[i] as f64;
        }
    }
    (y, dx, dg, db)
}

#[test]
fn layer_norm_matches_the_f64_reference() {
    let emu = Emulator::get();
    // Widths under, at and over a warp; row counts that leave a block part empty and
    // make three chunks of the parameter sums.
    for (i, (rows, d)) in [(1, 5), (13, 32), (150, 70), (9, 200)]
        .into_iter()
        .enumerate()
    {
        let s = 10 * i as u64;
        let x = seeded(rows * d, 1.5, s);
        let g = seeded(d, 1.0, s + 1);
        let b = seeded(d, 0.5, s + 2);
        let dy = seeded(rows * d, 1.0, s + 3);
        let (y, dx, dg, db) = layer_norm_reference(&x, &g, &b, &dy, 1e-5);
        let e = emu.layer_norm_fwd(&x, &g, &b, 1e-5);
        let (edx, edg, edb) = emu.layer_norm_bwd(&x, &g, &dy, 1e-5, u32::MAX);
        // Fewer block rows than chunks (past 65,535 chunks on a GPU): the same sums.
        let (_, cdg, cdb) = emu.layer_norm_bwd(&x, &g, &dy, 1e-5, 2);
        assert_eq!((bits(&cdg), bits(&cdb)), (bits(&edg), bits(&edb)));
        for (what, got, want) in [
            ("y", &e, &y),
            ("dx", &edx, &dx),
            ("dγ", &edg, &dg),
            ("dβ", &edb, &db),
        ] {
            let err = worst(got, want);
            assert!(err < 2e-5, "rows {rows} × {d}: {what} off by {err:e}");
        }
    }
}

/// Rows far from zero, constant rows and huge values: finite, and as close to the f64
/// result as the CPU op's f32 arithmetic gets.
#[test]
fn layer_norm_is_finite_and_close_on_extreme_rows() {
    let emu = Emulator::get();
    let d = 48;
    let mut x = seeded(4 * d, 1.0, 5);
    x[..d].iter_mut().for_each(|v| *v += 1e4); // offset: cancellation in the variance
    x[d..2 * d].iter_mut().for_each(|v| *v = 0.1); // constant: variance 0
    x[2 * d..3 * d].iter_mut().for_each(|v| *v *= 1e18); // huge but squares stay finite
    let g = seeded(d, 1.0, 6);
    let b = seeded(d, 1.0, 7);
    let dy = seeded(4 * d, 1.0, 8);
    let (y, dx, dg, db) = layer_norm_reference(&x, &g, &b, &dy, 1e-5);
    let cpu = {
        let t = |v: &[f32], s: &[usize]| Tensor::from_slice(v, s, &Device::Cpu).unwrap();
        let xv = Var::from_tensor(&t(&x, &[4, d])).unwrap();
        let out = crate::layer_norm(xv.as_tensor(), &t(&g, &[d]), &t(&b, &[d]), 1e-5).unwrap();
        let grads = (out.clone() * t(&dy, &[4, d]))
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        (values(&out), values(grads.get(xv.as_tensor()).unwrap()))
    };
    let e = emu.layer_norm_fwd(&x, &g, &b, 1e-5);
    let (edx, edg, edb) = emu.layer_norm_bwd(&x, &g, &dy, 1e-5, u32::MAX);
    // The CPU op's own error against f64 sets the bar (the offset row loses bits in f32).
    let bar = |cpu: &[f32], r: &[f64]| worst(cpu, r).max(1e-5) * 4.0;
    assert!(
        worst(&e, &y) <= bar(&cpu.0, &y),
        "y: {:e} against the CPU's {:e}",
        worst(&e, &y),
        worst(&cpu.0, &y)
    );
    assert!(
        worst(&edx, &dx) <= bar(&cpu.1, &dx),
        "dx: {:e} against the CPU's {:e}",
        worst(&edx, &dx),
        worst(&cpu.1, &dx)
    );
    assert!(worst(&edg, &dg) < 1e-3 && worst(&edb, &db) < 1e-5);
}

fn softmax_reference(x: &[f32], dy: &[f32], d: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut y, mut dx) = (vec![], vec![]);
    for (xr, dyr) in x.chunks(d).zip(dy.chunks(d)) {
        let m = xr.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
        let e: Vec<f64> = xr.iter().map(|&v| (v as f64 - m).exp()).collect();
        let s: f64 = e.iter().sum();
        let yr: Vec<f64> = e.iter().map(|v| v / s).collect();
        let dot: f64 = yr.iter().zip(dyr).map(|(a, &b)| a * b as f64).sum();
        dx.extend(yr.iter().zip(dyr).map(|(a, &b)| a * (b as f64 - dot)));
        y.extend(yr);
    }
    (y, dx)
}

#[test]
fn softmax_matches_the_f64_reference_on_ordinary_and_extreme_rows() {
    let emu = Emulator::get();
    for (i, (rows, d, scale)) in [(3, 1, 1.0), (17, 5, 3.0), (40, 33, 2.0), (6, 300, 1.0)]
        .into_iter()
        .enumerate()
    {
        let mut x = seeded(rows * d, scale, 40 + i as u64);
        if d > 1 {
            // One row of huge logits of both signs, one of equal ones.
            x[..d]
                .iter_mut()
                .enumerate()
                .for_each(|(j, v)| *v = if j % 2 == 0 { 1e30 } else { -3e38 });
            x[d..2 * d].iter_mut().for_each(|v| *v = 7.0);
        }
        let dy = seeded(rows * d, 1.0, 50 + i as u64);
        let (y, dx) = softmax_reference(&x, &dy, d);
        let e = emu.softmax_fwd(&x, d);
        let edx = emu.softmax_bwd(&e, &dy, d);
        let (ey, edxe) = (worst(&e, &y), worst(&edx, &dx));
        assert!(
            ey < 1e-6 && edxe < 1e-5,
            "rows {rows} × {d}: y {ey:e}, dx {edxe:e}"
        );
    }
}

/// The scaled in-place softmax backward (the attention node's) writes the bits of the
/// softmax backward kernel followed by `x · scale + 0` (candle's affine), on ordinary and
/// extreme rows, rows of one, wider than a warp and not a multiple of it.
#[test]
fn the_scaled_softmax_backward_in_place_gives_the_two_ops_bits() {
    let emu = Emulator::get();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for (i, (rows, d)) in [(3, 1), (17, 5), (40, 33), (6, 300)]
        .into_iter()
        .enumerate()
    {
        let mut x = seeded(rows * d, 2.0, 80 + i as u64);
        if d > 1 {
            x[..d]
                .iter_mut()
                .enumerate()
                .for_each(|(j, v)| *v = if j % 2 == 0 { 1e30 } else { -3e38 });
        }
        let y = emu.softmax_fwd(&x, d);
        let dy = seeded(rows * d, 1.0, 90 + i as u64);
        for scale in [0.125f32, 0.088_388_35] {
            let want: Vec<f32> = emu
                .softmax_bwd(&y, &dy, d)
                .iter()
                .map(|g| g * scale + 0.0)
                .collect();
            let mut got = dy.clone();
            emu.softmax_bwd_scaled_in_place(&y, &mut got, d, scale);
            assert_eq!(bits(&got), bits(&want), "rows {rows} × {d}, scale {scale}");
        }
    }
}

const ACTS: [Option<MlpAct>; 4] = [
    None,
    Some(MlpAct::Relu),
    Some(MlpAct::LeakyRelu(0.01)),
    Some(MlpAct::Gelu),
];

/// `act(x + b)` and its input gradient against the CPU op, with large and tiny values
/// mixed in, over the launch `cuda::elementwise` uses and over one too small for the elements (the
/// kernels' grid-stride loops then take several turns).
#[test]
fn bias_act_matches_the_cpu_op() {
    let emu = Emulator::get();
    let (rows, d) = (37, 19);
    let mut x = seeded(rows * d, 2.0, 60);
    for (j, v) in [1e30f32, -1e30, 1e-30, -1e-30, 0.0, -0.0, 3e37]
        .into_iter()
        .enumerate()
    {
        x[j * 11] = v;
    }
    let b = seeded(d, 0.5, 61);
    // x + b exactly 0: where the (leaky) ReLU's derivative switches.
    for r in [3, 20] {
        x[r * d + 4] = -b[4];
    }
    let dy = seeded(rows * d, 1.0, 62);
    let t = |v: &[f32], s: &[usize]| Tensor::from_slice(v, s, &Device::Cpu).unwrap();
    for act in ACTS {
        let (cpu_y, cpu_dx) = with_fused(true, || {
            let xv = Var::from_tensor(&t(&x, &[rows, d])).unwrap();
            let y = crate::bias_act(xv.as_tensor(), &t(&b, &[d]), act).unwrap();
            let grads = (y.clone() * t(&dy, &[rows, d]))
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            (values(&y), values(grads.get(xv.as_tensor()).unwrap()))
        });
        let code = act_code(act);
        let small = Launch {
            grid: (3, 1, 1),
            block: (64, 1, 1),
        };
        for l in [geometry::elementwise(x.len()), small] {
            let y = emu.bias_act_fwd(&x, &b, code, l);
            assert!(
                worst(&y, &f64s(&cpu_y)) < 1e-6,
                "{act:?} over {l:?}: {:e}",
                worst(&y, &f64s(&cpu_y))
            );
        }
        let dz = emu.bias_act_bwd(&x, &b, &dy, code);
        assert!(
            worst(&dz, &f64s(&cpu_dx)) < 1e-6,
            "{act:?} gradient: {:e}",
            worst(&dz, &f64s(&cpu_dx))
        );
    }
}

/// The bf16-to-bf16 kernel (`osrt_bias_act_low`) writes the CPU op's bits (the `half`
/// crate's rounding, ties to even), over both launches.
#[test]
fn bias_act_low_matches_the_cpu_op() {
    use candle_core::DType;
    let emu = Emulator::get();
    let (rows, d) = (41, 23);
    let mut x = seeded(rows * d, 2.0, 73);
    for (j, v) in [
        3.3e38f32,
        -3.3e38,
        1e-30,
        -1e-30,
        0.0,
        -0.0,
        1.0 + 1.0 / 256.0,
    ]
    .into_iter()
    .enumerate()
    {
        x[j * 13] = v;
    }
    let b = seeded(d, 0.5, 74);
    let z = Tensor::from_slice(&x, (rows, d), &Device::Cpu)
        .unwrap()
        .to_dtype(DType::BF16)
        .unwrap();
    let zbits: Vec<u16> = z
        .flatten_all()
        .unwrap()
        .to_vec1::<half::bf16>()
        .unwrap()
        .iter()
        .map(|v| v.to_bits())
        .collect();
    let bt = Tensor::from_slice(&b, d, &Device::Cpu).unwrap();
    let small = Launch {
        grid: (3, 1, 1),
        block: (64, 1, 1),
    };
    for act in ACTS {
        let cpu: Vec<u16> = crate::cpu::bias_act::bias_act_low(&z, &bt, act)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<half::bf16>()
            .unwrap()
            .iter()
            .map(|v| v.to_bits())
            .collect();
        for l in [geometry::elementwise(zbits.len()), small] {
            let y = emu.bias_act_low(&zbits, &b, act_code(act), l);
            assert_eq!(y, cpu, "{act:?} over {l:?}");
        }
    }
}

/// The in-place kernels (`osrt_bias_act_*_inplace`, over the bf16 MLP node's own f32
/// copies) write the out-of-place kernels' bits, over both launches.
#[test]
fn bias_act_in_place_gives_the_out_of_place_bits() {
    let emu = Emulator::get();
    let (rows, d) = (41, 23);
    let mut x = seeded(rows * d, 2.0, 70);
    for (j, v) in [1e30f32, -1e30, 1e-30, -1e-30, 0.0, -0.0, 3e37]
        .into_iter()
        .enumerate()
    {
        x[j * 13] = v;
    }
    let b = seeded(d, 0.5, 71);
    x[5 * d + 2] = -b[2];
    let dy = seeded(rows * d, 1.0, 72);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let small = Launch {
        grid: (3, 1, 1),
        block: (64, 1, 1),
    };
    for act in ACTS {
        let code = act_code(act);
        for l in [geometry::elementwise(x.len()), small] {
            let y = emu.bias_act_fwd(&x, &b, code, l);
            let mut h = x.clone();
            emu.bias_act_fwd_in_place(&mut h, &b, code, l);
            assert_eq!(bits(&h), bits(&y), "{act:?} over {l:?}");
            if let Some(a) = act {
                let dz = emu.bias_act_bwd(&x, &b, &dy, act_code(Some(a)));
                let mut g = x.clone();
                emu.bias_act_bwd_in_place(&mut g, &b, &dy, act_code(Some(a)), l);
                assert_eq!(bits(&g), bits(&dz), "{a:?} gradient over {l:?}");
            }
        }
    }
}

/// The backward kernel from bf16 (`osrt_bias_act_bwd_low`) writes the f32 kernel's bits on
/// the widened operands, over both launches, with sums that overflow and exact zeros of
/// `z + b`.
#[test]
fn bias_act_bwd_low_gives_the_widened_kernel_bits() {
    let emu = Emulator::get();
    let (rows, d) = (41, 23);
    let mut x = seeded(rows * d, 2.0, 75);
    let mut g = seeded(rows * d, 1.0, 76);
    for (j, v) in [
        3.3e38f32,
        -3.3e38,
        1e-30,
        -1e-30,
        0.0,
        -0.0,
        1.0 + 1.0 / 128.0,
    ]
    .into_iter()
    .enumerate()
    {
        x[j * 13] = v;
        g[j * 13 + 5] = v;
    }
    let b = seeded(d, 0.5, 77);
    let low = |v: &[f32]| -> Vec<u16> {
        v.iter()
            .map(|&x| half::bf16::from_f32(x).to_bits())
            .collect()
    };
    let (zbits, dybits) = (low(&x), low(&g));
    // An exact zero of z + b in row 5, column 2.
    let mut b2 = b;
    b2[2] = -half::bf16::from_bits(zbits[5 * d + 2]).to_f32();
    let wide = |v: &[u16]| -> Vec<f32> {
        v.iter()
            .map(|&u| half::bf16::from_bits(u).to_f32())
            .collect()
    };
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let small = Launch {
        grid: (3, 1, 1),
        block: (64, 1, 1),
    };
    for a in [MlpAct::Relu, MlpAct::LeakyRelu(0.01), MlpAct::Gelu] {
        let code = act_code(Some(a));
        let want = emu.bias_act_bwd(&wide(&zbits), &b2, &wide(&dybits), code);
        for l in [geometry::elementwise(zbits.len()), small] {
            let got = emu.bias_act_bwd_low(&zbits, &b2, &dybits, code, l);
            assert_eq!(bits(&got), bits(&want), "{a:?} over {l:?}");
        }
    }
}

#[test]
fn column_sums_match_the_f64_reference() {
    let emu = Emulator::get();
    for (rows, d) in [(1, 1), (64, 3), (150, 130), (200, 7)] {
        let a = seeded(rows * d, 1.0, (rows * d) as u64);
        let want: Vec<f64> = (0..d)
            .map(|c| (0..rows).map(|r| a[r * d + c] as f64).sum())
            .collect();
        let got = emu.column_sum(&a, d, u32::MAX);
        let capped = emu.column_sum(&a, d, 2);
        assert_eq!(bits(&capped), bits(&got), "{rows} × {d}, 2 block rows");
        assert!(
            worst(&got, &want) < 1e-5,
            "{rows} × {d}: {:e}",
            worst(&got, &want)
        );
    }
}

/// A convolution's geometry: `(n, (h, w, c), k, stride, pad)`.
type Geometry = (usize, (usize, usize, usize), usize, usize, usize);

/// Square and not, strides 1–3, padding wider than a tap, a kernel wider than the
/// image, 1×1.
const GEOMETRIES: [Geometry; 6] = [
    (2, (9, 7, 3), 3, 1, 1),
    (1, (8, 8, 2), 4, 2, 1),
    (3, (5, 11, 1), 1, 1, 0),
    (2, (13, 6, 4), 5, 3, 2),
    (1, (4, 4, 5), 7, 1, 3),
    (2, (16, 16, 3), 3, 2, 1),
];

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// f32 values to bf16 bit patterns (truncated: any bf16 will do) and back.
fn to_bf16(v: &[f32]) -> Vec<u16> {
    v.iter().map(|x| (x.to_bits() >> 16) as u16).collect()
}
fn from_bf16(v: &[u16]) -> Vec<f32> {
    v.iter()
        .map(|&b| f32::from_bits((b as u32) << 16))
        .collect()
}

/// The unfolding and its adjoint give the CPU's bits, f32 and bf16, over `cuda::elementwise`'s
/// launch and a launch too small for them.
#[test]
fn im2col_and_col2im_give_the_cpu_ops_bits() {
    let emu = Emulator::get();
    for (i, (n, hwc, k, stride, pad)) in GEOMETRIES.into_iter().enumerate() {
        let g = ConvGeom::new(n, hwc, k, stride, pad);
        let dims = g.sizes();
        let (h, w, c) = hwc;
        let (_, ho, wo) = g.output();
        let x = seeded(n * h * w * c, 1.0, 70 + i as u64);
        let total = n * ho * wo * c * k * k;
        let xt = Tensor::from_slice(&x, (n, h, w, c), &Device::Cpu).unwrap();
        let cpu_cols = values(&conv::im2col(&xt, g).unwrap());
        assert_eq!(cpu_cols.len(), total);
        let cols_in = seeded(total, 1.0, 80 + i as u64);
        let ct = Tensor::from_slice(&cols_in, (n * ho * wo, c * k * k), &Device::Cpu).unwrap();
        let cpu_dx = values(&conv::col2im(&ct, g).unwrap());
        let bf_cols_in = to_bf16(&cols_in);
        let cpu_dx_bf = {
            let t = Tensor::from_vec(
                from_bf16(&bf_cols_in),
                (n * ho * wo, c * k * k),
                &Device::Cpu,
            );
            values(&conv::col2im(&t.unwrap(), g).unwrap())
        };
        let small = Launch {
            grid: (2, 1, 1),
            block: (96, 1, 1),
        };
        let what = format!("n {n}, {hwc:?}, k {k}, stride {stride}, pad {pad}");
        for l in [geometry::elementwise(total.max(n * h * w * c)), small] {
            let cols = emu.fold("osrt_im2col_f32", &x, total, f32::NAN, dims, l);
            assert_eq!(bits(&cols), bits(&cpu_cols), "im2col f32, {what}, {l:?}");
            let cols = emu.fold("osrt_im2col_bf16", &to_bf16(&x), total, 0xffffu16, dims, l);
            assert_eq!(cols, to_bf16(&cpu_cols), "im2col bf16, {what}, {l:?}");
            let dx = emu.fold("osrt_col2im_f32", &cols_in, x.len(), f32::NAN, dims, l);
            assert_eq!(bits(&dx), bits(&cpu_dx), "col2im f32, {what}, {l:?}");
            let dx = emu.fold("osrt_col2im_bf16", &bf_cols_in, x.len(), f32::NAN, dims, l);
            assert_eq!(bits(&dx), bits(&cpu_dx_bf), "col2im bf16, {what}, {l:?}");
        }
    }
}

/// The emulator itself: a warp's shuffles exchange between the lanes they name (a kernel
/// that ignored them would pass the row tests only by chance of the data).
#[test]
fn a_warp_sum_reaches_every_lane() {
    let emu = Emulator::get();
    // One row of 32 ones: each lane holds 1, the warp's sum is 32 on every lane, and a
    // softmax of equal logits is 1/32 everywhere only if every lane saw the sum.
    let y = emu.softmax_fwd(&[1.0; 32], 32);
    assert!(y.iter().all(|&v| v == 1.0 / 32.0), "{y:?}");
}

/// No rows: the kernels write nothing to rows and the column sums are zeros (`cuda::rows`
/// launches them for empty tensors, as the CPU ops return empty tensors).
#[test]
fn empty_inputs_give_empty_rows_and_zero_sums() {
    let emu = Emulator::get();
    let g = seeded(6, 1.0, 90);
    assert!(emu.layer_norm_fwd(&[], &g, &g, 1e-5).is_empty());
    let (dx, dg, db) = emu.layer_norm_bwd(&[], &g, &[], 1e-5, u32::MAX);
    assert!(dx.is_empty() && dg == [0.0; 6] && db == [0.0; 6]);
    assert!(emu.softmax_fwd(&[], 6).is_empty());
    assert_eq!(emu.column_sum(&[], 6, u32::MAX), [0.0; 6]);
    let l = geometry::elementwise(0);
    assert!(emu.bias_act_fwd(&[], &g, (2, 0.0), l).is_empty());
}
