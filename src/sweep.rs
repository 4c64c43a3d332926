//! `osrt sweep FILE.toml` and `osrt report RUN_OR_SWEEP`: a grid of runs trained on the
//! local cluster and evaluated, then tables, charts and a static HTML page.

use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_dataset::Manifest;
use osrt_store::Location;
use osrt_sweep::html::{self, Report};
use osrt_sweep::seeds::{Group, Member, SeedReport, Target};
use osrt_sweep::{Curve, PointResult, RESULT_FILE, RunSummary, SweepFile};
use std::path::{Path, PathBuf};

/// A copy of the sweep file in its output folder: marks the folder as a sweep.
const SWEEP_COPY: &str = "sweep.toml";
/// In a report folder: each seed group's mean curves as TensorBoard events, in
/// `tensorboard/<group>/tb/` (`tensorboard --logdir REPORT/tensorboard`).
const TENSORBOARD_DIR: &str = "tensorboard";

#[derive(Args)]
pub struct SweepArgs {
    /// Sweep file: a base job and axes (see configs/sweeps/).
    pub file: PathBuf,
    /// Output folder (default: runs/sweeps/<name>); one run folder per point inside.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// List the points and what is already finished, train nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// A validation figure to time each seed to, METRIC=VALUE with METRIC fg_ari or psnr
    /// (`--target fg_ari=0.85`); repeat for several. The report gives each seed's first
    /// evaluation at or above it and each seed group's mean over the seeds that got there.
    #[arg(long = "target", value_name = "METRIC=VALUE")]
    pub targets: Vec<Target>,
}

#[derive(Args)]
pub struct ReportArgs {
    /// A sweep's output folder, or one or more run folders of `osrt train` (several runs
    /// share one chart: seeds, or settings compared by hand).
    #[arg(required = true, num_args = 1..)]
    pub paths: Vec<PathBuf>,
    /// Where the page and its charts go (default: PATH/report for one run, PATH for a
    /// sweep; required for several runs, and for a run in an object store).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep the page of one running job current (its step, run time, restarts, ETA and
    /// newest validation with its pictures) until the job is over; the run folder may be
    /// a path or an object-store URL.
    #[arg(long)]
    pub watch: bool,
    /// With --watch: seconds between rewrites of the page.
    #[arg(long, default_value_t = 30, requires = "watch")]
    pub every: u64,
    /// A validation figure to time each seed to, METRIC=VALUE with METRIC fg_ari or psnr
    /// (`--target psnr=28`); repeat for several. Runs that differ only in their seed (a
    /// sweep's points, or run folders whose job configs differ only in `train.seed`) are
    /// one group.
    #[arg(long = "target", value_name = "METRIC=VALUE", conflicts_with = "watch")]
    pub targets: Vec<Target>,
}

fn budget(f: &SweepFile) -> String {
    match (f.max_steps, f.max_minutes) {
        (Some(s), Some(m)) => format!("{s} steps or {m} minutes, whichever comes first"),
        (Some(s), None) => format!("{s} steps"),
        (None, Some(m)) => format!("{m} minutes"),
        (None, None) => unreachable!("checked when the sweep file is parsed"),
    }
}

fn note(f: &SweepFile) -> String {
    format!(
        "Sweep `{}` on {} ({} worker{} per point), the same training budget per point: {}. \
         Final figures: the newest committed checkpoint evaluated on the `{}` split{}; \
         curves: the validation subset evaluated during training.",
        f.name,
        f.data,
        f.workers,
        if f.workers == 1 { "" } else { "s" },
        budget(f),
        f.eval_split,
        f.eval_scenes
            .map_or(String::new(), |n| format!(" (first {n} scenes)")),
    )
}

/// Makes `out` the folder of the sweep in `file` (a copy of the file goes there); a folder
/// holding another sweep is refused, one holding this sweep with fewer points is kept
/// (its finished points are not run again).
fn claim_folder(file: &Path, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let copy = out.join(SWEEP_COPY);
    let text = std::fs::read_to_string(file)?;
    match std::fs::read_to_string(&copy) {
        Ok(old) if old != text => {
            let extends = match (SweepFile::load(file), SweepFile::load(&copy)) {
                (Ok(now), Ok(was)) => now.extends(&was),
                _ => false,
            };
            if !extends {
                bail!(
                    "{} holds a different sweep ({}): a sweep file may add points to the one \
                     there, nothing else; choose another --out or remove it",
                    out.display(),
                    copy.display()
                );
            }
            eprintln!(
                "{} holds this sweep with fewer points: its finished points are kept",
                out.display()
            );
            std::fs::write(&copy, &text)?
        }
        _ => std::fs::write(&copy, &text)?,
    }
    Ok(())
}

