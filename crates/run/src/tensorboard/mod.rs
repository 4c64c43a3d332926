//! TensorBoard event files in `RUN/tb/`, written by the coordinator from the records it
//! persists in `metrics.jsonl`, so TensorBoard (or anything reading its format) follows a
//! job while it runs, from wherever the run folder can be read.
//!
//! An event file is a TFRecord file (the framing `osrt_dataset::import::tfrecord` reads)
//! of `tensorflow.Event` messages (`proto/tensorflow/event.proto`): a `file_version`
//! event, then one event per record with its figures as scalar summaries and, for an
//! evaluation, the pictures rank 0 left in `RUN/eval/` as image summaries.
//!
//! One value per tag and step: records can be dropped after they were written (a
//! generation that ended after its last checkpoint is replayed, a restarted coordinator
//! resumes from its checkpoint), and then the events past the kept step are cut out. A
//! file whose content changes other than by growing is written under a new name, later in
//! name order, and the old one deleted: TensorBoard reads a folder's files in name order
//! and follows the newest as it grows, so it never reads a file that shrank under it.
//!
//! Names are `events.out.tfevents.<µs since the epoch, 16 digits>.osrt`, always later
//! than every name already there; files of other names are left alone.
//!
//! The TFRecord framing is in `frames`; the records' figures as summaries in `summaries`.

use crate::{Result, RunError};
use frames::{frame, malformed};
use object_store::{ObjectStore, ObjectStoreExt};
use osrt_store::Location;
use prost::Message;

mod frames;
mod summaries;

pub use frames::{BadRecord, read_events, scan_events};
pub use summaries::{image, scalars};

/// TensorBoard's messages (`proto/tensorflow/event.proto`).
pub mod proto {
    include!(concat!(env!("OUT_DIR"), "/tensorflow.rs"));
}
use proto::{Event, Summary, event, summary};

/// The event folder in the run folder.
pub const TB_DIR: &str = "tb";
/// The file version TensorBoard expects in a file's first event.
const FILE_VERSION: &str = "brain.Event:2";
const NAME_PREFIX: &str = "events.out.tfevents.";
const NAME_SUFFIX: &str = ".osrt";
/// A file is closed and a new one begun past this size: a rewrite (object stores write
/// the open file whole at every flush) stays small.
const ROLL_BYTES: usize = 16 << 20;

/// Where rank 0 leaves the picture `name` of the validation at `step`, in the run folder.
pub fn eval_picture(step: u64, name: &str) -> String {
    format!("eval/step-{step:09}/{name}.png")
}

/// The pictures an evaluation may leave, in the order they are shown.
pub const EVAL_PICTURES: [&str; 2] = ["render", "segmentation"];

/// The step of an event that carries data (`None` for the file-version event).
fn data_step(e: &Event) -> Option<u64> {
    matches!(e.what, Some(event::What::Summary(_))).then_some(e.step.max(0) as u64)
}

/// The file being appended to: its bytes are kept, so a store that cannot append gets it
/// whole, and a cut needs no read.
struct Open {
    /// Empty until first written.
    name: String,
    bytes: Vec<u8>,
    /// `(step, end offset)` of each data event, in order.
    steps: Vec<(u64, usize)>,
    /// Bytes the store holds (a prefix of `bytes`); `None`: it must be written whole.
    stored: Option<usize>,
}

/// The writer of `RUN/tb/`. Only the coordinator holding the run folder's lease writes
/// there.
pub struct EventLog {
    dir: Location,
    /// Appends in place (a local run folder); otherwise the open file is put whole.
    can_append: bool,
    /// Our files in name order, each with its last data step where known (`None`: not
    /// read, or it holds none).
    files: Vec<(String, Option<u64>)>,
    open: Option<Open>,
    /// A cut the next flush makes first.
    cut: Option<Option<u64>>,
    /// Files replaced by a cut, deleted once their replacement is written.
    to_delete: Vec<String>,
    /// The files [`EventLog::open`] read that end in a frame it could not read.
    damaged: Vec<RunError>,
}

impl EventLog {
    /// The event folder of `run`, and the last step it holds events of.
    pub async fn open(run: &Location, can_append: bool) -> Result<(Self, Option<u64>)> {
        let dir = run.join(TB_DIR);
        let mut files: Vec<(String, Option<u64>)> =
            list(&dir).await?.into_iter().map(|n| (n, None)).collect();
        let mut log = Self {
            dir,
            can_append,
            files: Vec::new(),
            open: None,
            cut: None,
            to_delete: Vec::new(),
            damaged: Vec::new(),
        };
        let mut last = None;
        for i in (0..files.len()).rev() {
            let (events, bad) = scan_events(&log.get(&files[i].0).await?);
            if let Some(bad) = bad {
                // Its whole frames count; new events go to a file of their own, and a cut
                // that reaches it writes its readable part again without the rest.
                let e = malformed(&log.dir.describe(&log.dir.path(&files[i].0)), &bad);
                tracing::warn!(error = %e, "an event file is damaged: events go to a new file");
                log.damaged.push(e);
            }
            if let Some(s) = events.iter().rev().find_map(|(e, _)| data_step(e)) {
                files[i].1 = Some(s);
                last = Some(s);
                break;
            }
        }
        log.files = files;
        Ok((log, last))
    }

