//! The learner: one rank's side of a generation without the cluster around it. It opens
//! the generation's starting point (a verified checkpoint, or fresh weights), deals this
//! rank's data epoch by epoch, computes each step's gradients, applies the reduced step,
//! and decides what the step leaves behind: metrics records, the parameter hash, a
//! validation run, a checkpoint snapshot. It makes no RPC; the worker shell
//! ([`crate::worker`]) does membership, heartbeats, the all-reduce and the reports.
//!
//! A generation runs as:
//! ```text
//! Learner::open ─▶ (fresh: shell broadcasts rank 0's weights) ─▶ begin
//!   loop: gradients ─▶ (shell: all-reduce) ─▶ finish_step ─▶ (shell: reports, commit)
//! ```

use crate::checkpoint::{self, Snapshot};
use crate::config::{JobConfig, TrainConfig};
use crate::distributed::{Reduced, Signals};
use crate::error::{Result, TrainError};
use crate::eval::{EvalOptions, EvalResult, evaluate};
use crate::feed::Feed;
use crate::lr_schedule::{Horizon, RateClock};
use crate::retry::{READ_RETRY_BUDGET, retry_transient};
use crate::shard::{EpochPlan, scene_rng};
use crate::step::{ApplyOutcome, Gradient, StepGradients, Trainer};
use candle_core::Device;
use osrt_dataset::{
    BatchConfig, Columns, RowGroupRef, Scene, SplitReader, build_batch_each, load_split,
};
use osrt_run::checkpoint::{CheckpointState, param_hash, step_dir};
use osrt_run::{EvalRecord, MetricsRecord, ObjectCountRecord, TrainRecord, unix_now};
use osrt_store::Location;
use std::sync::Arc;
use std::time::Instant;

/// Where a generation starts and who this rank is in it.
pub struct Start {
    pub data: Location,
    pub run: Location,
    pub rank: usize,
    pub world: usize,
    /// The committed checkpoint to start from; `None`: fresh weights.
    pub resume_step: Option<u64>,
    /// SHA-256 of the job config's TOML: a checkpoint of another config is refused.
    pub config_hash: String,
    /// Generations the coordinator formed again before this one (for the records).
    pub restarts: u32,
    /// The job's budget: its step limit and deadline (Unix seconds).
    pub max_steps: Option<u64>,
    pub deadline_unix_s: Option<f64>,
}

/// What a finished step asks of the shell.
pub struct StepEnd {
    /// Records for `metrics.jsonl` (rank 0 only).
    pub records: Vec<MetricsRecord>,
    /// This replica's parameter hash, when the coordinator compares them.
    pub hash: Option<String>,
    /// A checkpoint to commit (rank 0, every `checkpoint_every` steps and at the end).
    pub snapshot: Option<Snapshot>,
    /// The job's last step (the step limit or the deadline).
    pub last: bool,
    /// The decay horizon this step decided (a budget job's, measured on rank 0): the
    /// shell records it in `run.json`.
    pub horizon_decided: Option<u64>,
}

/// The epoch in progress: its sequence, this rank's scenes of it, its first step.
struct Epoch {
    feed: Feed,
    start_step: u64,
}

impl Epoch {
    fn plan(&self) -> &EpochPlan {
        self.feed.plan()
    }
}

/// The training window a [`TrainRecord`] averages over.
struct Window {
    since: Instant,
    samples: f64,
    loss: f64,
    steps: u64,
    /// Sum and count of the applied steps' gradient norms.
    grad_norm: f64,
    applied: u64,
}

impl Window {
    fn new() -> Self {
        Self {
            since: Instant::now(),
            samples: 0.0,
            loss: 0.0,
            steps: 0,
            grad_norm: 0.0,
            applied: 0,
        }
    }
}

