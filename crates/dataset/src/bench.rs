//! Throughput of the data path, for `osrt bench data`: scenes generated per second, and
//! scenes read and decoded per second with and without masks (plus the bytes fetched,
//! which shows what projection saves).

use crate::error::Result;
use crate::generator::{GeneratorConfig, generate_scene};
use crate::reader::{ReadStats, SplitReader};
use crate::schema::Columns;
use crate::store::Location;
use crate::writer::{SplitWriter, WriterOptions};
use rayon::prelude::*;
use serde::Serialize;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, Clone, Serialize)]
pub struct ReadFigures {
    pub scenes_per_s: f64,
    pub median_s: f64,
    pub data_bytes: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DataBench {
    pub preset: String,
    pub image_size: u32,
    pub scenes: usize,
    pub threads: usize,
    pub generate_scenes_per_s: f64,
    pub write_scenes_per_s: f64,
    pub file_bytes: u64,
    pub read_with_masks: ReadFigures,
    pub read_without_masks: ReadFigures,
}

/// Median of timings (upper median for even counts); shared by every benchmark.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Generates `scenes` scenes, writes them to `store` (a scratch location), then reads the
/// split back `repeats` times each way. Reported figures are medians.
pub async fn bench_data(
    cfg: &GeneratorConfig,
    scenes: usize,
    repeats: usize,
    store: Location,
) -> Result<DataBench> {
    let t = Instant::now();
    let cfg2 = cfg.clone();
    let generated = tokio::task::spawn_blocking(move || {
        (0..scenes as u64)
            .into_par_iter()
            .map(|i| generate_scene(&cfg2, 0, "bench", i))
            .collect::<Result<Vec<_>>>()
    })
    .await
    .expect("generator task")?;
    let gen_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut w = SplitWriter::new(store.clone(), WriterOptions::default());
    w.push(generated).await?;
    w.finish().await?;
    let write_s = t.elapsed().as_secs_f64();

    let reader = SplitReader::open(store).await?;
    let file_bytes = reader.files().iter().map(|f| f.size).sum();
    let rgs = reader.row_groups().await?;
    let mut figures = Vec::new();
    for cols in [
        Columns {
            masks: true,
            objects: false,
        },
        Columns::TRAIN,
    ] {
        let mut times = Vec::new();
        let mut bytes = 0;
        for _ in 0..repeats.max(1) {
            let stats = Arc::new(ReadStats::default());
            let t = Instant::now();
            let mut n = 0;
            for rg in &rgs {
                n += reader
                    .read_row_group_with_stats(rg, cols, stats.clone())
                    .await?
                    .len();
            }
            assert_eq!(n, scenes);
            times.push(t.elapsed().as_secs_f64());
            bytes = stats.bytes();
        }
        let m = median(times);
        figures.push(ReadFigures {
            scenes_per_s: scenes as f64 / m,
            median_s: m,
            data_bytes: bytes,
        });
    }
    let without = figures.pop().expect("two figures");
    let with = figures.pop().expect("two figures");
    Ok(DataBench {
        preset: cfg.preset.clone(),
        image_size: cfg.image_size,
        scenes,
        threads: rayon::current_num_threads(),
        generate_scenes_per_s: scenes as f64 / gen_s,
        write_scenes_per_s: scenes as f64 / write_s,
        file_bytes,
        read_with_masks: with,
        read_without_masks: without,
    })
}
