//! A split read into memory (validation and test scenes; training shards are read per
//! epoch by the worker).

use crate::error::Result;
use osrt_dataset::{Columns, Location, Scene, SplitReader};

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
