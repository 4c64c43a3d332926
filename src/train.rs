//! `osrt train` and `osrt eval`: argument types and their calls into osrt-trainer.

use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    Columns, Manifest, WriterOptions, generator::SplitSizes, generator::generate_dataset,
};
use osrt_kernels::{Kernels, Precision};
use osrt_model::slot_attention::SlotInit;
use osrt_run::MetricsRecord;
use osrt_store::Location;
use osrt_trainer::{JobConfig, TestTime, device::DeviceSpec, eval_options, evaluate, load_run_on};
use std::io::IsTerminal;
use std::path::PathBuf;

/// Where `osrt train` with no `--data` looks for (and generates) the embedded default.
const DEFAULT_DATA: &str = "data";

#[derive(Args)]
pub struct TrainArgs {
    /// Job config (TOML, a full `JobConfig`); default: the `--preset`.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Named job preset when no --config is given: clevr-lite-cpu, clevr-lite-gpu, tiny,
    /// paper, clevr3d, msn-hard (the paper's settings for those datasets).
    #[arg(long, default_value = "clevr-lite-cpu")]
    pub preset: String,
    /// Dataset directory or URL; the default ./data is generated (clevr-lite) if absent.
    #[arg(long, default_value = DEFAULT_DATA)]
    pub data: String,
    /// Worker processes on this machine (a coordinator runs in this process); default 2
    /// on the CPU, one per GPU on `cuda`.
    #[arg(long, value_parser = crate::flags::workers)]
    pub workers: Option<usize>,
    /// Compute threads per worker (default: the machine's cores divided among workers).
    #[arg(long, value_parser = crate::flags::threads)]
    pub threads: Option<usize>,
    /// Run folder or URL (default: runs/<preset>-<unix time>).
    #[arg(long)]
    pub run: Option<String>,
    /// Continue the job in --run from its newest committed checkpoint (with the run's own
    /// config; --max-steps counts from step 0).
    #[arg(long)]
    pub resume: bool,
    /// With --resume: take the run folder from a coordinator known to be dead without
    /// waiting to see that its lease is not renewed (a live one is otherwise refused).
    #[arg(long, requires = "resume")]
    pub take_over: bool,
    /// Stop after this many optimiser steps.
    #[arg(long)]
    pub max_steps: Option<u64>,
    /// Stop after this many minutes of wall-clock time (positive, finite, at most a year).
    #[arg(long, value_parser = crate::flags::minutes)]
    pub max_minutes: Option<f64>,
    /// Override the seed (initial weights and data order).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Override the peak learning rate.
    #[arg(long)]
    pub lr: Option<f64>,
    /// Where the learning rate's decay ends (`train.horizon`): `fixed` (the config's
    /// decay_steps), `budget` (the job's last step: --max-steps, or measured from
    /// --max-minutes over the warm-up and recorded in run.json) or a step count (a
    /// budget run's recorded horizon reruns it to the bit on any host).
    #[arg(long)]
    pub horizon: Option<osrt_trainer::lr_schedule::Horizon>,
    /// Override scenes per step.
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Run each worker's share of a step in passes of at most this many scenes, summing
    /// their gradients (`train.micro_batch_size`): the same step, the memory of one pass.
    /// Unset, a share that does not fit this machine gets the largest micro-batch that
    /// does.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub micro_batch_size: Option<u64>,
    /// Override target rays per scene.
    #[arg(long)]
    pub rays_per_scene: Option<usize>,
    /// Share of target rays drawn from salient pixels (0 = uniform, the paper's setting).
    #[arg(long)]
    pub salient_fraction: Option<f32>,
    /// Override the decoder: slot_mixer, spatial_broadcast, transformer, volumetric
    /// (V-OSRT; samples inside the dataset manifest's scene box).
    #[arg(long)]
    pub decoder: Option<String>,
    /// Override the number of slots.
    #[arg(long)]
    pub slots: Option<usize>,
    /// Override slot-attention iterations.
    #[arg(long)]
    pub iterations: Option<usize>,
    /// How the gradient flows through the slot iterations: full (the paper's), implicit
    /// (the last iteration only) or bilevel (the last, passed straight to the initial
    /// slots: BO-QSA).
    #[arg(long)]
    pub slot_gradient: Option<osrt_model::slot_attention::SlotGradient>,
    /// Override the slot init: learned, random, or tokens (an option beyond the paper).
    #[arg(long)]
    pub slot_init: Option<String>,
    /// Override how the ray encoding enters the encoder: concat (paper) or add (an
    /// option beyond the paper: RGB-only CNN plus a ray-patch embedding).
    #[arg(long)]
    pub ray_input: Option<String>,
    /// Input poses: absolute (OSRT) or unposed (Up-OSRT: camera-ID and 2D position
    /// embeddings, target rays relative to the first input camera).
    #[arg(long)]
    pub poses: Option<String>,
    /// Where the workers compute: cpu, cuda or cuda:N (worker k takes GPU k; needs a
    /// build with the `cuda` feature).
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Matrix products in f32 or bf16 (on a GPU, or the CPU's AMX / AVX512-BF16 units; weights and optimiser stay f32).
    #[arg(long)]
    pub precision: Option<Precision>,
    /// `fused` (the one-node CPU kernels; the default), `composed` (candle's ops only) or
    /// `device` (the GPU's graph, on any device): the same functions, at different speeds.
    #[arg(long)]
    pub kernels: Option<Kernels>,
    /// Make the transformer blocks', convolutions' and render MLP's activations again in
    /// the backward pass instead of keeping them (`train.recompute`): a smaller peak for
    /// a second forward pass, the same gradients.
    #[arg(long)]
    pub recompute: bool,
    /// Override seconds between validation runs.
    #[arg(long, value_parser = crate::flags::positive_seconds)]
    pub eval_every_s: Option<f64>,
    /// Override the validation subset size.
    #[arg(long)]
    pub eval_scenes: Option<usize>,
    /// Start even where the step's estimated peak memory exceeds this machine's.
    #[arg(long)]
    pub skip_memory_check: bool,
}

#[derive(Args)]
pub struct EvalArgs {
    /// Run folder or URL of `osrt train` (its newest committed checkpoint is evaluated).
    #[arg(long)]
    pub run: String,
    /// Split to evaluate.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Dataset (default: the one the run trained on).
    #[arg(long)]
    pub data: Option<String>,
    /// Evaluate at most this many scenes.
    #[arg(long)]
    pub scenes: Option<usize>,
    /// Input views at test time (default: as trained; more than trained with is the
    /// paper's §4.3 study). Novel target views need scenes with more views than this.
    #[arg(long)]
    pub views: Option<usize>,
    /// Feed grey-level input images (robustness study); targets stay in colour.
    #[arg(long)]
    pub grayscale: bool,
    /// Slots at test time (random slot init only), e.g. more slots on the `ood` split.
    #[arg(long)]
    pub slots: Option<usize>,
    /// Slot-attention iterations at test time (default: as trained); they share their
    /// weights, so any count runs the trained model.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub slot_iterations: Option<u64>,
    /// Where the model runs: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

fn job_config(a: &TrainArgs) -> Result<JobConfig> {
    let mut job = JobConfig::load_or_preset(a.config.as_deref(), &a.preset)?;
    let t = &mut job.train;
    if let Some(v) = a.seed {
        t.seed = v;
    }
    if let Some(v) = a.lr {
        t.lr = v;
    }
    if let Some(v) = a.horizon {
        t.horizon = v;
    }
    if let Some(v) = a.batch_size {
        t.batch_size = v;
    }
    if let Some(v) = a.micro_batch_size {
        t.micro_batch_size = Some(usize::try_from(v).unwrap_or(usize::MAX));
    }
    if let Some(v) = a.rays_per_scene {
        t.rays_per_scene = v;
    }
    if let Some(v) = a.salient_fraction {
        t.salient_fraction = v;
    }
    if let Some(v) = a.eval_every_s {
        t.eval_every_s = v;
    }
    if let Some(v) = a.eval_scenes {
        t.eval_scenes = v;
    }
    if let Some(v) = a.device {
        t.device = v;
    }
    if let Some(v) = a.precision {
        t.precision = v;
    }
    if let Some(v) = a.kernels {
        t.kernels = v;
    }
    if a.recompute {
        t.recompute = true;
    }
    if let Some(d) = &a.decoder {
        job.model = job.model.clone().with_decoder(d).with_context(|| {
            format!(
                "unknown decoder `{d}`: expected slot_mixer, spatial_broadcast, transformer or \
                 volumetric"
            )
        })?;
    }
    if let Some(v) = &a.ray_input {
        job.model.encoder.ray_input = v.parse().map_err(anyhow::Error::msg)?;
    }
    if let Some(v) = &a.poses {
        job.model.encoder.poses = v.parse().map_err(anyhow::Error::msg)?;
    }
    let sa = &mut job.model.slot_attention;
    if let Some(v) = a.slots {
        sa.num_slots = v;
    }
    if let Some(v) = a.iterations {
        sa.iterations = v;
    }
    if let Some(v) = a.slot_gradient {
        sa.gradient = v;
    }
    if let Some(v) = &a.slot_init {
        sa.init = v.parse::<SlotInit>().map_err(anyhow::Error::msg)?;
    }
    job.validate()?;
    Ok(job)
}

/// Generates the embedded default dataset if `./data` holds none.
pub async fn ensure_default_data(data: &str) -> Result<()> {
    if data != DEFAULT_DATA {
        return Ok(());
    }
    let loc = Location::parse(data)?;
    // 20,000 training scenes: with 2,000 the CPU preset memorised its scenes'
    // decomposition within 15 minutes (docs/time-to-quality.md).
    let sizes = SplitSizes {
        train: 20_000,
        val: 100,
        test: 100,
    };
    if let Ok(manifest) = Manifest::read(&loc).await {
        let train = manifest.splits.get("train").map_or(0, |s| s.scenes);
        if train != sizes.train {
            eprintln!(
                "note: ./{data} holds {train} training scenes, the embedded default has {} \
                 (remove ./{data} to generate it; the same val and test scenes either way)",
                sizes.train
            );
        }
        return Ok(());
    }
    // The CPU presets train on 32×32 views: on two cores, small images buy more steps in
    // the same wall-clock time.
    eprintln!(
        "no dataset in ./{data}: generating the default clevr-lite dataset (32×32, seed 0, \
         {} training scenes)",
        sizes.train
    );
    generate_dataset(
        &loc,
        &GeneratorConfig {
            image_size: 32,
            ..GeneratorConfig::clevr_lite()
        },
        0,
        sizes,
        WriterOptions::default(),
        std::io::stderr().is_terminal(),
    )
    .await?;
    Ok(())
}

pub async fn train(a: TrainArgs) -> Result<()> {
    if a.resume && a.run.is_none() {
        bail!("--resume needs the --run folder to continue");
    }
    let mut job = job_config(&a)?;
    job.train.device.check_available()?;
    let mut workers = a.workers.unwrap_or(if job.train.device.is_cuda() {
        osrt_trainer::device::cuda_device_count().max(1)
    } else {
        2
    });
    let batch = job.train.batch_size;
    if workers > batch {
        // Each worker needs at least one scene of the step.
        eprintln!(
            "{workers} workers asked for; a step's {batch} scenes (--batch-size) feed at most \
             {batch}: starting {batch}"
        );
        workers = batch.max(1);
    }
    // The launcher starts exactly `workers`: the job (a resumed one too) waits for them.
    let overrides = osrt_run::cluster_config::ClusterOverrides {
        min_workers: Some(workers),
        ..Default::default()
    };
    overrides.apply(&mut job.cluster);
    ensure_default_data(&a.data).await?;
    let run = a.run.clone().unwrap_or_else(|| {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        format!("runs/{}-{now}", a.preset)
    });
    if a.max_steps.is_none() && a.max_minutes.is_none() {
        eprintln!(
            "no --max-steps or --max-minutes: training until interrupted is not supported, stopping after 10 minutes"
        );
    }
    let max_minutes = a.max_minutes.or(if a.max_steps.is_none() {
        Some(10.0)
    } else {
        None
    });
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let threads = a.threads.unwrap_or((cores / workers).max(1));
    eprintln!(
        "run folder: {run} ({} worker{} × {threads} thread{}, on {}{})",
        workers,
        if workers == 1 { "" } else { "s" },
        if threads == 1 { "" } else { "s" },
        job.train.device,
        if job.train.device.is_cuda() && workers > 1 {
            ", worker k on GPU k"
        } else {
            ""
        },
    );
    // Every worker of a CPU job shares this machine's RAM; GPU workers have a GPU each.
    let here = if job.train.device.is_cuda() {
        1
    } else {
        workers
    };
    let check = crate::cluster::MemoryCheck {
        skip: a.skip_memory_check,
        // A resumed job keeps the micro-batch its run folder's config names.
        pick_micro_batch: !a.resume,
    };
    crate::cluster::memory_check(&mut job, &a.data, (here, workers), threads, check).await?;
    let mut spec = crate::cluster::spec(job, &a.data, &run, a.max_steps, max_minutes).await?;
    spec.cluster_overrides = overrides;
    let status = crate::cluster::run_local(crate::cluster::LocalJob {
        spec,
        workers,
        threads_per_worker: threads,
        skip_memory_check: a.skip_memory_check,
        open: osrt_coordinator::OpenOptions {
            resume: a.resume,
            take_over: a.take_over,
            ..Default::default()
        },
    })
    .await?;
    print_outcome(&run, &status).await
}

/// What a finished `osrt train` says: the step it trained to, its restarts, where its
/// checkpoints are, and its last validation.
async fn print_outcome(run: &str, status: &osrt_coordinator::StatusSnapshot) -> Result<()> {
    let loc = Location::parse(run)?;
    let metrics = osrt_run::metrics_log::read_all(&loc)
        .await?
        .unwrap_or_default();
    let last_eval = metrics
        .lines()
        .filter_map(MetricsRecord::parse)
        .filter_map(|r| match r {
            MetricsRecord::Eval(e) => Some(e),
            MetricsRecord::Train(_) => None,
        })
        .next_back();
    println!(
        "trained to step {} ({} restarts); checkpoints: {run}/checkpoints",
        status.last_checkpoint.unwrap_or(0),
        status.restarts,
    );
    if let Some(e) = last_eval {
        println!(
            "validation: PSNR {:.2} dB (mean-colour baseline {:.2} dB), FG-ARI {}",
            e.psnr,
            e.baseline_psnr.unwrap_or(f64::NAN),
            e.fg_ari.map_or("n/a".into(), |v| format!("{v:.3}"))
        );
    }
    Ok(())
}

/// How to evaluate a run: split, dataset (default: the one the run trained on) and the
/// test-time changes of `osrt eval`.
#[derive(Debug, Clone, Default)]
pub struct EvalRequest {
    pub split: String,
    pub data: Option<String>,
    pub scenes: Option<usize>,
    pub views: Option<usize>,
    pub grayscale: bool,
    pub slots: Option<usize>,
    pub slot_iterations: Option<usize>,
    pub device: DeviceSpec,
}

/// A run's newest committed checkpoint evaluated as `req` asks; returns the checkpoint's
/// step, the dataset and the result.
pub async fn evaluate_run(
    run: &str,
    req: &EvalRequest,
) -> Result<(u64, String, osrt_trainer::EvalResult)> {
    let split = req.split.as_str();
    let test = TestTime {
        num_slots: req.slots,
        slot_iterations: req.slot_iterations,
    };
    let loaded = load_run_on(run, &test, req.device)
        .await
        .with_context(|| format!("loading run {run}"))?;
    let data = req.data.clone().unwrap_or_else(|| loaded.info.data.clone());
    let loc = Location::parse(&data)?;
    let scenes = osrt_dataset::load_split(
        &loc,
        split,
        Columns {
            masks: true,
            objects: true,
        },
        req.scenes,
    )
    .await
    .with_context(|| match &req.data {
        // A run records where its data was; that folder may since have moved.
        None => format!(
            "reading the {split} split of {data}, the dataset run {run} trained on \
             (pass --data to evaluate on a copy of it elsewhere)"
        ),
        Some(_) => format!("reading the {split} split of {data}"),
    })?;
    let mut opts = eval_options(&loaded.job);
    opts.grayscale = req.grayscale;
    if let Some(v) = req.views {
        let fewest = scenes.iter().map(|s| s.views.len()).min().unwrap_or(0);
        if v == 0 || v > fewest {
            bail!(
                "--views {v}: {data}/{split} has scenes with only {fewest} views (need 1..={fewest})"
            );
        }
        opts.input_views = v;
    }
    let r = evaluate(&loaded.trainer.model, &scenes, &opts)?;
    Ok((loaded.step, data, r))
}

pub async fn eval(a: EvalArgs) -> Result<()> {
    let req = EvalRequest {
        split: a.split.clone(),
        data: a.data.clone(),
        scenes: a.scenes,
        views: a.views,
        grayscale: a.grayscale,
        slots: a.slots,
        slot_iterations: a.slot_iterations.map(|n| n as usize),
        device: a.device,
    };
    let (step, data, r) = evaluate_run(&a.run, &req).await?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let show = |v: Option<f64>| {
            v.map_or("n/a (decoder has no slot weights)".to_string(), |v| {
                format!("{v:.4}")
            })
        };
        println!(
            "run {} (step {step}) on {data}/{} ({} scenes)",
            a.run, a.split, r.scenes
        );
        println!("  protocol    {}", r.protocol);
        if a.slot_iterations.is_some() {
            println!("  slot iters  {}", r.slot_iterations);
        }
        println!(
            "  PSNR        {:.2} dB (mean-colour baseline {:.2} dB)",
            r.psnr, r.baseline_psnr
        );
        println!("  FG-ARI      {}", show(r.fg_ari));
        println!("  2D-FG-ARI   {}", show(r.fg_ari_2d));
        println!("  ARI         {}", show(r.ari));
        println!("  ratio       {}", show(r.ratio));
        println!("  render fps  {:.1}", r.render_fps);
        if !r.by_objects.is_empty() {
            println!("  FG-ARI by object count:");
            for o in &r.by_objects {
                println!(
                    "    {:>2} objects  {:>4} scenes  FG-ARI {}  ARI {}",
                    o.objects,
                    o.scenes,
                    o.fg_ari.map_or("n/a".into(), |v| format!("{v:.4}")),
                    o.ari.map_or("n/a".into(), |v| format!("{v:.4}")),
                );
            }
        }
    }
    Ok(())
}