pub async fn sweep(a: SweepArgs) -> Result<()> {
    let file = SweepFile::load(&a.file)?;
    let dir = a.file.parent().unwrap_or(Path::new("."));
    let base = file.base_job(dir)?;
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs/sweeps").join(&file.name));
    crate::train::ensure_default_data(&file.data).await?;
    let manifest = Manifest::read(&Location::parse(&file.data)?)
        .await
        .with_context(|| format!("reading the dataset {}", file.data))?;
    let points = file.check(&base, manifest.views_per_scene[0] as usize)?;
    claim_folder(&a.file, &out)?;
    let n = points.len();
    eprintln!(
        "sweep `{}`: {n} point{} into {} (budget per point: {})",
        file.name,
        if n == 1 { "" } else { "s" },
        out.display(),
        budget(&file)
    );
    for (i, (point, job)) in points.into_iter().enumerate() {
        let name = point.name();
        let run_dir = out.join(&name);
        let result_path = run_dir.join(RESULT_FILE);
        if result_path.exists() {
            eprintln!("[{}/{n}] {name}: finished, skipped", i + 1);
            continue;
        }
        let started = run_dir.join(osrt_run::JOB_FILE).exists();
        if a.dry_run {
            let state = if started {
                "interrupted: resumes"
            } else {
                "to train"
            };
            eprintln!("[{}/{n}] {name}: {state}", i + 1);
            continue;
        }
        let run = run_dir.to_string_lossy().into_owned();
        // An interrupted point resumes from its checkpoint with what is left of its time.
        let mut max_minutes = file.max_minutes;
        if started && let Some(m) = max_minutes {
            let spent = RunSummary::load(&run_dir).map(|s| s.wall_s).unwrap_or(0.0);
            max_minutes = Some((m - spent / 60.0).max(0.1));
        }
        eprintln!(
            "[{}/{n}] {name}: {}",
            i + 1,
            if started { "resuming" } else { "training" }
        );
        let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
        let threads = file.threads.unwrap_or((cores / file.workers).max(1));
        let spec = crate::cluster::spec(job, &file.data, &run, file.max_steps, max_minutes).await?;
        crate::cluster::run_local(crate::cluster::LocalJob {
            spec,
            workers: file.workers,
            threads_per_worker: threads,
            skip_memory_check: false,
            open: osrt_coordinator::OpenOptions {
                resume: started,
                ..Default::default()
            },
        })
        .await
        .with_context(|| format!("training sweep point {name}"))?;
        let (row, r) = evaluate_point(&file, &point, &run_dir).await?;
        row.save(&result_path)?;
        eprintln!(
            "[{}/{n}] {name}: PSNR {:.2} dB (baseline {:.2}), FG-ARI {}",
            i + 1,
            r.psnr,
            r.baseline_psnr,
            r.fg_ari.map_or("n/a".into(), |v| format!("{v:.3}"))
        );
    }
    if a.dry_run {
        return Ok(());
    }
    let page = sweep_report(&out, &out, &a.targets).await?;
    println!(
        "results: {}, {} and {}; report: {}",
        out.join("results.md").display(),
        out.join("results.csv").display(),
        out.join(html::GROUPS_CSV).display(),
        page.display()
    );
    Ok(())
}

/// Evaluates a trained sweep point: its result row, and the evaluation it comes from.
async fn evaluate_point(
    file: &SweepFile,
    point: &osrt_sweep::Point,
    run_dir: &Path,
) -> Result<(PointResult, osrt_trainer::EvalResult)> {
    let summary = RunSummary::load(run_dir)?;
    let req = crate::train::EvalRequest {
        split: file.eval_split.clone(),
        data: Some(file.data.clone()),
        scenes: file.eval_scenes,
        ..Default::default()
    };
    let run = run_dir.to_string_lossy();
    let (_, _, r) = crate::train::evaluate_run(&run, &req)
        .await
        .with_context(|| format!("evaluating sweep point {}", point.name()))?;
    let row = PointResult {
        point: point.name(),
        settings: point.settings.clone(),
        train_wall_s: summary.wall_s,
        steps: summary.steps,
        scenes_per_s: summary.scenes_per_s,
        eval_split: file.eval_split.clone(),
        eval_scenes: r.scenes,
        psnr: r.psnr,
        baseline_psnr: r.baseline_psnr,
        fg_ari: r.fg_ari,
        ari: r.ari,
        fg_ari_2d: r.fg_ari_2d,
        ratio: r.ratio,
        render_fps: r.render_fps,
        peak_rss_mb: summary.peak_rss_mb,
    };
    Ok((row, r))
}

