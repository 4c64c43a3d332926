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

use crate::records::{MetricsRecord, TrainRecord};
use crate::{Result, RunError};
use object_store::{ObjectStore, ObjectStoreExt};
use osrt_store::Location;
use prost::Message;

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

/// TFRecord's checksum: CRC-32C (Castagnoli), rotated right by 15 bits plus a constant.
fn masked_crc(data: &[u8]) -> u32 {
    const CRC32C: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
    CRC32C
        .checksum(data)
        .rotate_right(15)
        .wrapping_add(0xa282_ead8)
}

/// One TFRecord frame around `payload`.
fn frame(payload: &[u8], out: &mut Vec<u8>) {
    let len = (payload.len() as u64).to_le_bytes();
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc(&len).to_le_bytes());
    out.extend_from_slice(payload);
    out.extend_from_slice(&masked_crc(payload).to_le_bytes());
}

/// Where and why an event file stops being readable.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadRecord {
    /// The offset of the frame that cannot be read.
    pub offset: usize,
    pub reason: String,
}

/// The events of an event file's bytes, each with the end offset of its frame, and the
/// frame reading stopped at (`None`: the bytes end with a whole frame). A torn frame (a
/// write cut short), a failed checksum or a payload that is no `Event` ends the read:
/// what follows cannot be framed. A frame's declared length is compared with the bytes
/// there before anything is sliced, so no length, however crafted, sizes an allocation
/// or reaches past the end.
pub fn scan_events(bytes: &[u8]) -> (Vec<(Event, usize)>, Option<BadRecord>) {
    let mut out = Vec::new();
    let mut at = 0usize;
    while at < bytes.len() {
        let rest = bytes.len() - at;
        let bad = |reason: String| Some(BadRecord { offset: at, reason });
        if rest < 12 {
            let reason = format!("a torn frame: {rest} bytes of its 12-byte header");
            return (out, bad(reason));
        }
        let head = &bytes[at..at + 12];
        let len = u64::from_le_bytes(head[..8].try_into().expect("8 bytes"));
        let crc = u32::from_le_bytes(head[8..].try_into().expect("4 bytes"));
        if masked_crc(&head[..8]) != crc {
            return (out, bad("the length's checksum does not match".into()));
        }
        // The header, the record, its 4-byte checksum.
        let fits = |l: &usize| rest.checked_sub(16).is_some_and(|room| *l <= room);
        let Some(len) = usize::try_from(len).ok().filter(fits) else {
            let reason = format!(
                "its header declares a record of {len} bytes and its 4-byte checksum, {} \
                 bytes follow",
                rest - 12
            );
            return (out, bad(reason));
        };
        let body = &bytes[at + 12..at + 12 + len];
        let tail = &bytes[at + 12 + len..at + 16 + len];
        if masked_crc(body).to_le_bytes() != tail {
            return (out, bad("the record's checksum does not match".into()));
        }
        match Event::decode(body) {
            Ok(e) => {
                at += 16 + len;
                out.push((e, at));
            }
            Err(e) => return (out, bad(format!("the record is no tensorflow.Event: {e}"))),
        }
    }
    (out, None)
}

/// The events of the event file `path` (as shown in errors) whose bytes are `bytes`,
/// each with the end offset of its frame; a file that is not whole frames throughout is
/// an error naming it.
pub fn read_events(path: &str, bytes: &[u8]) -> Result<Vec<(Event, usize)>> {
    match scan_events(bytes) {
        (events, None) => Ok(events),
        (_, Some(bad)) => Err(malformed(path, &bad)),
    }
}

fn malformed(path: &str, bad: &BadRecord) -> RunError {
    RunError::Run {
        path: path.to_string(),
        reason: format!(
            "event file unreadable from byte {}: {}",
            bad.offset, bad.reason
        ),
    }
}

fn scalar(tag: &str, v: f64) -> Option<summary::Value> {
    v.is_finite().then(|| summary::Value {
        tag: tag.into(),
        value: Some(summary::value::Value::SimpleValue(v as f32)),
    })
}

/// A PNG's size from its header (`None`: not a PNG).
fn png_size(png: &[u8]) -> Option<(i32, i32)> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    if png.len() < 24 || &png[..8] != SIGNATURE || &png[12..16] != b"IHDR" {
        return None;
    }
    let w = u32::from_be_bytes(png[16..20].try_into().ok()?);
    let h = u32::from_be_bytes(png[20..24].try_into().ok()?);
    Some((i32::try_from(w).ok()?, i32::try_from(h).ok()?))
}

/// An image summary of PNG bytes (`None`: not a PNG).
pub fn image(tag: &str, png: Vec<u8>) -> Option<summary::Value> {
    let (width, height) = png_size(&png)?;
    Some(summary::Value {
        tag: tag.into(),
        value: Some(summary::value::Value::Image(summary::Image {
            height,
            width,
            colorspace: 3,
            encoded_image_string: png,
        })),
    })
}

/// The scalar summaries of a record. `previous`: the training record before it (the
/// step time is the train seconds between the two over their steps). Non-finite figures
/// (a window whose every step was skipped) are left out: TensorBoard draws no NaN.
pub fn scalars(record: &MetricsRecord, previous: Option<&TrainRecord>) -> Vec<summary::Value> {
    let mut v = Vec::new();
    match record {
        MetricsRecord::Train(r) => {
            v.push(scalar("train/loss", r.loss));
            v.push(scalar("train/lr", r.lr));
            v.push(scalar("train/scenes_per_s", r.scenes_per_s));
            if let Some(p) = previous.filter(|p| p.step < r.step) {
                let s = (r.train_s - p.train_s) / (r.step - p.step) as f64;
                v.push(scalar("train/step_s", s));
            }
            v.push(r.grad_norm.and_then(|g| scalar("train/grad_norm", g)));
            v.push(scalar("train/skipped_steps", r.skipped as f64));
            v.push(scalar("train/epoch", r.epoch as f64));
            v.push(scalar("train/workers", r.workers as f64));
            v.push(r.peak_rss_mb.and_then(|m| scalar("train/peak_rss_mb", m)));
            v.push(scalar("job/restarts", r.restarts as f64));
        }
        MetricsRecord::Eval(r) => {
            v.push(scalar("eval/psnr", r.psnr));
            v.push(
                r.baseline_psnr
                    .and_then(|x| scalar("eval/baseline_psnr", x)),
            );
            v.push(r.fg_ari.and_then(|x| scalar("eval/fg_ari", x)));
            v.push(r.fg_ari_2d.and_then(|x| scalar("eval/fg_ari_2d", x)));
            v.push(r.ari.and_then(|x| scalar("eval/ari", x)));
            v.push(scalar("eval/render_fps", r.render_fps));
            for o in &r.by_objects {
                let tag = format!("eval/fg_ari_by_objects/{}", o.objects);
                v.push(o.fg_ari.and_then(|x| scalar(&tag, x)));
            }
        }
    }
    v.into_iter().flatten().collect()
}

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
