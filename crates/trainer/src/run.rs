//! A single-process training run: load data, train with periodic validation, log the
//! error-against-run-time record to `metrics.jsonl`, save weights as safetensors.
//!
//! Run folder:
//! ```text
//! RUN/config.toml          the resolved job config
//! RUN/run.json             dataset location, parameter count, start time
//! RUN/metrics.jsonl        one JSON object per line: training and evaluation records
//! RUN/weights.safetensors  final weights (written to a temporary name, then renamed)
//! RUN/state.json           step count and skip counters of the saved weights
//! ```

use crate::config::JobConfig;
use crate::data::{EpochSampler, load_split};
use crate::error::{Result, TrainError};
use crate::eval::{EvalOptions, EvalResult, evaluate};
use crate::step::{ApplyOutcome, Trainer};
use candle_core::Device;
use indicatif::{ProgressBar, ProgressStyle};
use osrt_dataset::{BatchConfig, Columns, Location, Scene, build_batch};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub struct TrainOptions {
    /// Dataset directory or URL.
    pub data: String,
    /// Local run folder.
    pub run: PathBuf,
    pub job: JobConfig,
    pub max_steps: Option<u64>,
    pub max_minutes: Option<f64>,
    pub progress: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunInfo {
    pub data: String,
    pub parameters: usize,
    pub workers: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunState {
    pub step: u64,
    pub skipped_total: u64,
    pub wall_s: f64,
}

#[derive(Debug, Clone)]
pub struct RunSummary {
    pub steps: u64,
    pub skipped: u64,
    pub wall_s: f64,
    pub final_eval: Option<EvalResult>,
}

/// Appends JSON lines, flushed per line so a crash loses at most the current record.
pub struct MetricsLog {
    file: std::fs::File,
    path: PathBuf,
}

impl MetricsLog {
    pub fn create(path: &Path) -> Result<Self> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .map_err(|e| TrainError::io(path.display(), e))?;
        Ok(Self {
            file,
            path: path.to_path_buf(),
        })
    }

    pub fn write(&mut self, record: &serde_json::Value) -> Result<()> {
        let line = format!("{record}\n");
        self.file
            .write_all(line.as_bytes())
            .and_then(|_| self.file.flush())
            .map_err(|e| TrainError::io(self.path.display(), e))
    }
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|e| TrainError::io(tmp.display(), e))?;
    std::fs::rename(&tmp, path).map_err(|e| TrainError::io(path.display(), e))
}

/// Saves the weights as safetensors (atomically: a crash leaves the previous file).
pub fn save_weights(trainer: &Trainer, path: &Path) -> Result<()> {
    let tensors = trainer.params.tensors();
    let bytes = safetensors::serialize(tensors.iter().map(|(k, v)| (k.as_str(), v)), None)
        .map_err(|e| TrainError::Run {
            path: path.display().to_string(),
            reason: format!("serialising weights: {e}"),
        })?;
    write_atomic(path, &bytes)
}

/// Loads weights saved by [`save_weights`] into `trainer`.
pub fn load_weights(trainer: &Trainer, path: &Path) -> Result<()> {
    let tensors =
        candle_core::safetensors::load(path, trainer.device()).map_err(|e| TrainError::Run {
            path: path.display().to_string(),
            reason: format!("reading weights: {e}"),
        })?;
    trainer
        .params
        .load_tensors(&tensors)
        .map_err(|e| TrainError::Run {
            path: path.display().to_string(),
            reason: e.to_string(),
        })
}

fn eval_record(step: u64, wall_s: f64, train_s: f64, r: &EvalResult) -> serde_json::Value {
    json!({
        "step": step,
        "wall_s": wall_s,
        "train_s": train_s,
        "psnr": r.psnr,
        "baseline_psnr": r.baseline_psnr,
        "fg_ari": r.fg_ari,
        "fg_ari_2d": r.fg_ari_2d,
        "ari": r.ari,
        "ratio": r.ratio,
        "render_fps": r.render_fps,
        "eval_scenes": r.scenes,
    })
}

