//! Which scenes each step takes, who reads them, and which random numbers each scene
//! uses: functions of the seed, the epoch, the step and the scene, never of how many
//! workers share a step or how a worker cuts its share into passes. A job draws the same
//! scenes and rays on one worker or four, a resume on another worker count continues the
//! same sequence, and any process can recompute all of it.
//!
//! Per epoch the train split's row groups (the unit of reading) are permuted by
//! `(seed, epoch)` and cut, in that order, into shuffle windows of whole row groups
//! holding at least [`WINDOW_SCENES`] scenes and two global batches; each window's scenes
//! are shuffled by `(seed, epoch, window)`. The windows' concatenation is the epoch's
//! sequence: step `k` of the epoch takes positions `k·B .. (k+1)·B` (`B` =
//! `train.batch_size`), so an epoch has `⌊scenes / B⌋` steps whatever the worker count.
//! Rank `r` of `W` takes a contiguous slice of every step's batch (`B/W` scenes, the
//! remainder to the first ranks) and reads, window by window, only the rows of its
//! slices (`crate::feed`): a rank holds its share of a few windows, never its share of
//! the whole split.

use crate::error::{Result, TrainError};
use osrt_dataset::RowGroupRef;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use std::ops::Range;

/// The fewest scenes a shuffle window holds (whole row groups, so often more). Larger
/// windows mix scenes of more row groups into each batch; a rank holds its share of the
/// window it reads and of the one read ahead.
pub const WINDOW_SCENES: usize = 1024;

/// What the RNG of a purpose is for; part of the derivation so streams never overlap.
#[derive(Debug, Clone, Copy)]
#[repr(u64)]
pub enum Stream {
    RowGroups = 1,
    SceneOrder = 2,
    /// A scene's draws in one step: input views, target rays, slot noise, ray offsets.
    Scene = 4,
}

/// A ChaCha RNG seeded from `(seed, stream, parts…)` by SplitMix64 mixing.
pub fn derive_rng(seed: u64, stream: Stream, parts: &[u64]) -> ChaCha8Rng {
    let mix = |mut z: u64| {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let h = parts
        .iter()
        .fold(mix(seed ^ mix(stream as u64)), |h, &p| mix(h ^ mix(p)));
    ChaCha8Rng::seed_from_u64(h)
}

/// The RNG of one scene in one training step: its input views, target rays, slot noise
/// and ray offsets, drawn in that order whichever rank, pass or batch position takes it.
pub fn scene_rng(seed: u64, step: u64, scene_id: u64) -> ChaCha8Rng {
    derive_rng(seed, Stream::Scene, &[step, scene_id])
}

/// Scenes per step of each rank: `batch / world`, remainder to the first ranks.
pub fn local_batch_sizes(batch: usize, world: usize) -> Vec<usize> {
    (0..world)
        .map(|r| batch / world + usize::from(r < batch % world))
        .collect()
}

/// Rank `rank`'s positions within each step's global batch of `batch` scenes.
pub fn share(batch: usize, world: usize, rank: usize) -> Range<usize> {
    let sizes = local_batch_sizes(batch, world);
    let start: usize = sizes[..rank].iter().sum();
    start..start + sizes[rank]
}

/// One scene of the split: its row group (an index into the split's listing) and its
/// row within the group.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SceneRef {
    pub group: usize,
    pub row: u64,
}

/// One epoch's sequence of scenes; the same on every rank and for every worker count.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochPlan {
    pub epoch: u64,
    /// Scenes per step over all workers (`train.batch_size`).
    pub batch: usize,
    /// Steps in the epoch: `⌊scenes / batch⌋`.
    pub steps: u64,
    /// Every scene of the split once, in the order the steps take them.
    pub order: Vec<SceneRef>,
    /// The shuffle windows: consecutive ranges of `order`, each of whole row groups.
    pub windows: Vec<Range<usize>>,
}

impl EpochPlan {
    pub fn new(all: &[RowGroupRef], seed: u64, epoch: u64, batch: usize) -> Result<Self> {
        let mut groups: Vec<usize> = (0..all.len()).collect();
        groups.shuffle(&mut derive_rng(seed, Stream::RowGroups, &[epoch]));
        let least = WINDOW_SCENES.max(2 * batch);
        let (mut order, mut windows) = (Vec::new(), Vec::new());
        let mut start = 0;
        for (i, &g) in groups.iter().enumerate() {
            order.extend((0..all[g].num_rows).map(|row| SceneRef { group: g, row }));
            if order.len() - start >= least || i + 1 == groups.len() {
                let w = windows.len() as u64;
                order[start..].shuffle(&mut derive_rng(seed, Stream::SceneOrder, &[epoch, w]));
                windows.push(start..order.len());
                start = order.len();
            }
        }
        let steps = (order.len() / batch.max(1)) as u64;
        if batch == 0 || steps == 0 {
            // Data that cannot fill a step is a configuration problem: no restart fixes it.
            return Err(TrainError::Config {
                path: "data plan".into(),
                reason: format!(
                    "the train split's {} scenes cannot fill one batch of {batch}: use a smaller batch or more scenes",
                    order.len()
                ),
            });
        }
        Ok(Self {
            epoch,
            batch,
            steps,
            order,
            windows,
        })
    }

