//! `osrt data …` and `osrt bench data`: argument types and their calls into osrt-dataset.

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::import::kubric::KubricSource;
use osrt_dataset::import::obsurf::ObsurfSource;
use osrt_dataset::import::{Format, ImportOptions, Source, Splits, import};
use osrt_dataset::{
    Columns, ImageCodec, WriterOptions, generator::SplitSizes, generator::generate_dataset,
    inspect, load_split,
};
use osrt_store::Location;
use std::io::IsTerminal;

#[derive(Subcommand)]
pub enum DataCommand {
    /// Generate a procedural CLEVR-like dataset (train/val/test splits + manifest.json).
    Generate(GenerateArgs),
    /// Print what a dataset holds; optionally draw a contact sheet.
    Inspect(InspectArgs),
    /// Import one of the paper's datasets (ObSuRF's CLEVR-3D or MSN-Easy folder, Kubric's
    /// MSN-Hard shards) into the osrt layout; a re-run with the same options finishes an
    /// interrupted import.
    Import(ImportArgs),
}

#[derive(Args)]
pub struct ImportArgs {
    /// Source format: clevr3d or msn-easy (ObSuRF's release folders), msn-hard (Kubric's
    /// TFDS TFRecord shards).
    #[arg(long)]
    pub format: Format,
    /// The source folder (metadata.npz, images/, masks/; or the *.tfrecord-* shards).
    pub src: std::path::PathBuf,
    /// Output dataset directory or URL.
    #[arg(long)]
    pub out: String,
    /// Split ranges by scene index, e.g. `train=0..1000,val=1000..1100` (default: the
    /// public loaders': CLEVR-3D 0–70000 / 70000–75000 / 85000–100000, MSN-Easy 0–80000 /
    /// 80000–80500 / 90000–100000).
    #[arg(long)]
    pub split: Option<String>,
    /// Leave out scenes with more objects (default: 6 for CLEVR-3D, none for MSN-Easy).
    #[arg(long)]
    pub max_objects: Option<usize>,
    /// At most this many scenes per split (a sample).
    #[arg(long)]
    pub limit: Option<u64>,
    /// How images and masks are stored.
    #[arg(long, default_value = "png")]
    pub codec: ImageCodec,
    /// Scenes per part file (the unit of resumption and of memory).
    #[arg(long, default_value_t = 64)]
    pub scenes_per_part: usize,
    /// Shrink every view to WIDTHxHEIGHT (e.g. 32x24): colours averaged over each pixel's
    /// area, masks by the nearest pixel, the cameras' intrinsics scaled.
    #[arg(long, value_parser = parse_size)]
    pub resize: Option<[u32; 2]>,
}

/// `WIDTHxHEIGHT`, e.g. `32x24`.
fn parse_size(s: &str) -> std::result::Result<[u32; 2], String> {
    let (w, h) = s
        .split_once(['x', 'X', '×'])
        .ok_or_else(|| format!("`{s}`: expected WIDTHxHEIGHT, e.g. 32x24"))?;
    let side = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("`{s}`: `{v}` is not a pixel count"))
    };
    Ok([side(w)?, side(h)?])
}

#[derive(Args)]
pub struct GenerateArgs {
    /// Generator preset: clevr-lite, hard-lite or ood.
    #[arg(long, default_value = "clevr-lite")]
    pub preset: String,
    /// Output directory or URL (file://, memory://, s3://).
    #[arg(long)]
    pub out: String,
    /// Scenes in the train split.
    #[arg(long, default_value_t = 2000)]
    pub train: u64,
    /// Scenes in the val split.
    #[arg(long, default_value_t = 100)]
    pub val: u64,
    /// Scenes in the test split.
    #[arg(long, default_value_t = 100)]
    pub test: u64,
    /// Random seed: the same seed gives the same bytes.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width and height in pixels (default: the preset's).
    #[arg(long)]
    pub image_size: Option<u32>,
    /// Supersampling per side for anti-aliasing (1 = off; default: the preset's).
    #[arg(long)]
    pub antialias: Option<u32>,
    /// Camera field of view in degrees (default: the preset's; CLEVR's is 49.1). A
    /// narrower one shows the objects larger.
    #[arg(long)]
    pub fov_deg: Option<f64>,
    /// Views per scene (default: the preset's); fixed rigs spread them evenly in azimuth.
    #[arg(long)]
    pub views: Option<usize>,
    /// Scenes per Parquet row group (the sharding unit).
    #[arg(long, default_value_t = 32)]
    pub scenes_per_row_group: usize,
    /// How images and masks are stored: raw pixels, or PNG.
    #[arg(long, default_value = "raw")]
    pub codec: ImageCodec,
}

