//! Who reads what, and which random numbers each step uses — all derived from the seed,
//! the epoch, the step and the ring (rank, world size), so any process can recompute them
//! and a resumed run replays exactly the same data order.
//!
//! Per epoch the train split's row groups (the sharding unit) are permuted by
//! `(seed, epoch)` and dealt round-robin to the ranks; each rank reads only its row
//! groups, shuffles their scenes by `(seed, epoch, rank, world)`, and takes `B/W` scenes
//! per step (the remainder of `B` goes to the first ranks). An epoch has as many steps as
//! the rank with the fewest batches allows, so every rank takes every step. A split with
//! fewer row groups than ranks is dealt in pieces: each row group cut into
//! `⌈world / groups⌉` contiguous scene ranges.

use crate::error::{Result, TrainError};
use osrt_dataset::RowGroupRef;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use std::ops::Range;

/// What the RNG of a purpose is for; part of the derivation so streams never overlap.
#[derive(Debug, Clone, Copy)]
#[repr(u64)]
pub enum Stream {
    RowGroups = 1,
    SceneOrder = 2,
    Step = 3,
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

/// The RNG of one training step on one rank (ray sampling, input-view choice, slot noise).
pub fn step_rng(seed: u64, step: u64, rank: usize, world: usize) -> ChaCha8Rng {
    derive_rng(seed, Stream::Step, &[step, rank as u64, world as u64])
}

/// Scenes per step of each rank: `batch / world`, remainder to the first ranks.
pub fn local_batch_sizes(batch: usize, world: usize) -> Vec<usize> {
    (0..world)
        .map(|r| batch / world + usize::from(r < batch % world))
        .collect()
}

/// Scenes `rows` (indices within the group) of one row group.
#[derive(Debug, Clone, PartialEq)]
pub struct Piece {
    pub group: RowGroupRef,
    pub rows: Range<u64>,
}

impl Piece {
    fn len(&self) -> u64 {
        self.rows.end - self.rows.start
    }
}

/// The units dealt to ranks: whole row groups, or — with fewer groups than ranks — each
/// group cut into `⌈world / groups⌉` contiguous ranges of near-equal size.
fn pieces(all: &[RowGroupRef], world: usize) -> Vec<Piece> {
    let cuts = if all.is_empty() {
        1
    } else {
        world.div_ceil(all.len()) as u64
    };
    all.iter()
        .flat_map(|g| {
            let n = g.num_rows;
            (0..cuts).map(move |j| Piece {
                group: g.clone(),
                rows: j * n / cuts..(j + 1) * n / cuts,
            })
        })
        .collect()
}

/// One rank's share of one epoch.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochPlan {
    pub epoch: u64,
    pub rank: usize,
    pub world: usize,
    /// This rank's pieces of row groups, in the order they are read.
    pub pieces: Vec<Piece>,
    /// Scenes this rank contributes to each step.
    pub local_batch: usize,
    /// Steps in the epoch (the same on every rank).
    pub steps: u64,
}

impl EpochPlan {
    pub fn new(
        all: &[RowGroupRef],
        seed: u64,
        epoch: u64,
        world: usize,
        rank: usize,
        batch: usize,
    ) -> Result<Self> {
        // Data that cannot be dealt is a configuration problem: no restart fixes it.
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
        let units = pieces(all, world);
        let mut order: Vec<usize> = (0..units.len()).collect();
        order.shuffle(&mut derive_rng(seed, Stream::RowGroups, &[epoch]));
        let sizes = local_batch_sizes(batch, world);
        let mut steps = u64::MAX;
        let mut mine = Vec::new();
        for (r, &size) in sizes.iter().enumerate() {
            let dealt: Vec<&Piece> = order
                .iter()
                .skip(r)
                .step_by(world)
                .map(|&i| &units[i])
                .collect();
            let rows: u64 = dealt.iter().map(|p| p.len()).sum();
            steps = steps.min(rows / size as u64);
            if r == rank {
                mine = dealt.into_iter().cloned().collect();
            }
        }
        if steps == 0 {
            return Err(bad(format!(
                "{} row groups cannot give each of {world} workers {} scenes per step: use fewer workers, a smaller batch or smaller row groups",
                all.len(),
                sizes[0]
            )));
        }
        Ok(Self {
            epoch,
            rank,
            world,
            pieces: mine,
            local_batch: sizes[rank],
            steps,
        })
    }

