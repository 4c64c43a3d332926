//! Throughput of the data path, for `osrt bench data`: scenes generated per second, and
//! scenes read and decoded per second with and without masks (plus the bytes fetched,
//! which shows what projection saves).

use osrt_dataset::generator::{GeneratorConfig, generate_scene};
use osrt_dataset::{
    Columns, ImageCodec, ReadStats, Result, Scene, SplitReader, SplitWriter, WriterOptions,
};
use osrt_store::Location;
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
    /// Rows kept of each square render (`image_size` wide), centred: 240 of 320 gives
    /// CLEVR-3D's 320×240.
    pub image_height: u32,
    pub codec: ImageCodec,
    pub scenes: usize,
    /// Views over all scenes.
    pub views: usize,
    pub threads: usize,
    pub generate_scenes_per_s: f64,
    pub write_scenes_per_s: f64,
    pub file_bytes: u64,
    pub read_with_masks: ReadFigures,
    pub read_without_masks: ReadFigures,
}

/// The middle `height` rows of a scene's square views (camera intrinsics follow).
fn crop_rows(mut scene: Scene, height: u32) -> Scene {
    for v in &mut scene.views {
        if height >= v.height {
            continue;
        }
        let top = ((v.height - height) / 2) as usize;
        let w = v.width as usize;
        v.image = v.image[top * w * 3..(top + height as usize) * w * 3].to_vec();
        if let Some(m) = &mut v.mask {
            *m = m[top * w..(top + height as usize) * w].to_vec();
        }
        v.camera.intrinsics.cy -= top as f32;
        v.height = height;
    }
    scene
}

/// Generates `scenes` scenes (cropped to `height` rows), writes them to `store` (a
/// scratch location) with `codec`, then reads the split back `repeats` times each way.
/// Reported figures are medians.
pub async fn bench_data(
    cfg: &GeneratorConfig,
    scenes: usize,
    repeats: usize,
    store: Location,
    (codec, height): (ImageCodec, Option<u32>),
) -> Result<DataBench> {
    let t = Instant::now();
    let cfg2 = cfg.clone();
    let height = height.unwrap_or(cfg.image_size).min(cfg.image_size);
    let generated = tokio::task::spawn_blocking(move || {
        (0..scenes as u64)
            .into_par_iter()
            .map(|i| generate_scene(&cfg2, 0, "bench", i).map(|s| crop_rows(s, height)))
            .collect::<Result<Vec<_>>>()
    })
    .await
    .expect("generator task")?;
    let gen_s = t.elapsed().as_secs_f64();
    let views = generated.iter().map(|s| s.views.len()).sum();

    let t = Instant::now();
    let opts = WriterOptions {
        codec,
        ..WriterOptions::default()
    };
    let mut w = SplitWriter::new(store.clone(), opts);
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
        let m = crate::median(times);
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
        image_height: height,
        codec,
        scenes,
        views,
        threads: rayon::current_num_threads(),
        generate_scenes_per_s: scenes as f64 / gen_s,
        write_scenes_per_s: scenes as f64 / write_s,
        file_bytes,
        read_with_masks: with,
        read_without_masks: without,
    })
}