    /// The files [`EventLog::open`] found damaged (a torn or malformed frame), each an
    /// error naming the file: their readable events count, new ones go to a new file.
    pub fn damaged(&self) -> &[RunError] {
        &self.damaged
    }

    /// Cuts out every event past `keep` (all of them for `None`): at once from the open
    /// file, from the closed files at the next [`EventLog::flush`] (before anything
    /// added after this call is written).
    pub fn cut_after(&mut self, keep: Option<u64>) {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        if let Some(open) = &mut self.open
            && let Some(at) = open.steps.iter().position(|&(s, _)| past(s))
        {
            let end = match at {
                0 => header_len(&open.bytes),
                i => open.steps[i - 1].1,
            };
            open.steps.truncate(at);
            open.bytes.truncate(end);
            // Changed other than by growing: written whole under a new name.
            let old = std::mem::take(&mut open.name);
            if !old.is_empty() {
                self.to_delete.push(old);
            }
            open.stored = None;
            if open.steps.is_empty() {
                self.open = None;
            } else {
                // Every closed file ends before the open one's kept steps.
                return;
            }
        }
        self.cut = Some(match self.cut {
            Some(earlier) => earlier.min(keep),
            None => keep,
        });
    }

    /// The closed files' part of a cut. Retried after a failure: a kept part is put under
    /// a new name before its file is listed for deletion.
    async fn apply_cut(&mut self, keep: Option<u64>) -> Result<()> {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        // Closed files, newest first, until one ends at or before `keep`: at most one
        // keeps a part. A torn tail (a write cut short) goes as well.
        let mut i = self.files.len();
        while i > 0 {
            i -= 1;
            let (name, last) = self.files[i].clone();
            if last.is_some_and(|l| !past(l)) {
                break;
            }
            let bytes = self.get(&name).await?;
            let (events, _) = scan_events(&bytes);
            let kept: Vec<&Event> = events
                .iter()
                .map(|(e, _)| e)
                .filter(|e| data_step(e).is_none_or(|s| !past(s)))
                .collect();
            let kept_last = kept.iter().rev().find_map(|e| data_step(e));
            let intact =
                kept.len() == events.len() && events.last().map_or(0, |l| l.1) == bytes.len();
            if intact {
                self.files[i].1 = kept_last;
                if kept_last.is_some() {
                    break;
                }
                continue;
            }
            self.files.remove(i);
            if let Some(last) = kept_last {
                let mut out = Vec::new();
                for e in kept {
                    frame(&e.encode_to_vec(), &mut out);
                }
                let renamed = self.next_name();
                if let Err(e) = self.put(&renamed, out).await {
                    self.files.insert(i, (name, last_unknown()));
                    return Err(e);
                }
                self.files.push((renamed, Some(last)));
                self.to_delete.push(name);
                break;
            }
            self.to_delete.push(name);
        }
        Ok(())
    }

    /// Adds the event of `values` at `step` (written at the next [`EventLog::flush`]).
    pub fn add(&mut self, step: u64, wall_time: f64, values: Vec<summary::Value>) {
        if values.is_empty() {
            return;
        }
        if self.open.is_none() {
            let mut bytes = Vec::new();
            let version = Event {
                wall_time,
                step: 0,
                what: Some(event::What::FileVersion(FILE_VERSION.into())),
            };
            frame(&version.encode_to_vec(), &mut bytes);
            self.open = Some(Open {
                name: String::new(),
                bytes,
                steps: Vec::new(),
                stored: None,
            });
        }
        let open = self.open.as_mut().expect("open");
        let e = Event {
            wall_time,
            step: step.min(i64::MAX as u64) as i64,
            what: Some(event::What::Summary(Summary { value: values })),
        };
        frame(&e.encode_to_vec(), &mut open.bytes);
        open.steps.push((step, open.bytes.len()));
    }

    /// Whether a cut, events or deletions wait for a flush.
    pub fn is_dirty(&self) -> bool {
        self.cut.is_some()
            || !self.to_delete.is_empty()
            || self
                .open
                .as_ref()
                .is_some_and(|o| o.stored != Some(o.bytes.len()))
    }

    /// Writes what was added: appended to the local file (synced), or the open file put
    /// whole. After a failure the next flush writes the file whole.
    pub async fn flush(&mut self) -> Result<()> {
        if let Some(keep) = self.cut {
            self.apply_cut(keep).await?;
            self.cut = None;
        }
        self.write_open().await?;
        while let Some(name) = self.to_delete.last() {
            self.delete(name).await?;
            self.to_delete.pop();
        }
        Ok(())
    }

