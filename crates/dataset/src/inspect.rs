//! `osrt data inspect`: what a dataset holds, and a contact sheet to look at it.

use crate::error::{DatasetError, Result};
use crate::manifest::Manifest;
use crate::reader::SplitReader;
use crate::scene::Scene;
use crate::schema::Columns;
use osrt_store::Location;
use serde::Serialize;
use std::collections::BTreeMap;

/// Counts of one split, read from the Parquet files themselves (not the manifest).
#[derive(Debug, Clone, Serialize)]
pub struct SplitReport {
    pub files: usize,
    pub bytes: u64,
    pub row_groups: usize,
    pub scenes: u64,
    /// `"WxH"` → number of views of that size.
    pub image_sizes: BTreeMap<String, u64>,
    /// views per scene → number of scenes.
    pub views_histogram: BTreeMap<usize, u64>,
    /// objects per scene → number of scenes (scenes without metadata or masks are absent).
    pub objects_histogram: BTreeMap<usize, u64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub location: String,
    pub manifest: Option<Manifest>,
    pub splits: BTreeMap<String, SplitReport>,
}

/// Reads every split found under the dataset (`train`, `val`, `test` and any the manifest
/// names). Object metadata is decoded, masks are not.
pub async fn inspect(dataset: &Location) -> Result<Report> {
    let manifest = match Manifest::read(dataset).await {
        Ok(m) => Some(m),
        Err(DatasetError::Store {
            source: object_store::Error::NotFound { .. },
            ..
        }) => None,
        Err(e) => return Err(e),
    };
    let mut names: Vec<String> = ["train", "val", "test"].map(String::from).to_vec();
    if let Some(m) = &manifest {
        names.extend(
            m.splits
                .keys()
                .filter(|k| !names.contains(k))
                .cloned()
                .collect::<Vec<_>>(),
        );
    }
    let mut splits = BTreeMap::new();
    for name in names {
        let reader = match SplitReader::open(dataset.join(&name)).await {
            Ok(r) => r,
            Err(DatasetError::EmptySplit { .. }) => continue,
            Err(e) => return Err(e),
        };
        let rgs = reader.row_groups().await?;
        let mut rep = SplitReport {
            files: reader.files().len(),
            bytes: reader.files().iter().map(|f| f.size).sum(),
            row_groups: rgs.len(),
            scenes: 0,
            image_sizes: BTreeMap::new(),
            views_histogram: BTreeMap::new(),
            objects_histogram: BTreeMap::new(),
        };
        let cols = Columns {
            masks: false,
            objects: true,
        };
        for rg in &rgs {
            for s in reader.read_row_group(rg, cols).await? {
                rep.scenes += 1;
                *rep.views_histogram.entry(s.views.len()).or_default() += 1;
                for v in &s.views {
                    *rep.image_sizes
                        .entry(format!("{}x{}", v.width, v.height))
                        .or_default() += 1;
                }
                if let Some(n) = s.num_objects() {
                    *rep.objects_histogram.entry(n).or_default() += 1;
                }
            }
        }
        splits.insert(name, rep);
    }
    if splits.is_empty() {
        return Err(DatasetError::EmptySplit {
            path: format!("{} (no split folder holds any scene)", dataset.display),
        });
    }
    Ok(Report {
        location: dataset.display.clone(),
        manifest,
        splits,
    })
}

/// A contact sheet: one row per scene, its views followed by their coloured masks.
/// Views of other sizes than the first are skipped. Returns an RGB8 image.
pub fn contact_sheet(scenes: &[Scene]) -> Result<image::RgbImage> {
    let first = scenes
        .first()
        .and_then(|s| s.views.first())
        .ok_or_else(|| DatasetError::Image {
            path: "contact sheet".into(),
            reason: "no scenes to draw".into(),
        })?;
    let (w, h) = (first.width, first.height);
    let cols = scenes.iter().map(|s| s.views.len() * 2).max().unwrap_or(1) as u32;
    let pad = 2;
    let mut sheet = image::RgbImage::from_pixel(
        cols * (w + pad) + pad,
        scenes.len() as u32 * (h + pad) + pad,
        image::Rgb([255, 255, 255]),
    );
    for (row, s) in scenes.iter().enumerate() {
        let views: Vec<_> = s
            .views
            .iter()
            .filter(|v| v.width == w && v.height == h)
            .collect();
        for (i, v) in views.iter().enumerate() {
            let y0 = pad + row as u32 * (h + pad);
            let xi = pad + i as u32 * (w + pad);
            let xm = pad + (views.len() + i) as u32 * (w + pad);
            for y in 0..h {
                for x in 0..w {
                    sheet.put_pixel(xi + x, y0 + y, image::Rgb(v.rgb(x, y)));
                    if let Some(m) = &v.mask {
                        let id = m[(y * w + x) as usize];
                        sheet.put_pixel(
                            xm + x,
                            y0 + y,
                            image::Rgb(crate::palette::instance_colour(id)),
                        );
                    }
                }
            }
        }
    }
    Ok(sheet)
}
