//! The job config's `[cluster]` table: how the job runs as a cluster (membership, the
//! collective, checkpoints). The coordinator reads this table and nothing else of the job
//! config; workers read it with the rest (`osrt_trainer::JobConfig`).

use crate::error::{Result, RunError};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// The longest any duration of the job or the command line may be: a year. Longer than
/// any wait a job means, and far inside what `Duration` and `Instant` arithmetic hold
/// (`Duration::from_secs_f64(1e30)` panics).
pub const MAX_DURATION_S: f64 = 365.0 * 86_400.0;

/// The collective's largest chunk, 1 MiB of f32: `osrt_proto::MAX_CHUNK_FLOATS`, which
/// this crate does not depend on (the coordinator's tests hold the two equal).
pub const MAX_CHUNK_FLOATS: usize = 1 << 18;

/// The smallest chunk (4 KiB of f32), and the smallest bucket (256 KiB). A rank receives
/// `2 (W − 1)` segments of `bucket / W` floats per bucket, each in chunks, so one
/// all-reduce of `n` floats holds fewer than `2 n / chunk + 2 W (n / bucket + 1)` hops in
/// its schedule: with these floors and `W ≤` [`MAX_WORKERS`], under `n / 30 + 2 W`, where
/// `bucket_floats = 1` made one hop per float and ran out of memory.
pub const MIN_CHUNK_FLOATS: usize = 1 << 10;
pub const MIN_BUCKET_FLOATS: usize = 1 << 16;

/// The most workers a job may have: a ring of more would cut a bucket into segments too
/// small to be worth a hop each.
pub const MAX_WORKERS: usize = 1024;

/// `v` seconds as a [`Duration`], or why it cannot be one: it must be finite, positive
/// (`positive`) or non-negative, and at most [`MAX_DURATION_S`]. The reason leaves the
/// setting's name to the caller, which knows it (a config field or a flag).
pub fn duration_s(v: f64, positive: bool) -> std::result::Result<Duration, String> {
    let least_ok = if positive { v > 0.0 } else { v >= 0.0 };
    if v.is_finite() && least_ok && v <= MAX_DURATION_S {
        return Ok(Duration::from_secs_f64(v));
    }
    let want = if positive { "positive" } else { "non-negative" };
    Err(format!(
        "must be a {want}, finite number of seconds, at most {MAX_DURATION_S} (a year); got {v:?}"
    ))
}

/// A validated setting's duration; values outside [`duration_s`]'s range (a config not
/// validated) saturate instead of panicking.
fn saturating_duration(v: f64) -> Duration {
    Duration::try_from_secs_f64(v.clamp(0.0, MAX_DURATION_S)).unwrap_or(Duration::ZERO)
}

/// How the job runs as a cluster: membership, the collective, checkpoints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ClusterConfig {
    /// The job starts (and continues after a loss) with at least this many workers.
    pub min_workers: usize,
    /// Registrations beyond this many are refused.
    pub max_workers: usize,
    /// Generation changes after a lost member or a failed round before the job fails.
    pub max_restarts: u32,
    /// A member silent for this long is lost. Every duration here is at most
    /// [`MAX_DURATION_S`].
    pub heartbeat_timeout_s: f64,
    /// Once `min_workers` are present, wait this long for more (up to `max_workers`).
    pub join_grace_s: f64,
    /// The job fails if no generation forms for this long (too few workers ever came).
    pub wait_timeout_s: f64,
    /// Deadline of every collective RPC and wait: a dead peer fails the round this fast.
    pub rpc_timeout_s: f64,
    /// All-reduce bucket size (floats): at least [`MIN_BUCKET_FLOATS`] and `chunk_floats`.
    pub bucket_floats: usize,
    /// All-reduce chunk size (floats): [`MIN_CHUNK_FLOATS`] to [`MAX_CHUNK_FLOATS`].
    pub chunk_floats: usize,
    /// Compare replicas' parameter hashes through the coordinator every this many steps.
    pub hash_every: u64,
    /// Commit a checkpoint every this many steps (and always at the end).
    pub checkpoint_every: u64,
    /// Retention: the newest `keep_last` checkpoints plus the best by validation FG-ARI.
    pub keep_last: usize,
}

impl Default for ClusterConfig {
    fn default() -> Self {
        Self {
            min_workers: 1,
            max_workers: 64,
            max_restarts: 5,
            heartbeat_timeout_s: 5.0,
            join_grace_s: 1.0,
            wait_timeout_s: 600.0,
            rpc_timeout_s: 10.0,
            bucket_floats: 1 << 22,
            chunk_floats: MAX_CHUNK_FLOATS,
            hash_every: 10,
            checkpoint_every: 500,
            keep_last: 3,
        }
    }
}