pub fn eval_options(job: &JobConfig) -> EvalOptions {
    EvalOptions {
        input_views: job.train.input_views,
        target_views: job.train.eval_target_views,
        grayscale: false,
        seed: job.train.seed ^ 0xE7A1,
    }
}

/// Trains in this process until `max_steps` or `max_minutes` (whichever comes first).
pub async fn train(opts: TrainOptions) -> Result<RunSummary> {
    let job = opts.job.clone();
    job.validate()?;
    let run = &opts.run;
    std::fs::create_dir_all(run).map_err(|e| TrainError::io(run.display(), e))?;
    let metrics_path = run.join("metrics.jsonl");
    if metrics_path
        .metadata()
        .map(|m| m.len() > 0)
        .unwrap_or(false)
    {
        return Err(TrainError::Run {
            path: run.display().to_string(),
            reason: "already holds a run (metrics.jsonl is not empty); choose a new --run folder"
                .into(),
        });
    }
    let dataset = Location::parse(&opts.data)?;
    let t = &job.train;
    let train_scenes = load_split(&dataset, "train", Columns::TRAIN, None).await?;
    let val_scenes = load_split(
        &dataset,
        "val",
        Columns {
            masks: true,
            objects: false,
        },
        Some(t.eval_scenes),
    )
    .await?;
    tracing::info!(train = train_scenes.len(), val = val_scenes.len(), data = %opts.data, "data loaded");

    let mut trainer = Trainer::new(job.clone(), Device::Cpu)?;
    std::fs::write(run.join("config.toml"), job.to_toml())
        .map_err(|e| TrainError::io(run.display(), e))?;
    let info = RunInfo {
        data: opts.data.clone(),
        parameters: trainer.num_parameters(),
        workers: 1,
    };
    std::fs::write(
        run.join("run.json"),
        serde_json::to_vec_pretty(&info).expect("serialises"),
    )
    .map_err(|e| TrainError::io(run.display(), e))?;
    let mut log = MetricsLog::create(&metrics_path)?;

    let batch_cfg = BatchConfig {
        input_views: t.input_views,
        input_selection: t.input_selection,
        target_views: t.target_views,
        rays_per_scene: Some(t.rays_per_scene),
        with_masks: false,
        salient_fraction: t.salient_fraction,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(t.seed.wrapping_add(1));
    let mut sampler = EpochSampler::new(train_scenes.len());
    let eval_opts = eval_options(&job);

    let bar = if opts.progress {
        let b = match opts.max_steps {
            Some(n) => ProgressBar::new(n),
            None => ProgressBar::no_length(),
        };
        b.set_style(
            ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] step {pos}/{len} {msg} ETA {eta}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        b
    } else {
        ProgressBar::hidden()
    };

    let start = Instant::now();
    let mut train_s = 0.0;
    let mut last_eval = start;
    let mut window = (Instant::now(), 0usize, 0.0f64, 0u64);
    let deadline = opts
        .max_minutes
        .map(|m| start + std::time::Duration::from_secs_f64(m * 60.0));
    let evaluate_now = |trainer: &Trainer,
                        step: u64,
                        wall: f64,
                        train_s: f64,
                        log: &mut MetricsLog|
     -> Result<EvalResult> {
        let r = evaluate(&trainer.model, &val_scenes, &eval_opts)?;
        log.write(&eval_record(step, wall, train_s, &r))?;
        tracing::info!(
            step,
            wall_s = wall,
            psnr = r.psnr,
            baseline_psnr = r.baseline_psnr,
            fg_ari = r.fg_ari.unwrap_or(f64::NAN),
            "validation"
        );
        Ok(r)
    };
    evaluate_now(&trainer, 0, 0.0, 0.0, &mut log)?;
    loop {
        if opts.max_steps.is_some_and(|n| trainer.step >= n)
            || deadline.is_some_and(|d| Instant::now() >= d)
        {
            break;
        }
        let step_start = Instant::now();
        let idx = sampler.next_batch(t.batch_size, &mut rng);
        let refs: Vec<&Scene> = idx.iter().map(|&i| &train_scenes[i]).collect();
        let batch = build_batch(&refs, &batch_cfg, &mut rng)?;
        let g = trainer.gradients(&batch, &mut rng)?;
        let outcome = trainer.apply(g.loss, g.grads)?;
        train_s += step_start.elapsed().as_secs_f64();
        if let ApplyOutcome::Skipped { .. } = outcome
            && trainer.skipped_in_a_row >= t.max_consecutive_skips
        {
            return Err(TrainError::TooManySkips {
                skipped: trainer.skipped_in_a_row,
                limit: t.max_consecutive_skips,
            });
        }
        window.1 += batch.batch_size;
        window.2 += g.loss;
        window.3 += 1;
        bar.set_position(trainer.step);
        if trainer.step % t.log_every == 0 {
            let dt = window.0.elapsed().as_secs_f64().max(1e-9);
            let scenes_per_s = window.1 as f64 / dt;
            let loss = window.2 / window.3 as f64;
            let lr = t.lr_at(trainer.step - 1);
            log.write(&json!({
                "step": trainer.step,
                "wall_s": start.elapsed().as_secs_f64(),
                "train_s": train_s,
                "loss": loss,
                "scenes_per_s": scenes_per_s,
                "lr": lr,
                "skipped": trainer.skipped_total,
                "epoch": sampler.epoch,
            }))?;
            bar.set_message(format!("loss {loss:.5} {scenes_per_s:.1} scenes/s"));
            window = (Instant::now(), 0, 0.0, 0);
        }
        if last_eval.elapsed().as_secs_f64() >= t.eval_every_s {
            let wall = start.elapsed().as_secs_f64();
            bar.suspend(|| evaluate_now(&trainer, trainer.step, wall, train_s, &mut log))?;
            last_eval = Instant::now();
        }
    }
    bar.finish_and_clear();
    let wall_s = start.elapsed().as_secs_f64();
    let final_eval = evaluate_now(&trainer, trainer.step, wall_s, train_s, &mut log)?;
    save_weights(&trainer, &run.join("weights.safetensors"))?;
    let state = RunState {
        step: trainer.step,
        skipped_total: trainer.skipped_total,
        wall_s,
    };
    write_atomic(
        &run.join("state.json"),
        &serde_json::to_vec_pretty(&state).expect("serialises"),
    )?;
    Ok(RunSummary {
        steps: trainer.step,
        skipped: trainer.skipped_total,
        wall_s,
        final_eval: Some(final_eval),
    })
}

/// A trained run, loaded for evaluation or rendering.
pub struct LoadedRun {
    pub job: JobConfig,
    pub info: RunInfo,
    pub trainer: Trainer,
}

pub fn load_run(run: &Path) -> Result<LoadedRun> {
    let job = JobConfig::load(&run.join("config.toml"))?;
    let info_path = run.join("run.json");
    let info: RunInfo = serde_json::from_slice(
        &std::fs::read(&info_path).map_err(|e| TrainError::io(info_path.display(), e))?,
    )
    .map_err(|e| TrainError::Run {
        path: info_path.display().to_string(),
        reason: e.to_string(),
    })?;
    let trainer = Trainer::new(job.clone(), Device::Cpu)?;
    let weights = run.join("weights.safetensors");
    if !weights.exists() {
        return Err(TrainError::Run {
            path: run.display().to_string(),
            reason: "no weights.safetensors: the run has not finished (or was not saved)".into(),
        });
    }
    load_weights(&trainer, &weights)?;
    Ok(LoadedRun { job, info, trainer })
}