    /// Positions in [`EpochPlan::order`] of `share`'s scenes at step `k` of the epoch.
    pub fn positions(&self, k: u64, share: &Range<usize>) -> Range<usize> {
        let at = k as usize * self.batch;
        at + share.start..at + share.end
    }

    /// The window that holds position `p`.
    pub fn window_of(&self, p: usize) -> usize {
        self.windows.partition_point(|w| w.end <= p)
    }

    /// The positions in window `w` that `share` takes in some step of the epoch, in
    /// increasing order.
    pub fn share_in_window(&self, w: usize, share: &Range<usize>) -> Vec<usize> {
        let used = self.steps as usize * self.batch;
        self.windows[w]
            .clone()
            .filter(|&p| p < used && share.contains(&(p % self.batch)))
            .collect()
    }
}

/// Checks that `world` ranks can share a batch of `batch` scenes.
pub fn check_world(batch: usize, world: usize, rank: usize) -> Result<()> {
    let bad = |reason: String| TrainError::Config {
        path: "data plan".into(),
        reason,
    };
    if world == 0 || rank >= world {
        return Err(bad(format!("rank {rank} outside a ring of {world}")));
    }
    if batch < world {
        return Err(bad(format!(
            "batch size {batch} is smaller than the {world} workers: every worker needs at least one scene per step"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn groups(n: usize, rows: u64) -> Vec<RowGroupRef> {
        (0..n)
            .map(|i| RowGroupRef {
                file: format!("part-{:05}.parquet", i / 4),
                index: i % 4,
                num_rows: rows,
            })
            .collect()
    }

    #[test]
    fn an_epoch_takes_every_scene_once_and_reproducibly() {
        let all = groups(100, 32);
        let plan = EpochPlan::new(&all, 7, 3, 48).unwrap();
        let mut seen = plan.order.clone();
        seen.sort();
        let want: Vec<SceneRef> = (0..100)
            .flat_map(|group| (0..32).map(move |row| SceneRef { group, row }))
            .collect();
        assert_eq!(seen, want, "every scene exactly once");
        assert_eq!(plan.steps, 3200 / 48);
        assert_eq!(plan, EpochPlan::new(&all, 7, 3, 48).unwrap(), "same inputs");
        assert_ne!(plan.order, EpochPlan::new(&all, 7, 4, 48).unwrap().order);
        // Windows: whole row groups, ≥ WINDOW_SCENES each but the last, covering all.
        assert_eq!(plan.windows.len(), 4, "{:?}", plan.windows);
        for w in &plan.windows[..3] {
            assert_eq!(w.len(), 1024);
        }
        assert_eq!(plan.windows[3], 3072..3200);
        let groups_of = |w: &Range<usize>| {
            let mut g: Vec<usize> = plan.order[w.clone()].iter().map(|s| s.group).collect();
            g.sort();
            g.dedup();
            g.len() * 32
        };
        assert!(plan.windows.iter().all(|w| groups_of(w) == w.len()));
        // A batch larger than half the minimum makes windows of two batches.
        let big = EpochPlan::new(&all, 7, 3, 800).unwrap();
        assert_eq!(big.windows[0].len(), 1600);
    }

    #[test]
    fn shares_cut_each_step_the_same_way_for_any_worker_count() {
        let plan = EpochPlan::new(&groups(10, 30), 1, 0, 7).unwrap();
        for world in 1..=7 {
            let shares: Vec<Range<usize>> = (0..world).map(|r| share(7, world, r)).collect();
            for k in 0..plan.steps {
                let joined: Vec<usize> = shares.iter().flat_map(|s| plan.positions(k, s)).collect();
                let whole: Vec<usize> = plan.positions(k, &(0..7)).collect();
                assert_eq!(joined, whole, "world {world}, step {k}");
            }
            // Each rank's positions per window are exactly its steps' positions.
            for s in &shares {
                let by_window: Vec<usize> = (0..plan.windows.len())
                    .flat_map(|w| plan.share_in_window(w, s))
                    .collect();
                let by_step: Vec<usize> =
                    (0..plan.steps).flat_map(|k| plan.positions(k, s)).collect();
                assert_eq!(by_window, by_step, "world {world}");
                for &p in &by_step {
                    assert!(plan.windows[plan.window_of(p)].contains(&p));
                }
            }
        }
    }

    #[test]
    fn too_small_data_or_batch_is_a_clear_error() {
        let e = EpochPlan::new(&groups(1, 4), 0, 0, 8)
            .unwrap_err()
            .to_string();
        assert!(e.contains("4 scenes cannot fill one batch of 8"), "{e}");
        let e = check_world(2, 4, 0).unwrap_err().to_string();
        assert!(e.contains("smaller than the 4 workers"), "{e}");
        check_world(4, 4, 3).unwrap();
    }

    #[test]
    fn scene_rngs_differ_by_seed_step_and_scene() {
        use rand::Rng;
        let x = |seed, s, id| scene_rng(seed, s, id).random::<u64>();
        assert_eq!(x(1, 5, 9), x(1, 5, 9));
        assert_ne!(x(1, 5, 9), x(1, 6, 9));
        assert_ne!(x(1, 5, 9), x(1, 5, 10));
        assert_ne!(x(1, 5, 9), x(2, 5, 9));
    }
}