#[derive(Args)]
pub struct InspectArgs {
    /// Dataset directory or URL.
    pub dataset: String,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Write a contact sheet PNG (views and coloured masks of the first scenes).
    #[arg(long)]
    pub sheet: Option<std::path::PathBuf>,
    /// Split drawn on the contact sheet.
    #[arg(long, default_value = "train")]
    pub sheet_split: String,
    /// Scenes on the contact sheet.
    #[arg(long, default_value_t = 6)]
    pub sheet_scenes: usize,
}

#[derive(Args)]
pub struct BenchDataArgs {
    /// Generator preset to benchmark.
    #[arg(long, default_value = "clevr-lite")]
    pub preset: String,
    /// Scenes to generate, write and read per case.
    #[arg(long, default_value_t = 64)]
    pub scenes: usize,
    /// Image sizes WxH (W ≥ H: square renders cropped to H rows), one case each.
    #[arg(long, value_delimiter = ',', default_value = "128x128,320x240")]
    pub sizes: Vec<String>,
    /// Storage codecs, one case each.
    #[arg(long, value_delimiter = ',', default_value = "raw,png")]
    pub codecs: Vec<ImageCodec>,
    /// Read passes; the median is reported.
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// What training consumes: scenes per step …
    #[arg(long, default_value_t = 256)]
    pub step_batch: usize,
    /// … and milliseconds per step (default: the `paper` preset's bf16 step in PyTorch
    /// on one H200, 125 ms).
    #[arg(long, default_value_t = 125.0, value_parser = crate::flags::positive_millis)]
    pub step_ms: f64,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Where the JSON figures are saved.
    #[arg(long, default_value = "target/bench/data.json")]
    pub out: std::path::PathBuf,
}

pub async fn run(cmd: DataCommand) -> Result<()> {
    match cmd {
        DataCommand::Generate(a) => generate(a).await,
        DataCommand::Inspect(a) => inspect_cmd(a).await,
        DataCommand::Import(a) => import_cmd(a).await,
    }
}

fn preset(
    name: &str,
    image_size: Option<u32>,
    antialias: Option<u32>,
    fov_deg: Option<f64>,
    views: Option<usize>,
) -> Result<GeneratorConfig> {
    let mut cfg = GeneratorConfig::preset(name)?;
    if let Some(v) = views {
        cfg.cameras = cfg.cameras.with_views(v);
    }
    if let Some(f) = fov_deg {
        cfg.fov_deg = f;
    }
    if let Some(s) = image_size {
        cfg.image_size = s;
    }
    if let Some(a) = antialias {
        cfg.antialias = a;
    }
    cfg.validate()?;
    Ok(cfg)
}

async fn generate(a: GenerateArgs) -> Result<()> {
    let cfg = preset(&a.preset, a.image_size, a.antialias, a.fov_deg, a.views)?;
    let loc = Location::parse(&a.out)?;
    let sizes = SplitSizes {
        train: a.train,
        val: a.val,
        test: a.test,
    };
    let opts = WriterOptions {
        scenes_per_row_group: a.scenes_per_row_group.max(1),
        codec: a.codec,
        ..WriterOptions::default()
    };
    let t = std::time::Instant::now();
    let m = generate_dataset(
        &loc,
        &cfg,
        a.seed,
        sizes,
        opts,
        std::io::stderr().is_terminal(),
    )
    .await
    .with_context(|| format!("generating {} into {}", a.preset, a.out))?;
    tracing::info!(
        preset = %a.preset,
        out = %a.out,
        seconds = t.elapsed().as_secs_f64(),
        "dataset written"
    );
    for (name, s) in &m.splits {
        println!(
            "{name:>5}: {} scenes in {} files, {} row groups",
            s.scenes, s.files, s.row_groups
        );
    }
    Ok(())
}

async fn import_cmd(a: ImportArgs) -> Result<()> {
    let mut opts = ImportOptions::new(a.format);
    // The source as an absolute path, so that re-runs from another working folder agree.
    opts.source = std::fs::canonicalize(&a.src)
        .map_or_else(|_| a.src.display().to_string(), |p| p.display().to_string());
    if let Some(s) = &a.split {
        opts.splits = Splits::parse(s, opts.splits).map_err(anyhow::Error::msg)?;
    }
    if a.max_objects.is_some() {
        opts.max_objects = a.max_objects;
    }
    opts.limit = a.limit;
    opts.codec = a.codec;
    opts.scenes_per_part = a.scenes_per_part.max(1);
    opts.resize = a.resize;
    let src: std::sync::Arc<dyn Source> = match a.format {
        Format::Clevr3d | Format::MsnEasy => std::sync::Arc::new(ObsurfSource::open(&a.src)?),
        Format::MsnHard => {
            if a.split.is_some() || a.max_objects.is_some() {
                bail!(
                    "msn-hard: the shards are split already and the records hold no object \
                     counts; --split and --max-objects do not apply (--limit takes a sample)"
                );
            }
            let src = KubricSource::open(&a.src)?;
            opts.splits = src.splits();
            std::sync::Arc::new(src)
        }
    };
    let out = Location::parse(&a.out)?;
    let t = std::time::Instant::now();
    let m = import(src, &out, &opts, std::io::stderr().is_terminal()).await?;
    eprintln!(
        "imported into {} in {:.1}s ({} images, {}x{}):",
        a.out,
        t.elapsed().as_secs_f64(),
        m.image_codec,
        m.image_size[0],
        m.image_size[1]
    );
    for (name, s) in &m.splits {
        eprintln!("  {name}: {} scenes in {} files", s.scenes, s.files);
    }
    Ok(())
}

