//! One generation's run on a fixed ring: the plan's job config and memory check, the
//! ring's opening and rank 0's weights, the learner's steps with their all-reduce, the
//! progress reports, validation pictures and checkpoint commits in the background.

use crate::error::{Result, WorkerError};
use crate::link::{Client, CoordinatorLink};
use crate::membership::{Liveness, aborted, spawn_heartbeat};
use crate::reduce::{broadcast_from_rank0, reduce};
use crate::shell::WorkerOptions;
use osrt_collective::{Mailbox, Ring, RingConfig};
use osrt_proto::convert::{Directive, WorkerPlan};
use osrt_run::cluster_config::ClusterConfig;
use osrt_run::{MetricsRecord, checkpoint};
use osrt_store::Location;
use osrt_trainer::checkpoint::Snapshot;
use osrt_trainer::learner::{Learner, Start};
use osrt_trainer::staging::Staging;
use osrt_trainer::{JobConfig, TrainError};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How a generation ended.
pub(crate) enum Ended {
    /// The job's final checkpoint is committed (rank 0) or the final step taken.
    Finished,
    /// Aborted; ask for the next plan. `report` = tell the coordinator why.
    Aborted { reason: String, report: bool },
    /// The coordinator no longer knows this worker (it restarted): register again.
    Forgotten,
}

/// One generation of `plan`: heartbeats and the ring around the learner's loop, the
/// step's reports and the checkpoint commits.
pub(crate) async fn run_generation(
    opts: &WorkerOptions,
    client: &mut Client,
    mailbox: &Arc<Mailbox>,
    worker_id: u64,
    plan: &WorkerPlan,
) -> Result<Ended> {
    let (job, device) = plan_job(opts, plan).await?;
    let c = job.cluster.clone();
    let run = Location::parse(&plan.run)?;
    let rank = plan.rank;

    let live = Arc::new(Liveness {
        step: AtomicU64::new(0),
        abort: Mutex::new(None),
    });
    mailbox.set_generation(plan.generation, rank, first_all_reduce(plan));
    // Five heartbeats per timeout: one lost beat never looks like a lost member.
    let every = Duration::from_secs_f64((c.heartbeat_timeout_s / 5.0).clamp(0.05, 1.0));
    let beats = (client.clone(), worker_id, every, opts.coordinator_timeout);
    let _stop_heartbeat = AbortOnDrop(Some(spawn_heartbeat(beats, plan, &live, mailbox)));
    let mut ring = open_ring(opts, plan, &c, mailbox)?;

    let mut learner = Learner::open(job, device, start_of(plan, &run)?).await?;
    let mut link = CoordinatorLink::new(client.clone(), plan, worker_id);
    if learner.is_fresh()
        && let Err(e) = take_rank0_weights(&mut learner, ring.as_mut(), rank).await
    {
        return aborted(&live, e);
    }
    // Records a report could not deliver go again with the next one (the coordinator
    // drops a record it already holds).
    let mut unsent: Vec<MetricsRecord> = learner.begin()?.into_iter().collect();
    put_pictures(&run, learner.take_pictures()).await;
    if !unsent.is_empty() {
        link.step(0, None, &mut unsent).await;
    }

    // Resumed at (or past) the step limit, e.g. a job that was stopped after its final
    // checkpoint committed but before the coordinator recorded it: that checkpoint is the
    // job's last one, and rank 0 reports it as final so the job ends instead of waiting.
    if plan.max_steps.is_some_and(|m| learner.step() >= m) {
        if rank == 0 {
            link.checkpoint(learner.step(), true).await?;
        }
        return Ok(Ended::Finished);
    }

    // A save still running when the generation is aborted is cancelled (its checkpoint
    // stays torn: no manifest); a finished generation awaits it.
    let mut pending_save: Option<AbortOnDrop<Result<u64>>> = None;
    // A GPU's gradient on its way to the ring and back (kept from step to step).
    let mut staging = None;
    loop {
        if let Some(a) = live.take_abort() {
            return Ok(a);
        }
        let step = learner.step();
        if plan.max_steps.is_some_and(|m| step >= m) {
            break;
        }
        live.step.store(step, Ordering::Relaxed);
        let reduced = match reduced_step(&mut learner, &mut ring, &mut staging, plan).await? {
            Ok(r) => r,
            Err(e) => return aborted(&live, e),
        };
        let end = learner.finish_step(reduced)?;
        // Before the record that names them reaches the coordinator.
        put_step_files(&run, learner.take_pictures(), end.horizon_decided).await;
        let step = learner.step();
        live.step.store(step, Ordering::Relaxed);
        unsent.extend(end.records);
        if (end.hash.is_some() || !unsent.is_empty())
            && link.step(step, end.hash, &mut unsent).await == Some(Directive::Stop)
        {
            return Ok(Ended::Aborted {
                reason: "the coordinator stopped the job".into(),
                report: false,
            });
        }
        if let Some(snap) = end.snapshot {
            let save = commit_and_report(
                snap,
                run.clone(),
                link.clone(),
                unsent.clone(),
                end.last,
                plan.generation,
            );
            save_in_background(&mut pending_save, save, end.last).await?;
        }
        if end.last {
            break;
        }
    }
    if let Some(prev) = pending_save.take() {
        prev.join().await?;
    }
    Ok(Ended::Finished)
}

