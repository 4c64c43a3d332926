//! Opening a job's run folder: a new job (refused before anything is written if it
//! cannot run), a restarted coordinator's or a `--resume`d job's continuation, or a job
//! started from a checkpoint `osrt import-checkpoint` wrote.

use super::Coordinator;
use crate::core::{Core, JobSpec, Persisted};
use crate::error::CoordinatorError;
use osrt_run::{
    CONFIG_FILE, INFO_FILE, JOB_FILE, METRICS_FILE, RunError, RunInfo, checkpoint,
    cluster_config::ClusterConfig, read_file, write_file,
};
use osrt_store::Location;
use std::time::Instant;

/// Refuses a job whose `min_workers` its batch cannot feed (one scene per worker), or
/// whose chunks the collective does not carry.
fn gatherable(spec: &JobSpec, run: &Location) -> Result<(), CoordinatorError> {
    let chunk = spec.cluster.chunk_floats;
    if chunk > osrt_proto::MAX_CHUNK_FLOATS {
        return Err(run_err(
            run,
            CONFIG_FILE,
            format!(
                "cluster.chunk_floats = {chunk} exceeds the collective's chunk of 1 MiB of f32 ({})",
                osrt_proto::MAX_CHUNK_FLOATS
            ),
        ));
    }
    let min = spec.cluster.min_workers;
    match ClusterConfig::global_batch_of(&spec.job_toml).filter(|&b| min > b) {
        Some(b) => Err(run_err(
            run,
            CONFIG_FILE,
            format!(
                "cluster.min_workers = {min} can never gather: a step's {b} scenes \
                 (train.batch_size) feed at most {b} workers; lower --min-workers or raise \
                 --batch-size"
            ),
        )),
        None => Ok(()),
    }
}

pub(super) fn run_err(
    run: &Location,
    name: &str,
    reason: impl std::fmt::Display,
) -> CoordinatorError {
    CoordinatorError::Run(RunError::Run {
        path: run.describe(&run.path(name)),
        reason: reason.to_string(),
    })
}

impl Coordinator {
    /// The job's state from the run folder (read again under the lease: the folder's
    /// previous holder may have written last), or a new job's; `last_record`: the newest
    /// step of the folder's metrics records.
    pub(super) async fn open_core(
        mut spec: JobSpec,
        run: &Location,
        resume: bool,
        last_record: Option<u64>,
    ) -> Result<Core, CoordinatorError> {
        let run = run.clone();
        let persisted: Option<Persisted> = match read_file(&run, JOB_FILE).await? {
            Some(b) => Some(
                serde_json::from_slice(&b)
                    .map_err(|e| run_err(&run, JOB_FILE, format!("unreadable: {e}")))?,
            ),
            None => None,
        };
        let now = Instant::now();
        let core = match persisted {
            None if resume => Self::continue_imported(spec, &run, last_record, now).await?,
            None => Self::create(spec, &run, last_record, now).await?,
            Some(p) => {
                let finished = p.state == "done" || p.state == "failed";
                if finished && !resume {
                    return Err(run_err(
                        &run,
                        JOB_FILE,
                        format!(
                            "the job in this run folder is {}; pass --resume to continue it with new limits, or choose a new --run",
                            p.state
                        ),
                    ));
                }
                let text = read_file(&run, CONFIG_FILE)
                    .await?
                    .ok_or_else(|| run_err(&run, CONFIG_FILE, "missing"))?;
                let text = String::from_utf8_lossy(&text).into_owned();
                spec.cluster =
                    ClusterConfig::from_job_toml(&run.describe(&run.path(CONFIG_FILE)), &text)?;
                // The command line's membership limits win over the stored ones; the
                // stored text (hashed into checkpoints) is what workers get.
                spec.cluster_overrides.apply(&mut spec.cluster);
                spec.cluster.validate()?;
                spec.job_toml = text;
                spec.job_id = p.job_id.clone();
                spec.data = p.data.clone();
                gatherable(&spec, &run)?;
                if !resume {
                    // A restarted coordinator keeps the job's limits.
                    spec.max_steps = p.max_steps;
                    spec.deadline_unix_s = p.deadline_unix_s;
                }
                // The job continues from the checkpoint `job.json` recorded (or the newest
                // older one that verifies), and never from past the last step whose records
                // reached the store (flushed every 1 s, 5 s on object stores): the steps after
                // it are replayed and their records sent again, so none is missing.
                // No record at all: the job starts over.
                let at_most = checkpoint::resume_bound(last_record, p.last_checkpoint);
                let checkpoint = checkpoint::latest_verified(&run, Some(at_most)).await?;
                tracing::info!(
                    job = %p.job_id,
                    generation = p.generation,
                    checkpoint = ?checkpoint,
                    "continuing the job in the run folder"
                );
                let mut core = Core::new(spec, now);
                core.restore(&p, last_record, checkpoint, resume, now);
                core
            }
        };
        Ok(core)
    }

