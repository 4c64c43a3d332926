//! Output buffers filled in parallel without a serial zero-fill first.
//!
//! Why: `vec![0f32; n]` zeroes the whole buffer on the calling thread before the parallel
//! kernel overwrites it. For the decoder's `[8192, 96–192]` activations that is a pass
//! over cold memory on one thread while the other waits, and that `memset` is the largest
//! serial item of a 2-thread step that zero-fills them (docs/performance.md). Here
//! each parallel task zeroes its own chunk (cache-resident, on every thread) right
//! before its kernel writes it.
//!
//! `unsafe` (one of the workspace's few such modules): the chunks of the vector's spare
//! capacity are handed to the kernels as `&mut [f32]` only after their task has
//! initialised every element, and the length is set only after every task has run.

#![allow(unsafe_code)]

use rayon::prelude::*;
use std::mem::MaybeUninit;

/// A buffer of `len` values, chunk `i` (values `i·per ..`, the last one shorter) filled by
/// `fill(i, chunk)` in parallel; each chunk is zeroed first by the task that fills it.
pub(crate) fn par_filled(
    len: usize,
    per: usize,
    fill: impl Fn(usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    let mut v: Vec<f32> = Vec::with_capacity(len);
    v.spare_capacity_mut()[..len]
        .par_chunks_mut(per.max(1))
        .enumerate()
        .for_each(|(i, chunk)| fill(i, zeroed(chunk)));
    // SAFETY: the chunks above cover `0..len` of the capacity, and every task initialised
    // its chunk (`zeroed`) before anything else; `for_each` returns only after all tasks
    // have (a panic in one propagates before this line, leaving the length at 0).
    unsafe { v.set_len(len) };
    v
}

/// Writes zeros into every element and returns the now-initialised slice.
fn zeroed(chunk: &mut [MaybeUninit<f32>]) -> &mut [f32] {
    for x in chunk.iter_mut() {
        x.write(0.0);
    }
    // SAFETY: every element was just written; `MaybeUninit<f32>` has `f32`'s layout.
    unsafe { &mut *(chunk as *mut [MaybeUninit<f32>] as *mut [f32]) }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every chunk arrives zeroed, exactly once, with its index; the result is what the
    /// kernels wrote, for lengths that do and do not divide into chunks (and zero).
    #[test]
    fn every_chunk_is_zeroed_then_filled_once() {
        for (len, per) in [(0usize, 4usize), (1, 4), (10, 4), (12, 4), (1000, 7)] {
            let seen = std::sync::Mutex::new(vec![0usize; len.div_ceil(per)]);
            let v = par_filled(len, per, |i, c| {
                assert!(c.iter().all(|&x| x == 0.0), "chunk {i} not zeroed");
                assert_eq!(c.len(), per.min(len - i * per));
                seen.lock().unwrap()[i] += 1;
                for (j, x) in c.iter_mut().enumerate() {
                    *x = (i * per + j) as f32;
                }
            });
            assert!(seen.into_inner().unwrap().iter().all(|&n| n == 1));
            assert_eq!(v, (0..len).map(|x| x as f32).collect::<Vec<_>>());
        }
    }
}
