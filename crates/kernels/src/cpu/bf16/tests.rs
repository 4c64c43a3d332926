use super::layout::{bf16_bits, bf16_value};
use super::*;
use crate::cpu::matrix::MatRef;

fn values(n: usize, seed: u64, scale: f32) -> Vec<f32> {
    let t = crate::testing::randn(&[n.max(1)], scale, seed);
    let mut v: Vec<f32> = t.to_vec1().unwrap();
    v.truncate(n);
    v
}

/// Every unit this CPU has (none: the test has nothing to check, and says so).
fn units() -> Vec<Unit> {
    let u: Vec<Unit> = [Unit::Amx, Unit::Avx512Bf16]
        .into_iter()
        .filter(|&u| runs(u))
        .collect();
    if u.is_empty() {
        eprintln!("no bf16 products on this CPU: the bf16 units are not exercised");
    }
    u
}

/// The exact product of the operands rounded to bf16 (f64 sums of exact products), and
/// the sum of the products' magnitudes (the scale of f32 summation error).
fn reference(a: MatRef, b: MatRef) -> (Vec<f64>, Vec<f64>) {
    let ((m, k), (_, n)) = (a.dims(), b.dims());
    let r = |x: f32| bf16_value(bf16_bits(x)) as f64;
    let (mut c, mut mag) = (vec![0f64; m * n], vec![0f64; m * n]);
    for i in 0..m {
        for j in 0..n {
            for p in 0..k {
                let v = r(a.get(i, p)) * r(b.get(p, j));
                c[i * n + j] += v;
                mag[i * n + j] += v.abs();
            }
        }
    }
    (c, mag)
}

/// Products of row-major, transposed, row-sliced and general-strided views, at shapes on
/// and off the 16 / 32 block edges (an inner dim of 0, 1, 33, the paper's 1,716), are the
/// exact products of the bf16-rounded operands within f32 summation error, on every unit
/// this CPU has, with one or all threads giving the same bits.
#[test]
fn products_are_the_bf16_operands_products_in_f32() {
    for (m, k, n) in [
        (37, 19, 23),
        (1, 64, 9),
        (5, 1, 7),
        (32, 32, 32),
        (130, 70, 3),
        (300, 33, 65),
        (17, 1716, 40),
        (4, 0, 5),
    ] {
        let (av, bv) = (values(m * k + 3, 1, 1.0), values(k * n, 2, 1.0));
        let views: Vec<(&str, MatRef, MatRef)> = vec![
            (
                "row-major",
                MatRef::new(&av, 3, (m, k), (k, 1)).unwrap(),
                MatRef::new(&bv, 0, (k, n), (n, 1)).unwrap(),
            ),
            (
                "transposed",
                MatRef::new(&av, 3, (k, m), (m, 1)).unwrap().t(),
                MatRef::new(&bv, 0, (n, k), (k, 1)).unwrap().t(),
            ),
        ];
        for (what, a, b) in views {
            let (want, mag) = reference(a, b);
            for u in units() {
                let got = matmul(a, b, Threads::Pool, u);
                let one = matmul(a, b, Threads::One, u);
                assert_eq!(
                    got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    one.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "{u} {what} {m}×{k}×{n}: the thread count changed bits"
                );
                for (i, ((g, w), s)) in got.iter().zip(&want).zip(&mag).enumerate() {
                    let tol = 4.0 * f32::EPSILON as f64 * s * (k as f64).sqrt().max(1.0);
                    assert!(
                        (*g as f64 - w).abs() <= tol + 1e-30,
                        "{u} {what} {m}×{k}×{n} [{i}]: {g} against {w} (±{tol})"
                    );
                }
            }
        }
    }
}

/// The vector packing (contiguous rows or columns) and the one-value-at-a-time packing
/// (other strides) round the same values to the same bits: the same operands copied into
/// every other element of a wider buffer give the same product bits, special values
/// (NaN, infinities, subnormals, ties) included.
#[test]
fn strided_operands_pack_to_the_contiguous_ones_bits() {
    let (m, k, n) = (21, 45, 19);
    let mut av = values(m * k, 3, 1.0);
    let specials = [
        f32::NAN,
        f32::INFINITY,
        1e-39,
        -1e-39,
        f32::from_bits(0x3f80_8000),
        f32::from_bits(0x3f81_8000),
        f32::MAX,
        -0.0,
    ];
    av[..specials.len()].copy_from_slice(&specials);
    let bv = values(k * n, 4, 1.0);
    let spread = |v: &[f32]| -> Vec<f32> { v.iter().flat_map(|&x| [x, 7.0]).collect() };
    let (aw, bw) = (spread(&av), spread(&bv));
    let plain = (
        MatRef::new(&av, 0, (m, k), (k, 1)).unwrap(),
        MatRef::new(&bv, 0, (k, n), (n, 1)).unwrap(),
    );
    let strided = (
        MatRef::new(&aw, 0, (m, k), (2 * k, 2)).unwrap(),
        MatRef::new(&bw, 0, (k, n), (2 * n, 2)).unwrap(),
    );
    for u in units() {
        let want = matmul(plain.0, plain.1, Threads::Pool, u);
        let got = matmul(strided.0, strided.1, Threads::Pool, u);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&want), "{u}");
        // Row 0 met a NaN and an infinity: NaN; the others are finite.
        assert!(want[..n].iter().all(|v| v.is_nan()), "{u}");
        assert!(want[n..].iter().all(|v| v.is_finite()), "{u}");
    }
}

