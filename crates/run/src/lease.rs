//! The run folder's lease (`RUN/lease.json`): at most one coordinator drives a run folder.
//!
//! The holder writes the lease create-only when it starts, and renews it every
//! [`LeaseTiming::renew_every`] by writing it again with its renewal count one higher,
//! after checking that the lease is still its own (a holder that finds another's lease has
//! lost the folder and must stop). A newcomer that finds a lease watches it for
//! [`LeaseTiming::watch`]: if the count moves, the holder is alive and the newcomer is
//! refused, with the holder's name and how long it has held the folder; if it does not
//! move, the holder is dead (a crashed coordinator: the restart path) and the newcomer
//! takes the lease over. A holder on the same machine whose process is gone is dead
//! without watching (a local restart after a crash). Liveness is judged by a count seen to move, not by timestamps,
//! so clocks of different machines need not agree. `take_over` skips the watch, for a
//! holder known to be dead.
//!
//! Object stores offer create-only writes but no compare-and-swap on every backend, so
//! two newcomers taking over a dead holder's lease at the same moment can both believe
//! they hold it until the first renewal, when one of them finds the other's lease and
//! stops.

use crate::error::{Result, RunError};
use crate::{Location, read_file};
use object_store::{ObjectStoreExt, PutMode, PutOptions, PutPayload};
use serde::{Deserialize, Serialize};
use std::time::Duration;

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
}

/// How often the holder renews, and how long a newcomer watches a lease for a renewal.
#[derive(Debug, Clone, Copy)]
pub struct LeaseTiming {
    pub renew_every: Duration,
    pub watch: Duration,
}

impl Default for LeaseTiming {
    /// Renewed every 3 s, watched for 10 s: a live holder renews three times within the
    /// watch, even with a slow store; a crashed coordinator's restart waits 10 s.
    fn default() -> Self {
        Self {
            renew_every: Duration::from_secs(3),
            watch: Duration::from_secs(10),
        }
    }
}

/// A held lease; renew it every [`LeaseTiming::renew_every`] and release it at the end.
#[derive(Debug)]
pub struct Lease {
    run: Location,
    file: LeaseFile,
    pub timing: LeaseTiming,
}

fn lease_err(run: &Location, reason: impl std::fmt::Display) -> RunError {
    RunError::Run {
        path: run.describe(&run.path(LEASE_FILE)),
        reason: reason.to_string(),
    }
}

/// Whether process `pid` of this machine is running (Linux: `/proc/PID`); true where that
/// cannot be told, so that the lease is watched instead.
fn process_alive(pid: u32) -> bool {
    let proc = std::path::Path::new("/proc");
    !proc.is_dir() || proc.join(pid.to_string()).exists()
}

fn unix_now() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

async fn read_lease(run: &Location) -> Result<Option<LeaseFile>> {
    match read_file(run, LEASE_FILE).await? {
        None => Ok(None),
        Some(b) => serde_json::from_slice(&b).map(Some).map_err(|e| {
            lease_err(
                run,
                format!("unreadable ({e}); delete it if no job runs here"),
            )
        }),
    }
}