pub struct Learner {
    pub trainer: Trainer,
    state: CheckpointState,
    job: JobConfig,
    rank: usize,
    world: usize,
    fresh: bool,
    data: Location,
    groups: Arc<Vec<RowGroupRef>>,
    val: Vec<Scene>,
    epoch: Epoch,
    batch_cfg: BatchConfig,
    eval_opts: EvalOptions,
    /// Clocks: the generation's start, the job's wall and train seconds before it, the
    /// train seconds so far, the last validation, the step in progress.
    gen_start: Instant,
    wall0: f64,
    train_s: f64,
    last_eval: Instant,
    step_start: Instant,
    window: Window,
    restarts: u32,
    max_steps: Option<u64>,
    deadline_unix_s: Option<f64>,
    /// Rank 0's step rate, for a budget job's horizon (`crate::schedule`).
    rate: RateClock,
    /// Pictures of validations for the run folder (rank 0), `(step, name, PNG)`, until
    /// the shell takes them.
    pictures: Vec<(u64, &'static str, Vec<u8>)>,
}

impl Learner {
    /// Builds the model and opens the generation's starting point, this rank's first
    /// epoch and the validation scenes. Checkpoints past the starting point (an abandoned
    /// timeline's) were discarded by the coordinator, the run folder's lease holder,
    /// before this generation's plans went out; workers never delete.
    pub async fn open(job: JobConfig, device: Device, s: Start) -> Result<Self> {
        let (rank, world) = (s.rank, s.world);
        let mut trainer = tokio::task::block_in_place(|| Trainer::new(job.clone(), device))?;
        if rank == 0
            && let Err(e) = osrt_run::record_parameters(&s.run, trainer.num_parameters()).await
        {
            tracing::warn!(error = %e, "could not record the parameter count in run.json");
        }
        let t = &job.train;
        let mut state = match s.resume_step {
            Some(step) => {
                let st = checkpoint::load(&s.run, step, &mut trainer).await?;
                if st.config_hash != s.config_hash {
                    return Err(TrainError::Config {
                        path: s.run.describe(&s.run.path(&step_dir(step))),
                        reason: "the checkpoint was written with another job config; resume with the run's own config.toml".into(),
                    });
                }
                st
            }
            None => fresh_state(world, &s.config_hash),
        };
        // The data sequence and the draws do not depend on the worker count: another
        // world size continues the epoch where it stood.
        state.world_size = world;
        state.rng = format!(
            "ChaCha8 per scene and step from (seed {}, step, scene id)",
            t.seed
        );
        if rank == 0 {
            say_products(t);
        }
        trainer.horizon = starting_horizon(t, state.horizon, &s);
        state.horizon = trainer.horizon;
        let data = s.data;
        let groups = Arc::new(
            retry_transient("listing the train split", READ_RETRY_BUDGET, || {
                list_row_groups(&data)
            })
            .await?,
        );
        let val = retry_transient("reading the validation scenes", READ_RETRY_BUDGET, || {
            let columns = Columns {
                masks: true,
                objects: false,
            };
            let data = &data;
            async move { Ok(load_split(data, "val", columns, Some(t.eval_scenes)).await?) }
        })
        .await?;
        let epoch = open_epoch(
            &data,
            &groups,
            t,
            state.epoch,
            state.epoch_start_step,
            rank,
            world,
        )?;
        let batch_cfg = BatchConfig {
            input_views: t.input_views,
            input_selection: t.input_selection,
            target_views: t.target_views,
            rays_per_scene: Some(t.rays_per_scene),
            with_masks: false,
            salient_fraction: t.salient_fraction,
            ray_frame: crate::config::ray_frame(&job.model),
            input_stride: t.input_stride,
        };
        let eval_opts = crate::loaded::eval_options(&job);
        let now = Instant::now();
        Ok(Self {
            trainer,
            wall0: state.wall_s,
            train_s: state.train_s,
            state,
            job,
            rank,
            world,
            fresh: s.resume_step.is_none(),
            data,
            groups,
            val,
            epoch,
            batch_cfg,
            eval_opts,
            gen_start: now,
            last_eval: now,
            step_start: now,
            window: Window::new(),
            restarts: s.restarts,
            max_steps: s.max_steps,
            deadline_unix_s: s.deadline_unix_s,
            rate: RateClock::default(),
            pictures: Vec::new(),
        })
    }

    /// Whether the weights are fresh (not from a checkpoint): the shell then makes every
    /// rank's weights rank 0's before [`Learner::begin`].
    pub fn is_fresh(&self) -> bool {
        self.fresh
    }

    /// The optimiser steps taken so far.
    pub fn step(&self) -> u64 {
        self.trainer.step
    }

    fn train(&self) -> &TrainConfig {
        &self.job.train
    }

    fn wall(&self) -> f64 {
        self.wall0 + self.gen_start.elapsed().as_secs_f64()
    }