/// The vector 16 × 16 transpose of the packing is the plain one.
#[test]
fn the_block_transpose_transposes() {
    if !runs(Unit::Avx512Bf16) {
        return;
    }
    let t: [u32; 256] = std::array::from_fn(|i| (i as u32).wrapping_mul(2654435761));
    let mut out = [0u32; 256];
    // SAFETY: AVX-512 runs here (checked above).
    unsafe { pack::transpose(&t, &mut out) };
    for r in 0..16 {
        for x in 0..16 {
            assert_eq!(out[r * 16 + x], t[x * 16 + r], "({r}, {x})");
        }
    }
}

/// The scalar rounding is the hardware's: nearest even, subnormals to signed zero, NaN
/// quieted, past bf16's largest to infinity (values read off `VCVTNE2PS2BF16`).
#[test]
fn rounding_is_the_hardwares() {
    for (x, want) in [
        (0x000a_e398u32, 0x0000u16),
        (0x800a_e398, 0x8000),
        (0x7fc0_0000, 0x7fc0),
        (0x7fa0_0000, 0x7fe0),
        (0x7f80_0000, 0x7f80),
        (0x3f80_8000, 0x3f80),
        (0x3f81_8000, 0x3f82),
        (0x3f80_8001, 0x3f81),
        (0x7f7f_ffff, 0x7f80),
        (0x0080_0000, 0x0080),
    ] {
        assert_eq!(bf16_bits(f32::from_bits(x)), want, "{x:08x}");
    }
}

/// Extreme scales: operands of 1e17 and 1e-18 give their products' values (bf16 has f32's
/// exponent range); products below f32's normal range come out as zeros or subnormals,
/// never NaN or anything larger.
#[test]
fn extreme_scales_keep_their_range() {
    let (m, k, n) = (9, 40, 11);
    for (sa, sb) in [
        (1e17f32, 1e17f32),
        (1e17, 1e-17),
        (1e-18, 1.0),
        (1e-20, 1e-20),
    ] {
        let (av, bv) = (values(m * k, 5, sa), values(k * n, 6, sb));
        let a = MatRef::new(&av, 0, (m, k), (k, 1)).unwrap();
        let b = MatRef::new(&bv, 0, (k, n), (n, 1)).unwrap();
        let (want, mag) = reference(a, b);
        let tiny = (sa as f64) * (sb as f64) < f32::MIN_POSITIVE as f64;
        for u in units() {
            let got = matmul(a, b, Threads::Pool, u);
            for ((g, w), s) in got.iter().zip(&want).zip(&mag) {
                assert!(g.is_finite(), "{u} {sa}·{sb}: {g}");
                if tiny {
                    assert!(
                        g.abs() <= k as f32 * f32::MIN_POSITIVE,
                        "{u} {sa}·{sb}: {g}"
                    );
                } else {
                    let tol = 8.0 * f32::EPSILON as f64 * s;
                    assert!((*g as f64 - w).abs() <= tol, "{u} {sa}·{sb}: {g} vs {w}");
                }
            }
        }
    }
}

/// The two units compute the same products (within f32 summation error of each other).
#[test]
fn the_units_agree() {
    if !(runs(Unit::Amx) && runs(Unit::Avx512Bf16)) {
        eprintln!("this CPU lacks one of the units: nothing to compare");
        return;
    }
    let (m, k, n) = (200, 230, 96);
    let (av, bv) = (values(m * k, 7, 1.0), values(k * n, 8, 1.0));
    let a = MatRef::new(&av, 0, (m, k), (k, 1)).unwrap();
    let b = MatRef::new(&bv, 0, (n, k), (k, 1)).unwrap().t();
    let x = matmul(a, b, Threads::Pool, Unit::Amx);
    let y = matmul(a, b, Threads::Pool, Unit::Avx512Bf16);
    let (_, mag) = reference(a, b);
    for ((x, y), s) in x.iter().zip(&y).zip(&mag) {
        assert!(((x - y) as f64).abs() <= 8.0 * f32::EPSILON as f64 * s);
    }
}
