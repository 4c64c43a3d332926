//! Writes a split as Parquet files through `object_store`: `part-00000.parquet`, … each
//! holding whole row groups of `scenes_per_row_group` scenes (the sharding unit).

use crate::error::{DatasetError, Result};
use crate::manifest::SplitInfo;
use crate::scene::Scene;
use crate::schema::{CODEC_KEY, ImageCodec, VERSION_KEY, arrow_schema, scenes_to_batch_with};
use object_store::buffered::BufWriter;
use osrt_store::Location;
use parquet::arrow::AsyncArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::{EnabledStatistics, WriterProperties};

#[derive(Debug, Clone, Copy)]
pub struct WriterOptions {
    /// Scenes per row group: the unit the coordinator assigns to workers.
    pub scenes_per_row_group: usize,
    /// Row groups per file; a new file starts when one is full.
    pub row_groups_per_file: usize,
    /// How images and masks are stored.
    pub codec: ImageCodec,
}

impl Default for WriterOptions {
    fn default() -> Self {
        Self {
            scenes_per_row_group: 32,
            row_groups_per_file: 32,
            codec: ImageCodec::Raw,
        }
    }
}

fn properties(rows: usize, codec: ImageCodec) -> WriterProperties {
    let version = codec.schema_version();
    let mut kv = vec![KeyValue::new(VERSION_KEY.to_string(), version.to_string())];
    if !codec.is_raw() {
        kv.push(KeyValue::new(CODEC_KEY.to_string(), codec.to_string()));
    }
    WriterProperties::builder()
        .set_compression(Compression::ZSTD(
            ZstdLevel::try_new(3).expect("valid level"),
        ))
        // Images and masks are high-entropy blobs: dictionaries and min/max statistics on
        // them only cost space.
        .set_dictionary_enabled(false)
        .set_statistics_enabled(EnabledStatistics::None)
        .set_max_row_group_row_count(Some(rows))
        // A fixed writer string keeps files byte-identical across builds of this version.
        .set_created_by(format!("osrt scene schema v{version}"))
        .set_key_value_metadata(Some(kv))
        .build()
}

/// Streams scenes into a split folder. Call [`SplitWriter::finish`] to close the last
/// file; an unfinished file is never visible (object_store completes the upload on close).
pub struct SplitWriter {
    split: Location,
    opts: WriterOptions,
    file_index: usize,
    current: Option<(AsyncArrowWriter<BufWriter>, usize)>,
    pending: Vec<Scene>,
    info: SplitInfo,
}

impl SplitWriter {
    pub fn new(split: Location, opts: WriterOptions) -> Self {
        assert!(opts.scenes_per_row_group > 0 && opts.row_groups_per_file > 0);
        Self {
            split,
            opts,
            file_index: 0,
            current: None,
            pending: Vec::new(),
            info: SplitInfo {
                scenes: 0,
                files: 0,
                row_groups: 0,
                views: 0,
            },
        }
    }

    /// Numbers this writer's files from `index` (`part-{index:05}.parquet`, …): parts of
    /// a split written one writer each.
    pub fn with_first_file(mut self, index: usize) -> Self {
        self.file_index = index;
        self
    }

    /// Validates and buffers scenes; full row groups are written out.
    pub async fn push(&mut self, scenes: Vec<Scene>) -> Result<()> {
        for s in &scenes {
            if s.views.is_empty() {
                return Err(DatasetError::InvalidScene {
                    path: self.split.display.clone(),
                    scene_id: s.id,
                    reason: "scene has no views".into(),
                });
            }
            for (view, v) in s.views.iter().enumerate() {
                v.validate().map_err(|reason| DatasetError::InvalidView {
                    path: self.split.display.clone(),
                    scene_id: s.id,
                    view,
                    reason,
                })?;
            }
        }
        self.pending.extend(scenes);
        while self.pending.len() >= self.opts.scenes_per_row_group {
            let rest = self.pending.split_off(self.opts.scenes_per_row_group);
            let group = std::mem::replace(&mut self.pending, rest);
            self.write_row_group(&group).await?;
        }
        Ok(())
    }

    async fn write_row_group(&mut self, scenes: &[Scene]) -> Result<()> {
        if self.current.is_none() {
            let name = format!("part-{:05}.parquet", self.file_index);
            let path = self.split.path(&name);
            let obj = BufWriter::new(self.split.store.clone(), path.clone());
            let w = AsyncArrowWriter::try_new(
                obj,
                arrow_schema(),
                Some(properties(self.opts.scenes_per_row_group, self.opts.codec)),
            )
            .map_err(|e| DatasetError::parquet(self.split.describe(&path), e))?;
            self.current = Some((w, 0));
            self.file_index += 1;
            self.info.files += 1;
        }
        let shown = self.split.display.clone();
        let (w, groups) = self.current.as_mut().expect("opened above");
        let batch = scenes_to_batch_with(scenes, self.opts.codec)?;
        w.write(&batch)
            .await
            .map_err(|e| DatasetError::parquet(&shown, e))?;
        w.flush()
            .await
            .map_err(|e| DatasetError::parquet(&shown, e))?;
        *groups += 1;
        self.info.row_groups += 1;
        self.info.scenes += scenes.len() as u64;
        self.info.views += scenes.iter().map(|s| s.views.len() as u64).sum::<u64>();
        if *groups >= self.opts.row_groups_per_file {
            self.close_file().await?;
        }
        Ok(())
    }

    async fn close_file(&mut self) -> Result<()> {
        if let Some((w, _)) = self.current.take() {
            w.close()
                .await
                .map_err(|e| DatasetError::parquet(&self.split.display, e))?;
        }
        Ok(())
    }

    /// Writes the last (possibly short) row group, closes the file, returns the counts.
    pub async fn finish(mut self) -> Result<SplitInfo> {
        if !self.pending.is_empty() {
            let group = std::mem::take(&mut self.pending);
            self.write_row_group(&group).await?;
        }
        self.close_file().await?;
        Ok(self.info)
    }
}
