//! Where a run's metrics records live, and how they are read and written with bounded
//! memory.
//!
//! A local run folder holds them as one file, `RUN/metrics.jsonl`, appended in place and
//! synced. An object store cannot append, so there they are parts of at most
//! [`PART_LINES`] lines, `RUN/metrics/000000.jsonl`, `000001.jsonl`, …: only the last part
//! is ever written again, so an upload stays small however long the job runs. A run
//! folder written by an older osrt on an object store (one whole `metrics.jsonl`) is
//! moved into parts when a coordinator next opens it.
//!
//! Records are in step order within the file (or the parts in name order): a new
//! generation first cuts the records past its checkpoint, then appends. Readers take the
//! lines in order from whichever form the folder holds ([`for_each_line`], [`read_all`]).

use crate::{METRICS_FILE, Result, RunError, read_file, write_file};
use futures::TryStreamExt;
use object_store::ObjectStoreExt;
use object_store::path::Path;
use osrt_store::Location;
use std::path::PathBuf;

/// The folder of an object store's parts.
pub const PARTS_DIR: &str = "metrics";

/// Lines per part: a few hundred kilobytes, the most one metrics upload puts.
pub const PART_LINES: usize = 1024;

/// `RUN/metrics/NNNNNN.jsonl`.
pub fn part_name(index: u64) -> String {
    format!("{PARTS_DIR}/{index:06}.jsonl")
}

fn run_err(run: &Location, path: &Path, reason: impl std::fmt::Display) -> RunError {
    RunError::Run {
        path: run.describe(path),
        reason: reason.to_string(),
    }
}

/// The step of a record line (`None`: not a record).
fn step_of(line: &str) -> Option<u64> {
    crate::MetricsRecord::parse(line).map(|r| r.step())
}

/// The parts' indices in order (empty: none).
async fn part_indices(run: &Location) -> Result<Vec<u64>> {
    let dir = run.path(PARTS_DIR);
    let listed: Vec<_> = run
        .store
        .list(Some(&dir))
        .try_collect()
        .await
        .map_err(|e| run_err(run, &dir, format!("listing: {e}")))?;
    let mut indices: Vec<u64> = listed
        .iter()
        .filter_map(|m| m.location.filename()?.strip_suffix(".jsonl")?.parse().ok())
        .collect();
    indices.sort_unstable();
    Ok(indices)
}

/// Calls `f` with every line of `RUN/path` in order, raw and without its newline, and
/// whether it had one (only a last line cut short has not), reading the object as a
/// stream (one chunk and one line held at a time). `Ok(false)`: there is no such object.
async fn stream_raw(run: &Location, path: &Path, f: &mut impl FnMut(&[u8], bool)) -> Result<bool> {
    let err = |e: object_store::Error| run_err(run, path, e);
    let mut stream = match run.store.get(path).await {
        Ok(r) => r.into_stream(),
        Err(object_store::Error::NotFound { .. }) => return Ok(false),
        Err(e) => return Err(err(e)),
    };
    let mut pending: Vec<u8> = Vec::new();
    while let Some(chunk) = stream.try_next().await.map_err(err)? {
        pending.extend_from_slice(&chunk);
        let mut start = 0;
        while let Some(n) = pending[start..].iter().position(|&b| b == b'\n') {
            f(&pending[start..start + n], true);
            start += n + 1;
        }
        pending.drain(..start);
    }
    if !pending.is_empty() {
        f(&pending, false);
    }
    Ok(true)
}

/// [`stream_raw`] with each line as text.
async fn stream_lines(run: &Location, path: &Path, f: &mut impl FnMut(&str)) -> Result<bool> {
    stream_raw(run, path, &mut |l, _| f(&String::from_utf8_lossy(l))).await
}

/// A part's record lines with their steps.
async fn read_part(run: &Location, index: u64) -> Result<Vec<(u64, String)>> {
    let mut lines = Vec::new();
    stream_lines(run, &run.path(&part_name(index)), &mut |l| {
        if let Some(s) = step_of(l) {
            lines.push((s, l.to_string()));
        }
    })
    .await?;
    Ok(lines)
}

/// Calls `f` with every record line of the run in order (without its newline), holding
/// one chunk of one object at a time. Reads nothing and returns `Ok(false)` where the run
/// has no metrics yet.
pub async fn for_each_line(run: &Location, mut f: impl FnMut(&str)) -> Result<bool> {
    if stream_lines(run, &run.path(METRICS_FILE), &mut f).await? {
        return Ok(true);
    }
    let parts = part_indices(run).await?;
    for &i in &parts {
        stream_lines(run, &run.path(&part_name(i)), &mut f).await?;
    }
    Ok(!parts.is_empty())
}

