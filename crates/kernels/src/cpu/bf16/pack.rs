//! Packing f32 operands into the bf16 blocks the units read.
//!
//! A block is 16 × 16 `u32`, each `u32` a pair of bf16 values adjacent along the inner
//! dim (the lower half the even index). Seen through an operand `M[x][p]` (`x` an output
//! row of `A`, or an output column of `B`; `p` the inner index):
//!
//! - an `A` block is **x-major**: `T[x][r] = (M[x0 + x][p0 + 2r], M[x0 + x][p0 + 2r + 1])`
//!   — 16 rows of 32 inner values, an AMX `A` tile;
//! - a `B` block is **p-major**: `U[r][x]`, the same pairs transposed — 16 inner pairs of
//!   16 columns, an AMX `B` tile.
//!
//! Values outside the operand are zeros. Each kind has a vector path for the operand
//! layout it reads directly (x-major: `M`'s inner dim contiguous; p-major: its `x` dim
//! contiguous), takes the other's path and transposes for the other layout, and converts
//! one value at a time for any other strides.

use super::layout::{BLOCK, BLOCK_LEN, K_BLOCK, bf16_bits};
use crate::cpu::matrix::{MatRef, Threads};
use rayon::prelude::*;
use std::arch::x86_64::*;

/// `A`'s rows `r0 .. r0 + rows` packed into `out` (resized; every value written): for
/// each 32-row group, for each of `kb` inner blocks, its two 16-row x-major blocks
/// (`[groups][kb][2][16 × 16]`).
pub(crate) fn pack_a(a: MatRef, r0: usize, rows: usize, kb: usize, out: &mut Vec<u32>) {
    let groups = rows.div_ceil(2 * BLOCK);
    out.resize(groups * kb * 2 * BLOCK_LEN, 0);
    for (i, blk) in out.chunks_exact_mut(BLOCK_LEN).enumerate() {
        let (g, q, t) = (i / (2 * kb), (i / 2) % kb, i % 2);
        let x0 = r0 + g * 2 * BLOCK + t * BLOCK;
        // Rows past this task's are another task's (or past the operand): zeros.
        let limit = (r0 + rows).min(a.dims().0);
        x_major(
            a,
            (x0, limit),
            q * K_BLOCK,
            blk.try_into().expect("a block"),
        );
    }
}

/// `B: [k, n]` packed: for each of `nb` 16-column blocks, its `kb` p-major blocks
/// (`[nb][kb][16 × 16]`).
pub(crate) fn pack_b(b: MatRef, kb: usize, nb: usize, threads: Threads) -> Vec<u32> {
    let m = b.t();
    let mut out = vec![0u32; nb * kb * BLOCK_LEN];
    let fill = |(i, blk): (usize, &mut [u32])| {
        let (j, q) = (i / kb.max(1), i % kb.max(1));
        let x0 = j * BLOCK;
        p_major(
            m,
            (x0, m.dims().0),
            q * K_BLOCK,
            blk.try_into().expect("a block"),
        );
    };
    match threads {
        Threads::Pool => out
            .par_chunks_exact_mut(BLOCK_LEN)
            .enumerate()
            .for_each(fill),
        Threads::One => out.chunks_exact_mut(BLOCK_LEN).enumerate().for_each(fill),
    }
    out
}

/// How many of `want` indices from `start` lie below `limit`.
fn within(start: usize, want: usize, limit: usize) -> usize {
    limit.saturating_sub(start).min(want)
}