/// The learner's next step `step`: its gradients (an error here ends the generation as
/// the trainer's errors do) reduced over the ring as all-reduce `step + 1`, a GPU's
/// through `staging` (an error there is the ring's: the inner result). Logs both phases' seconds at debug level: the all-reduce's share
/// of the step.
async fn reduced_step(
    learner: &mut Learner,
    ring: &mut Option<Ring>,
    staging: &mut Option<Staging>,
    plan: &WorkerPlan,
) -> Result<Result<osrt_trainer::distributed::Reduced>> {
    let (step, rank) = (learner.step(), plan.rank);
    let t = Instant::now();
    let g = learner.gradients().await?;
    let gradients_s = t.elapsed().as_secs_f64();
    if let Some(ring) = ring.as_mut() {
        // The predecessor computes the same share of work: it may still be at it when
        // this rank is done (a long step, micro-batches), for about as long again.
        ring.set_peer_grace(t.elapsed().saturating_mul(2));
    }
    let signals = learner.signals();
    let reduced = reduce(ring.as_mut(), staging, step + 1, rank, g, signals).await;
    let reduce_s = t.elapsed().as_secs_f64() - gradients_s;
    tracing::debug!(
        step,
        gradients_s,
        reduce_s,
        "step's gradients and all-reduce"
    );
    Ok(reduced)
}