/// The run's records as one text (`None`: no metrics yet), for readers that want them
/// all (`osrt watch`, a finished job's summary).
pub async fn read_all(run: &Location) -> Result<Option<String>> {
    let mut text = String::new();
    let found = for_each_line(run, |l| {
        text.push_str(l);
        text.push('\n');
    })
    .await?;
    Ok(found.then_some(text))
}

/// A sealed object-store part: full, never written again unless a cut reaches it.
#[derive(Debug, Clone, Copy)]
struct Part {
    index: u64,
    first: Option<u64>,
    last: Option<u64>,
}

impl Part {
    fn of(index: u64, lines: &[(u64, String)]) -> Self {
        Self {
            index,
            first: lines.first().map(|(s, _)| *s),
            last: lines.last().map(|(s, _)| *s),
        }
    }
}

#[derive(Debug)]
enum Form {
    /// `RUN/metrics.jsonl` on a local disk, `len` bytes of which are synced records.
    Local { file: PathBuf, len: u64 },
    /// Parts on an object store: the sealed ones, then the open one (its index and every
    /// line of it, written whole at each flush).
    Parts {
        sealed: Vec<Part>,
        open_index: u64,
        open: Vec<(u64, String)>,
    },
}

/// The writer of a run's records (the coordinator's). Lines and cuts are taken in memory
/// at once ([`MetricsLog::push`], [`MetricsLog::cut_after`]); [`MetricsLog::flush`] makes
/// them durable and may be called again after a failure: it holds what it has not
/// written, never more than the unwritten lines and one part.
#[derive(Debug)]
pub struct MetricsLog {
    run: Location,
    form: Form,
    /// Lines pushed since the last flush (after the cut, if any).
    pending: Vec<(u64, String)>,
    /// A cut still to be made in what is written: drop the lines past this step
    /// (`Some(None)`: all of them).
    cut: Option<Option<u64>>,
    /// Something is pushed or cut but not written.
    dirty: bool,
    /// The newest step pushed (after cuts).
    last: Option<u64>,
    /// An object store still holding an older osrt's single `metrics.jsonl`.
    legacy: bool,
}

impl MetricsLog {
    /// Opens the run's records for writing. Before anything is appended a restarted job
    /// cuts the records past its checkpoint, which also drops a line a crash left
    /// half-written.
    pub async fn open(run: &Location) -> Result<Self> {
        let path = run.path(METRICS_FILE);
        let (form, legacy) = match run.local_file(&path) {
            Some(file) => {
                let len = tokio::fs::metadata(&file).await.map_or(0, |m| m.len());
                (Form::Local { file, len }, false)
            }
            // An older osrt's single file is moved into parts at the first flush: a
            // coordinator that refuses the job must leave the folder as it found it.
            None if exists(run, &path).await? => (
                Form::Parts {
                    sealed: Vec::new(),
                    open_index: 0,
                    open: Vec::new(),
                },
                true,
            ),
            None => (Self::open_parts(run).await?, false),
        };
        let mut log = Self {
            run: run.clone(),
            form,
            legacy,
            pending: Vec::new(),
            cut: None,
            dirty: false,
            last: None,
        };
        match &log.form {
            // The parts were just read: their newest step is known.
            Form::Parts { sealed, open, .. } if !legacy => {
                log.last = open
                    .last()
                    .map(|(s, _)| *s)
                    .or_else(|| sealed.last().and_then(|p| p.last));
            }
            _ => {
                for_each_line(run, |l| {
                    if let Some(s) = step_of(l) {
                        log.last = Some(s);
                    }
                })
                .await?;
            }
        }
        Ok(log)
    }

    /// The parts of an object store: the last one, if not full, is reopened.
    async fn open_parts(run: &Location) -> Result<Form> {
        let mut sealed = Vec::new();
        let mut last: Option<(u64, Vec<(u64, String)>)> = None;
        for i in part_indices(run).await? {
            // Every part but the last counts as sealed, full or not.
            if let Some((index, lines)) = last.take() {
                sealed.push(Part::of(index, &lines));
            }
            last = Some((i, read_part(run, i).await?));
        }
        let (open_index, open) = match last {
            Some((i, lines)) if lines.len() >= PART_LINES => {
                sealed.push(Part::of(i, &lines));
                (i + 1, Vec::new())
            }
            Some((i, lines)) => (i, lines),
            None => (0, Vec::new()),
        };
        Ok(Form::Parts {
            sealed,
            open_index,
            open,
        })
    }

