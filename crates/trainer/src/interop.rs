//! Models of stelzner/osrt (PyTorch) as osrt run folders, and back
//! (`osrt import-checkpoint`, `osrt export-checkpoint`). The formats and the mapping of
//! every tensor: `osrt_interop::stelzner`.

use crate::checkpoint::Snapshot;
use crate::config::JobConfig;
use crate::error::{Result, TrainError};
use crate::loaded::load_run;
use crate::step::Trainer;
use candle_core::{Device, Tensor};
use osrt_interop::stelzner::{self, Imported, PeerCheckpoint, PeerConfig};
use osrt_run::checkpoint::{self, CheckpointState};
use osrt_run::{CONFIG_FILE, INFO_FILE, RunInfo, read_file, write_file};
use osrt_store::Location;
use std::collections::HashMap;
use std::path::Path;

/// What an import wrote.
#[derive(Debug, Clone)]
pub struct ImportReport {
    pub job: JobConfig,
    pub parameters: usize,
    /// The checkpoint's step: Adam's update count (the peer's `it` without one).
    pub step: u64,
    /// Whether Adam's moments came along (fine-tuning continues the peer's optimiser).
    pub moments: bool,
}

/// The job of an imported model: the osrt preset of the peer's dataset (`clevr3d`, MSN's
/// `osrt` → `msn-hard`, else `paper`) with the peer's model, batch, rays, schedule
/// (peak 1e-4, warm-up, 0.16 decay: its `train.py`) and Adam settings.
pub fn imported_job(cfg: &PeerConfig, imported: &Imported) -> Result<JobConfig> {
    let dataset = cfg.data.as_ref().map(|d| d.dataset.as_str());
    let preset = match dataset {
        Some("clevr3d") => "clevr3d",
        Some("osrt") => "msn-hard",
        _ => "paper",
    };
    let mut job = JobConfig::preset(preset)?;
    job.model = imported.config.clone();
    let t = &mut job.train;
    if let Some(n) = cfg.data.as_ref().and_then(|d| d.num_points) {
        t.rays_per_scene = n;
    }
    if let Some(tr) = &cfg.training {
        t.batch_size = tr.batch_size.unwrap_or(t.batch_size);
        t.warmup_steps = tr.lr_warmup.unwrap_or(2500);
        t.decay_steps = tr.decay_it.unwrap_or(4e6);
    }
    t.input_stride = cfg.input_stride();
    t.lr = 1e-4;
    t.decay_rate = 0.16;
    t.clip_norm = None;
    if let Some(a) = &imported.adam {
        (t.beta1, t.beta2, t.adam_eps, t.weight_decay) = (
            a.settings.beta1,
            a.settings.beta2,
            a.settings.eps,
            a.settings.weight_decay,
        );
    }
    Ok(job)
}

/// Imports the peer's `model` (a `model.pt`, or the safetensors `osrt export-checkpoint`
/// writes) with its run `config` into a new run folder `run`: `config.toml`, `run.json`
/// (dataset `data`, empty if not given) and one verified checkpoint. Refuses a folder
/// that holds a run already.
pub async fn import_stelzner(
    model: &Path,
    config: &Path,
    run_url: &str,
    data: Option<&str>,
) -> Result<ImportReport> {
    // Everything is read and checked before the run folder is touched.
    let (job, imported) = tokio::task::block_in_place(|| -> Result<_> {
        let cfg = PeerConfig::read(config)?;
        let ckpt = PeerCheckpoint::read(model)?;
        let imported = stelzner::import(&ckpt, &cfg)?;
        Ok((imported_job(&cfg, &imported)?, imported))
    })?;
    let run = &Location::parse(run_url)?;
    for name in [CONFIG_FILE, INFO_FILE] {
        if read_file(run, name).await?.is_some() {
            return Err(TrainError::Run {
                path: run.describe(&run.path(name)),
                reason: "exists: import writes a new run folder, never into an existing run".into(),
            });
        }
    }
    let toml = job.to_toml();
    let mut trainer = Trainer::new(job.clone(), Device::Cpu)?;
    let step = imported
        .adam
        .as_ref()
        .map(|a| a.settings.step)
        .or(imported.peer_it.map(|i| i.max(0) as u64))
        .unwrap_or(0);
    let moments = load_into(&mut trainer, &imported)?;
    let state = CheckpointState {
        step,
        epoch: 0,
        epoch_start_step: step,
        world_size: 1,
        rng: String::new(),
        adam_t: if moments { step } else { 0 },
        skipped_total: 0,
        wall_s: 0.0,
        train_s: 0.0,
        config_hash: checkpoint::config_hash(&toml),
        val_fg_ari: None,
        val_psnr: None,
        horizon: None,
    };
    let info = RunInfo {
        data: data.unwrap_or_default().to_string(),
        parameters: Some(trainer.num_parameters()),
        workers: 1,
        horizon: None,
    };
    write_file(run, CONFIG_FILE, toml.into_bytes()).await?;
    write_file(
        run,
        INFO_FILE,
        serde_json::to_vec_pretty(&info).expect("serialises"),
    )
    .await?;
    let flat = trainer.params.flatten()?;
    Snapshot::take(&trainer, state)?.commit(run, None).await?;
    // Read back through the loader every command uses: the checkpoint verifies and holds
    // these exact weights.
    let loaded = load_run(run_url).await?;
    if loaded.trainer.params.flatten()? != flat {
        return Err(TrainError::Checkpoint {
            path: run.describe(&run.path("checkpoints")),
            reason: "the checkpoint read back differs from the imported weights".into(),
        });
    }
    Ok(ImportReport {
        parameters: trainer.num_parameters(),
        job,
        step,
        moments,
    })
}

