//! One rank's scenes of an epoch, read window by window (`crate::shard`): the rows of
//! its slices in the window a step needs, read when first needed, and the next window's
//! read ahead in the background while the steps run. A window is dropped once no step
//! needs it, so a rank holds its share of at most three windows: the one in use, the
//! next where a step straddles the two (a window holds at least two batches), and the
//! one read ahead.

use crate::error::Result;
use crate::retry::{READ_RETRY_BUDGET, retry_transient};
use crate::shard::EpochPlan;
use osrt_dataset::{Columns, RowGroupRef, Scene, SplitReader};
use osrt_store::Location;
use std::collections::{BTreeMap, HashMap};
use std::ops::Range;
use std::sync::Arc;
use tokio::task::JoinHandle;

/// A window's scenes by their position in the epoch's sequence.
type Held = HashMap<usize, Scene>;

pub struct Feed {
    data: Location,
    groups: Arc<Vec<RowGroupRef>>,
    plan: Arc<EpochPlan>,
    /// This rank's positions within every step's global batch.
    share: Range<usize>,
    held: BTreeMap<usize, Held>,
    ahead: Option<(usize, JoinHandle<Result<Held>>)>,
}

impl Feed {
    pub fn new(
        data: Location,
        groups: Arc<Vec<RowGroupRef>>,
        plan: Arc<EpochPlan>,
        share: Range<usize>,
    ) -> Self {
        Self {
            data,
            groups,
            plan,
            share,
            held: BTreeMap::new(),
            ahead: None,
        }
    }

    pub fn plan(&self) -> &EpochPlan {
        &self.plan
    }

    /// Scenes of this rank's share of the epoch's step `k`, in batch order.
    pub async fn scenes(&mut self, k: u64) -> Result<Vec<&Scene>> {
        let positions = self.plan.positions(k, &self.share);
        let first = self.plan.window_of(positions.start);
        let last = self.plan.window_of(positions.end - 1);
        // Windows before this step's are done with.
        self.held.retain(|&w, _| w >= first);
        for w in first..=last {
            if !self.held.contains_key(&w) {
                let waited = std::time::Instant::now();
                let scenes = match self.ahead.take() {
                    Some((a, task)) if a == w => match task.await {
                        Ok(read) => read?,
                        Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
                        // Cancelled (only a dropped feed cancels): read it here.
                        Err(_) => self.read(w).await?,
                    },
                    other => {
                        if let Some((_, task)) = other {
                            task.abort();
                        }
                        self.read(w).await?
                    }
                };
                tracing::debug!(
                    window = w,
                    scenes = scenes.len(),
                    waited_s = waited.elapsed().as_secs_f64(),
                    "data window ready"
                );
                self.held.insert(w, scenes);
            }
        }
        let next = last + 1;
        if next < self.plan.windows.len() && self.ahead.is_none() {
            let (data, groups, plan, share) = (
                self.data.clone(),
                self.groups.clone(),
                self.plan.clone(),
                self.share.clone(),
            );
            self.ahead = Some((
                next,
                tokio::spawn(async move { read_window(&data, &groups, &plan, &share, next).await }),
            ));
        }
        Ok(positions
            .map(|p| &self.held[&self.plan.window_of(p)][&p])
            .collect())
    }

    async fn read(&self, w: usize) -> Result<Held> {
        read_window(&self.data, &self.groups, &self.plan, &self.share, w).await
    }
}

impl Drop for Feed {
    fn drop(&mut self) {
        if let Some((_, task)) = self.ahead.take() {
            task.abort();
        }
    }
}

/// Reads `share`'s scenes of window `w` (only those rows of each row group), retrying
/// what a store may fail transiently.
async fn read_window(
    data: &Location,
    groups: &[RowGroupRef],
    plan: &EpochPlan,
    share: &Range<usize>,
    w: usize,
) -> Result<Held> {
    // Positions by row group, rows increasing.
    let mut by_group: BTreeMap<usize, Vec<(u64, usize)>> = BTreeMap::new();
    for p in plan.share_in_window(w, share) {
        let s = plan.order[p];
        by_group.entry(s.group).or_default().push((s.row, p));
    }
    for rows in by_group.values_mut() {
        rows.sort_unstable();
    }
    let by_group = &by_group;
    retry_transient(
        "reading this rank's scenes",
        READ_RETRY_BUDGET,
        || async move {
            let reader = SplitReader::open(data.join("train")).await?;
            let mut held = Held::new();
            for (&g, rows) in by_group {
                let wanted: Vec<u64> = rows.iter().map(|&(r, _)| r).collect();
                let scenes = reader
                    .read_rows(&groups[g], &wanted, Columns::TRAIN)
                    .await?;
                held.extend(rows.iter().map(|&(_, p)| p).zip(scenes));
            }
            Ok(held)
        },
    )
    .await
}
