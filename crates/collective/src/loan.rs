//! The buffer an all-reduce works on, with chunks of it lent to the transport.
//!
//! Sending a chunk used to copy its floats into a fresh allocation that HTTP/2 could own;
//! on two memory-bound cores that copy cost about as much as the reduction. Instead the
//! buffer moves into a [`LentBuffer`] for the duration of the all-reduce and chunks go out
//! as [`Bytes`] that *borrow* ranges of it ([`LentBuffer::lend`]): the kernel's copy into
//! the socket reads the gradient memory directly.
//!
//! Soundness rests on these rules, all enforced here:
//! - a lent range is only read, by whoever holds the `Bytes`, and is written again only
//!   after every loan overlapping it has been dropped ([`LentBuffer::write`] waits);
//! - there is one writer: `LentBuffer` is not `Clone` and writes take `&mut self`, so no
//!   two writes, and no write and a new loan, overlap in time; every write goes through
//!   the one raw pointer taken when the buffer moved in, to ranges no loan covers, so
//!   readers of other ranges never alias it;
//! - each loan holds an `Arc` of the storage, so the memory outlives every loan even when
//!   the all-reduce fails or is cancelled with chunks still queued in the transport:
//!   [`LentBuffer::reclaim`] takes the buffer back only once it is the last owner (or
//!   copies it out, which is only a read, when the transport is slow to let go).
//!
//! This module and `osrt_kernels::fastmath`'s feature dispatch are the workspace's only
//! `unsafe` code.
#![allow(unsafe_code)]

use bytes::Bytes;
use std::ops::Range;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use tokio::sync::Notify;
use tokio::time::Instant;

/// The storage: a `Vec<f32>` taken apart, and the ranges currently lent out of it.
struct Shared {
    ptr: *mut f32,
    len: usize,
    cap: usize,
    /// Ranges currently lent; a range appears once per loan.
    lent: Mutex<Vec<Range<usize>>>,
    released: Notify,
}

// SAFETY: the floats behind `ptr` are owned by `Shared` (a `Vec` taken apart) and a
// `Vec<f32>` may be freed on any thread; the rules in the module docs keep writes and
// reads of one range apart in time, and `lent` is behind a mutex.
unsafe impl Send for Shared {}
unsafe impl Sync for Shared {}

impl Shared {
    /// `lent`, also after a panic elsewhere poisoned it (the list itself stays valid:
    /// every update is a single push or removal).
    fn lent(&self) -> MutexGuard<'_, Vec<Range<usize>>> {
        self.lent.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A copy of the floats in `range` (reading is allowed while ranges are lent).
    fn read(&self, range: Range<usize>) -> Vec<f32> {
        assert!(
            range.start <= range.end && range.end <= self.len,
            "read {range:?}"
        );
        // SAFETY: in bounds; the only writer is the `LentBuffer`, and this is called
        // through it (`&self`), so no write is in progress.
        unsafe { std::slice::from_raw_parts(self.ptr.add(range.start), range.len()).to_vec() }
    }
}

impl Drop for Shared {
    fn drop(&mut self) {
        if self.cap != 0 {
            // SAFETY: the parts came from a `Vec<f32>` in `LentBuffer::new` and were not
            // given back by `LentBuffer::reclaim` (which zeroes `cap`).
            drop(unsafe { Vec::from_raw_parts(self.ptr, self.len, self.cap) });
        }
    }
}

/// A range of the storage, seen as the little-endian bytes the wire carries.
struct Loan {
    shared: Arc<Shared>,
    range: Range<usize>,
}

impl AsRef<[u8]> for Loan {
    fn as_ref(&self) -> &[u8] {
        // SAFETY: the range was checked against the buffer's length when lent, the buffer
        // lives as long as `self.shared`, and no one writes the range while this loan is
        // registered in `lent` (see `LentBuffer::write`).
        unsafe {
            std::slice::from_raw_parts(
                self.shared.ptr.add(self.range.start).cast::<u8>(),
                self.range.len() * 4,
            )
        }
    }
}

