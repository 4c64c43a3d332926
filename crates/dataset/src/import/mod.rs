//! Importers of the paper's datasets into the osrt layout (`manifest.json` and
//! `{train,val,test}/part-NNNNN.parquet`), so every other command works on them unchanged.
//! One file per source format: [`obsurf`] (CLEVR-3D and MSN-Easy, the ObSuRF release) and
//! [`kubric`] (MSN-Hard, TFDS TFRecord shards).
//!
//! The import streams: each split's scenes (by index range, filtered and limited) are cut
//! into parts of [`ImportOptions::scenes_per_part`] scenes, decoded in parallel over the
//! cores, and written as one Parquet file each. Memory holds one part (pixels, masks,
//! their PNGs and the decoders' buffers), whatever the dataset's size: peak resident
//! memory 265 MB at the default 64 scenes of 3 views of 320×240, 123 MB at 16 (`osrt data
//! import` of 400 noise-image scenes, 2026-11-26, 2-core Intel Xeon). A part file
//! becomes visible only when whole (object_store completes it on close), so an interrupted
//! import re-run with the same options keeps the finished parts and writes the rest;
//! `import.json` records the source and the options, and a re-run from another source or
//! with other options is refused.

pub mod kubric;
pub mod npy;
pub mod obsurf;
pub mod tfrecord;

use crate::codec::{check_decoded_bytes, image_error, image_limits};
use crate::error::{DatasetError, Result};
use crate::manifest::{Manifest, SplitInfo};
use crate::reader::SplitReader;
use crate::scene::Scene;
use crate::schema::ImageCodec;
use crate::writer::{SplitWriter, WriterOptions};
use object_store::ObjectStoreExt;
use osrt_store::Location;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::sync::Arc;

/// The file recording how a dataset was imported.
pub const IMPORT_FILE: &str = "import.json";

/// The source formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    /// ObSuRF's CLEVR-3D.
    Clevr3d,
    /// ObSuRF's MultiShapeNet-Easy.
    MsnEasy,
    /// Kubric's MultiShapeNet-Hard (TFDS TFRecord shards; splits are the shards').
    MsnHard,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "clevr3d" => Ok(Self::Clevr3d),
            "msn-easy" => Ok(Self::MsnEasy),
            "msn-hard" => Ok(Self::MsnHard),
            other => Err(format!(
                "unknown format `{other}`: expected clevr3d, msn-easy or msn-hard"
            )),
        }
    }
}

impl Format {
    /// The public loaders' splits by scene index (MSN-Hard: none; its shards are split).
    pub fn default_splits(self) -> Splits {
        match self {
            Self::MsnHard => Splits {
                train: 0..0,
                val: 0..0,
                test: 0..0,
            },
            Self::Clevr3d => Splits {
                train: 0..70_000,
                val: 70_000..75_000,
                test: 85_000..100_000,
            },
            Self::MsnEasy => Splits {
                train: 0..80_000,
                val: 80_000..80_500,
                test: 90_000..100_000,
            },
        }
    }
}

/// Scene-index ranges of the three splits.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Splits {
    pub train: Range<u64>,
    pub val: Range<u64>,
    pub test: Range<u64>,
}

impl Splits {
    fn named(&self) -> [(&'static str, Range<u64>); 3] {
        [
            ("train", self.train.clone()),
            ("val", self.val.clone()),
            ("test", self.test.clone()),
        ]
    }

    /// `train=A..B,val=C..D,test=E..F` over `base` (splits not named keep theirs).
    pub fn parse(text: &str, base: Splits) -> std::result::Result<Self, String> {
        let mut s = base;
        for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (name, range) = part
                .split_once('=')
                .ok_or_else(|| format!("`{part}`: expected SPLIT=A..B"))?;
            let (a, b) = range
                .split_once("..")
                .ok_or_else(|| format!("`{part}`: expected a range A..B"))?;
            let parse = |x: &str| {
                x.trim()
                    .parse::<u64>()
                    .map_err(|_| format!("`{part}`: `{x}` is not a scene index"))
            };
            let r = parse(a)?..parse(b)?;
            if r.start > r.end {
                return Err(format!("`{part}`: the range is reversed"));
            }
            match name.trim() {
                "train" => s.train = r,
                "val" => s.val = r,
                "test" => s.test = r,
                other => return Err(format!("unknown split `{other}`: train, val or test")),
            }
        }
        Ok(s)
    }
}

