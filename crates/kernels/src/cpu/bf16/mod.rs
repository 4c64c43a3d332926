//! Matrix products on bf16 operands with f32 accumulation on the CPU, as PyTorch's CPU
//! autocast runs them: both operands rounded to bfloat16 (round to nearest even), the
//! products summed in f32, the result returned in f32. The fused ops call it through
//! [`super::gemm::matmul`] when their node was built in bf16 ([`crate::Precision`]).
//!
//! Two units do the arithmetic, chosen once per process at run time (the same binary runs
//! on any x86-64): AMX tiles (`TDPBF16PS`, Intel Sapphire Rapids and later) where the CPU
//! has them and Linux grants the process their state, else AVX512-BF16 dot products
//! (`VDPBF16PS`, Intel Cooper Lake and later, AMD Zen 4 and later). Neither: [`unit`] is
//! `None` and the products stay f32 (the caller's choice, `gemm::matmul`).
//!
//! Why hand-written: candle's CPU bf16 product widens both operands to f32 and runs the
//! f32 gemm (no faster than f32, plus the casts), and the `gemm` crate has no bf16
//! kernels. The AVX512-BF16 intrinsics are stable Rust; the AMX ones are not, so the tile
//! instructions are `asm!` (`amx.rs`).
//!
//! The layout both units read (`pack.rs`): operands are packed per product into 1 KiB
//! blocks of 16 × 16 bf16 pairs, the pairs running along the inner (reduction) dim — the
//! AMX tile layout, in which `A` blocks are 16 rows × 32 inner values and `B` blocks 16
//! inner pairs × 16 columns (the "VNNI" layout). `B` is packed once per product, `A` per
//! task of [`ROWS_PER_TASK`] rows; each task computes its rows' outputs in 32 × 32 blocks
//! over the whole inner dim, so every output value is one task's, summed in one order:
//! the bits do not depend on the thread count.
//!
//! Numerics (both units, as the hardware defines them and PyTorch's oneDNN gets them on
//! the same CPU): operands round to nearest even, subnormal f32 operands become zeros,
//! NaN stays NaN, values past bf16's largest round to infinity; the sums are f32 with
//! subnormal results flushed to zero. The two units sum in different orders, so their
//! results agree to f32 rounding, not in every bit.

#![allow(unsafe_code)]

mod amx;
mod dot;
mod layout;
mod pack;

use super::matrix::{MatRef, Threads};
use layout::{BLOCK, K_BLOCK};
use rayon::prelude::*;
use std::mem::MaybeUninit;
use std::sync::OnceLock;

/// Output rows per parallel task: a task's packed `A` (128 rows × the inner dim in bf16;
/// 440 KiB at the paper's widest layer, 1,716) stays in L2 while it meets every column
/// block of `B`.
pub(crate) const ROWS_PER_TASK: usize = 128;

/// The unit that runs bf16 products.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Unit {
    /// AMX tiles: `TDPBF16PS`, 16 × 16 outputs over 32 inner values per instruction.
    Amx,
    /// AVX512-BF16: `VDPBF16PS`, 16 outputs over 2 inner values per instruction.
    Avx512Bf16,
}

impl std::fmt::Display for Unit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Amx => "AMX",
            Self::Avx512Bf16 => "AVX512-BF16",
        })
    }
}

/// The environment variable that narrows the choice (`amx`, `avx512-bf16`, `off`), for
/// measuring each unit on one machine; a unit the CPU lacks is never chosen.
pub(crate) const UNIT_ENV: &str = "OSRT_CPU_BF16";

/// The unit bf16 products run on in this process: the best the CPU has and the OS allows,
/// within [`UNIT_ENV`]; `None` where the CPU has no bf16 products (they then run in f32).
pub(crate) fn unit() -> Option<Unit> {
    static UNIT: OnceLock<Option<Unit>> = OnceLock::new();
    *UNIT.get_or_init(|| {
        let wanted = std::env::var(UNIT_ENV).unwrap_or_default();
        let allow_amx = !matches!(wanted.as_str(), "avx512-bf16" | "off");
        let allow_dot = wanted != "off";
        if allow_amx && amx::available() {
            Some(Unit::Amx)
        } else if allow_dot && dot::available() {
            Some(Unit::Avx512Bf16)
        } else {
            None
        }
    })
}

/// Whether `u` can run here (the tests run every unit the CPU has).
#[cfg(test)]
pub(crate) fn runs(u: Unit) -> bool {
    match u {
        Unit::Amx => amx::available(),
        Unit::Avx512Bf16 => dot::available(),
    }
}