async fn put(run: &Location, file: &LeaseFile, create_only: bool) -> Result<bool> {
    let bytes = serde_json::to_vec_pretty(file).expect("serialises");
    let mode = if create_only {
        PutMode::Create
    } else {
        PutMode::Overwrite
    };
    let opts = PutOptions {
        mode,
        ..Default::default()
    };
    match run
        .store
        .put_opts(&run.path(LEASE_FILE), PutPayload::from(bytes), opts)
        .await
    {
        Ok(_) => Ok(true),
        Err(object_store::Error::AlreadyExists { .. }) => Ok(false),
        Err(e) => Err(lease_err(run, e)),
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
        let mine = LeaseFile {
            holder,
            renewals: 0,
            renewed_unix_s: unix_now(),
        };
        let lease = Self {
            run: run.clone(),
            file: mine,
            timing,
        };
        if put(run, &lease.file, true).await? {
            return Ok(lease);
        }
        if !take_over {
            lease.watch_existing().await?;
        }
        // The holder is gone: its lease is replaced by ours.
        put(run, &lease.file, false).await?;
        tracing::warn!(run = %run.describe(&run.path(LEASE_FILE)), "took over the run folder's lease");
        Ok(lease)
    }

    /// Watches the lease there for a renewal; an error naming the holder if one comes.
    async fn watch_existing(&self) -> Result<()> {
        let run = &self.run;
        let Some(first) = read_lease(run).await? else {
            return Ok(());
        };
        if first.holder.host == self.file.holder.host && !process_alive(first.holder.pid) {
            // A holder on this machine whose process is gone (a restart after a crash):
            // nothing to watch.
            tracing::warn!(holder = %first.holder, "the run folder's holder is no longer running");
            return Ok(());
        }
        tracing::info!(
            holder = %first.holder,
            watch_s = self.timing.watch.as_secs_f64(),
            "the run folder has a lease: watching it for a renewal"
        );
        let deadline = tokio::time::Instant::now() + self.timing.watch;
        let step = (self.timing.renew_every / 3).max(Duration::from_millis(50));
        while tokio::time::Instant::now() < deadline {
            tokio::time::sleep(step).await;
            match read_lease(run).await? {
                // Released meanwhile: the folder is free.
                None => return Ok(()),
                Some(now) if now.holder != first.holder || now.renewals != first.renewals => {
                    let held_s = unix_now().saturating_sub(now.holder.started_unix_s);
                    return Err(lease_err(
                        run,
                        format!(
                            "another coordinator drives this run folder: {} since {held_s} s, \
                             renewing its lease (renewal {}). Wait for it to end, choose another \
                             --run, or pass --take-over if that process is known to be dead",
                            now.holder, now.renewals
                        ),
                    ));
                }
                Some(_) => {}
            }
        }
        tracing::warn!(holder = %first.holder, "the run folder's lease was not renewed: its holder is gone");
        Ok(())
    }

    pub fn holder(&self) -> &Holder {
        &self.file.holder
    }

    /// Renews the lease; an error where another holder's lease is there (this process
    /// has lost the run folder and must stop writing to it).
    pub async fn renew(&mut self) -> Result<()> {
        match read_lease(&self.run).await? {
            Some(there) if there.holder.token == self.file.holder.token => {}
            Some(there) => {
                return Err(RunError::LeaseLost {
                    path: self.run.describe(&self.run.path(LEASE_FILE)),
                    holder: there.holder.to_string(),
                });
            }
            // Deleted by hand: taken back.
            None => {}
        }
        self.file.renewals += 1;
        self.file.renewed_unix_s = unix_now();
        put(&self.run, &self.file, false).await?;
        Ok(())
    }

    /// Removes the lease where it is still this holder's.
    pub async fn release(self) -> Result<()> {
        if let Some(there) = read_lease(&self.run).await?
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

    #[tokio::test]
    async fn a_live_holder_keeps_the_folder_and_a_dead_one_is_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let mut a = Lease::acquire(&run, holder("a"), quick(), false)
            .await
            .unwrap();
        // A second holder while the first renews: refused, naming the first.
        let renewing = async {
            for _ in 0..12 {
                tokio::time::sleep(Duration::from_millis(60)).await;
                a.renew().await.unwrap();
            }
        };
        let (e, ()) = tokio::join!(Lease::acquire(&run, holder("b"), quick(), false), renewing);
        let e = e.unwrap_err().to_string();
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

    #[tokio::test]
    async fn a_holder_on_this_machine_whose_process_is_gone_is_replaced_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead = child.id();
        child.wait().unwrap();
        let mut gone = holder("a");
        gone.pid = dead;
        let file = LeaseFile {
            holder: gone,
            renewals: 7,
            renewed_unix_s: 0,
        };
        assert!(put(&run, &file, true).await.unwrap());
        let slow = LeaseTiming {
            renew_every: Duration::from_secs(3),
            watch: Duration::from_secs(3600),
        };
        let b = tokio::time::timeout(
            Duration::from_secs(5),
            Lease::acquire(&run, holder("b"), slow, false),
        )
        .await
        .expect("no watch")
        .unwrap();
        assert_eq!(b.holder().job_id, "b");
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
