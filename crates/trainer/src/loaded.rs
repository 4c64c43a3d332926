//! A trained run loaded for evaluation or rendering: the job config, and the model from
//! its newest checkpoint that verifies. The folder's layout and files: `osrt_run`.

use crate::checkpoint;
use crate::config::JobConfig;
use crate::device::DeviceSpec;
use crate::error::{Result, TrainError};
use crate::eval::EvalOptions;
use crate::step::Trainer;
use osrt_run::{CONFIG_FILE, INFO_FILE, RunInfo, read_file};
use osrt_store::Location;

pub fn eval_options(job: &JobConfig) -> EvalOptions {
    EvalOptions {
        input_views: job.train.input_views,
        input_stride: job.train.input_stride,
        target_views: job.train.eval_target_views,
        grayscale: false,
        seed: job.train.seed ^ 0xE7A1,
        kernels: job.train.kernels,
    }
}

/// A trained run, loaded for evaluation or rendering.
pub struct LoadedRun {
    pub job: JobConfig,
    pub info: RunInfo,
    pub trainer: Trainer,
    /// The checkpoint the weights come from.
    pub step: u64,
}

pub async fn load_run(run: &str) -> Result<LoadedRun> {
    load_run_on(run, &TestTime::default(), DeviceSpec::Cpu).await
}

/// What evaluation may change in a trained model without touching its weights.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TestTime {
    /// Slots instead of the trained count (evaluating scenes with more objects than
    /// training had, paper §4.3). Only random slot init has weights independent of the
    /// slot count; the learned and tokens inits hold one embedding per slot and are
    /// refused with a clear error.
    pub num_slots: Option<usize>,
    /// Slot-attention iterations instead of the trained count: the iterations share
    /// their weights, so more of them refine the same fixed point further.
    pub slot_iterations: Option<usize>,
}

/// A trained run with the model built as `test` asks, on `device` (evaluation and
/// rendering on a GPU).
pub async fn load_run_on(run: &str, test: &TestTime, device: DeviceSpec) -> Result<LoadedRun> {
    let loc = Location::parse(run)?;
    let missing = |name: &str| TrainError::Run {
        path: loc.describe(&loc.path(name)),
        reason: "missing: not a run folder (or the run never started)".into(),
    };
    let text = read_file(&loc, CONFIG_FILE)
        .await?
        .ok_or_else(|| missing(CONFIG_FILE))?;
    let job = JobConfig::from_toml(
        &loc.describe(&loc.path(CONFIG_FILE)),
        &String::from_utf8_lossy(&text),
    )?;
    let info_bytes = read_file(&loc, INFO_FILE)
        .await?
        .ok_or_else(|| missing(INFO_FILE))?;
    let info: RunInfo = serde_json::from_slice(&info_bytes).map_err(|e| TrainError::Run {
        path: loc.describe(&loc.path(INFO_FILE)),
        reason: e.to_string(),
    })?;
    let mut job = job;
    if let Some(k) = test.num_slots {
        let sa = &mut job.model.slot_attention;
        if k != sa.num_slots && sa.init != osrt_model::slot_attention::SlotInit::Random {
            return Err(TrainError::Config {
                path: loc.describe(&loc.path(CONFIG_FILE)),
                reason: format!(
                    "trained with {:?} slot init and {} slots: its weights hold one \
                     embedding per slot, so it cannot be evaluated with {k} slots (only \
                     random slot init can change the slot count)",
                    sa.init, sa.num_slots
                ),
            });
        }
        if k == 0 {
            return Err(TrainError::Config {
                path: "--slots".into(),
                reason: "the slot count must be at least 1".into(),
            });
        }
        sa.num_slots = k;
    }
    if let Some(n) = test.slot_iterations {
        if n == 0 {
            return Err(TrainError::Config {
                path: "--slot-iterations".into(),
                reason: "slot attention needs at least 1 iteration".into(),
            });
        }
        job.model.slot_attention.iterations = n;
    }
    let mut trainer = Trainer::new(job.clone(), device.open()?)?;
    let step = osrt_run::checkpoint::latest_verified(&loc, None)
        .await?
        .ok_or_else(|| TrainError::Run {
            path: loc.describe(&loc.path("checkpoints")),
            reason: "no committed checkpoint: the run has not saved one yet".into(),
        })?;
    checkpoint::load(&loc, step, &mut trainer).await?;
    Ok(LoadedRun {
        job,
        info,
        trainer,
        step,
    })
}