    /// An older osrt's whole `metrics.jsonl` on an object store, written as parts; the
    /// file is deleted last, so a move cut short is made again from it.
    async fn move_into_parts(run: &Location, whole: &[u8]) -> Result<()> {
        let text = String::from_utf8_lossy(whole);
        let lines: Vec<&str> = text.lines().filter(|l| step_of(l).is_some()).collect();
        let mut written = 0;
        for (i, chunk) in lines.chunks(PART_LINES).enumerate() {
            write_file(run, &part_name(i as u64), join(chunk.iter().copied())).await?;
            written += 1;
        }
        for i in part_indices(run).await? {
            if i >= written {
                delete(run, &run.path(&part_name(i))).await?;
            }
        }
        delete(run, &run.path(METRICS_FILE)).await?;
        tracing::info!(parts = written, "metrics.jsonl moved into parts");
        Ok(())
    }

    /// The newest step pushed (what the run holds once flushed).
    pub fn last_step(&self) -> Option<u64> {
        self.last
    }

    /// The record lines held in memory: those not written yet, and an object store's open
    /// part (at most [`PART_LINES`] once flushed).
    pub fn held(&self) -> usize {
        self.pending.len()
            + match &self.form {
                Form::Local { .. } => 0,
                Form::Parts { open, .. } => open.len(),
            }
    }

    /// Whether something pushed or cut is not written yet.
    pub fn is_dirty(&self) -> bool {
        self.dirty
    }

    /// Whether appends go to a local file (flushes are cheap; an object store's rewrite
    /// the open part).
    pub fn appends_in_place(&self) -> bool {
        matches!(self.form, Form::Local { .. })
    }

    /// Drops the records past `keep` (`None`: all), written or not.
    pub fn cut_after(&mut self, keep: Option<u64>) {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        self.pending.retain(|(s, _)| !past(*s));
        if let Form::Parts { open, .. } = &mut self.form {
            open.retain(|(s, _)| !past(*s));
        }
        self.cut = Some(match self.cut {
            Some(earlier) => earlier.min(keep),
            None => keep,
        });
        self.last = self.last.filter(|&s| !past(s));
        self.dirty = true;
    }

    /// Takes record lines (in step order, after what the log holds).
    pub fn push(&mut self, lines: impl IntoIterator<Item = (u64, String)>) {
        for (s, l) in lines {
            self.last = Some(s);
            self.pending.push((s, l));
            self.dirty = true;
        }
    }

    /// Writes the cut and the lines taken since the last flush. On an error nothing taken
    /// is lost: the next flush tries again from what is written.
    pub async fn flush(&mut self) -> Result<()> {
        if !self.dirty {
            return Ok(());
        }
        if self.legacy {
            if let Some(whole) = read_file(&self.run, METRICS_FILE).await? {
                Self::move_into_parts(&self.run, &whole).await?;
            }
            self.form = Self::open_parts(&self.run).await?;
            self.legacy = false;
        }
        if let Some(keep) = self.cut {
            let kept = self.write_cut(keep).await?;
            self.cut = None;
            // The newest step now written; lines pushed since the cut come after it.
            self.last = self.pending.last().map(|(s, _)| *s).or(kept);
        }
        match &mut self.form {
            Form::Local { file, len } => {
                let text = join(self.pending.iter().map(|(_, l)| l.as_str()));
                let (file, at) = (file.clone(), *len);
                let path = self.run.path(METRICS_FILE);
                let written = tokio::task::spawn_blocking(move || append_at(&file, at, &text))
                    .await
                    .map_err(|e| run_err(&self.run, &path, e))?
                    .map_err(|e| run_err(&self.run, &path, format!("appending: {e}")))?;
                *len = written;
                self.pending.clear();
            }
            Form::Parts {
                sealed,
                open_index,
                open,
            } => {
                open.append(&mut self.pending);
                while open.len() >= PART_LINES {
                    let full = join(open[..PART_LINES].iter().map(|(_, l)| l.as_str()));
                    write_file(&self.run, &part_name(*open_index), full).await?;
                    sealed.push(Part::of(*open_index, &open[..PART_LINES]));
                    open.drain(..PART_LINES);
                    *open_index += 1;
                }
                let name = part_name(*open_index);
                if open.is_empty() {
                    // A cut may have emptied it.
                    delete(&self.run, &self.run.path(&name)).await?;
                } else {
                    let text = join(open.iter().map(|(_, l)| l.as_str()));
                    write_file(&self.run, &name, text).await?;
                }
            }
        }
        self.dirty = false;
        Ok(())
    }