/// The x-major block of `m` at rows `x0 ..` (rows from `limit` on are zeros) and inner
/// values `p0 .. p0 + 32`.
pub(crate) fn x_major(m: MatRef, (x0, limit): (usize, usize), p0: usize, out: &mut [u32; 256]) {
    let (data, off, (rs, cs)) = m.raw();
    let nx = within(x0, BLOCK, limit);
    let np = within(p0, K_BLOCK, m.dims().1);
    if nx == 0 || np == 0 {
        out.fill(0);
        return;
    }
    if cs == 1 && super::dot::available() {
        // SAFETY: AVX512-BF16 runs here (checked above); rows `x0 .. x0 + nx` and inner
        // values `p0 .. p0 + np` lie inside `data` (`MatRef::new` checked every element
        // of the view), and the masked loads read only those.
        unsafe { x_major_rows(data, off + x0 * rs + p0, rs, (nx, np), out) };
    } else if rs == 1 && super::dot::available() {
        let mut t = [0u32; BLOCK_LEN];
        // SAFETY: as above, with the x dim contiguous.
        unsafe {
            p_major_cols(data, off + x0 + p0 * cs, cs, (nx, np), &mut t);
            transpose(&t, out);
        }
    } else {
        out.fill(0);
        for x in 0..nx {
            for r in 0..np.div_ceil(2) {
                out[x * BLOCK + r] = pair(m, x0 + x, p0 + 2 * r);
            }
        }
    }
}

/// The p-major block of `m` at `x0 ..` (from `limit` on zeros) and inner values
/// `p0 .. p0 + 32`.
pub(crate) fn p_major(m: MatRef, (x0, limit): (usize, usize), p0: usize, out: &mut [u32; 256]) {
    let (data, off, (rs, cs)) = m.raw();
    let nx = within(x0, BLOCK, limit);
    let np = within(p0, K_BLOCK, m.dims().1);
    if nx == 0 || np == 0 {
        out.fill(0);
        return;
    }
    if rs == 1 && super::dot::available() {
        // SAFETY: as in `x_major`, with the x dim contiguous.
        unsafe { p_major_cols(data, off + x0 + p0 * cs, cs, (nx, np), out) };
    } else if cs == 1 && super::dot::available() {
        let mut t = [0u32; BLOCK_LEN];
        // SAFETY: as in `x_major`.
        unsafe {
            x_major_rows(data, off + x0 * rs + p0, rs, (nx, np), &mut t);
            transpose(&t, out);
        }
    } else {
        out.fill(0);
        for r in 0..np.div_ceil(2) {
            for x in 0..nx {
                out[r * BLOCK + x] = pair(m, x0 + x, p0 + 2 * r);
            }
        }
    }
}

/// `(M[x][p], M[x][p + 1])` as a pair (zero past the inner dim).
fn pair(m: MatRef, x: usize, p: usize) -> u32 {
    let lo = bf16_bits(m.get(x, p)) as u32;
    let hi = match p + 1 < m.dims().1 {
        true => bf16_bits(m.get(x, p + 1)) as u32,
        false => 0,
    };
    lo | (hi << 16)
}

/// `out[r][x] = t[x][r]` for a 16 × 16 block: 32-bit interleaves of row pairs, 64-bit
/// interleaves of those, then two rounds of 128-bit lane shuffles.
///
/// # Safety
/// AVX-512 must run here.
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn transpose(t: &[u32; BLOCK_LEN], out: &mut [u32; BLOCK_LEN]) {
    // SAFETY: 16 rows of 16 `u32` read and written inside the two blocks.
    unsafe {
        let r: [__m512i; 16] =
            std::array::from_fn(|i| _mm512_loadu_si512(t.as_ptr().add(i * BLOCK).cast()));
        // Per 128-bit lane: rows 2i, 2i + 1 interleaved by 32 bits.
        let a: [__m512i; 16] = std::array::from_fn(|i| match i % 2 {
            0 => _mm512_unpacklo_epi32(r[i], r[i + 1]),
            _ => _mm512_unpackhi_epi32(r[i - 1], r[i]),
        });
        // Per lane: column 4l + j of rows 4g .. 4g + 4, at index 4g + j.
        let u: [__m512i; 16] = std::array::from_fn(|i| {
            let (g, j) = (i / 4, i % 4);
            let (lo, hi) = (a[4 * g + j / 2], a[4 * g + 2 + j / 2]);
            match j % 2 {
                0 => _mm512_unpacklo_epi64(lo, hi),
                _ => _mm512_unpackhi_epi64(lo, hi),
            }
        });
        for j in 0..4 {
            // Lanes (col j, col 8 + j) then (col 4 + j, col 12 + j) of rows 0–7, 8–15.
            let v0 = _mm512_shuffle_i32x4::<0x88>(u[j], u[4 + j]);
            let v1 = _mm512_shuffle_i32x4::<0xdd>(u[j], u[4 + j]);
            let w0 = _mm512_shuffle_i32x4::<0x88>(u[8 + j], u[12 + j]);
            let w1 = _mm512_shuffle_i32x4::<0xdd>(u[8 + j], u[12 + j]);
            let cols = [
                (j, _mm512_shuffle_i32x4::<0x88>(v0, w0)),
                (8 + j, _mm512_shuffle_i32x4::<0xdd>(v0, w0)),
                (4 + j, _mm512_shuffle_i32x4::<0x88>(v1, w1)),
                (12 + j, _mm512_shuffle_i32x4::<0xdd>(v1, w1)),
            ];
            for (c, v) in cols {
                _mm512_storeu_si512(out.as_mut_ptr().add(c * BLOCK).cast(), v);
            }
        }
    }
}

