//! `osrt import-checkpoint`, `osrt export-checkpoint` (models of stelzner/osrt in and
//! out) and `osrt predict` (inputs and outputs as NumPy arrays).

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use osrt_dataset::Columns;
use osrt_store::Location;
use osrt_trainer::predict::{PredictInputs, inputs_from_npz, inputs_from_scenes, predict};
use osrt_trainer::{TestTime, device::DeviceSpec, load_run_on};
use std::path::PathBuf;

/// Implementations whose checkpoints osrt reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Peer {
    /// github.com/stelzner/osrt (PyTorch): its `model.pt` and `config.yaml`.
    StelznerOsrt,
}

#[derive(Args)]
pub struct ImportArgs {
    /// The implementation that wrote the checkpoint.
    #[arg(long = "from", value_enum)]
    pub from: Peer,
    /// Its checkpoint (`model.pt`; or a safetensors file of its state dict, as
    /// `osrt export-checkpoint` writes).
    pub model: PathBuf,
    /// Its run config (`runs/…/config.yaml`): the model's settings.
    #[arg(long)]
    pub config: PathBuf,
    /// New run folder or URL to write (config.toml, run.json, one checkpoint).
    #[arg(long)]
    pub run: String,
    /// The dataset the run evaluates and fine-tunes on by default.
    #[arg(long)]
    pub data: Option<String>,
}

pub async fn import(a: ImportArgs) -> Result<()> {
    let Peer::StelznerOsrt = a.from;
    let r = osrt_trainer::interop::import_stelzner(&a.model, &a.config, &a.run, a.data.as_deref())
        .await
        .with_context(|| format!("importing {}", a.model.display()))?;
    println!(
        "imported {} ({} parameters) into run {} at step {}; Adam's moments: {}",
        a.model.display(),
        r.parameters,
        a.run,
        r.step,
        if r.moments {
            "imported (fine-tuning continues the peer's optimiser)"
        } else {
            "none in the file (fine-tuning starts a fresh Adam)"
        }
    );
    if a.data.is_none() {
        println!("no --data given: pass --data to osrt eval, render and predict");
    }
    Ok(())
}

#[derive(Args)]
pub struct ExportArgs {
    /// The implementation to write for.
    #[arg(long = "to", value_enum)]
    pub to: Peer,
    /// Run folder or URL (its newest committed checkpoint is written).
    pub run: String,
    /// Output file (safetensors with the peer's state-dict names).
    pub out: PathBuf,
    /// Write models whose widths the peer's classes do not build (they then load into a
    /// model built at these widths, not into the peer's `OSRT(cfg)`).
    #[arg(long)]
    pub any_widths: bool,
}

pub async fn export(a: ExportArgs) -> Result<()> {
    let Peer::StelznerOsrt = a.to;
    let r = osrt_trainer::interop::export_stelzner(&a.run, &a.out, a.any_widths)
        .await
        .with_context(|| format!("exporting run {}", a.run))?;
    println!(
        "wrote {} ({} tensors, step {}). In stelzner/osrt, with this model config:\n\n{}\n\
         load it with:\n\n    model.load_state_dict(safetensors.torch.load_file(\"{}\"))",
        a.out.display(),
        r.tensors,
        r.step,
        r.peer_yaml,
        a.out.display()
    );
    Ok(())
}

#[derive(Args)]
pub struct PredictArgs {
    /// Run folder or URL (its newest committed checkpoint predicts).
    #[arg(long)]
    pub run: String,
    /// Dataset (default: the one the run trained on); scenes run under the evaluation
    /// protocol (first input views in, every pixel of the other views out).
    #[arg(long, conflicts_with = "inputs")]
    pub data: Option<String>,
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Scenes of the split, `A..B` (positions, B excluded).
    #[arg(long, default_value = "0..1", value_parser = parse_range)]
    pub scenes: std::ops::Range<usize>,
    /// Instead of a dataset: the model's inputs as arrays (`input_images`,
    /// `input_origins`, `input_directions` `[S, V, H, W, 3]`; `target_origins`,
    /// `target_directions` `[S, …, 3]`; optional `target_rgb`).
    #[arg(long)]
    pub inputs: Option<PathBuf>,
    /// Output `.npz` (inputs, `rgb`, `slot_weights`, `slots`, ground truth).
    #[arg(long)]
    pub out: PathBuf,
    /// Where the model runs: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
}

fn parse_range(s: &str) -> Result<std::ops::Range<usize>, String> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| format!("`{s}`: expected A..B"))?;
    let (a, b): (usize, usize) = (
        a.parse()
            .map_err(|_| format!("`{s}`: `{a}` is not a number"))?,
        b.parse()
            .map_err(|_| format!("`{s}`: `{b}` is not a number"))?,
    );
    if b <= a {
        return Err(format!("`{s}`: empty range"));
    }
    Ok(a..b)
}

pub async fn run_predict(a: PredictArgs) -> Result<()> {
    let loaded = load_run_on(&a.run, &TestTime::default(), a.device)
        .await
        .with_context(|| format!("loading run {}", a.run))?;
    let model = &loaded.trainer.model;
    let inputs: PredictInputs = match &a.inputs {
        Some(path) => inputs_from_npz(path)?,
        None => {
            let data = a.data.clone().unwrap_or_else(|| loaded.info.data.clone());
            if data.is_empty() {
                bail!(
                    "run {} names no dataset (an imported model): pass --data",
                    a.run
                );
            }
            let loc = Location::parse(&data)?;
            let cols = Columns {
                masks: true,
                objects: false,
            };
            let scenes = osrt_dataset::load_split(&loc, &a.split, cols, Some(a.scenes.end))
                .await
                .with_context(|| format!("reading the {} split of {data}", a.split))?;
            if scenes.len() < a.scenes.end {
                bail!(
                    "--scenes {}..{}: {data}/{} has {} scenes",
                    a.scenes.start,
                    a.scenes.end,
                    a.split,
                    scenes.len()
                );
            }
            let job = &loaded.job.train;
            let (views, stride) = (job.input_views, job.input_stride);
            let scenes = &scenes[a.scenes.clone()];
            inputs_from_scenes(model, scenes, views, stride, job.eval_target_views)?
        }
    };
    let seed = loaded.job.train.seed ^ 0xE7A1;
    let kernels = loaded.job.train.kernels;
    let bar = if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        indicatif::ProgressBar::new(inputs.views[0] as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] scene {pos}/{len} (ETA {eta})",
            )
            .expect("a valid progress template"),
        )
    } else {
        indicatif::ProgressBar::hidden()
    };
    let arrays = tokio::task::block_in_place(|| {
        osrt_kernels::with_kernels(kernels, || {
            predict(model, &inputs, seed, &|n| bar.set_position(n as u64))
        })
    })?;
    bar.finish_and_clear();
    let shown = a.out.display().to_string();
    let file = std::fs::File::create(&a.out).with_context(|| format!("creating {shown}"))?;
    osrt_interop::npz::write_npz(std::io::BufWriter::new(file), &shown, &arrays)?;
    println!("wrote {shown}:");
    for x in &arrays {
        println!("  {:<18} {:?}", x.name, x.shape);
    }
    Ok(())
}