    /// Drops the written records past `keep`: the local file is truncated at the first
    /// of them (or at a line a crash cut short); the parts past it are deleted, newest
    /// first, and the part holding it becomes the open part again. Returns the newest step
    /// left.
    async fn write_cut(&mut self, keep: Option<u64>) -> Result<Option<u64>> {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        match &mut self.form {
            Form::Local { file, len } => {
                let mut offset = 0u64;
                let mut cut_at: Option<u64> = None;
                let mut kept = None;
                stream_raw(&self.run, &self.run.path(METRICS_FILE), &mut |l, whole| {
                    let step = step_of(&String::from_utf8_lossy(l));
                    if cut_at.is_none() {
                        if !whole || step.is_some_and(past) {
                            cut_at = Some(offset);
                        } else if step.is_some() {
                            kept = step;
                        }
                    }
                    offset += l.len() as u64 + 1;
                })
                .await?;
                let at = cut_at.unwrap_or(offset);
                let f = file.clone();
                let path = self.run.path(METRICS_FILE);
                tokio::task::spawn_blocking(move || truncate(&f, at))
                    .await
                    .map_err(|e| run_err(&self.run, &path, e))?
                    .map_err(|e| run_err(&self.run, &path, format!("truncating: {e}")))?;
                *len = at;
                Ok(kept)
            }
            Form::Parts {
                sealed,
                open_index,
                open,
            } => {
                // The sealed parts that start past `keep` go, with the open part.
                if let Some(from) = sealed.iter().position(|p| p.first.is_some_and(past)) {
                    for i in (sealed[from].index..=*open_index).rev() {
                        delete(&self.run, &self.run.path(&part_name(i))).await?;
                    }
                    sealed.truncate(from);
                    open.clear();
                    *open_index = sealed.last().map_or(0, |p| p.index + 1);
                }
                // The last one left may still hold some.
                self.cut_last_sealed(keep).await?;
                let Form::Parts { sealed, open, .. } = &self.form else {
                    unreachable!("a run folder's form does not change");
                };
                Ok(open
                    .last()
                    .map(|(s, _)| *s)
                    .or_else(|| sealed.last().and_then(|p| p.last)))
            }
        }
    }

    /// The last sealed part, if it holds records past `keep`, read back, cut and made
    /// the open part (the open part's lines were cut in memory already).
    async fn cut_last_sealed(&mut self, keep: Option<u64>) -> Result<()> {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        let Form::Parts {
            sealed,
            open_index,
            open,
        } = &mut self.form
        else {
            return Ok(());
        };
        let Some(last) = sealed.last().copied().filter(|p| p.last.is_some_and(past)) else {
            return Ok(());
        };
        let mut lines = read_part(&self.run, last.index).await?;
        // The open part (past `keep` entirely) goes; the sealed one becomes open.
        delete(&self.run, &self.run.path(&part_name(*open_index))).await?;
        lines.retain(|(s, _)| !past(*s));
        sealed.pop();
        *open_index = last.index;
        *open = lines;
        Ok(())
    }
}

fn join<'a>(lines: impl IntoIterator<Item = &'a str>) -> Vec<u8> {
    let mut text = Vec::new();
    for l in lines {
        text.extend_from_slice(l.as_bytes());
        text.push(b'\n');
    }
    text
}

/// Whether `path` exists.
async fn exists(run: &Location, path: &Path) -> Result<bool> {
    match run.store.head(path).await {
        Ok(_) => Ok(true),
        Err(object_store::Error::NotFound { .. }) => Ok(false),
        Err(e) => Err(run_err(run, path, e)),
    }
}

/// Deletes `path`; one already gone is fine.
async fn delete(run: &Location, path: &Path) -> Result<()> {
    match run.store.delete(path).await {
        Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
        Err(e) => Err(run_err(run, path, format!("deleting: {e}"))),
    }
}

/// Writes `text` at byte `at` of `file` (cutting off whatever a failed append left past
/// it), syncs, and returns the new length.
fn append_at(file: &std::path::Path, at: u64, text: &[u8]) -> std::io::Result<u64> {
    use std::io::{Seek, SeekFrom, Write};
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(file)?;
    if f.metadata()?.len() != at {
        f.set_len(at)?;
    }
    f.seek(SeekFrom::Start(at))?;
    f.write_all(text)?;
    f.sync_data()?;
    Ok(at + text.len() as u64)
}

fn truncate(file: &std::path::Path, at: u64) -> std::io::Result<()> {
    match std::fs::OpenOptions::new().write(true).open(file) {
        Ok(f) => {
            f.set_len(at)?;
            f.sync_data()
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
    }
}
