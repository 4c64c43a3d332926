//! Staging: a buffer whose floats reach the ring bucket by bucket, and whose buckets' sums
//! leave it one by one ([`crate::Ring::all_reduce_staged`]).

use crate::loan::LentBuffer;
use crate::{CollectiveError, Layout};
use std::time::Duration;

/// Where an all-reduce's buffer comes from and where its sums go, one bucket at a time
/// ([`Ring::all_reduce_staged`]): a gradient that lives on a GPU is copied to the host
/// bucket by bucket while the ring already works on the buckets before it, and each
/// bucket's sums can go back as soon as they are final.
///
/// Buckets are numbered in [`Layout`] order (from the buffer's end), and every method is
/// called for bucket 0, 1, … in turn, once each.
pub trait Stage: Send {
    /// Resolves once bucket `bucket` can be written into the buffer. The ring polls it
    /// beside its other work and may drop it unfinished to poll it again later, so it
    /// must be cancel-safe.
    fn staged(
        &mut self,
        bucket: usize,
    ) -> impl std::future::Future<Output = Result<(), String>> + Send;
    /// Writes bucket `bucket`'s floats into `dst` (its range of the buffer), after
    /// [`Stage::staged`] resolved for it.
    fn fill(&mut self, bucket: usize, dst: &mut [f32]) -> Result<(), String>;
    /// This rank holds the final sums of bucket `bucket`: `sums` is its range of the
    /// buffer, which it keeps until the all-reduce returns.
    fn reduced(&mut self, bucket: usize, sums: &[f32]) -> Result<(), String>;
}

/// The stage of a buffer that is complete before the all-reduce starts.
pub(crate) struct Whole;

impl Stage for Whole {
    async fn staged(&mut self, _: usize) -> Result<(), String> {
        Ok(())
    }
    fn fill(&mut self, _: usize, _: &mut [f32]) -> Result<(), String> {
        Ok(())
    }
    fn reduced(&mut self, _: usize, _: &[f32]) -> Result<(), String> {
        Ok(())
    }
}

/// The ring's side of a [`Stage`]: which buckets are filled, and the calls into it. Without
/// a stage every bucket counts as filled from the start and nothing is reported.
pub(crate) struct Fill<'a, S> {
    stage: Option<&'a mut S>,
    layout: &'a Layout,
    /// Buckets filled so far (in layout order): a rank sends a bucket's chunks, and takes
    /// in its predecessor's, only once the bucket holds its own floats.
    filled: usize,
    rank: usize,
    timeout: Duration,
}

impl<'a, S: Stage> Fill<'a, S> {
    pub(crate) fn new(
        stage: Option<&'a mut S>,
        layout: &'a Layout,
        rank: usize,
        timeout: Duration,
    ) -> Self {
        let filled = if stage.is_some() {
            0
        } else {
            layout.buckets.len()
        };
        Self {
            stage,
            layout,
            filled,
            rank,
            timeout,
        }
    }

    /// Whether bucket `b` holds this rank's floats.
    pub(crate) fn has(&self, b: usize) -> bool {
        b < self.filled
    }

    /// Whether a bucket is still to be filled.
    pub(crate) fn pending(&self) -> bool {
        self.filled < self.layout.buckets.len()
    }

    fn failed(&self, bucket: usize, reason: String) -> CollectiveError {
        CollectiveError::Stage {
            rank: self.rank,
            bucket,
            reason,
        }
    }

    /// Resolves once the next bucket can be filled (cancel-safe as [`Stage::staged`]).
    pub(crate) async fn staged(&mut self) -> Result<(), String> {
        match self.stage.as_deref_mut() {
            Some(s) => s.staged(self.filled).await,
            None => Ok(()),
        }
    }

    /// Fills the next bucket, after [`Fill::staged`] gave `staged`.
    pub(crate) async fn fill(
        &mut self,
        staged: Result<(), String>,
        shared: &mut LentBuffer,
    ) -> Result<(), CollectiveError> {
        let b = self.filled;
        staged.map_err(|e| self.failed(b, e))?;
        let Some(s) = self.stage.as_deref_mut() else {
            return Ok(());
        };
        let range = self.layout.buckets[b].clone();
        // The bucket was never lent (nothing of it was sent): the write does not wait.
        let written = shared
            .write(range, self.timeout, |dst| s.fill(b, dst))
            .await;
        written
            .map_err(|e| CollectiveError::StillLent {
                rank: self.rank,
                range: e.0,
                timeout: self.timeout,
            })?
            .map_err(|e| self.failed(b, e))?;
        self.filled += 1;
        Ok(())
    }

    /// Bucket `b`'s sums are final in `shared`.
    pub(crate) fn reduced(&mut self, b: usize, shared: &LentBuffer) -> Result<(), CollectiveError> {
        let Some(s) = self.stage.as_deref_mut() else {
            return Ok(());
        };
        let sums = shared.view(self.layout.buckets[b].clone());
        s.reduced(b, sums).map_err(|e| self.failed(b, e))
    }
}

/// A staged all-reduce on a ring of one: every bucket filled, and its sums are its own.
pub(crate) async fn alone(
    rank: usize,
    layout: &Layout,
    buf: &mut [f32],
    stage: &mut impl Stage,
) -> Result<(), CollectiveError> {
    for (b, range) in layout.buckets.iter().enumerate() {
        let failed = |reason| CollectiveError::Stage {
            rank,
            bucket: b,
            reason,
        };
        stage.staged(b).await.map_err(failed)?;
        stage.fill(b, &mut buf[range.clone()]).map_err(failed)?;
        stage.reduced(b, &buf[range.clone()]).map_err(failed)?;
    }
    Ok(())
}
