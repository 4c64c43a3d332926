//! The AVX512-BF16 unit: one 32 × 32 output block from packed blocks with `VDPBF16PS`
//! (16 f32 sums, each adding two bf16 products), 8 rows × 32 columns in registers at a
//! time.

use super::layout::BLOCK;
use std::arch::x86_64::*;

/// Whether this CPU has AVX512-BF16 (and the AVX-512 the packing uses with it).
pub(crate) fn available() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512bw")
        && std::arch::is_x86_feature_detected!("avx512bf16")
}

/// Rows summed in registers at once: 8 rows × 2 column vectors = 16 accumulators.
const ROWS: usize = 8;

/// The 32 × 32 output block at `dst` (rows `ld` values apart) = the 32-row group `a`
/// (`kb` pairs of x-major blocks, `[kb][2][16 × 16]`) times the column blocks `b0`, `b1`
/// (`kb` p-major blocks each).
///
/// # Safety
/// AVX512-BF16 must run here ([`available`]); `a` must hold `2·kb` blocks, `b0` and `b1`
/// `kb` each; `dst` must be valid for writes of 32 rows of 32 f32 values, `ld` apart.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
pub(crate) unsafe fn block(
    a: &[u32],
    b0: &[u32],
    b1: &[u32],
    kb: usize,
    (dst, ld): (*mut f32, usize),
) {
    const L: usize = BLOCK * BLOCK;
    assert!(a.len() >= 2 * kb * L && b0.len() >= kb * L && b1.len() >= kb * L);
    for t in 0..2 {
        for rg in 0..BLOCK / ROWS {
            let mut acc = [[_mm512_setzero_ps(); 2]; ROWS];
            for q in 0..kb {
                let at = &a[(2 * q + t) * L..(2 * q + t + 1) * L];
                let (bt0, bt1) = (&b0[q * L..(q + 1) * L], &b1[q * L..(q + 1) * L]);
                for r in 0..BLOCK {
                    // SAFETY: rows `r` of the blocks, in bounds (the slices above).
                    let (v0, v1) = unsafe {
                        (
                            _mm512_loadu_si512(bt0.as_ptr().add(r * BLOCK).cast()),
                            _mm512_loadu_si512(bt1.as_ptr().add(r * BLOCK).cast()),
                        )
                    };
                    let (v0, v1): (__m512bh, __m512bh) =
                        // SAFETY: the same 512 bits, as 32 bf16 values.
                        unsafe { (std::mem::transmute::<__m512i, __m512bh>(v0), std::mem::transmute::<__m512i, __m512bh>(v1)) };
                    for (i, acc) in acc.iter_mut().enumerate() {
                        let pair = at[(rg * ROWS + i) * BLOCK + r] as i32;
                        // SAFETY: the same 512 bits, as 32 bf16 values.
                        let x: __m512bh = unsafe {
                            std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(pair))
                        };
                        acc[0] = _mm512_dpbf16_ps(acc[0], x, v0);
                        acc[1] = _mm512_dpbf16_ps(acc[1], x, v1);
                    }
                }
            }
            for (i, acc) in acc.iter().enumerate() {
                let row = (t * BLOCK + rg * ROWS + i) * ld;
                // SAFETY: row `t·16 + rg·8 + i` of the block (the caller's contract).
                unsafe {
                    _mm512_storeu_ps(dst.add(row), acc[0]);
                    _mm512_storeu_ps(dst.add(row + BLOCK), acc[1]);
                }
            }
        }
    }
}
