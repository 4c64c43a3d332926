//! The run folder's lease (`RUN/lease.json`): at most one coordinator drives a run folder.
//!
//! The holder writes the lease create-only when it starts, and renews it every
//! [`LeaseTiming::renew_every`] by writing it again with its renewal count one higher, as
//! a conditional write on the version it wrote last (`PutMode::Update`): a renewal can
//! never overwrite a newcomer's lease, and one that fails because the lease changed tells
//! the holder it has lost the folder. A newcomer that finds a lease watches it for
//! [`LeaseTiming::watch`]: if it changes, the holder is alive and the newcomer is
//! refused, with the holder's name and how long it has held the folder; if it does not,
//! the holder is gone and the newcomer takes the lease over, again conditionally on the
//! version it watched, so of two newcomers one wins. Liveness is judged only by renewals
//! seen on the store, never by process ids (which mean nothing across PID namespaces or
//! hosts sharing a name) nor by comparing clocks of different machines.
//!
//! Fencing: a holder whose renewals fail stops driving the job once
//! [`LeaseTiming::expiry`] has passed since the start of its last renewal that the store
//! took, which is before any newcomer can have watched the lease unchanged for
//! [`LeaseTiming::watch`] ([`Keeper`]). Deletions of checkpoints check the lease is still
//! the deleter's ([`still_held`]).
//!
//! Local folders get conditional writes from `osrt_store` (a lock beside the file);
//! object stores from the store itself. [`probe_store`] refuses a store that ignores
//! create-only or conditional writes before a job runs on it.

use crate::error::{Result, RunError};
use object_store::{ObjectStoreExt, PutMode, PutOptions, PutPayload, PutResult, UpdateVersion};
use osrt_store::Location;
use serde::{Deserialize, Serialize};
use std::time::Duration;

mod keeper;
mod probe;

pub use keeper::Keeper;
pub use probe::probe_store;

pub const LEASE_FILE: &str = "lease.json";

/// Who holds a run folder.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Holder {
    pub host: String,
    pub pid: u32,
    pub job_id: String,
    /// Unique to this holder (host, pid, start time and a random part).
    pub token: String,
    pub started_unix_s: u64,
}

impl Holder {
    /// This process, holding the folder for `job_id`.
    pub fn this_process(job_id: &str) -> Self {
        let host = host_name().unwrap_or_else(|| "unknown-host".into());
        let started_unix_s = unix_now();
        let pid = std::process::id();
        let nonce: u64 = rand::random();
        Self {
            token: format!("{host}-{pid}-{started_unix_s}-{nonce:016x}"),
            host,
            pid,
            job_id: job_id.to_string(),
            started_unix_s,
        }
    }
}

/// This machine's host name (`HOSTNAME`, else `/etc/hostname`), where it has one.
pub fn host_name() -> Option<String> {
    std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
}

impl std::fmt::Display for Holder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "job {} (host {}, pid {})",
            self.job_id, self.host, self.pid
        )
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct LeaseFile {
    holder: Holder,
    /// Renewals so far: a count that moves while the holder is alive.
    renewals: u64,
    renewed_unix_s: u64,
    /// The job's generation the holder drives: checkpoint commits of an older
    /// generation are refused ([`check_fence`]).
    #[serde(default)]
    generation: u64,
}

/// How often the holder renews, how long a newcomer watches a lease for a renewal, and
/// how long a holder goes on without a renewal the store took.
#[derive(Debug, Clone, Copy)]
pub struct LeaseTiming {
    pub renew_every: Duration,
    pub watch: Duration,
}

impl LeaseTiming {
    /// A holder stops driving the job this long after the start of its last renewal the
    /// store took: a renewal period before a newcomer's watch can have ended.
    pub fn expiry(&self) -> Duration {
        self.watch.saturating_sub(self.renew_every)
    }
}

impl Default for LeaseTiming {
    /// Renewed every 3 s, watched for 15 s: a live holder renews four times within the
    /// watch, even with a slow store; a holder that cannot renew for 12 s stops; a
    /// crashed coordinator's restart waits 15 s.
    fn default() -> Self {
        Self {
            renew_every: Duration::from_secs(3),
            watch: Duration::from_secs(15),
        }
    }
}

/// A held lease; renew it every [`LeaseTiming::renew_every`] (or let a [`Keeper`] do it)
/// and release it at the end.
#[derive(Debug)]
pub struct Lease {
    run: Location,
    file: LeaseFile,
    /// The version of the lease object this holder wrote last.
    version: UpdateVersion,
    pub timing: LeaseTiming,
}

fn lease_err(run: &Location, reason: impl std::fmt::Display) -> RunError {
    RunError::Run {
        path: run.describe(&run.path(LEASE_FILE)),
        reason: reason.to_string(),
    }
}