impl ClusterConfig {
    /// The `[cluster]` table of a job config's TOML (defaults where it is absent or
    /// partial); `path` names the file in errors. Other tables are not read.
    pub fn from_job_toml(path: &str, text: &str) -> Result<Self> {
        #[derive(Deserialize)]
        struct Only {
            #[serde(default)]
            cluster: ClusterConfig,
        }
        let only: Only = toml::from_str(text).map_err(|e| RunError::Config {
            path: path.to_string(),
            reason: e.to_string(),
        })?;
        Ok(only.cluster)
    }

    /// The job's global batch (`[train] batch_size` of its TOML), where it says: a step
    /// feeds at most that many workers (one scene each). `None` where the table or the
    /// key is absent or unreadable (the trainer validates the config itself).
    pub fn global_batch_of(text: &str) -> Option<usize> {
        #[derive(Deserialize)]
        struct Train {
            batch_size: Option<usize>,
        }
        #[derive(Deserialize)]
        struct Only {
            train: Option<Train>,
        }
        toml::from_str::<Only>(text).ok()?.train?.batch_size
    }

    /// Rejects settings that cannot run, by name.
    pub fn validate(&self) -> Result<()> {
        let c = self;
        let bad = |reason: String| {
            Err(RunError::Config {
                path: "job config".into(),
                reason,
            })
        };
        if c.min_workers == 0 || c.min_workers > c.max_workers || c.max_workers > MAX_WORKERS {
            return bad(format!(
                "need 1 <= cluster.min_workers ({}) <= cluster.max_workers ({}) <= {MAX_WORKERS}",
                c.min_workers, c.max_workers
            ));
        }
        for (name, v) in [
            ("hash_every", c.hash_every),
            ("checkpoint_every", c.checkpoint_every),
            ("keep_last", c.keep_last as u64),
        ] {
            if v == 0 {
                // keep_last = 0 would let retention delete the newest committed checkpoint.
                return bad(format!("cluster.{name} must be positive"));
            }
        }
        if !(MIN_CHUNK_FLOATS..=MAX_CHUNK_FLOATS).contains(&c.chunk_floats) {
            return bad(format!(
                "cluster.chunk_floats must be in {MIN_CHUNK_FLOATS}..={MAX_CHUNK_FLOATS} \
                 (4 KiB to 1 MiB of f32), got {}",
                c.chunk_floats
            ));
        }
        let least = MIN_BUCKET_FLOATS.max(c.chunk_floats);
        if c.bucket_floats < least {
            return bad(format!(
                "cluster.bucket_floats must be at least {MIN_BUCKET_FLOATS} and at least \
                 cluster.chunk_floats ({}), got {}",
                c.chunk_floats, c.bucket_floats
            ));
        }
        for (name, v, positive) in [
            ("heartbeat_timeout_s", c.heartbeat_timeout_s, true),
            ("rpc_timeout_s", c.rpc_timeout_s, true),
            ("wait_timeout_s", c.wait_timeout_s, true),
            ("join_grace_s", c.join_grace_s, false),
        ] {
            if let Err(why) = duration_s(v, positive) {
                return bad(format!("cluster.{name} {why}"));
            }
        }
        Ok(())
    }

    /// `heartbeat_timeout_s`: a member silent for this long is lost.
    pub fn heartbeat_timeout(&self) -> Duration {
        saturating_duration(self.heartbeat_timeout_s)
    }

    /// `join_grace_s`: how long a generation waits for more than `min_workers`.
    pub fn join_grace(&self) -> Duration {
        saturating_duration(self.join_grace_s)
    }

    /// `wait_timeout_s`: how long the job waits for a generation to form.
    pub fn wait_timeout(&self) -> Duration {
        saturating_duration(self.wait_timeout_s)
    }

    /// `rpc_timeout_s`: the deadline of every collective RPC and wait.
    pub fn rpc_timeout(&self) -> Duration {
        saturating_duration(self.rpc_timeout_s)
    }
}

/// `--min-workers`, `--max-workers`, `--max-restarts`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ClusterOverrides {
    pub min_workers: Option<usize>,
    pub max_workers: Option<usize>,
    pub max_restarts: Option<u32>,
}