/// Tables, charts and page of the sweep in `dir`, written into `out`: its points, and its
/// seed groups timed to `targets`.
async fn sweep_report(dir: &Path, out: &Path, targets: &[Target]) -> Result<PathBuf> {
    let file = SweepFile::load(&dir.join(SWEEP_COPY))?;
    let (mut rows, mut curves, mut strips, mut members) = (vec![], vec![], vec![], vec![]);
    for point in file.points() {
        let name = point.name();
        let run_dir = dir.join(&name);
        let curve = RunSummary::load(&run_dir).ok().map(|s| s.curve(&name));
        curves.extend(curve.clone());
        let result_path = run_dir.join(RESULT_FILE);
        let result = match result_path.exists() {
            true => Some(PointResult::load(&result_path)?),
            false => None,
        };
        if result.is_some() {
            let png = format!("render-{name}.png");
            let (split, data) = (&file.eval_split, Some(file.data.as_str()));
            strips.push(render_strip(&run_dir, data, split, out, &png, &name).await);
        }
        rows.extend(result.clone());
        // A point not started yet is no seed of its group.
        if curve.is_some() || result.is_some() {
            let curve = curve.unwrap_or_else(|| Curve {
                label: name,
                points: Vec::new(),
            });
            members.push((point, curve, result));
        }
    }
    let seeds = SeedReport::new(&Group::by_settings(members), targets);
    let strips = strips.into_iter().flatten().collect();
    let report = Report {
        title: format!("sweep {}", file.name),
        note: note(&file),
        rows: &rows,
        curves: &curves,
        strips,
        refresh_s: None,
    };
    publish(out, &report, &seeds).await
}

/// One report's page, its seed groups' TensorBoard events and their times to the
/// targets on stderr.
async fn publish(out: &Path, report: &Report<'_>, seeds: &SeedReport) -> Result<PathBuf> {
    let page = html::write_with_seeds(out, report, seeds)?;
    write_tensorboard(out, seeds).await?;
    say_targets(seeds);
    Ok(page)
}

/// Each seed group's mean curves as TensorBoard scalars in `out/tensorboard/<group>/tb/`
/// (the event writer of run folders, which keeps its files in `tb/`). A report drawn
/// again replaces the events rather than adding to them.
async fn write_tensorboard(out: &Path, seeds: &SeedReport) -> Result<()> {
    for g in &seeds.groups {
        let events = g.tensorboard_events();
        if events.is_empty() {
            continue;
        }
        let dir = out.join(TENSORBOARD_DIR).join(g.folder_name());
        let loc = Location::parse(&dir.to_string_lossy())?;
        let (mut log, _) = osrt_run::tensorboard::EventLog::open(&loc, true).await?;
        log.cut_after(None);
        for (step, wall_s, values) in events {
            log.add(step, wall_s, values);
        }
        log.flush()
            .await
            .with_context(|| format!("writing TensorBoard events of group {}", g.name))?;
    }
    Ok(())
}

/// Each group's time to each target, on stderr.
fn say_targets(seeds: &SeedReport) {
    for g in &seeds.groups {
        for t in &g.targets {
            let mean = t.mean().map_or(String::new(), |(s, k)| {
                format!(", after {s:.1} s (step {k:.0}) on average")
            });
            eprintln!(
                "{}: {} reached by {} of {} seed{}{mean}",
                g.name,
                t.target,
                t.reached(),
                t.hits.len(),
                if t.hits.len() == 1 { "" } else { "s" },
            );
        }
    }
}

/// The report's render strip of a run (first scene of `split`: truth | render | slots per
/// view), as `(caption, file)`; a run that cannot render is reported and left out.
async fn render_strip(
    run: &Path,
    data: Option<&str>,
    split: &str,
    out: &Path,
    png: &str,
    label: &str,
) -> Option<(String, String)> {
    let run_s = run.to_string_lossy();
    match crate::render::report_strip(&run_s, data, split, &out.join(png)).await {
        Ok(_) => Some((
            format!("{label}: first {split} scene, per view: ground truth | render | slots"),
            png.to_string(),
        )),
        Err(e) => {
            eprintln!("no render strip for {label}: {e:#}");
            None
        }
    }
}

pub async fn report(a: ReportArgs) -> Result<()> {
    if a.watch {
        let [one] = a.paths.as_slice() else {
            bail!("--watch follows one run folder, not {}", a.paths.len());
        };
        return crate::watch::watch(&one.to_string_lossy(), a.out.as_deref(), a.every).await;
    }
    let page = match a.paths.as_slice() {
        [one] if one.join(SWEEP_COPY).exists() => {
            sweep_report(one, a.out.as_deref().unwrap_or(one), &a.targets).await?
        }
        [one] => {
            let out = a.out.clone().unwrap_or_else(|| one.join("report"));
            runs_report(&a.paths, &out, &a.targets).await?
        }
        several => {
            if let Some(sweep) = several.iter().find(|p| p.join(SWEEP_COPY).exists()) {
                bail!(
                    "{} is a sweep folder: report a sweep on its own",
                    sweep.display()
                );
            }
            let Some(out) = &a.out else {
                bail!(
                    "{} runs: say where their page goes with --out",
                    several.len()
                );
            };
            runs_report(several, out, &a.targets).await?
        }
    };
    println!("report: {}", page.display());
    Ok(())
}