    /// Shuffled order of this rank's `n` scenes for the epoch.
    pub fn scene_order(&self, seed: u64, n: usize) -> Vec<usize> {
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut derive_rng(
            seed,
            Stream::SceneOrder,
            &[self.epoch, self.rank as u64, self.world as u64],
        ));
        order
    }
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
    fn ranks_partition_the_row_groups_reproducibly() {
        let all = groups(10, 32);
        for world in 1..=3 {
            let plans: Vec<EpochPlan> = (0..world)
                .map(|r| EpochPlan::new(&all, 7, 3, world, r, 6).unwrap())
                .collect();
            let mut seen: Vec<RowGroupRef> = plans
                .iter()
                .flat_map(|p| p.pieces.iter().map(|x| x.group.clone()))
                .collect();
            seen.sort_by(|a, b| (&a.file, a.index).cmp(&(&b.file, b.index)));
            let mut want = all.clone();
            want.sort_by(|a, b| (&a.file, a.index).cmp(&(&b.file, b.index)));
            assert_eq!(seen, want, "world {world}: every group exactly once");
            assert!(plans.iter().all(|p| p.steps == plans[0].steps));
            assert_eq!(plans.iter().map(|p| p.local_batch).sum::<usize>(), 6);
            // Same inputs, same plan.
            assert_eq!(plans[0], EpochPlan::new(&all, 7, 3, world, 0, 6).unwrap());
        }
        let a = EpochPlan::new(&all, 7, 3, 2, 0, 6).unwrap();
        let b = EpochPlan::new(&all, 7, 4, 2, 0, 6).unwrap();
        assert_ne!(a.pieces, b.pieces, "epochs reshuffle");
        assert!(a.pieces.iter().all(|p| p.rows == (0..32)), "whole groups");
    }

    /// 32 scenes in one row group train on 2 workers: each gets its own half.
    #[test]
    fn fewer_row_groups_than_workers_are_split_by_scene_ranges() {
        for (n, world, batch) in [(1, 2, 16), (1, 3, 6), (2, 3, 6)] {
            let all = groups(n, 32);
            let plans: Vec<EpochPlan> = (0..world)
                .map(|r| EpochPlan::new(&all, 0, 0, world, r, batch).unwrap())
                .collect();
            let mut covered: Vec<(usize, u64)> = plans
                .iter()
                .flat_map(|p| p.pieces.iter())
                .flat_map(|p| p.rows.clone().map(|r| (p.group.index, r)))
                .collect();
            covered.sort();
            let want: Vec<(usize, u64)> =
                (0..n).flat_map(|g| (0..32).map(move |r| (g, r))).collect();
            assert_eq!(
                covered, want,
                "{n} groups, {world} workers: every scene once"
            );
            assert!(plans.iter().all(|p| !p.pieces.is_empty()));
            assert!(plans[0].steps >= 1);
        }
    }

    #[test]
    fn too_small_data_or_batch_is_a_clear_error() {
        let e = EpochPlan::new(&groups(1, 4), 0, 0, 2, 0, 8)
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot give each of 2 workers"), "{e}");
        let e = EpochPlan::new(&groups(4, 4), 0, 0, 4, 0, 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("smaller than the 4 workers"), "{e}");
    }

    #[test]
    fn step_rngs_differ_by_step_rank_and_world() {
        use rand::Rng;
        let x = |s, r, w| step_rng(1, s, r, w).random::<u64>();
        assert_eq!(x(5, 0, 2), x(5, 0, 2));
        assert_ne!(x(5, 0, 2), x(6, 0, 2));
        assert_ne!(x(5, 0, 2), x(5, 1, 2));
        assert_ne!(x(5, 0, 2), x(5, 0, 1));
    }
}