fn unix_now() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// The lease there and the version of its object.
async fn read_lease(run: &Location) -> Result<Option<(LeaseFile, UpdateVersion)>> {
    let got = match run.store.get(&run.path(LEASE_FILE)).await {
        Ok(got) => got,
        Err(object_store::Error::NotFound { .. }) => return Ok(None),
        Err(e) => return Err(lease_err(run, e)),
    };
    let version = UpdateVersion {
        e_tag: got.meta.e_tag.clone(),
        version: got.meta.version.clone(),
    };
    let bytes = got.bytes().await.map_err(|e| lease_err(run, e))?;
    let file = serde_json::from_slice(&bytes).map_err(|e| {
        lease_err(
            run,
            format!("unreadable ({e}); delete it if no job runs here"),
        )
    })?;
    Ok(Some((file, version)))
}

/// How a write of the lease came out.
enum Put {
    Written(UpdateVersion),
    /// Create-only, and a lease is there.
    Exists,
    /// Conditional, and the lease is no longer the version it was conditioned on.
    Changed,
}

async fn put(run: &Location, file: &LeaseFile, mode: PutMode) -> Result<Put> {
    let bytes = serde_json::to_vec_pretty(file).expect("serialises");
    let opts = PutOptions {
        mode,
        ..Default::default()
    };
    match run
        .store
        .put_opts(&run.path(LEASE_FILE), PutPayload::from(bytes), opts)
        .await
    {
        Ok(PutResult { e_tag, version, .. }) => Ok(Put::Written(UpdateVersion { e_tag, version })),
        Err(object_store::Error::AlreadyExists { .. }) => Ok(Put::Exists),
        // S3 reports an `If-Match` on a missing object as a failed precondition too.
        Err(object_store::Error::Precondition { .. } | object_store::Error::NotFound { .. }) => {
            Ok(Put::Changed)
        }
        Err(e) => Err(lease_err(run, e)),
    }
}

/// The lease of `run` is still the one holding `token`: an error otherwise (checked
/// before a deletion that only the holder may make).
pub async fn still_held(run: &Location, token: &str) -> Result<()> {
    match read_lease(run).await? {
        Some((there, _)) if there.holder.token == token => Ok(()),
        Some((there, _)) => Err(RunError::LeaseLost {
            path: run.describe(&run.path(LEASE_FILE)),
            holder: there.holder.to_string(),
        }),
        None => Err(RunError::LeaseLost {
            path: run.describe(&run.path(LEASE_FILE)),
            holder: "nobody (the lease file was deleted)".into(),
        }),
    }
}

/// Refuses a write of the job's `generation` where the run folder's lease says a newer
/// generation (or nobody) drives it: a rank of an abandoned generation, or of a job whose
/// coordinator was replaced, must not commit a checkpoint the new timeline would meet.
pub async fn check_fence(run: &Location, generation: u64) -> Result<()> {
    let path = run.describe(&run.path(LEASE_FILE));
    match read_lease(run).await? {
        Some((there, _)) if there.generation <= generation => Ok(()),
        Some((there, _)) => Err(RunError::Fenced {
            path,
            reason: format!(
                "generation {} of {} drives the run folder; this is generation {generation}",
                there.generation, there.holder
            ),
        }),
        None => Err(RunError::Fenced {
            path,
            reason: "no coordinator holds the run folder".into(),
        }),
    }
}

impl Lease {
    /// Takes the run folder's lease for `holder`: at once where there is none; after
    /// watching it for `timing.watch` where its holder does not renew it (or at once with
    /// `take_over`); refused where its holder is alive.
    pub async fn acquire(
        run: &Location,
        holder: Holder,
        timing: LeaseTiming,
        take_over: bool,
    ) -> Result<Self> {
        Self::acquire_fencing(run, holder, timing, take_over, 0).await
    }

    /// [`Lease::acquire`], naming `generation` in the lease from the first write: a
    /// coordinator continuing a job whose persisted generation is `g` fences off every
    /// rank of `g` and older (a previous holder's) as soon as it holds the folder.
    pub async fn acquire_fencing(
        run: &Location,
        holder: Holder,
        timing: LeaseTiming,
        take_over: bool,
        generation: u64,
    ) -> Result<Self> {
        let file = LeaseFile {
            holder,
            renewals: 0,
            renewed_unix_s: unix_now(),
            generation,
        };
        loop {
            if let Put::Written(version) = put(run, &file, PutMode::Create).await? {
                return Ok(Self {
                    run: run.clone(),
                    file,
                    version,
                    timing,
                });
            }
            let Some((there, version)) = read_lease(run).await? else {
                // Released between the two calls: try again.
                continue;
            };
            if there.holder.token == file.holder.token {
                // This create went through and a retry of it was answered `AlreadyExists`.
                return Ok(Self {
                    run: run.clone(),
                    file,
                    version,
                    timing,
                });
            }
            let version = if take_over {
                version
            } else {
                match watch(run, there, version, timing).await? {
                    Some(v) => v,
                    None => continue,
                }
            };
            // The holder is gone: its lease is replaced by ours, unless it changed since
            // it was watched (it renewed at the last moment, or another newcomer won).
            match put(run, &file, PutMode::Update(version)).await? {
                Put::Written(version) => {
                    tracing::warn!(run = %run.describe(&run.path(LEASE_FILE)), "took over the run folder's lease");
                    return Ok(Self {
                        run: run.clone(),
                        file,
                        version,
                        timing,
                    });
                }
                Put::Exists | Put::Changed => {
                    let now = read_lease(run).await?;
                    return Err(refusal(run, now.map(|(f, _)| f)));
                }
            }
        }
    }