    /// `--resume` on a folder without a job: one `osrt import-checkpoint` wrote (its
    /// config and a checkpoint of a model trained elsewhere, no records) starts a job
    /// from that checkpoint, with the folder's config; its records begin at that step.
    /// Anything else has no job to resume.
    async fn continue_imported(
        mut spec: JobSpec,
        run: &Location,
        last_record: Option<u64>,
        now: Instant,
    ) -> Result<Core, CoordinatorError> {
        let no_job = || {
            run_err(
                run,
                JOB_FILE,
                "--resume: no job to resume in this run folder",
            )
        };
        let Some(text) = read_file(run, CONFIG_FILE).await? else {
            return Err(no_job());
        };
        if last_record.is_some() {
            return Err(no_job());
        }
        let Some(step) = checkpoint::latest_verified(run, None).await? else {
            return Err(no_job());
        };
        let text = String::from_utf8_lossy(&text).into_owned();
        spec.cluster = ClusterConfig::from_job_toml(&run.describe(&run.path(CONFIG_FILE)), &text)?;
        spec.cluster_overrides.apply(&mut spec.cluster);
        spec.cluster.validate()?;
        spec.job_toml = text;
        gatherable(&spec, run)?;
        let mut info: RunInfo = match read_file(run, INFO_FILE).await? {
            Some(b) => serde_json::from_slice(&b)
                .map_err(|e| run_err(run, INFO_FILE, format!("unreadable: {e}")))?,
            None => return Err(no_job()),
        };
        info.data = spec.data.clone();
        info.workers = spec.cluster.min_workers;
        let bytes = serde_json::to_vec_pretty(&info).expect("serialises");
        write_file(run, INFO_FILE, bytes).await?;
        tracing::info!(
            checkpoint = step,
            "starting the job from the imported checkpoint"
        );
        let p = Persisted {
            job_id: spec.job_id.clone(),
            data: spec.data.clone(),
            max_steps: spec.max_steps,
            deadline_unix_s: spec.deadline_unix_s,
            generation: 0,
            restarts: 0,
            last_checkpoint: Some(step),
            hash_checks: 0,
            state: "waiting".into(),
            message: String::new(),
        };
        let mut core = Core::new(spec, now);
        // The folder's history begins at the checkpoint: nothing before it is missing.
        core.restore(&p, Some(step), Some(step), true, now);
        Ok(core)
    }

    /// A new job in an empty run folder: refused before anything is written if it cannot
    /// run; then its config and run info are written.
    async fn create(
        spec: JobSpec,
        run: &Location,
        last_record: Option<u64>,
        now: Instant,
    ) -> Result<Core, CoordinatorError> {
        let metrics = read_file(run, METRICS_FILE).await?;
        if last_record.is_some() || metrics.is_some_and(|m| !m.is_empty()) {
            return Err(run_err(
                run,
                METRICS_FILE,
                "the run folder already holds a run; choose a new --run or pass --resume",
            ));
        }
        if !checkpoint::list_steps(run).await?.is_empty() {
            return Err(run_err(
                run,
                "checkpoints",
                "the run folder holds checkpoints (a model imported with osrt \
                 import-checkpoint?): pass --resume to continue from them, or choose a new --run",
            ));
        }
        // Refused before anything is written.
        gatherable(&spec, run)?;
        write_file(run, CONFIG_FILE, spec.job_toml.clone().into_bytes()).await?;
        // The parameter count comes from rank 0: the coordinator never builds the
        // model (the `paper` preset's weights and optimizer state are a gigabyte).
        let info = RunInfo {
            data: spec.data.clone(),
            parameters: None,
            workers: spec.cluster.min_workers,
            horizon: None,
        };
        write_file(
            run,
            INFO_FILE,
            serde_json::to_vec_pretty(&info).expect("serialises"),
        )
        .await?;
        Ok(Core::new(spec, now))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(cluster: ClusterConfig) -> JobSpec {
        JobSpec {
            job_id: "j".into(),
            cluster,
            job_toml: String::new(),
            data: "data".into(),
            run: "run".into(),
            max_steps: None,
            deadline_unix_s: None,
            cluster_overrides: Default::default(),
        }
    }

    /// The run folder's default chunk is the collective's largest, and a larger one is
    /// refused before any worker joins.
    #[test]
    fn chunks_the_collective_cannot_carry_are_refused() {
        let run = Location::parse("memory://gatherable").unwrap();
        let default = ClusterConfig::default();
        assert_eq!(default.chunk_floats, osrt_proto::MAX_CHUNK_FLOATS);
        assert!(gatherable(&spec(default.clone()), &run).is_ok());
        let big = ClusterConfig {
            chunk_floats: osrt_proto::MAX_CHUNK_FLOATS + 1,
            ..default
        };
        let e = gatherable(&spec(big), &run).unwrap_err().to_string();
        assert!(e.contains("exceeds the collective's chunk"), "{e}");
    }
}