impl Drop for Loan {
    fn drop(&mut self) {
        let mut lent = self.shared.lent();
        if let Some(i) = lent.iter().position(|r| *r == self.range) {
            lent.swap_remove(i);
        }
        drop(lent);
        self.shared.released.notify_waiters();
    }
}

/// Why a range could not be written: the transport still held a chunk of it.
#[derive(Debug)]
pub(crate) struct StillLent(pub Range<usize>);

/// `now + timeout`, or a day from now where that overflows (a huge configured timeout).
pub(crate) fn deadline(timeout: Duration) -> Instant {
    let now = Instant::now();
    now.checked_add(timeout)
        .unwrap_or_else(|| now + Duration::from_secs(86_400))
}

/// The buffer of one all-reduce: the only handle that writes it, lends ranges of it and
/// gives it back.
pub(crate) struct LentBuffer {
    shared: Arc<Shared>,
}

impl LentBuffer {
    pub(crate) fn new(buf: Vec<f32>) -> Self {
        let mut buf = std::mem::ManuallyDrop::new(buf);
        Self {
            shared: Arc::new(Shared {
                ptr: buf.as_mut_ptr(),
                len: buf.len(),
                cap: buf.capacity(),
                lent: Mutex::new(Vec::new()),
                released: Notify::new(),
            }),
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.shared.len
    }

    /// The floats of `range`, read in place (reading is allowed while ranges are lent;
    /// the borrow rules out a write until the slice is gone).
    pub(crate) fn view(&self, range: Range<usize>) -> &[f32] {
        let shared = &*self.shared;
        assert!(
            range.start <= range.end && range.end <= shared.len,
            "view {range:?}"
        );
        // SAFETY: in bounds; writes take `&mut self`, so none runs while this borrow of
        // `self` lives, and loans only read.
        unsafe { std::slice::from_raw_parts(shared.ptr.add(range.start), range.len()) }
    }

    /// The floats of `range` as wire bytes that borrow the buffer (little-endian machines)
    /// or own a copy (big-endian ones, where the bytes differ from memory).
    pub(crate) fn lend(&self, range: Range<usize>) -> Bytes {
        assert!(
            range.start <= range.end && range.end <= self.shared.len,
            "lend {range:?}"
        );
        if cfg!(target_endian = "big") {
            let v = self.shared.read(range);
            return Bytes::from(v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>());
        }
        self.shared.lent().push(range.clone());
        Bytes::from_owner(Loan {
            shared: self.shared.clone(),
            range,
        })
    }

    /// Runs `f` on the floats of `range` once no loan overlaps it, waiting at most
    /// `timeout` for the transport to drop the loans that do.
    pub(crate) async fn write<R>(
        &mut self,
        range: Range<usize>,
        timeout: Duration,
        f: impl FnOnce(&mut [f32]) -> R,
    ) -> Result<R, StillLent> {
        let shared = &*self.shared;
        assert!(
            range.start <= range.end && range.end <= shared.len,
            "write {range:?}"
        );
        let deadline = deadline(timeout);
        loop {
            // Register before looking, or a release between the look and the wait is lost.
            let notified = shared.released.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            let busy = shared
                .lent()
                .iter()
                .any(|r| r.start < range.end && range.start < r.end);
            if !busy {
                // SAFETY: in bounds; no loan covers the range, so no `Bytes` reads it;
                // `&mut self` makes this the only writer and rules out a new loan while
                // `f` runs.
                let s = unsafe {
                    std::slice::from_raw_parts_mut(shared.ptr.add(range.start), range.len())
                };
                return Ok(f(s));
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Err(StillLent(range));
            }
        }
    }

    /// The buffer back, once every loan is gone; if the transport still holds one after
    /// `timeout` (a connection stuck mid-write), a copy: the original stays alive until
    /// the last loan drops.
    pub(crate) async fn reclaim(self, timeout: Duration) -> Vec<f32> {
        let deadline = deadline(timeout);
        let mut shared = self.shared;
        loop {
            match Arc::try_unwrap(shared) {
                Ok(mut s) => {
                    // SAFETY: the parts came from a `Vec<f32>` in `new`; zeroing `cap`
                    // leaves `Shared::drop` nothing to free, so they become a `Vec` once.
                    let v = unsafe { Vec::from_raw_parts(s.ptr, s.len, s.cap) };
                    (s.len, s.cap) = (0, 0);
                    return v;
                }
                Err(still) => shared = still,
            }
            if Instant::now() >= deadline {
                return shared.read(0..shared.len);
            }
            // Rare (the transport drops a written chunk right after writing it), and a
            // loan notifies before it drops its `Arc`: poll.
            tokio::time::sleep(Duration::from_micros(200)).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn le(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    /// A loan reads the buffer itself (no copy), and the buffer comes back as the very
    /// allocation that went in once every loan is dropped.
    #[tokio::test]
    async fn loans_borrow_and_the_buffer_comes_back_uncopied() {
        let v: Vec<f32> = (0..1000).map(|i| i as f32 * 0.5 - 7.0).collect();
        let (ptr, want) = (v.as_ptr(), v.clone());
        let shared = LentBuffer::new(v);
        let a = shared.lend(10..20);
        let b = shared.lend(500..1000);
        assert_eq!(&a[..], &le(&want[10..20])[..]);
        assert_eq!(&b[..], &le(&want[500..])[..]);
        if cfg!(target_endian = "little") {
            assert_eq!(
                a.as_ptr(),
                ptr.wrapping_add(10).cast::<u8>(),
                "a copy was made"
            );
        }
        // A clone of the bytes keeps the loan: it ends with the last clone.
        let a2 = a.clone();
        drop((a, b));
        assert_eq!(shared.shared.lent().len(), 1);
        drop(a2);
        let back = LentBuffer::reclaim(shared, Duration::from_secs(1)).await;
        assert_eq!(back, want);
        assert_eq!(back.as_ptr(), ptr);
    }

    /// A write waits for overlapping loans to be dropped; one beside them does not wait.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_write_waits_for_overlapping_loans_only() {
        let mut shared = LentBuffer::new(vec![1.0f32; 100]);
        let loan = shared.lend(40..60);
        let t = Duration::from_secs(5);
        // Touches the loan's neighbours only: at once.
        shared.write(0..40, t, |s| s.fill(2.0)).await.unwrap();
        shared.write(60..100, t, |s| s.fill(3.0)).await.unwrap();
        let writer = tokio::spawn(async move {
            let r = shared.write(50..70, t, |s| s.fill(4.0)).await;
            (r, shared)
        });
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(!writer.is_finished(), "wrote while the range was lent");
        // The loan still reads what was lent.
        assert_eq!(&loan[..], &le(&[1.0; 20])[..]);
        drop(loan);
        let (r, shared) = writer.await.unwrap();
        r.unwrap();
        let v = LentBuffer::reclaim(shared, t).await;
        let want: Vec<f32> = (0..100)
            .map(|i| match i {
                0..40 => 2.0,
                40..50 => 1.0,
                50..70 => 4.0,
                _ => 3.0,
            })
            .collect();
        assert_eq!(v, want);
    }

    /// A loan the transport never drops fails the write after the timeout (it does not
    /// hang), and reclaiming then returns a copy while the loan stays readable.
    #[tokio::test]
    async fn a_loan_that_is_never_dropped_times_out_and_reclaim_copies() {
        let mut shared = LentBuffer::new((0..64).map(|i| i as f32).collect());
        let loan = shared.lend(0..32);
        let e = shared
            .write(16..17, Duration::from_millis(50), |s| s[0] = -1.0)
            .await
            .unwrap_err();
        assert_eq!(e.0, 16..17);
        let mut back = LentBuffer::reclaim(shared, Duration::from_millis(20)).await;
        assert_eq!(back, (0..64).map(|i| i as f32).collect::<Vec<_>>());
        back.fill(9.0);
        assert_eq!(
            &loan[..],
            &le(&(0..32).map(|i| i as f32).collect::<Vec<_>>())[..]
        );
    }

    #[tokio::test]
    async fn an_empty_buffer_round_trips() {
        let shared = LentBuffer::new(Vec::new());
        let none = shared.lend(0..0);
        assert!(none.is_empty());
        drop(none);
        assert!(LentBuffer::reclaim(shared, Duration::ZERO).await.is_empty());
    }
}