/// What to import and how.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImportOptions {
    /// The source folder as imported from (absolute): a re-run from another source into
    /// the same folder would mix the two datasets' parts. Empty in `import.json` files
    /// written before it was recorded (their source is then not compared).
    #[serde(default)]
    pub source: String,
    pub format: Format,
    pub splits: Splits,
    /// Scenes with more objects are left out, as the public loaders do.
    pub max_objects: Option<usize>,
    /// At most this many scenes per split (a sample).
    pub limit: Option<u64>,
    pub codec: ImageCodec,
    pub scenes_per_part: usize,
    pub scenes_per_row_group: usize,
    /// `[width, height]` the views are shrunk to (`--resize`), `None`: the release's size.
    #[serde(default)]
    pub resize: Option<[u32; 2]>,
}

impl ImportOptions {
    /// The format's defaults: its splits, PNG storage, parts of 64 scenes in row groups
    /// of 32; CLEVR-3D keeps scenes of at most 6 objects, as its loaders do.
    pub fn new(format: Format) -> Self {
        Self {
            source: String::new(),
            format,
            splits: format.default_splits(),
            max_objects: (format == Format::Clevr3d).then_some(6),
            limit: None,
            codec: ImageCodec::Png,
            scenes_per_part: 64,
            scenes_per_row_group: 32,
            resize: None,
        }
    }
}

/// A source dataset, scene by index.
pub trait Source: Send + Sync {
    /// Scenes in the source (indices `0..n`).
    fn num_scenes(&self) -> u64;
    /// Views and objects (where the metadata says) of scene `index`; no image is read.
    fn counts(&self, index: u64) -> (usize, Option<usize>);
    /// Scene `index` with its pixels, masks, cameras and objects.
    fn scene(&self, index: u64) -> Result<Scene>;
    /// Image `[width, height]` of the views.
    fn image_size(&self) -> Result<[u32; 2]>;
    /// Whether views carry instance masks.
    fn has_masks(&self) -> bool;
    /// Where view `view` of scene `index` comes from (a file, or a record of one), for
    /// errors.
    fn view_origin(&self, index: u64, view: usize) -> String;
}

/// A reader of the image file at `path`, its format guessed from its bytes, bounded by
/// [`crate::codec::MAX_IMAGE_BYTES`].
fn image_reader(
    path: &std::path::Path,
) -> std::result::Result<image::ImageReader<std::io::BufReader<std::fs::File>>, String> {
    let mut reader = image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| e.to_string())?;
    reader.limits(image_limits());
    Ok(reader)
}

/// Decodes the image file at `path` within the limit, streaming it from disk.
pub(crate) fn open_image(
    path: &std::path::Path,
) -> std::result::Result<image::DynamicImage, String> {
    image_reader(path)?.decode().map_err(image_error)
}

/// The `[width, height]` the image file at `path` declares, from its header alone. A
/// header announcing more than the limit is refused before its size is taken
/// for the dataset's: believed, it would make every well-formed view the odd one out.
pub(crate) fn image_dimensions(path: &std::path::Path) -> std::result::Result<[u32; 2], String> {
    use image::ImageDecoder;
    let decoder = image_reader(path)?.into_decoder().map_err(image_error)?;
    let (w, h) = decoder.dimensions();
    check_decoded_bytes(w, h, decoder.total_bytes())?;
    Ok([w, h])
}

/// Decodes a PNG held in memory within the limit.
pub(crate) fn decode_png(bytes: &[u8]) -> std::result::Result<image::DynamicImage, String> {
    crate::codec::decode_png(bytes, None).map_err(|e| e.to_string())
}

/// The scene indices of a split: its range within the source, filtered by object count,
/// at most `limit`.
fn split_indices(src: &dyn Source, range: &Range<u64>, opts: &ImportOptions) -> Vec<u64> {
    let end = range.end.min(src.num_scenes());
    (range.start.min(end)..end)
        .filter(|&i| {
            opts.max_objects
                .is_none_or(|m| src.counts(i).1.is_none_or(|n| n <= m))
        })
        .take(opts.limit.map_or(usize::MAX, |l| l as usize))
        .collect()
}