async fn inspect_cmd(a: InspectArgs) -> Result<()> {
    let loc = Location::parse(&a.dataset)?;
    let report = inspect::inspect(&loc).await?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("dataset {}", report.location);
        match &report.manifest {
            Some(m) => {
                println!(
                    "  schema version {}, images and masks stored {}",
                    m.schema_version, m.image_codec
                );
                if let Some(g) = &m.generator {
                    println!("  generator: preset {}, seed {}", g.preset, g.seed);
                }
            }
            None => println!("  (no manifest.json)"),
        }
        for (name, s) in &report.splits {
            let views: u64 = s.image_sizes.values().sum();
            println!(
                "  {name}: {} scenes, {} files ({:.1} MiB, {:.0} bytes per view), {} row groups",
                s.scenes,
                s.files,
                s.bytes as f64 / (1 << 20) as f64,
                s.bytes as f64 / views.max(1) as f64,
                s.row_groups
            );
            println!("    image sizes: {:?}", s.image_sizes);
            println!("    views per scene: {:?}", s.views_histogram);
            println!("    objects per scene: {:?}", s.objects_histogram);
        }
    }
    if let Some(path) = a.sheet {
        let columns = Columns {
            masks: true,
            objects: false,
        };
        let scenes = load_split(&loc, &a.sheet_split, columns, Some(a.sheet_scenes)).await?;
        let img = inspect::contact_sheet(&scenes)?;
        img.save(&path)
            .with_context(|| format!("writing contact sheet {}", path.display()))?;
        eprintln!("contact sheet: {}", path.display());
    }
    Ok(())
}

pub async fn bench(a: BenchDataArgs) -> Result<()> {
    let mut cases = Vec::new();
    for size in &a.sizes {
        let (w, h) = size
            .split_once('x')
            .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
            .filter(|&(w, h)| w >= h && h > 0)
            .with_context(|| format!("--sizes: `{size}` is not WxH with W >= H > 0"))?;
        let mut cfg = preset(&a.preset, Some(w), Some(1), None, None)?;
        cfg.antialias = 1;
        for &codec in &a.codecs {
            let scratch = Location::parse(&format!("memory://bench-data/{size}-{codec}"))?;
            eprintln!("{size} {codec}: {} scenes…", a.scenes);
            let r = osrt_bench::data_path::bench_data(
                &cfg,
                a.scenes,
                a.repeats,
                scratch,
                (codec, Some(h)),
            )
            .await?;
            cases.push(r);
        }
    }
    let need = a.step_batch as f64 / (a.step_ms / 1e3);
    let report = serde_json::json!({
        "cases": cases,
        "training_consumes_scenes_per_s": need,
        "step_batch": a.step_batch,
        "step_ms": a.step_ms,
    });
    let json = crate::bench::save_json(&a.out, &report)?;
    if a.json {
        println!("{json}");
        return Ok(());
    }
    println!(
        "data bench: {}, {} scenes per case, {} threads; training consumes {need:.0} scenes/s \
         ({} scenes per {} ms step)",
        a.preset,
        a.scenes,
        cases.first().map_or(0, |c| c.threads),
        a.step_batch,
        a.step_ms
    );
    println!(
        "  size     codec  bytes/view  write/s  read+decode/s (masks)  (no masks)  vs training"
    );
    for r in &cases {
        let views = r.views.max(1) as f64;
        println!(
            "  {:>3}x{:<4} {:<5} {:>10.0} {:>8.1} {:>22.1} {:>11.1} {:>10.2}x",
            r.image_size,
            r.image_height,
            r.codec.to_string(),
            r.file_bytes as f64 / views,
            r.write_scenes_per_s,
            r.read_with_masks.scenes_per_s,
            r.read_without_masks.scenes_per_s,
            r.read_without_masks.scenes_per_s / need
        );
    }
    println!("  saved to {}", a.out.display());
    Ok(())
}