    /// Starts the generation's clocks. A fresh job evaluates its initial weights (every
    /// rank, so none waits for rank 0 in the first all-reduce): the curve starts at step
    /// 0; rank 0 gets its record.
    pub fn begin(&mut self) -> Result<Option<MetricsRecord>> {
        self.gen_start = Instant::now();
        self.last_eval = Instant::now();
        self.window = Window::new();
        let warmup = self.train().warmup_steps;
        if self.trainer.step != 0 {
            self.rate.start(self.trainer.step, unix_now(), warmup);
            return Ok(None);
        }
        let r = self.evaluate()?;
        self.rate.evaluated(self.last_eval.elapsed().as_secs_f64());
        self.rate.start(0, unix_now(), warmup);
        self.keep_pictures(0, &r);
        Ok((self.rank == 0).then(|| eval_record(0, 0.0, 0.0, &r).into()))
    }

    /// Rank 0's clock decides for every rank: validate now (the interval has passed),
    /// stop now (the deadline has passed), the decay's horizon (a budget job's, from the
    /// last warm-up step on, until one is decided).
    pub fn signals(&self) -> Signals {
        let t = self.train();
        let now = unix_now();
        let horizon = match (t.horizon, self.trainer.horizon, self.deadline_unix_s) {
            (Horizon::Budget, None, Some(d)) => self.rate.propose(
                self.trainer.step,
                now,
                d,
                t.warmup_steps,
                t.eval_every_s,
                self.max_steps,
            ),
            _ => None,
        };
        Signals {
            evaluate: self.last_eval.elapsed().as_secs_f64() >= t.eval_every_s,
            stop: self.deadline_unix_s.is_some_and(|d| now >= d),
            horizon,
        }
    }

    /// This rank's gradients of the next step (its share of the global batch), opening
    /// the next epoch where the last one is used up. A worker on a GPU keeps its
    /// gradient there: alone it never leaves the device, and on a ring it goes to the
    /// host bucket by bucket as the ring needs it (`crate::staging`). The GPU's graph on
    /// the CPU (`kernels = "device"`) takes that staged path on a ring too, so that it
    /// runs where there is no GPU.
    pub async fn gradients(&mut self) -> Result<StepGradients<Gradient>> {
        let step = self.trainer.step;
        if step - self.epoch.start_step >= self.epoch.plan().steps {
            let next = self.epoch.plan().epoch + 1;
            let t = &self.job.train;
            self.epoch = open_epoch(
                &self.data,
                &self.groups,
                t,
                next,
                step,
                self.rank,
                self.world,
            )?;
        }
        self.step_start = Instant::now();
        let (world, seed) = (self.world, self.train().seed);
        let k = step - self.epoch.start_step;
        let refs = self.epoch.feed.scenes(k).await?;
        // Each scene's draws come from its own stream: the same for any worker count
        // and any micro-batch size.
        let mut rngs: Vec<_> = refs.iter().map(|s| scene_rng(seed, step, s.id)).collect();
        let (cfg, trainer) = (&self.batch_cfg, &self.trainer);
        let keep = !crate::device::is_cpu(trainer.device())
            || (world > 1 && self.job.train.kernels == osrt_kernels::Kernels::Device);
        tokio::task::block_in_place(|| {
            let batch = build_batch_each(&refs, cfg, &mut rngs)?;
            trainer.gradients_each(&batch, &mut rngs, keep)
        })
    }