/// Puts the imported weights (and moments, if any) into `trainer`; whether moments came.
pub fn load_into(trainer: &mut Trainer, imported: &Imported) -> Result<bool> {
    let dev = trainer.device().clone();
    let tensors = imported
        .params
        .iter()
        .map(|(n, (shape, v))| Ok((n.clone(), Tensor::from_slice(v, shape.as_slice(), &dev)?)))
        .collect::<Result<HashMap<_, _>>>()?;
    trainer.params.load_tensors(&tensors)?;
    let Some(adam) = imported.adam.as_ref().filter(|a| !a.m.is_empty()) else {
        return Ok(false);
    };
    let (mut m, mut v) = (Vec::new(), Vec::new());
    for (name, _) in trainer.params.vars() {
        m.extend(&adam.m[&name]);
        v.extend(&adam.v[&name]);
    }
    trainer.opt.restore(m, v, adam.settings.step)?;
    Ok(true)
}

/// What an export wrote.
#[derive(Debug, Clone)]
pub struct ExportReport {
    pub step: u64,
    pub tensors: usize,
    /// The peer's `model:` config section for this model.
    pub peer_yaml: String,
}

/// Writes the newest checkpoint of `run` as a safetensors file `out` holding the peer's
/// state dict of `OSRT(cfg)` (names `encoder.…`, `decoder.…`): the peer loads it with
/// `model.load_state_dict(safetensors.torch.load_file(out))`.
pub async fn export_stelzner(run: &str, out: &Path, any_widths: bool) -> Result<ExportReport> {
    let loaded = load_run(run).await?;
    let params = loaded
        .trainer
        .params
        .vars()
        .into_iter()
        .map(|(n, v)| {
            let shape = v.dims().to_vec();
            Ok((n, (shape, v.as_tensor().flatten_all()?.to_vec1::<f32>()?)))
        })
        .collect::<Result<_>>()?;
    let cfg = &loaded.job.model;
    let tensors = stelzner::export(cfg, &params, any_widths)?;
    let dev = Device::Cpu;
    let named = tensors
        .iter()
        .map(|a| {
            Ok((
                a.name.as_str(),
                Tensor::from_slice(&a.values, a.shape.as_slice(), &dev)?,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let shown = out.display().to_string();
    let bytes = safetensors::serialize(named.iter().map(|(k, v)| (*k, v)), None).map_err(|e| {
        TrainError::Checkpoint {
            path: shown.clone(),
            reason: format!("serialising: {e}"),
        }
    })?;
    std::fs::write(out, bytes).map_err(|e| TrainError::io(&shown, e))?;
    let mut peer_yaml = stelzner::peer_model_yaml(cfg);
    match loaded.job.train.input_stride {
        1 => {}
        s if s.is_power_of_two() => peer_yaml.push_str(&format!(
            "data:\n  kwargs:\n    downsample: {}\n",
            s.trailing_zeros()
        )),
        s => peer_yaml.push_str(&format!(
            "# train.input_stride = {s}: the peer's `downsample` takes powers of two only\n"
        )),
    }
    Ok(ExportReport {
        step: loaded.step,
        tensors: tensors.len(),
        peer_yaml,
    })
}
