//! Reads splits back: list the files and row groups of a split (the sharding unit), and
//! decode one row group with only the requested columns. Every file is checked for our
//! schema and version before anything is decoded, and every error names the file.

use crate::error::{DatasetError, Result};
use crate::scene::Scene;
use crate::schema::{
    Columns, ImageCodec, batch_to_scenes_with, check_schema, check_version, projection,
};
use bytes::Bytes;
use futures::future::BoxFuture;
use futures::{FutureExt, TryStreamExt};
use object_store::path::Path;
use object_store::{GetOptions, GetRange, ObjectStore, ObjectStoreExt};
use osrt_store::Location;
use parquet::arrow::ParquetRecordBatchStreamBuilder;
use parquet::arrow::arrow_reader::{ArrowReaderOptions, RowSelection, RowSelector};
use parquet::arrow::async_reader::{AsyncFileReader, MetadataSuffixFetch};
use parquet::errors::ParquetError;
use parquet::file::metadata::{ParquetMetaData, ParquetMetaDataReader};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// One row group of one file: the unit of sharding.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct RowGroupRef {
    /// File name inside the split folder (`part-00000.parquet`).
    pub file: String,
    pub index: usize,
    pub num_rows: u64,
}

/// The selection of `rows` (increasing) among a row group's `total`: runs of rows
/// skipped and selected.
fn selection(rows: &[u64], total: u64) -> RowSelection {
    let mut runs = Vec::new();
    let mut at = 0;
    for &r in rows {
        if r > at {
            runs.push(RowSelector::skip((r - at) as usize));
        }
        runs.push(RowSelector::select(1));
        at = r + 1;
    }
    if total > at {
        runs.push(RowSelector::skip((total - at) as usize));
    }
    RowSelection::from(runs)
}

/// Rows decoded per Arrow batch: a row group's declared size never sizes an allocation.
const MAX_BATCH_ROWS: u64 = 1024;

/// A Parquet file of a split, with its size.
#[derive(Debug, Clone)]
pub struct SplitFile {
    pub name: String,
    pub size: u64,
}

/// Bytes of data pages fetched from the store (footers excluded): how we prove that
/// projection really skips columns.
#[derive(Debug, Default)]
pub struct ReadStats {
    pub data_bytes: AtomicU64,
}

impl ReadStats {
    pub fn bytes(&self) -> u64 {
        self.data_bytes.load(Ordering::Relaxed)
    }
}

fn external(e: object_store::Error) -> ParquetError {
    ParquetError::External(Box::new(e))
}

/// Parquet's async reader over an object store, counting the bytes of every data range it
/// fetches (the footer is read by suffix and not counted).
struct StoreReader {
    store: Arc<dyn ObjectStore>,
    path: Path,
    stats: Arc<ReadStats>,
}

impl AsyncFileReader for StoreReader {
    fn get_bytes(&mut self, range: Range<u64>) -> BoxFuture<'_, parquet::errors::Result<Bytes>> {
        self.stats
            .data_bytes
            .fetch_add(range.end - range.start, Ordering::Relaxed);
        async move {
            self.store
                .get_range(&self.path, range)
                .await
                .map_err(external)
        }
        .boxed()
    }

    fn get_byte_ranges(
        &mut self,
        ranges: Vec<Range<u64>>,
    ) -> BoxFuture<'_, parquet::errors::Result<Vec<Bytes>>> {
        let n: u64 = ranges.iter().map(|r| r.end - r.start).sum();
        self.stats.data_bytes.fetch_add(n, Ordering::Relaxed);
        async move {
            self.store
                .get_ranges(&self.path, &ranges)
                .await
                .map_err(external)
        }
        .boxed()
    }

    fn get_metadata<'a>(
        &'a mut self,
        options: Option<&'a ArrowReaderOptions>,
    ) -> BoxFuture<'a, parquet::errors::Result<Arc<ParquetMetaData>>> {
        async move {
            let metadata = ParquetMetaDataReader::new()
                .with_arrow_reader_options(options)
                .load_via_suffix_and_finish(self)
                .await?;
            Ok(Arc::new(metadata))
        }
        .boxed()
    }
}