/// Refuses to continue an import made with other options; records these otherwise.
async fn claim(out: &Location, opts: &ImportOptions) -> Result<()> {
    let path = out.path(IMPORT_FILE);
    let shown = out.describe(&path);
    let mine = serde_json::to_vec_pretty(opts).expect("options serialise");
    match out.store.get(&path).await {
        Ok(r) => {
            let there = r
                .bytes()
                .await
                .map_err(|e| DatasetError::store(&shown, e))?;
            let theirs: Option<ImportOptions> = serde_json::from_slice(&there).ok();
            let reason = match theirs {
                Some(t) if t.source != opts.source && !t.source.is_empty() => format!(
                    "the folder holds an import from {}, not from {}: import into a new \
                     folder, or re-run from that source to finish it",
                    t.source, opts.source
                ),
                Some(t)
                    if t == ImportOptions {
                        source: t.source.clone(),
                        ..opts.clone()
                    } =>
                {
                    return Ok(());
                }
                _ => "the folder holds an import made with other options: import into a new \
                      folder, or re-run with the same options to finish it"
                    .into(),
            };
            Err(DatasetError::Import {
                path: shown,
                reason,
            })
        }
        Err(object_store::Error::NotFound { .. }) => out
            .store
            .put(&path, mine.into())
            .await
            .map(|_| ())
            .map_err(|e| DatasetError::store(&shown, e)),
        Err(e) => Err(DatasetError::store(&shown, e)),
    }
}

/// Imports `src` into `out`; `progress` shows scenes/s and the time left.
pub async fn import(
    src: Arc<dyn Source>,
    out: &Location,
    opts: &ImportOptions,
    progress: bool,
) -> Result<Manifest> {
    let size = src.image_size()?;
    if let Some(to) = opts.resize {
        crate::resize::check_target(size, to).map_err(|reason| DatasetError::Import {
            path: out.display.clone(),
            reason,
        })?;
    }
    claim(out, opts).await?;
    let resize = opts.resize;
    let per_part = opts.scenes_per_part.max(1);
    let splits: Vec<(&str, Vec<u64>)> = opts
        .splits
        .named()
        .into_iter()
        .map(|(name, r)| (name, split_indices(src.as_ref(), &r, opts)))
        .collect();
    let total: u64 = splits.iter().map(|s| s.1.len() as u64).sum();
    let bar = crate::generator::progress_bar(total, progress, "scenes");
    let (mut views, mut objects) = ([u32::MAX, 0], [u32::MAX, 0]);
    let mut manifest_splits = std::collections::BTreeMap::new();
    for (name, indices) in &splits {
        let loc = out.join(name);
        for &i in indices {
            let (v, o) = src.counts(i);
            views = [views[0].min(v as u32), views[1].max(v as u32)];
            if let Some(o) = o {
                objects = [objects[0].min(o as u32), objects[1].max(o as u32)];
            }
        }
        for (p, part) in indices.chunks(per_part).enumerate() {
            let file = format!("part-{p:05}.parquet");
            if loc.store.head(&loc.path(&file)).await.is_ok() {
                bar.inc(part.len() as u64);
                continue;
            }
            let (src, part) = (src.clone(), part.to_vec());
            let scenes: Vec<Scene> = tokio::task::spawn_blocking(move || {
                // Every scene's outcome, then the first error in scene order: a part
                // with several bad scenes names the same one however the threads ran.
                let decoded: Vec<Result<Scene>> = part
                    .par_iter()
                    .map(|&i| {
                        let scene = same_size(src.scene(i)?, src.as_ref(), i, size)?;
                        Ok(match resize {
                            Some(to) => crate::resize::resize_scene(scene, to),
                            None => scene,
                        })
                    })
                    .collect();
                decoded.into_iter().collect::<Result<Vec<_>>>()
            })
            .await
            .map_err(|e| DatasetError::Import {
                path: loc.display.clone(),
                reason: format!("decoding task: {e}"),
            })??;
            let n = scenes.len() as u64;
            let wopts = WriterOptions {
                scenes_per_row_group: opts.scenes_per_row_group.max(1),
                row_groups_per_file: per_part.div_ceil(opts.scenes_per_row_group.max(1)),
                codec: opts.codec,
            };
            let mut w = SplitWriter::new(loc.clone(), wopts).with_first_file(p);
            w.push(scenes).await?;
            w.finish().await?;
            bar.inc(n);
        }
        manifest_splits.insert(
            name.to_string(),
            split_info(&loc, indices, src.as_ref()).await?,
        );
    }
    bar.finish_and_clear();
    if total == 0 {
        return Err(DatasetError::Import {
            path: out.display.clone(),
            reason: "no scene falls in the split ranges (after the object-count filter)".into(),
        });
    }
    // Sources without object counts (MSN-Hard) record [0, 0].
    let objects = if objects[0] > objects[1] {
        [0, 0]
    } else {
        objects
    };
    let mut m = Manifest::new(resize.unwrap_or(size), views, objects).with_codec(opts.codec);
    m.has_masks = src.has_masks();
    m.splits = manifest_splits;
    m.write(out).await?;
    Ok(m)
}