/// Page of one or more run folders: their curves in one chart, each run's final
/// evaluation as a row where it has one, a render strip per run, and the runs that differ
/// only in their seed as groups timed to `targets`.
async fn runs_report(runs: &[PathBuf], out: &Path, targets: &[Target]) -> Result<PathBuf> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut labels: Vec<String> = runs
        .iter()
        .map(|p| {
            p.file_name()
                .map_or("run".into(), |n| n.to_string_lossy().into_owned())
        })
        .collect();
    if labels
        .iter()
        .enumerate()
        .any(|(i, l)| labels[..i].contains(l))
    {
        // Two runs of the same name in different folders: label by path instead.
        labels = runs.iter().map(|p| p.display().to_string()).collect();
    }
    let (mut rows, mut curves, mut strips, mut notes) = (vec![], vec![], vec![], vec![]);
    let mut members = Vec::new();
    for (i, (run, label)) in runs.iter().zip(&labels).enumerate() {
        let summary = RunSummary::load(run).with_context(|| {
            format!(
                "{} is neither a sweep folder nor a run folder",
                run.display()
            )
        })?;
        let result_path = run.join(RESULT_FILE);
        let result = match result_path.exists() {
            true => Some(PointResult::load(&result_path)?),
            false => None,
        };
        rows.extend(result.clone());
        notes.push(run_note(label, &summary));
        curves.push(summary.curve(label));
        members.push(Member {
            label: label.clone(),
            curve: summary.curve(label),
            result,
        });
        let png = if runs.len() == 1 {
            "render.png".to_string()
        } else {
            format!("render-{i}.png")
        };
        strips.extend(render_strip(run, None, "test", out, &png, label).await);
    }
    let seeds = SeedReport::new(&run_groups(runs, members), targets);
    let title = match labels.as_slice() {
        [one] => format!("run {one}"),
        several => format!("runs {}", several.join(", ")),
    };
    let report = Report {
        title,
        note: notes.join(" "),
        rows: &rows,
        curves: &curves,
        strips,
        refresh_s: None,
    };
    publish(out, &report, &seeds).await
}

/// What a run's records say: its training and its last validation.
fn run_note(label: &str, summary: &RunSummary) -> String {
    let last = summary.evaluations.last();
    format!(
        "{label}: {} steps in {:.0} s of training at {:.2} scenes/s{}; last validation: {}.",
        summary.steps,
        summary.wall_s,
        summary.scenes_per_s,
        summary
            .peak_rss_mb
            .map_or(String::new(), |m| format!(", peak RSS {m:.0} MiB")),
        last.map_or("none yet".into(), |e| format!(
            "PSNR {:.2} dB{}, FG-ARI {}",
            e.psnr,
            e.baseline_psnr.map_or(String::new(), |b| format!(
                " (mean-colour baseline {b:.2} dB)"
            )),
            e.fg_ari.map_or("n/a".into(), |v| format!("{v:.3}"))
        ))
    )
}

/// Run folders (`members` in the same order) grouped by their job config with the seed
/// cleared: runs whose configs differ only in `train.seed` are one group, named by its
/// runs' labels joined with `+`; a run without a readable config is a group of its own.
fn run_groups(runs: &[PathBuf], members: Vec<Member>) -> Vec<Group> {
    let keys: Vec<Option<osrt_trainer::JobConfig>> = runs
        .iter()
        .map(|run| {
            let mut job = osrt_trainer::JobConfig::load(&run.join(osrt_run::CONFIG_FILE)).ok()?;
            job.train.seed = 0;
            Some(job)
        })
        .collect();
    // Each run's group: the first run with an equal config (itself if none).
    let first: Vec<usize> = keys
        .iter()
        .enumerate()
        .map(|(i, k)| match k {
            Some(k) => keys.iter().position(|o| o.as_ref() == Some(k)).unwrap_or(i),
            None => i,
        })
        .collect();
    let names: Vec<String> = (0..runs.len())
        .map(|i| {
            let same = members.iter().zip(&first).filter(|(_, f)| **f == first[i]);
            same.map(|(m, _)| m.label.as_str())
                .collect::<Vec<_>>()
                .join("+")
        })
        .collect();
    Group::by_name(names.into_iter().zip(members))
}