/// What a step leaves in the run folder besides its checkpoint: validation pictures, and a
/// budget job's measured decay horizon in `run.json` (rank 0's step that decided it; a
/// failure is logged, not fatal: every checkpoint records it too).
async fn put_step_files(
    run: &Location,
    pictures: Vec<(u64, &'static str, Vec<u8>)>,
    decided: Option<u64>,
) {
    put_pictures(run, pictures).await;
    if let Some(h) = decided
        && let Err(e) = osrt_run::record_horizon(run, h).await
    {
        tracing::warn!(error = %e, horizon = h, "could not record the decay horizon in run.json");
    }
}

/// Where the plan's generation starts, and this rank in it.
fn start_of(plan: &WorkerPlan, run: &Location) -> Result<Start> {
    Ok(Start {
        data: Location::parse(&plan.data)?,
        run: run.clone(),
        rank: plan.rank,
        world: plan.world(),
        resume_step: plan.resume_step,
        config_hash: checkpoint::config_hash(&plan.job_config_toml),
        restarts: plan.restarts,
        max_steps: plan.max_steps,
        deadline_unix_s: plan.deadline_unix_s,
    })
}

/// Every rank starts from rank 0's fresh weights.
async fn take_rank0_weights(
    learner: &mut Learner,
    ring: Option<&mut Ring>,
    rank: usize,
) -> Result<()> {
    let mut flat = learner.trainer.params.flatten()?;
    broadcast_from_rank0(ring, 0, rank, &mut flat).await?;
    learner.trainer.params.load_flat(&flat)?;
    Ok(())
}

/// Commits a checkpoint in the background, one at a time (the previous one finished
/// first); the job's last one is awaited.
async fn save_in_background(
    pending: &mut Option<AbortOnDrop<Result<u64>>>,
    save: impl std::future::Future<Output = Result<u64>> + Send + 'static,
    last: bool,
) -> Result<()> {
    if let Some(prev) = pending.take() {
        prev.join().await?;
    }
    let task = AbortOnDrop(Some(tokio::spawn(save)));
    if last {
        task.join().await?;
    } else {
        *pending = Some(task);
    }
    Ok(())
}

/// Puts validation pictures into the run folder (`RUN/eval/`), for the coordinator's
/// TensorBoard events. A picture that cannot be written is left out, not a fault.
async fn put_pictures(run: &Location, pictures: Vec<(u64, &'static str, Vec<u8>)>) {
    for (step, name, png) in pictures {
        let path = osrt_run::tensorboard::eval_picture(step, name);
        if let Err(e) = osrt_run::write_file(run, &path, png).await {
            tracing::warn!(error = %e, step, "writing a validation picture");
        }
    }
}

/// Fails with a [`TrainError::Device`] (this worker leaves the job; another machine may
/// hold it) where the plan's step, as estimated, needs more memory than this machine has.
/// Only the fused CPU step's estimate is checked against measured peaks: for other op
/// paths an excess is logged.
async fn check_memory(job: &JobConfig, plan: &WorkerPlan, threads: usize) -> Result<()> {
    let Ok(data) = osrt_store::Location::parse(&plan.data) else {
        return Ok(());
    };
    // A dataset that cannot be read fails later, with its reason.
    let Ok(manifest) = osrt_dataset::Manifest::read(&data).await else {
        return Ok(());
    };
    let Some(fit) =
        osrt_trainer::footprint::check(job, manifest.image_size, plan.world(), threads, 1)
    else {
        return Ok(());
    };
    match fit.verdict {
        Ok(None) => Ok(()),
        Ok(Some(why)) => {
            tracing::warn!("{why}");
            Ok(())
        }
        Err(why) => Err(TrainError::Device(format!(
            "this worker's machine cannot hold the job's step: {why}"
        ))
        .into()),
    }
}

/// The plan's job config (with this worker's `--device`), checked (its memory too, unless
/// told not to), and its device.
async fn plan_job(
    opts: &WorkerOptions,
    plan: &WorkerPlan,
) -> Result<(JobConfig, candle_core::Device)> {
    let job = job_on_device(&plan.job_config_toml, opts.device)?;
    if opts.memory_check {
        check_memory(&job, plan, opts.threads).await?;
    }
    let device = job.train.device.open()?;
    Ok((job, device))
}

/// The job config of `toml` with `device` (this worker's `--device`) in place of its own.
/// A config that is wrong in itself is a [`TrainError::Config`] (the job's fault, fatal);
/// one that only this worker's device cannot run is a [`TrainError::Device`] (the worker
/// leaves, the job goes on without it).
fn job_on_device(
    toml: &str,
    device: Option<osrt_trainer::device::DeviceSpec>,
) -> Result<JobConfig> {
    let mut job = JobConfig::from_toml("plan from the coordinator", toml)?;
    job.validate()?;
    if let Some(d) = device.filter(|&d| d != job.train.device) {
        job.train.device = d;
        job.validate().map_err(|e| {
            TrainError::Device(format!(
                "this worker's --device {d} cannot run the job: {e}"
            ))
        })?;
    }
    Ok(job)
}

/// The number of the generation's first all-reduce: the weights' broadcast (0) of a fresh
/// job, else the gradient of the step after the checkpoint (`reduce` numbers step `s`'s
/// all-reduce `s + 1`).
fn first_all_reduce(plan: &WorkerPlan) -> u64 {
    plan.resume_step.map_or(0, |s| s + 1)
}

/// The generation's ring (none for a world of one).
fn open_ring(
    opts: &WorkerOptions,
    plan: &WorkerPlan,
    c: &ClusterConfig,
    mailbox: &Arc<Mailbox>,
) -> Result<Option<Ring>> {
    if plan.world() == 1 {
        return Ok(None);
    }
    let cfg = RingConfig {
        job: plan.job.clone(),
        generation: plan.generation,
        first_step: first_all_reduce(plan),
        rank: plan.rank,
        peers: plan.peers.clone(),
        bucket_floats: c.bucket_floats,
        chunk_floats: c.chunk_floats,
        timeout: Duration::from_secs_f64(c.rpc_timeout_s),
        credentials: opts.credentials.clone(),
    };
    Ok(Some(Ring::new(cfg, mailbox.clone())?))
}

/// Commits a checkpoint, delivers the records up to its step that earlier reports could
/// not (`unsent`), then reports the checkpoint: a checkpoint the coordinator accepts never
/// leaves a gap before it in `metrics.jsonl` (later steps are replayed if the generation
/// ends).
async fn commit_and_report(
    snap: Snapshot,
    run: Location,
    link: CoordinatorLink,
    unsent: Vec<MetricsRecord>,
    last: bool,
    generation: u64,
) -> Result<u64> {
    // Fenced by the generation: once the coordinator moved on (and recorded that in the
    // run folder's lease), this rank's commit is refused.
    let step = snap.commit(&run, Some(generation)).await?;
    if !unsent.is_empty() {
        link.held_records(step, &unsent).await?;
    }
    // Old checkpoints are the coordinator's to delete (`osrt_coordinator::retention`).
    link.checkpoint(step, last).await?;
    Ok(step)
}

/// A task that is cancelled if its handle is dropped before it is joined.
struct AbortOnDrop<T>(Option<tokio::task::JoinHandle<T>>);

impl<T> AbortOnDrop<Result<T>> {
    async fn join(mut self) -> Result<T> {
        let handle = self.0.take().expect("joined once");
        handle
            .await
            .map_err(|e| WorkerError::Cluster(format!("background task: {e}")))?
    }
}

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        if let Some(h) = &self.0 {
            h.abort();
        }
    }
}