    /// Applies the reduced step (or skips it everywhere, if it was not finite), then
    /// decides what the step leaves: a training record every `log_every` steps, a
    /// validation when rank 0's clock asked or at the end, the parameter hash every
    /// `hash_every` steps, a checkpoint snapshot every `checkpoint_every` steps.
    pub fn finish_step(&mut self, reduced: Reduced) -> Result<StepEnd> {
        let t = self.job.train.clone();
        let c = self.job.cluster.clone();
        let max_steps = self.max_steps;
        // Before the step's learning rate is taken.
        let horizon_decided = self.take_horizon(reduced.signals.horizon);
        let outcome = tokio::task::block_in_place(|| {
            self.trainer
                .apply_summarized(reduced.loss, reduced.grads, reduced.summary)
        })?;
        self.train_s += self.step_start.elapsed().as_secs_f64();
        if self.rank == 0 {
            self.rate.stepped(self.trainer.step, unix_now());
        }
        if let ApplyOutcome::Applied { grad_norm, .. } = outcome {
            self.window.grad_norm += grad_norm;
            self.window.applied += 1;
        }
        if let ApplyOutcome::Skipped { reason } = &outcome {
            tracing::warn!(step = self.trainer.step - 1, reason, from = %reduced.nonfinite, "step skipped on every rank");
            if self.trainer.skipped_in_a_row >= t.max_consecutive_skips {
                return Err(TrainError::TooManySkips {
                    skipped: self.trainer.skipped_in_a_row,
                    limit: t.max_consecutive_skips,
                });
            }
        }
        let step = self.trainer.step;
        self.window.samples += reduced.samples;
        self.window.loss += reduced.loss;
        self.window.steps += 1;

        let mut records = Vec::new();
        if self.rank == 0 && step.is_multiple_of(t.log_every) {
            let dt = self.window.since.elapsed().as_secs_f64().max(1e-9);
            let w = &self.window;
            records.push(MetricsRecord::Train(TrainRecord {
                epoch: self.epoch.plan().epoch,
                grad_norm: (w.applied > 0).then(|| w.grad_norm / w.applied as f64),
                loss: self.window.loss / self.window.steps as f64,
                lr: self.trainer.lr_at(step - 1),
                micro_batches: crate::step::micro_batches(
                    crate::shard::share(t.batch_size, self.world, self.rank).len(),
                    t.micro_batch_size,
                )
                .len() as u32,
                peak_rss_mb: crate::memory::peak_rss_mb(),
                restarts: self.restarts,
                scenes_per_s: self.window.samples / dt,
                skipped: self.trainer.skipped_total,
                step,
                train_s: self.train_s,
                wall_s: self.wall(),
                workers: self.world,
            }));
            self.window = Window::new();
        }
        let last = reduced.signals.stop || max_steps.is_some_and(|m| step >= m);
        if reduced.signals.evaluate || last {
            // Every rank evaluates (identical weights, identical result): nobody idles in
            // the next all-reduce waiting for rank 0.
            let t0 = Instant::now();
            let r = self.evaluate()?;
            self.rate.evaluated(t0.elapsed().as_secs_f64());
            self.state.val_fg_ari = r.fg_ari;
            self.state.val_psnr = Some(r.psnr);
            self.keep_pictures(step, &r);
            if self.rank == 0 {
                records.push(eval_record(step, self.wall(), self.train_s, &r).into());
            }
            self.last_eval = Instant::now();
        }
        let hash = (step.is_multiple_of(c.hash_every) || last)
            .then(|| self.trainer.params.flatten().map(|f| param_hash(&f)))
            .transpose()?;
        let snapshot = (self.rank == 0 && (step.is_multiple_of(c.checkpoint_every) || last))
            .then(|| {
                let st = CheckpointState {
                    step,
                    epoch: self.epoch.plan().epoch,
                    epoch_start_step: self.epoch.start_step,
                    world_size: self.world,
                    adam_t: self.trainer.opt.t(),
                    skipped_total: self.trainer.skipped_total,
                    wall_s: self.wall(),
                    train_s: self.train_s,
                    ..self.state.clone()
                };
                tokio::task::block_in_place(|| Snapshot::take(&self.trainer, st))
            })
            .transpose()?;
        Ok(StepEnd {
            records,
            hash,
            snapshot,
            last,
            horizon_decided: horizon_decided.filter(|_| self.rank == 0),
        })
    }

    /// Takes rank 0's proposed decay horizon (every rank has it from the all-reduce) where
    /// a budget job has none yet; returns it when taken.
    fn take_horizon(&mut self, proposed: Option<u64>) -> Option<u64> {
        let h = proposed.filter(|_| {
            self.trainer.horizon.is_none() && self.train().horizon == Horizon::Budget
        })?;
        self.trainer.horizon = Some(h);
        self.state.horizon = Some(h);
        if self.rank == 0 {
            tracing::info!(
                horizon = h,
                step = self.trainer.step,
                "decay horizon measured: the learning rate reaches its floor at step {h}, the deadline"
            );
        }
        Some(h)
    }

    /// Rank 0 keeps the pictures of the validation at `step` for the run folder.
    fn keep_pictures(&mut self, step: u64, r: &EvalResult) {
        if self.rank != 0 {
            return;
        }
        if let Some(sample) = &r.sample {
            for (name, png) in crate::pictures::eval_pictures(sample) {
                self.pictures.push((step, name, png));
            }
        }
    }