impl ClusterOverrides {
    /// Applies the limits given; without an explicit `max_workers`, the config's is
    /// raised to `min_workers` where it is lower.
    pub fn apply(&self, c: &mut ClusterConfig) {
        if let Some(v) = self.min_workers {
            c.min_workers = v;
        }
        match self.max_workers {
            Some(v) => c.max_workers = v,
            None => c.max_workers = c.max_workers.max(c.min_workers),
        }
        if let Some(v) = self.max_restarts {
            c.max_restarts = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only `[cluster]` is read: other tables may hold anything, an absent table gives
    /// the defaults, and a bad cluster value is refused by name.
    #[test]
    fn the_cluster_table_is_read_alone() {
        let text = "[model]\nwhatever = 1\n[train]\nlr = \"not a number\"\n\
                    [cluster]\nmin_workers = 3\nmax_workers = 4\n";
        let c = ClusterConfig::from_job_toml("job.toml", text).unwrap();
        assert_eq!((c.min_workers, c.max_workers), (3, 4));
        assert_eq!(c.keep_last, ClusterConfig::default().keep_last);
        let d = ClusterConfig::from_job_toml("job.toml", "[train]\nseed = 1\n").unwrap();
        assert_eq!(d, ClusterConfig::default());
        let zero = "[cluster]\nkeep_last = 0\n";
        let err = ClusterConfig::from_job_toml("job.toml", zero)
            .unwrap()
            .validate();
        assert!(err.unwrap_err().to_string().contains("cluster.keep_last"));
        let wrong = ClusterConfig::from_job_toml("job.toml", "[cluster]\nmin_workers = \"x\"\n");
        assert!(wrong.unwrap_err().to_string().contains("job.toml"));
    }

    /// `Duration::from_secs_f64(1e30)` panics: a duration beyond a year, or not finite,
    /// is refused by name, also where it comes from a stored config.toml (a restarted
    /// coordinator reads that), and every valid one converts.
    #[test]
    fn durations_are_finite_and_at_most_a_year() {
        for name in [
            "heartbeat_timeout_s",
            "join_grace_s",
            "rpc_timeout_s",
            "wait_timeout_s",
        ] {
            for v in ["1e30", "nan", "inf", "-1.0", "31536001.0"] {
                let text = format!("[cluster]\n{name} = {v}\n");
                let c = ClusterConfig::from_job_toml("config.toml", &text).unwrap();
                let e = c.validate().unwrap_err().to_string();
                assert!(e.contains(&format!("cluster.{name}")), "{name} = {v}: {e}");
            }
            let text = format!("[cluster]\n{name} = {MAX_DURATION_S:?}\n");
            let c = ClusterConfig::from_job_toml("config.toml", &text).unwrap();
            c.validate().unwrap();
            for d in [
                c.heartbeat_timeout(),
                c.join_grace(),
                c.rpc_timeout(),
                c.wait_timeout(),
            ] {
                assert!(d <= Duration::from_secs_f64(MAX_DURATION_S));
                assert!(std::time::Instant::now().checked_add(d).is_some());
            }
        }
        let unchecked = ClusterConfig {
            heartbeat_timeout_s: 1e30,
            join_grace_s: f64::NAN,
            ..ClusterConfig::default()
        };
        let year = Duration::from_secs_f64(MAX_DURATION_S);
        assert_eq!(unchecked.heartbeat_timeout(), year);
        assert_eq!(unchecked.join_grace(), Duration::ZERO);
    }

    /// `bucket_floats = 1` made one ring hop per float (tens of millions for a model)
    /// and ran out of memory: buckets and chunks are bounded below, chunks above.
    #[test]
    fn buckets_and_chunks_are_bounded() {
        type Edit = fn(&mut ClusterConfig);
        let cases: [(&str, Edit); 6] = [
            ("cluster.bucket_floats", |c| c.bucket_floats = 1),
            ("cluster.bucket_floats", |c| {
                c.bucket_floats = MIN_BUCKET_FLOATS - 1
            }),
            ("cluster.bucket_floats", |c| {
                c.bucket_floats = c.chunk_floats - 1
            }),
            ("cluster.chunk_floats", |c| c.chunk_floats = 1),
            ("cluster.chunk_floats", |c| {
                c.chunk_floats = MAX_CHUNK_FLOATS + 1
            }),
            ("max_workers", |c| c.max_workers = MAX_WORKERS + 1),
        ];
        for (name, edit) in cases {
            let mut c = ClusterConfig::default();
            edit(&mut c);
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(name), "{name}: {e}");
        }
        let least = ClusterConfig {
            bucket_floats: MIN_BUCKET_FLOATS,
            chunk_floats: MIN_CHUNK_FLOATS,
            max_workers: MAX_WORKERS,
            ..ClusterConfig::default()
        };
        least.validate().unwrap();
    }

    #[test]
    fn overrides_raise_max_workers_to_min_workers() {
        let mut c = ClusterConfig::default();
        ClusterOverrides {
            min_workers: Some(100),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!((c.min_workers, c.max_workers), (100, 100));
    }
}