#[cfg(test)]
mod device_tests {
    use super::*;
    use crate::membership::is_fatal;
    use osrt_kernels::Precision;
    use osrt_trainer::device::DeviceSpec;

    fn toml_of(f: impl FnOnce(&mut JobConfig)) -> String {
        let mut job = JobConfig::preset("tiny").unwrap();
        f(&mut job);
        job.to_toml()
    }

    /// A worker whose device cannot run a sound job has a device problem of its own (it
    /// leaves); a job that cannot run anywhere is the job's (fatal).
    #[test]
    fn a_device_only_this_worker_lacks_is_its_own_problem_not_the_jobs() {
        // bf16 with candle's composed ops runs on a GPU only.
        let bf16_gpu = toml_of(|j| {
            j.train.device = DeviceSpec::Cuda(0);
            j.train.precision = Precision::Bf16;
            j.train.kernels = osrt_kernels::Kernels::Composed;
        });
        let e = job_on_device(&bf16_gpu, Some(DeviceSpec::Cpu)).unwrap_err();
        assert!(
            matches!(e, WorkerError::Train(TrainError::Device(_))),
            "{e}"
        );
        assert!(e.to_string().contains("--device cpu"), "{e}");
        assert!(job_on_device(&bf16_gpu, Some(DeviceSpec::Cuda(1))).is_ok());
        // The same job written for a CPU is wrong in itself.
        let bf16_cpu = toml_of(|j| {
            j.train.precision = Precision::Bf16;
            j.train.kernels = osrt_kernels::Kernels::Composed;
        });
        let e = job_on_device(&bf16_cpu, None).unwrap_err();
        assert!(
            matches!(e, WorkerError::Train(TrainError::Config { .. })),
            "{e}"
        );
        assert!(is_fatal(&e));
        assert!(!is_fatal(&TrainError::Device("x".into()).into()));
    }
}