impl MetadataSuffixFetch for &mut StoreReader {
    fn fetch_suffix(&mut self, suffix: usize) -> BoxFuture<'_, parquet::errors::Result<Bytes>> {
        let options = GetOptions {
            range: Some(GetRange::Suffix(suffix as u64)),
            ..Default::default()
        };
        async move {
            let resp = self
                .store
                .get_opts(&self.path, options)
                .await
                .map_err(external)?;
            resp.bytes().await.map_err(external)
        }
        .boxed()
    }
}

/// A split folder (`DATASET/train`, …) opened for reading.
#[derive(Debug, Clone)]
pub struct SplitReader {
    pub split: Location,
    files: Vec<SplitFile>,
}

impl SplitReader {
    /// Lists `*.parquet` files of the split, sorted by name. An empty folder is an error.
    pub async fn open(split: Location) -> Result<Self> {
        let mut files: Vec<SplitFile> = split
            .store
            .list(Some(&split.prefix))
            .map_err(|e| DatasetError::store(&split.display, e))
            .try_filter_map(|meta| {
                let name = meta.location.filename().unwrap_or_default().to_string();
                let direct =
                    meta.location.prefix_match(&split.prefix).map(|p| p.count()) == Some(1);
                futures::future::ok((direct && name.ends_with(".parquet")).then_some(SplitFile {
                    name,
                    size: meta.size,
                }))
            })
            .try_collect()
            .await?;
        files.sort_by(|a, b| a.name.cmp(&b.name));
        if files.is_empty() {
            return Err(DatasetError::EmptySplit {
                path: split.display.clone(),
            });
        }
        Ok(Self { split, files })
    }

    pub fn files(&self) -> &[SplitFile] {
        &self.files
    }

    fn file(&self, name: &str) -> Result<&SplitFile> {
        self.files.iter().find(|f| f.name == name).ok_or_else(|| {
            DatasetError::schema(
                self.split.describe(&self.split.path(name)),
                "no such file in the split",
            )
        })
    }

    async fn builder(
        &self,
        file: &SplitFile,
        stats: Arc<ReadStats>,
    ) -> Result<(ParquetRecordBatchStreamBuilder<StoreReader>, ImageCodec)> {
        let shown = self.split.describe(&self.split.path(&file.name));
        let reader = StoreReader {
            store: self.split.store.clone(),
            path: self.split.path(&file.name),
            stats,
        };
        let builder = ParquetRecordBatchStreamBuilder::new(reader)
            .await
            .map_err(|e| DatasetError::parquet(&shown, e))?;
        let codec = check_version(
            &shown,
            builder.metadata().file_metadata().key_value_metadata(),
        )?;
        check_schema(&shown, builder.schema())?;
        Ok((builder, codec))
    }

    /// Every row group of every file, in file then row-group order. Reads footers only.
    pub async fn row_groups(&self) -> Result<Vec<RowGroupRef>> {
        let mut out = Vec::new();
        for f in &self.files {
            let (b, _) = self.builder(f, Arc::default()).await?;
            for (index, rg) in b.metadata().row_groups().iter().enumerate() {
                // A footer is data like any other: a negative count, or more rows than the
                // file has bytes, is a damaged or crafted file, never an allocation size.
                let num_rows = u64::try_from(rg.num_rows())
                    .ok()
                    .filter(|&n| n <= f.size)
                    .ok_or_else(|| {
                        DatasetError::schema(
                            self.split.describe(&self.split.path(&f.name)),
                            format!(
                                "row group {index} declares {} rows in a file of {} bytes",
                                rg.num_rows(),
                                f.size
                            ),
                        )
                    })?;
                out.push(RowGroupRef {
                    file: f.name.clone(),
                    index,
                    num_rows,
                });
            }
        }
        if out.iter().all(|r| r.num_rows == 0) {
            return Err(DatasetError::EmptySplit {
                path: self.split.display.clone(),
            });
        }
        Ok(out)
    }

