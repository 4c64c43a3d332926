//! The lease's keeper: a task of its own renews the lease, records the generation the
//! holder drives, and tells the holder when it must stop.

use super::{LEASE_FILE, Lease, LeaseTiming};
use crate::error::{Result, RunError};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// A lease renewed by a task of its own, so that no other store traffic delays a
/// renewal, and that knows when its holder must stop: at once when the lease was lost,
/// and once [`LeaseTiming::expiry`] has passed since the start of the last renewal the
/// store took.
pub struct Keeper {
    lease: Arc<tokio::sync::Mutex<Option<Lease>>>,
    state: Arc<Mutex<KeeperState>>,
    task: tokio::task::JoinHandle<()>,
    path: String,
    token: String,
    wake: Arc<tokio::sync::Notify>,
}

struct KeeperState {
    valid_until: Instant,
    last_ok: Instant,
    lost: Option<String>,
    /// The generation to record in the lease, and the newest one the store took.
    want_generation: u64,
    written_generation: u64,
}

impl Keeper {
    /// Starts renewing `lease` (just acquired or renewed: valid from now).
    pub fn start(lease: Lease) -> Self {
        let timing = lease.timing;
        let path = lease.run.describe(&lease.run.path(LEASE_FILE));
        let token = lease.file.holder.token.clone();
        let now = Instant::now();
        let state = Arc::new(Mutex::new(KeeperState {
            valid_until: now + timing.expiry(),
            last_ok: now,
            lost: None,
            want_generation: lease.file.generation,
            written_generation: lease.file.generation,
        }));
        let lease = Arc::new(tokio::sync::Mutex::new(Some(lease)));
        let wake = Arc::new(tokio::sync::Notify::new());
        let task = tokio::spawn(renewals(lease.clone(), state.clone(), wake.clone(), timing));
        Self {
            lease,
            state,
            task,
            path,
            token,
            wake,
        }
    }

    /// Records `generation` in the lease at once (a renewal out of turn); true once a
    /// renewal carrying it (or a newer one) was taken by the store, from when on ranks
    /// of older generations cannot commit ([`check_fence`](super::check_fence)).
    pub fn fence(&self, generation: u64) -> bool {
        let mut s = self.state.lock().expect("lease state");
        if s.written_generation >= generation {
            return true;
        }
        if s.want_generation < generation {
            s.want_generation = generation;
            self.wake.notify_one();
        }
        false
    }

    /// The holder's token (for [`still_held`](super::still_held)).
    pub fn token(&self) -> &str {
        &self.token
    }

    /// Whether this holder may still drive the job: an error once the lease was lost or
    /// has expired without a renewal the store took.
    pub fn check(&self) -> Result<()> {
        let s = self.state.lock().expect("lease state");
        if let Some(holder) = &s.lost {
            return Err(RunError::LeaseLost {
                path: self.path.clone(),
                holder: holder.clone(),
            });
        }
        if Instant::now() >= s.valid_until {
            return Err(RunError::Run {
                path: self.path.clone(),
                reason: format!(
                    "the lease could not be renewed for {:.1} s: stopping, so that no two \
                     coordinators drive the folder (a newcomer may take it over now)",
                    s.last_ok.elapsed().as_secs_f64()
                ),
            });
        }
        Ok(())
    }

    /// Stops renewing and removes the lease where it is still this holder's.
    pub async fn release(self) -> Result<()> {
        self.task.abort();
        let _ = self.task.await;
        match self.lease.lock().await.take() {
            Some(lease) => lease.release().await,
            None => Ok(()),
        }
    }
}

async fn renewals(
    lease: Arc<tokio::sync::Mutex<Option<Lease>>>,
    state: Arc<Mutex<KeeperState>>,
    wake: Arc<tokio::sync::Notify>,
    timing: LeaseTiming,
) {
    loop {
        tokio::select! {
            _ = tokio::time::sleep(timing.renew_every) => {}
            _ = wake.notified() => {}
        }
        let started = Instant::now();
        let generation = state.lock().expect("lease state").want_generation;
        let mut guard = lease.lock().await;
        let Some(l) = guard.as_mut() else { return };
        match l.renew_for(generation).await {
            Ok(()) => {
                let mut s = state.lock().expect("lease state");
                s.valid_until = started + timing.expiry();
                s.last_ok = started;
                s.written_generation = s.written_generation.max(generation);
            }
            Err(RunError::LeaseLost { holder, .. }) => {
                state.lock().expect("lease state").lost = Some(holder);
                // Never released: it is another holder's now.
                guard.take();
                return;
            }
            Err(e) => tracing::warn!(error = %e, "renewing the run folder's lease"),
        }
    }
}