/// Lanes `0 .. n` of a 16-lane mask.
fn lanes(n: usize) -> __mmask16 {
    ((1u32 << n.min(16)) - 1) as __mmask16
}

/// x-major from rows with contiguous inner values: row `x` starts at `data[at + x·rs]`.
///
/// # Safety
/// AVX512-BF16 must run here; `data[at + x·rs + p]` must be in bounds for `x < nx`,
/// `p < np`.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn x_major_rows(
    data: &[f32],
    at: usize,
    rs: usize,
    (nx, np): (usize, usize),
    out: &mut [u32; BLOCK_LEN],
) {
    let (m_lo, m_hi) = (lanes(np), lanes(np.saturating_sub(16)));
    for x in 0..BLOCK {
        let row = data.as_ptr().wrapping_add(at + x * rs);
        // SAFETY: rows `x < nx` and, by the masks, inner values `< np`: in bounds (the
        // contract); masked lanes are not read; rows from `nx` on are zeros.
        unsafe {
            let v: __m512i = match x < nx {
                true => {
                    let lo = _mm512_maskz_loadu_ps(m_lo, row);
                    let hi = _mm512_maskz_loadu_ps(m_hi, row.wrapping_add(16));
                    std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo))
                }
                false => _mm512_setzero_si512(),
            };
            _mm512_storeu_si512(out.as_mut_ptr().add(x * BLOCK).cast(), v);
        }
    }
}

/// p-major from columns with a contiguous x dim: inner value `p` of the block starts at
/// `data[at + p·cs]`.
///
/// # Safety
/// AVX512-BF16 must run here; `data[at + p·cs + x]` must be in bounds for `x < nx`,
/// `p < np`.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn p_major_cols(
    data: &[f32],
    at: usize,
    cs: usize,
    (nx, np): (usize, usize),
    out: &mut [u32; BLOCK_LEN],
) {
    let mask = lanes(nx);
    // Lane 2i takes the even inner value's lane i, lane 2i + 1 the odd one's (lane 16 + i
    // of the converted pair of vectors).
    let idx: [u16; 32] = std::array::from_fn(|l| (l / 2 + (l % 2) * 16) as u16);
    // SAFETY: a plain load of 32 `u16`.
    let idx = unsafe { _mm512_loadu_si512(idx.as_ptr().cast()) };
    for r in 0..BLOCK {
        let (p, q) = (2 * r, 2 * r + 1);
        let col = |p: usize| data.as_ptr().wrapping_add(at + p * cs);
        if p >= np {
            // SAFETY: row `r` of the block.
            unsafe {
                _mm512_storeu_si512(
                    out.as_mut_ptr().add(r * BLOCK).cast(),
                    _mm512_setzero_si512(),
                )
            };
            continue;
        }
        // SAFETY: columns `p < np` with lanes `x < nx`, in bounds (the contract).
        unsafe {
            let lo = _mm512_maskz_loadu_ps(mask, col(p));
            let hi = match q < np {
                true => _mm512_maskz_loadu_ps(mask, col(q)),
                false => _mm512_setzero_ps(),
            };
            let v: __m512i = std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(hi, lo));
            let v = _mm512_permutexvar_epi16(idx, v);
            _mm512_storeu_si512(out.as_mut_ptr().add(r * BLOCK).cast(), v);
        }
    }
}