/// `scene` (source index `i`) if every view has the dataset's `[width, height]`: a view
/// of another size is refused at import, not hours into training.
fn same_size(scene: Scene, src: &dyn Source, i: u64, size: [u32; 2]) -> Result<Scene> {
    for (v, view) in scene.views.iter().enumerate() {
        if [view.width, view.height] != size {
            return Err(DatasetError::Import {
                path: src.view_origin(i, v),
                reason: format!(
                    "scene {i}, view {v} is {}×{} pixels, the dataset's views are {}×{}",
                    view.width, view.height, size[0], size[1]
                ),
            });
        }
    }
    Ok(scene)
}

/// The counts of an imported split, from its files' footers.
async fn split_info(loc: &Location, indices: &[u64], src: &dyn Source) -> Result<SplitInfo> {
    if indices.is_empty() {
        return Ok(SplitInfo {
            scenes: 0,
            files: 0,
            row_groups: 0,
            views: 0,
        });
    }
    let reader = SplitReader::open(loc.clone()).await?;
    let groups = reader.row_groups().await?;
    Ok(SplitInfo {
        scenes: groups.iter().map(|g| g.num_rows).sum(),
        files: reader.files().len() as u64,
        row_groups: groups.len() as u64,
        views: indices.iter().map(|&i| src.counts(i).0 as u64).sum(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eight scenes, each failing with an error naming it; scene 0's comes last in time.
    struct Failing;

    impl Source for Failing {
        fn num_scenes(&self) -> u64 {
            8
        }
        fn counts(&self, _: u64) -> (usize, Option<usize>) {
            (1, Some(1))
        }
        fn scene(&self, index: u64) -> Result<Scene> {
            if index == 0 {
                std::thread::sleep(std::time::Duration::from_millis(300));
            }
            Err(DatasetError::Import {
                path: self.view_origin(index, 0),
                reason: "unreadable".into(),
            })
        }
        fn image_size(&self) -> Result<[u32; 2]> {
            Ok([4, 4])
        }
        fn has_masks(&self) -> bool {
            false
        }
        fn view_origin(&self, index: u64, _: usize) -> String {
            format!("scene-{index}.png")
        }
    }

    /// A part with several bad scenes names the first of them, whichever thread failed
    /// first: the error a user (or a test) sees does not depend on scheduling.
    #[tokio::test]
    async fn the_first_bad_scene_in_order_is_named_however_the_threads_ran() {
        let mut opts = ImportOptions::new(Format::Clevr3d);
        opts.splits = Splits::parse("train=0..8,val=0..0,test=0..0", opts.splits).unwrap();
        opts.scenes_per_part = 8;
        for run in 0..3 {
            let out = Location::parse(&format!("memory://order-{run}/ds")).unwrap();
            let e = import(Arc::new(Failing), &out, &opts, false)
                .await
                .unwrap_err()
                .to_string();
            assert_eq!(e, "import scene-0.png: unreadable", "run {run}");
        }
    }

    #[test]
    fn split_ranges_parse_over_the_defaults() {
        let base = Format::Clevr3d.default_splits();
        let s = Splits::parse("train=0..8, test=10..12", base.clone()).unwrap();
        assert_eq!((s.train, s.val, s.test), (0..8, base.val.clone(), 10..12));
        for bad in ["train=5", "dev=0..1", "val=3..1", "test=a..2"] {
            assert!(Splits::parse(bad, base.clone()).is_err(), "{bad}");
        }
        assert_eq!("msn-hard".parse::<Format>(), Ok(Format::MsnHard));
        assert!(
            "msn-medium"
                .parse::<Format>()
                .unwrap_err()
                .contains("msn-hard")
        );
    }
}
