//! `osrt`: train and evaluate the Object Scene Representation Transformer as a
//! distributed batch job. This binary only parses arguments and calls the libraries.

mod bench;
mod check_device;
mod cluster;
mod data;
mod flags;
mod interop;
mod render;
mod sweep;
mod train;
mod watch;

use clap::{Parser, Subcommand};

/// Counts heap bytes so that `osrt bench model` can state a step's peak allocation.
#[global_allocator]
static ALLOC: osrt_trainer::memory::CountingAlloc = osrt_trainer::memory::CountingAlloc;
use tracing_subscriber::EnvFilter;

#[derive(Parser)]
#[command(name = "osrt", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate and inspect scene datasets.
    Data {
        #[command(subcommand)]
        command: data::DataCommand,
    },
    /// Train on this machine: a coordinator and N worker processes on loopback.
    Train(Box<train::TrainArgs>),
    /// Run a job's coordinator (the cluster's side of `osrt train`).
    Coordinator(Box<cluster::CoordinatorArgs>),
    /// Run one worker of a job (registers with the coordinator, trains until done).
    Worker(cluster::WorkerArgs),
    /// Print a job preset as a TOML job config (a starting point for --config).
    Config {
        #[arg(long, default_value = "clevr-lite-cpu")]
        preset: String,
    },
    /// Evaluate a trained run on a split.
    Eval(train::EvalArgs),
    /// Novel views of a scene along a camera path with slot segmentations (PNG frames and
    /// a GIF), and scene editing: drop a slot, add one from another scene.
    Render(Box<render::RenderArgs>),
    /// Train and evaluate every point of a sweep file (resumable), then write its tables,
    /// charts and report page.
    Sweep(sweep::SweepArgs),
    /// Charts and a static HTML page of a run or a sweep (error against run time).
    Report(sweep::ReportArgs),
    /// Bring in a model trained by another implementation (stelzner/osrt's PyTorch
    /// checkpoints) as a run folder that eval, render, predict and train --resume use.
    ImportCheckpoint(interop::ImportArgs),
    /// Write a run's model for another implementation (stelzner/osrt's state dict).
    ExportCheckpoint(interop::ExportArgs),
    /// A run's inputs and predictions (colours, slot weights, slots) as NumPy arrays.
    Predict(Box<interop::PredictArgs>),
    /// Compare a GPU's train step with the CPU's (gradients, one optimiser step).
    CheckDevice(check_device::CheckDeviceArgs),
    /// Benchmarks that print (and save) throughput figures.
    Bench {
        #[command(subcommand)]
        command: BenchCommand,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Scenes/s generated, and read + decoded with and without masks.
    Data(data::BenchDataArgs),
    /// Train-step time per preset and render speed per decoder, at 1 and 2 threads.
    Model(bench::BenchModelArgs),
    /// Ring all-reduce throughput of 2 ranks on loopback beside a raw TCP copy.
    Allreduce(bench::BenchAllReduceArgs),
    /// Training throughput of local clusters: 1×1, 1×2 and 2×1 workers × threads.
    Cluster(bench::BenchClusterArgs),
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Data { command } => data::run(command).await,
        Command::Train(args) => train::train(*args).await,
        Command::Coordinator(args) => cluster::coordinator(*args).await,
        Command::Worker(args) => cluster::worker(args).await,
        Command::Eval(args) => train::eval(args).await,
        Command::Render(args) => render::render(*args).await,
        Command::Sweep(args) => sweep::sweep(args).await,
        Command::CheckDevice(args) => check_device::run(args),
        Command::ImportCheckpoint(args) => interop::import(args).await,
        Command::ExportCheckpoint(args) => interop::export(args).await,
        Command::Predict(args) => interop::run_predict(*args).await,
        Command::Report(args) => sweep::report(args).await,
        Command::Config { preset } => {
            print!("{}", osrt_trainer::JobConfig::preset(&preset)?.to_toml());
            Ok(())
        }
        Command::Bench {
            command: BenchCommand::Data(args),
        } => data::bench(args).await,
        Command::Bench {
            command: BenchCommand::Model(args),
        } => bench::run(args),
        Command::Bench {
            command: BenchCommand::Allreduce(args),
        } => bench::allreduce(args).await,
        Command::Bench {
            command: BenchCommand::Cluster(args),
        } => bench::cluster(args),
    }
}