    pub fn holder(&self) -> &Holder {
        &self.file.holder
    }

    /// Renews the lease; [`RunError::LeaseLost`] where it is no longer the version this
    /// holder wrote (another holder's, or deleted: this process must stop writing).
    pub async fn renew(&mut self) -> Result<()> {
        let generation = self.file.generation;
        self.renew_for(generation).await
    }

    /// [`Lease::renew`], recording that the holder now drives `generation`.
    pub async fn renew_for(&mut self, generation: u64) -> Result<()> {
        let mut next = self.file.clone();
        next.generation = generation;
        next.renewals += 1;
        next.renewed_unix_s = unix_now();
        match put(&self.run, &next, PutMode::Update(self.version.clone())).await? {
            Put::Written(version) => {
                self.file = next;
                self.version = version;
                Ok(())
            }
            Put::Exists | Put::Changed => {
                let holder = match read_lease(&self.run).await {
                    Ok(Some((there, _))) => there.holder.to_string(),
                    Ok(None) => "nobody (the lease file was deleted)".into(),
                    Err(e) => format!("an unreadable lease ({e})"),
                };
                Err(RunError::LeaseLost {
                    path: self.run.describe(&self.run.path(LEASE_FILE)),
                    holder,
                })
            }
        }
    }

    /// Removes the lease where it is still this holder's.
    pub async fn release(self) -> Result<()> {
        if let Some((there, _)) = read_lease(&self.run).await?
            && there.holder.token == self.file.holder.token
        {
            match self.run.store.delete(&self.run.path(LEASE_FILE)).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(lease_err(&self.run, e)),
            }
        }
        Ok(())
    }
}

/// Watches the lease `first` (object version `version`) for a change: `Ok(Some(v))` with
/// the version to take over where none came, `Ok(None)` where it was released, an error
/// naming the holder where it was renewed.
async fn watch(
    run: &Location,
    first: LeaseFile,
    version: UpdateVersion,
    timing: LeaseTiming,
) -> Result<Option<UpdateVersion>> {
    tracing::info!(
        holder = %first.holder,
        watch_s = timing.watch.as_secs_f64(),
        "the run folder has a lease: watching it for a renewal"
    );
    let deadline = tokio::time::Instant::now() + timing.watch;
    let step = (timing.renew_every / 3).max(Duration::from_millis(50));
    while tokio::time::Instant::now() < deadline {
        tokio::time::sleep(step).await;
        match read_lease(run).await? {
            None => return Ok(None),
            Some((now, v))
                if v != version || now.holder != first.holder || now.renewals != first.renewals =>
            {
                return Err(refusal(run, Some(now)));
            }
            Some(_) => {}
        }
    }
    tracing::warn!(holder = %first.holder, "the run folder's lease was not renewed: its holder is gone");
    Ok(Some(version))
}

