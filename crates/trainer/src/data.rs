//! Training data held in memory: a split decoded once (without masks), and an epoch
//! sampler that shuffles scene order with the job's seeded RNG.

use crate::error::Result;
use osrt_dataset::{Columns, Location, Scene, SplitReader};
use rand::Rng;
use rand::seq::SliceRandom;

/// Reads a split of `dataset`, at most `limit` scenes (whole row groups, then truncated).
pub async fn load_split(
    dataset: &Location,
    split: &str,
    columns: Columns,
    limit: Option<usize>,
) -> Result<Vec<Scene>> {
    let reader = SplitReader::open(dataset.join(split)).await?;
    let mut scenes = Vec::new();
    for rg in reader.row_groups().await? {
        if limit.is_some_and(|l| scenes.len() >= l) {
            break;
        }
        scenes.extend(reader.read_row_group(&rg, columns).await?);
    }
    if let Some(l) = limit {
        scenes.truncate(l);
    }
    Ok(scenes)
}

/// Draws batches without replacement within an epoch; reshuffles at each epoch start.
#[derive(Debug, Clone)]
pub struct EpochSampler {
    n: usize,
    order: Vec<usize>,
    pos: usize,
    pub epoch: u64,
}

impl EpochSampler {
    pub fn new(n: usize) -> Self {
        assert!(n > 0, "cannot sample from an empty split");
        Self {
            n,
            order: Vec::new(),
            pos: 0,
            epoch: 0,
        }
    }

    /// Indices of the next `batch` scenes; an epoch boundary inside a batch continues into
    /// the next permutation.
    pub fn next_batch(&mut self, batch: usize, rng: &mut impl Rng) -> Vec<usize> {
        let mut out = Vec::with_capacity(batch);
        while out.len() < batch {
            if self.pos >= self.order.len() {
                if !self.order.is_empty() {
                    self.epoch += 1;
                }
                self.order = (0..self.n).collect();
                self.order.shuffle(rng);
                self.pos = 0;
            }
            out.push(self.order[self.pos]);
            self.pos += 1;
        }
        out
    }
}
