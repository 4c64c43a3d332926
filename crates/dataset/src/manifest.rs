//! The dataset manifest: a small JSON file beside the split folders that says what the
//! dataset holds, so tools can plan without opening Parquet files.

use crate::error::{DatasetError, Result};
use crate::schema::{ImageCodec, SCHEMA_VERSION};
use object_store::ObjectStoreExt;
use osrt_store::Location;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub const MANIFEST_FILE: &str = "manifest.json";

/// Counts of one split.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitInfo {
    pub scenes: u64,
    pub files: u64,
    pub row_groups: u64,
    pub views: u64,
}

/// How the dataset was made (absent for imported data).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GeneratorInfo {
    pub preset: String,
    pub seed: u64,
    /// The resolved generator settings, for reproduction.
    pub settings: serde_json::Value,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub schema_version: u32,
    /// `[width, height]` of every image.
    pub image_size: [u32; 2],
    /// Fewest and most views per scene.
    pub views_per_scene: [u32; 2],
    /// Fewest and most objects per scene.
    pub objects_per_scene: [u32; 2],
    pub has_masks: bool,
    /// How images and masks are stored (absent: raw).
    #[serde(default, skip_serializing_if = "ImageCodec::is_raw")]
    pub image_codec: ImageCodec,
    pub generator: Option<GeneratorInfo>,
    pub splits: BTreeMap<String, SplitInfo>,
    /// `[min, max]` corners of an axis-aligned box, in world coordinates, that holds
    /// everything a ray can meet besides the background (objects and the floor beneath
    /// them): what a volumetric decoder samples. Absent: unknown (generated datasets
    /// from before it was recorded derive it from their generator settings).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_bounds: Option<[[f32; 3]; 2]>,
}

impl Manifest {
    pub fn new(image_size: [u32; 2], views: [u32; 2], objects: [u32; 2]) -> Self {
        Self {
            schema_version: ImageCodec::Raw.schema_version(),
            image_size,
            views_per_scene: views,
            objects_per_scene: objects,
            has_masks: true,
            image_codec: ImageCodec::Raw,
            generator: None,
            splits: BTreeMap::new(),
            scene_bounds: None,
        }
    }

    /// The manifest of a dataset stored in `codec`.
    pub fn with_codec(mut self, codec: ImageCodec) -> Self {
        self.image_codec = codec;
        self.schema_version = codec.schema_version();
        self
    }

    /// The scene box: recorded, or derived from the generator's settings.
    pub fn scene_bounds(&self) -> Option<[[f32; 3]; 2]> {
        self.scene_bounds.or_else(|| {
            let g = self.generator.as_ref()?;
            let cfg: crate::generator::GeneratorConfig =
                serde_json::from_value(g.settings.clone()).ok()?;
            Some(cfg.scene_bounds())
        })
    }

    pub async fn write(&self, dataset: &Location) -> Result<()> {
        let path = dataset.path(MANIFEST_FILE);
        let json = serde_json::to_vec_pretty(self).expect("manifest serialises");
        dataset
            .store
            .put(&path, json.into())
            .await
            .map_err(|e| DatasetError::store(dataset.describe(&path), e))?;
        Ok(())
    }

    /// Reads and checks `manifest.json` of a dataset.
    pub async fn read(dataset: &Location) -> Result<Self> {
        let path = dataset.path(MANIFEST_FILE);
        let shown = dataset.describe(&path);
        let bytes = dataset
            .store
            .get(&path)
            .await
            .map_err(|e| DatasetError::store(&shown, e))?
            .bytes()
            .await
            .map_err(|e| DatasetError::store(&shown, e))?;
        let m: Manifest = serde_json::from_slice(&bytes).map_err(|e| DatasetError::Manifest {
            path: shown.clone(),
            reason: e.to_string(),
        })?;
        if !(1..=SCHEMA_VERSION).contains(&m.schema_version) {
            return Err(DatasetError::Manifest {
                path: shown,
                reason: format!(
                    "schema version {}, this build reads version {SCHEMA_VERSION}",
                    m.schema_version
                ),
            });
        }
        Ok(m)
    }
}