/// `a · b` → `[a.rows, b.cols]`, row-major f32, on bf16 operands with f32 sums, on `unit`
/// (which must run here: [`unit`]). `a.cols == b.rows` (checked by the caller).
pub(crate) fn matmul(a: MatRef, b: MatRef, threads: Threads, unit: Unit) -> Vec<f32> {
    let ((m, k), (_, n)) = (a.dims(), b.dims());
    if m == 0 || n == 0 {
        return vec![0f32; m * n];
    }
    // Not zero-filled first: a serial pass over the whole output (`gemm.rs` says why);
    // the tasks write every element.
    let mut dst: Vec<MaybeUninit<f32>> = Vec::with_capacity(m * n);
    // SAFETY: `MaybeUninit` needs no initialisation; the capacity is `m·n`.
    unsafe { dst.set_len(m * n) };
    let kb = k.div_ceil(K_BLOCK);
    // Column blocks of 16, paired: each 32 × 32 output block reads two.
    let nb = n.div_ceil(2 * BLOCK) * 2;
    let packed_b = pack::pack_b(b, kb, nb, threads);
    let task = |(t, out): (usize, &mut [MaybeUninit<f32>])| {
        let rows = out.len() / n;
        // The thread's packing buffer, taken (a task that runs on this thread while this
        // one waits finds none and makes its own).
        let mut a_rows = A_ROWS.with(|c| c.take());
        pack::pack_a(a, t * ROWS_PER_TASK, rows, kb, &mut a_rows);
        // SAFETY: `unit` runs on this CPU (the caller's contract, from `unit()`); the
        // packed operands hold `kb` blocks for every 32-row group and 16-column block the
        // loops below address.
        unsafe { blocks(unit, &a_rows, &packed_b, (rows, n, kb, nb), out) };
        A_ROWS.with(|c| c.set(a_rows));
    };
    match threads {
        Threads::Pool => dst
            .par_chunks_mut(ROWS_PER_TASK * n)
            .enumerate()
            .for_each(task),
        Threads::One => dst.chunks_mut(ROWS_PER_TASK * n).enumerate().for_each(task),
    }
    // Every element was written: `blocks` covers all rows and all columns of each task.
    let mut dst = std::mem::ManuallyDrop::new(dst);
    // SAFETY: the same allocation, length and capacity; `MaybeUninit<f32>` has `f32`'s
    // layout and every element is initialised (above).
    unsafe { Vec::from_raw_parts(dst.as_mut_ptr().cast::<f32>(), dst.len(), dst.capacity()) }
}

thread_local! {
    /// A thread's buffer for a task's packed rows, kept between tasks.
    static A_ROWS: std::cell::Cell<Vec<u32>> = const { std::cell::Cell::new(Vec::new()) };
}

/// One task's outputs `out: [rows, n]` (every element written) from its packed rows and the packed `B`, in
/// 32 × 32 blocks.
///
/// # Safety
/// `unit` must run on this CPU; `a` holds `rows.div_ceil(32) · kb · 2` blocks and `b`
/// `nb · kb` blocks (`pack_a`, `pack_b`).
unsafe fn blocks(
    unit: Unit,
    a: &[u32],
    b: &[u32],
    (rows, n, kb, nb): (usize, usize, usize, usize),
    out: &mut [MaybeUninit<f32>],
) {
    const B: usize = BLOCK;
    let mut c = [0f32; 4 * B * B];
    if unit == Unit::Amx {
        // SAFETY: AMX runs here (the caller's contract).
        unsafe { amx::configure() };
    }
    for jp in 0..nb / 2 {
        let b0 = &b[2 * jp * kb * B * B..];
        let b1 = &b[(2 * jp + 1) * kb * B * B..];
        let (c0, cols) = (2 * jp * B, (n - 2 * jp * B).min(2 * B));
        for g in 0..rows.div_ceil(2 * B) {
            let ag = &a[g * kb * 2 * B * B..];
            let (r0, len) = (g * 2 * B, (rows - g * 2 * B).min(2 * B));
            // A whole 32 × 32 block is stored where it goes; an edge block through `c`.
            let whole = len == 2 * B && cols == 2 * B;
            let (dst, ld) = match whole {
                true => (out[r0 * n + c0..].as_mut_ptr().cast::<f32>(), n),
                false => (c.as_mut_ptr(), 2 * B),
            };
            // SAFETY: the unit runs here; `ag` holds the group's `2·kb` blocks, `b0` and
            // `b1` `kb` blocks each (the caller's contract on `a` and `b`); `dst` has 32
            // rows of 32 values `ld` apart: inside `out` for a whole block (rows
            // `r0 .. r0 + 32` of `rows`, columns `c0 .. c0 + 32` of `n`), else `c`.
            unsafe {
                match unit {
                    Unit::Amx => amx::block(ag, b0, b1, kb, (dst, ld)),
                    Unit::Avx512Bf16 => dot::block(ag, b0, b1, kb, (dst, ld)),
                }
            }
            if whole {
                continue;
            }
            for (i, row) in c.chunks(2 * B).take(len).enumerate() {
                let at = (r0 + i) * n + c0;
                for (o, v) in out[at..at + cols].iter_mut().zip(row) {
                    o.write(*v);
                }
            }
        }
    }
    if unit == Unit::Amx {
        // SAFETY: as above; the tiles are this task's, released for the next user.
        unsafe { amx::release() };
    }
}

#[cfg(test)]
mod tests;