    /// Decodes one row group, projecting only `columns`; `stats` counts fetched bytes.
    pub async fn read_row_group_with_stats(
        &self,
        rg: &RowGroupRef,
        columns: Columns,
        stats: Arc<ReadStats>,
    ) -> Result<Vec<Scene>> {
        self.read(rg, None, columns, stats).await
    }

    pub async fn read_row_group(&self, rg: &RowGroupRef, columns: Columns) -> Result<Vec<Scene>> {
        self.read_row_group_with_stats(rg, columns, Arc::default())
            .await
    }

    /// Decodes only `rows` (indices within the row group, increasing) of one row group, in
    /// that order: a training rank takes its own scenes of a row group the ranks share,
    /// and the pictures of the others are never decoded.
    pub async fn read_rows(
        &self,
        rg: &RowGroupRef,
        rows: &[u64],
        columns: Columns,
    ) -> Result<Vec<Scene>> {
        self.read(rg, Some(rows), columns, Arc::default()).await
    }

    async fn read(
        &self,
        rg: &RowGroupRef,
        rows: Option<&[u64]>,
        columns: Columns,
        stats: Arc<ReadStats>,
    ) -> Result<Vec<Scene>> {
        let file = self.file(&rg.file)?;
        let shown = self.split.describe(&self.split.path(&file.name));
        let (builder, codec) = self.builder(file, stats).await?;
        let n = builder.metadata().num_row_groups();
        if rg.index >= n {
            return Err(DatasetError::schema(
                &shown,
                format!("row group {} requested, the file has {n}", rg.index),
            ));
        }
        let wanted = match rows {
            Some(rows) => {
                if !rows.windows(2).all(|w| w[0] < w[1]) || rows.last() >= Some(&rg.num_rows) {
                    return Err(DatasetError::schema(
                        &shown,
                        format!(
                            "rows of row group {} must increase and lie below its {} rows",
                            rg.index, rg.num_rows
                        ),
                    ));
                }
                rows.len() as u64
            }
            None => rg.num_rows,
        };
        let mask = projection(builder.parquet_schema(), columns);
        let mut builder = builder
            .with_row_groups(vec![rg.index])
            .with_projection(mask)
            .with_batch_size(wanted.clamp(1, MAX_BATCH_ROWS) as usize);
        if let Some(rows) = rows {
            builder = builder.with_row_selection(selection(rows, rg.num_rows));
        }
        let stream = builder
            .build()
            .map_err(|e| DatasetError::parquet(&shown, e))?;
        let batches: Vec<_> = stream
            .try_collect()
            .await
            .map_err(|e| DatasetError::parquet(&shown, e))?;
        let mut scenes = Vec::with_capacity(wanted.min(MAX_BATCH_ROWS) as usize);
        for b in &batches {
            scenes.extend(batch_to_scenes_with(b, &shown, codec)?);
        }
        if scenes.len() as u64 != wanted {
            // The listing and the file disagree (a file replaced since it was listed, or
            // a footer that lies): every rank's plan counted on the listed rows.
            return Err(DatasetError::schema(
                &shown,
                format!(
                    "row group {} was listed with {} scenes, {} decoded{}",
                    rg.index,
                    rg.num_rows,
                    scenes.len(),
                    match rows {
                        Some(_) => format!(" of {wanted} selected rows"),
                        None => String::new(),
                    }
                ),
            ));
        }
        Ok(scenes)
    }

    /// Decodes the whole split (small splits: validation, tests, inspection).
    pub async fn read_all(&self, columns: Columns) -> Result<Vec<Scene>> {
        let mut scenes = Vec::new();
        for rg in self.row_groups().await? {
            scenes.extend(self.read_row_group(&rg, columns).await?);
        }
        Ok(scenes)
    }
}
/// Reads a split of `dataset` into memory, at most `limit` scenes (whole row groups,
/// then truncated): validation and test scenes, renders, contact sheets. (Training shards
/// are read per epoch and rank, by row-group pieces.)
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