    /// The validation pictures not yet taken: `(step, name, PNG)`.
    pub fn take_pictures(&mut self) -> Vec<(u64, &'static str, Vec<u8>)> {
        std::mem::take(&mut self.pictures)
    }

    fn evaluate(&self) -> Result<EvalResult> {
        tokio::task::block_in_place(|| evaluate(&self.trainer.model, &self.val, &self.eval_opts))
    }
}

/// Says which unit runs a bf16 job's products on the CPU's fused kernels (or that the
/// CPU has none and they run in f32).
fn say_products(t: &TrainConfig) {
    if t.precision != osrt_kernels::Precision::Bf16
        || t.device.is_cuda()
        || t.kernels != osrt_kernels::Kernels::Fused
    {
        return;
    }
    match osrt_kernels::cpu_bf16_products() {
        Some(unit) => tracing::info!(unit, "bf16 products on the CPU's {unit}"),
        None => tracing::warn!(
            "train.precision = \"bf16\", but this CPU has no bf16 products (AMX or \
             AVX512-BF16): the products run in f32"
        ),
    }
}

/// The decay horizon a generation starts with: one a budget job decided before holds for
/// the rest of the job; else the config's or the step limit's, if any. Rank 0 says which.
fn starting_horizon(t: &TrainConfig, recorded: Option<u64>, s: &Start) -> Option<u64> {
    let schedule = t.schedule();
    let horizon = match (schedule.horizon, recorded) {
        (Horizon::Budget, Some(h)) => Some(h),
        _ => schedule.initial_horizon(s.max_steps, s.deadline_unix_s.is_some()),
    };
    if s.rank == 0 && schedule.horizon == Horizon::Budget {
        match (horizon, s.deadline_unix_s) {
            (Some(h), _) => tracing::info!(
                horizon = h,
                "the learning rate decays to its floor at step {h}"
            ),
            (None, Some(_)) => tracing::info!(
                "the learning rate's decay horizon is measured over the warm-up ({} steps) from the time left",
                t.warmup_steps
            ),
            (None, None) => tracing::warn!(
                decay_steps = t.decay_steps,
                "horizon = \"budget\" without --max-steps or --max-minutes: the decay follows decay_steps"
            ),
        }
    }
    horizon
}

/// The state of a job that starts from fresh weights.
fn fresh_state(world: usize, config_hash: &str) -> CheckpointState {
    CheckpointState {
        step: 0,
        epoch: 0,
        epoch_start_step: 0,
        world_size: world,
        rng: String::new(),
        adam_t: 0,
        skipped_total: 0,
        wall_s: 0.0,
        train_s: 0.0,
        config_hash: config_hash.to_string(),
        val_fg_ari: None,
        val_psnr: None,
        horizon: None,
    }
}

/// The record of a validation at `step`.
pub fn eval_record(step: u64, wall_s: f64, train_s: f64, r: &EvalResult) -> EvalRecord {
    EvalRecord {
        ari: r.ari,
        baseline_psnr: Some(r.baseline_psnr).filter(|v| v.is_finite()),
        by_objects: r
            .by_objects
            .iter()
            .map(|o| ObjectCountRecord {
                fg_ari: o.fg_ari,
                objects: o.objects,
                scenes: o.scenes,
            })
            .collect(),
        eval_scenes: r.scenes,
        fg_ari: r.fg_ari,
        fg_ari_2d: r.fg_ari_2d,
        psnr: r.psnr,
        ratio: r.ratio,
        render_fps: r.render_fps,
        step,
        train_s,
        wall_s,
    }
}

/// The train split's row groups, listed once per generation.
async fn list_row_groups(data: &Location) -> Result<Vec<RowGroupRef>> {
    Ok(SplitReader::open(data.join("train"))
        .await?
        .row_groups()
        .await?)
}

/// The epoch's sequence and this rank's feed of it; its scenes are read as the steps
/// need them.
fn open_epoch(
    data: &Location,
    groups: &Arc<Vec<RowGroupRef>>,
    t: &TrainConfig,
    epoch: u64,
    start_step: u64,
    rank: usize,
    world: usize,
) -> Result<Epoch> {
    crate::shard::check_world(t.batch_size, world, rank)?;
    let plan = EpochPlan::new(groups, t.seed, epoch, t.batch_size)?;
    let share = crate::shard::share(t.batch_size, world, rank);
    Ok(Epoch {
        feed: Feed::new(data.clone(), groups.clone(), Arc::new(plan), share),
        start_step,
    })
}