fn refusal(run: &Location, now: Option<LeaseFile>) -> RunError {
    let Some(now) = now else {
        return lease_err(run, "the lease changed while it was taken over; try again");
    };
    let held_s = unix_now().saturating_sub(now.holder.started_unix_s);
    lease_err(
        run,
        format!(
            "another coordinator drives this run folder: {} since {held_s} s, \
             renewing its lease (renewal {}). Wait for it to end, choose another \
             --run, or pass --take-over if that process is known to be dead",
            now.holder, now.renewals
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quick() -> LeaseTiming {
        LeaseTiming {
            renew_every: Duration::from_millis(60),
            watch: Duration::from_millis(400),
        }
    }

    fn holder(job: &str) -> Holder {
        Holder::this_process(job)
    }

    /// The error a newcomer ("b") gets while `a` renews its lease.
    async fn refused_while_renewing(run: &Location, a: &mut Lease) -> String {
        let renewing = async {
            for _ in 0..12 {
                tokio::time::sleep(Duration::from_millis(60)).await;
                a.renew().await.unwrap();
            }
        };
        let (e, ()) = tokio::join!(Lease::acquire(run, holder("b"), quick(), false), renewing);
        e.unwrap_err().to_string()
    }

    #[tokio::test]
    async fn a_live_holder_keeps_the_folder_and_a_dead_one_is_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let mut a = Lease::acquire(&run, holder("a"), quick(), false)
            .await
            .unwrap();
        // A second holder while the first renews: refused, naming the first.
        let e = refused_while_renewing(&run, &mut a).await;
        assert!(e.contains("job a") && e.contains("--take-over"), "{e}");
        // The first stops renewing (a crash): the next one takes over after the watch,
        // and the first, renewing late, learns it has lost the folder.
        let c = Lease::acquire(&run, holder("c"), quick(), false)
            .await
            .unwrap();
        let e = a.renew().await.unwrap_err().to_string();
        assert!(e.contains("taken over by job c"), "{e}");
        // Released: the folder is free at once.
        c.release().await.unwrap();
        let d = Lease::acquire(&run, holder("d"), quick(), false)
            .await
            .unwrap();
        assert_eq!(d.holder().job_id, "d");
    }

    /// A holder whose process id names no process here may live in another PID
    /// namespace or on another host of the same name: it is watched like any other, and
    /// refused while it renews.
    #[tokio::test]
    async fn a_holder_is_judged_by_its_renewals_not_by_its_process_id() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead = child.id();
        child.wait().unwrap();
        let mut elsewhere = holder("a");
        elsewhere.pid = dead;
        let mut a = Lease::acquire(&run, elsewhere, quick(), false)
            .await
            .unwrap();
        let e = refused_while_renewing(&run, &mut a).await;
        assert!(
            e.contains("job a") && e.contains("another coordinator"),
            "{e}"
        );
    }

    /// A renewal is conditional on the version its holder wrote: once a newcomer took the
    /// lease over, a late renewal fails and leaves the newcomer's lease as it is.
    #[tokio::test]
    async fn a_late_renewal_never_overwrites_a_newcomers_lease() {
        for url in ["memory://lease-late/run", ""] {
            let dir = tempfile::tempdir().unwrap();
            let run = if url.is_empty() {
                Location::parse(dir.path().to_str().unwrap()).unwrap()
            } else {
                Location::parse(url).unwrap()
            };
            let mut a = Lease::acquire(&run, holder("a"), quick(), false)
                .await
                .unwrap();
            let b = Lease::acquire(&run, holder("b"), quick(), true)
                .await
                .unwrap();
            let e = a.renew().await.unwrap_err().to_string();
            assert!(e.contains("taken over by job b"), "{url}: {e}");
            still_held(&run, &b.holder().token).await.unwrap();
            assert!(still_held(&run, &a.holder().token).await.is_err());
        }
    }

    /// A keeper whose renewals the store does not take stops its holder once the expiry
    /// has passed, before a newcomer's watch can end.
    #[tokio::test]
    async fn a_keeper_that_cannot_renew_expires() {
        let run = Location::parse("memory://lease-keeper/run").unwrap();
        let timing = LeaseTiming {
            renew_every: Duration::from_millis(50),
            watch: Duration::from_millis(300),
        };
        let lease = Lease::acquire(&run, holder("a"), timing, false)
            .await
            .unwrap();
        let keeper = Keeper::start(lease);
        tokio::time::sleep(Duration::from_millis(400)).await;
        keeper.check().unwrap();
        // Another holder takes over by force: the keeper learns at its next renewal.
        let _b = Lease::acquire(&run, holder("b"), timing, true)
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(200)).await;
        let e = keeper.check().unwrap_err().to_string();
        assert!(e.contains("taken over by job b"), "{e}");
        keeper.release().await.unwrap();
        still_held(&run, &_b.holder().token).await.unwrap();
    }

    #[tokio::test]
    async fn take_over_replaces_a_lease_without_watching() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let slow = LeaseTiming {
            renew_every: Duration::from_secs(3),
            watch: Duration::from_secs(3600),
        };
        let _a = Lease::acquire(&run, holder("a"), slow, false)
            .await
            .unwrap();
        let b = tokio::time::timeout(
            Duration::from_secs(5),
            Lease::acquire(&run, holder("b"), slow, true),
        )
        .await
        .expect("no watch")
        .unwrap();
        assert_eq!(b.holder().job_id, "b");
    }

    #[tokio::test]
    async fn an_unreadable_lease_is_an_error_that_says_what_to_do() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(LEASE_FILE), b"{not json").unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let e = Lease::acquire(&run, holder("a"), quick(), false)
            .await
            .unwrap_err()
            .to_string();
        assert!(e.contains("lease.json") && e.contains("unreadable"), "{e}");
    }
}