    async fn write_open(&mut self) -> Result<()> {
        if self.open.as_ref().is_some_and(|o| o.name.is_empty()) {
            // Named when first written: after every file a cut renamed.
            let name = self.next_name();
            self.open.as_mut().expect("open").name = name;
        }
        let Some(open) = self.open.as_mut() else {
            return Ok(());
        };
        if open.stored == Some(open.bytes.len()) {
            return Ok(());
        }
        let path = self.dir.path(&open.name);
        let local = self.dir.local_file(&path).filter(|_| self.can_append);
        let written = match (local, open.stored) {
            (Some(file), Some(from)) => {
                let tail = open.bytes[from..].to_vec();
                tokio::task::spawn_blocking(move || append(&file, &tail, from as u64))
                    .await
                    .map_err(|e| e.to_string())
                    .and_then(|r| r.map_err(|e| e.to_string()))
            }
            _ => self
                .dir
                .store
                .put(&path, open.bytes.clone().into())
                .await
                .map(|_| ())
                .map_err(|e| e.to_string()),
        };
        match written {
            Ok(()) => {
                open.stored = Some(open.bytes.len());
                if open.bytes.len() >= ROLL_BYTES {
                    let o = self.open.take().expect("open");
                    self.files.push((o.name, o.steps.last().map(|s| s.0)));
                }
                Ok(())
            }
            Err(reason) => {
                open.stored = None;
                Err(RunError::Run {
                    path: self.dir.describe(&path),
                    reason: format!("writing events: {reason}"),
                })
            }
        }
    }

    /// A name later than every name of ours there.
    fn next_name(&self) -> String {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_micros() as u64);
        let latest = self
            .files
            .iter()
            .map(|f| &f.0)
            .chain(
                self.open
                    .as_ref()
                    .map(|o| &o.name)
                    .filter(|n| !n.is_empty()),
            )
            .filter_map(|n| micros_of(n))
            .max();
        let t = latest.map_or(now, |l| now.max(l + 1));
        format!("{NAME_PREFIX}{t:016}{NAME_SUFFIX}")
    }

    async fn get(&self, name: &str) -> Result<bytes::Bytes> {
        let path = self.dir.path(name);
        let err = |e: object_store::Error| RunError::Run {
            path: self.dir.describe(&path),
            reason: format!("reading events: {e}"),
        };
        self.dir
            .store
            .get(&path)
            .await
            .map_err(err)?
            .bytes()
            .await
            .map_err(err)
    }

    async fn put(&self, name: &str, bytes: Vec<u8>) -> Result<()> {
        let path = self.dir.path(name);
        self.dir
            .store
            .put(&path, bytes.into())
            .await
            .map(|_| ())
            .map_err(|e| RunError::Run {
                path: self.dir.describe(&path),
                reason: format!("writing events: {e}"),
            })
    }

    async fn delete(&self, name: &str) -> Result<()> {
        let path = self.dir.path(name);
        match self.dir.store.delete(&path).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(RunError::Run {
                path: self.dir.describe(&path),
                reason: format!("deleting events: {e}"),
            }),
        }
    }
}

/// Bytes of a file before its first data event (its file-version event).
fn header_len(bytes: &[u8]) -> usize {
    scan_events(bytes)
        .0
        .first()
        .filter(|(e, _)| data_step(e).is_none())
        .map_or(0, |(_, end)| *end)
}

/// A closed file's last step, not known until it is read again.
fn last_unknown() -> Option<u64> {
    None
}

/// The µs in one of our file names.
fn micros_of(name: &str) -> Option<u64> {
    name.strip_prefix(NAME_PREFIX)?
        .strip_suffix(NAME_SUFFIX)?
        .parse()
        .ok()
}

/// Our event files in `dir`, in name order.
async fn list(dir: &Location) -> Result<Vec<String>> {
    use futures::TryStreamExt;
    let listed: Vec<_> = dir
        .store
        .list(Some(&dir.prefix))
        .try_collect()
        .await
        .map_err(|e| RunError::Run {
            path: dir.display.clone(),
            reason: format!("listing events: {e}"),
        })?;
    let mut names: Vec<String> = listed
        .into_iter()
        .filter_map(|m| m.location.filename().map(str::to_string))
        .filter(|n| micros_of(n).is_some())
        .collect();
    names.sort();
    Ok(names)
}

/// Writes `tail` at `at` of the local file `file` (created if missing) and syncs it: a
/// retry after a failed append overwrites what that one left.
fn append(file: &std::path::Path, tail: &[u8], at: u64) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    if let Some(dir) = file.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .write(true)
        .truncate(false)
        .open(file)?;
    f.set_len(at)?;
    f.seek(SeekFrom::Start(at))?;
    f.write_all(tail)?;
    f.sync_data()
}

#[cfg(test)]
mod tests;
