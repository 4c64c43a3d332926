//! The job config's `[cluster]` table: how the job runs as a cluster (membership, the
//! collective, checkpoints). The coordinator reads this table and nothing else of the job
//! config; workers read it with the rest (`osrt_trainer::JobConfig`).

use crate::error::{Result, RunError};
use serde::{Deserialize, Serialize};

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
    /// A member silent for this long is lost.
    pub heartbeat_timeout_s: f64,
    /// Once `min_workers` are present, wait this long for more (up to `max_workers`).
    pub join_grace_s: f64,
    /// The job fails if no generation forms for this long (too few workers ever came).
    pub wait_timeout_s: f64,
    /// Deadline of every collective RPC and wait: a dead peer fails the round this fast.
    pub rpc_timeout_s: f64,
    /// All-reduce bucket size (floats) and chunk size (floats, at most 1 MiB of f32).
    pub bucket_floats: usize,
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
            // The collective's largest chunk (`osrt_proto::MAX_CHUNK_FLOATS`, 1 MiB of
            // f32), which the coordinator holds `chunk_floats` to.
            chunk_floats: 1 << 18,
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
        if c.min_workers == 0 || c.min_workers > c.max_workers {
            return bad(format!(
                "cluster: need 1 <= min_workers ({}) <= max_workers ({})",
                c.min_workers, c.max_workers
            ));
        }
        for (name, v) in [
            ("bucket_floats", c.bucket_floats as u64),
            ("chunk_floats", c.chunk_floats as u64),
            ("hash_every", c.hash_every),
            ("checkpoint_every", c.checkpoint_every),
            ("keep_last", c.keep_last as u64),
        ] {
            if v == 0 {
                // keep_last = 0 would let retention delete the newest committed checkpoint.
                return bad(format!("cluster.{name} must be positive"));
            }
        }
        for (name, v) in [
            ("heartbeat_timeout_s", c.heartbeat_timeout_s),
            ("rpc_timeout_s", c.rpc_timeout_s),
            ("wait_timeout_s", c.wait_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!(
                    "cluster.{name} must be positive and finite, got {v}"
                ));
            }
        }
        if !(c.join_grace_s.is_finite() && c.join_grace_s >= 0.0) {
            return bad(format!(
                "cluster.join_grace_s must be non-negative and finite, got {}",
                c.join_grace_s
            ));
        }
        Ok(())
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
