//! `osrt report RUN --watch`: the report page of a running job, rewritten every few
//! seconds from its run folder (a path or an object-store URL) until the job is over.

use anyhow::{Context, Result, bail};
use osrt_run::tensorboard::{EVAL_PICTURES, eval_picture};
use osrt_run::{JOB_FILE, METRICS_FILE, read_file};
use osrt_sweep::RunSummary;
use osrt_sweep::html::{self, Report};
use osrt_sweep::live::{JobView, Live, utc};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What each picture of a validation shows.
fn caption(name: &str) -> &'static str {
    match name {
        "render" => "first input view | target view | render",
        _ => "target's objects | slots",
    }
}

/// Keeps the page of the run at `run` current in `out` every `every` seconds; returns
/// once the job is over (after a last page) or on Ctrl-C or SIGTERM.
pub async fn watch(run: &str, out: Option<&Path>, every: u64) -> Result<()> {
    if every == 0 {
        bail!("--every must be at least 1 second");
    }
    let loc = osrt_store::Location::parse(run)?;
    let out: PathBuf = match (out, loc.local_file(&loc.path(METRICS_FILE))) {
        (Some(o), _) => o.to_path_buf(),
        (None, Some(_)) => Path::new(run).join("report"),
        (None, None) => bail!("{run} is not a local folder: say where its page goes with --out"),
    };
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let label = run
        .trim_end_matches('/')
        .rsplit('/')
        .next()
        .unwrap_or(run)
        .to_string();
    let stop = crate::cluster::shutdown_signal();
    tokio::pin!(stop);
    loop {
        let page = write_page(&loc, &out, &label, every).await?;
        if page.job.is_over() {
            println!(
                "report: {} (the job is {})",
                out.join(html::PAGE).display(),
                page.job.state
            );
            return Ok(());
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(every)) => {}
            _ = &mut stop => {
                println!("report: {}", out.join(html::PAGE).display());
                return Ok(());
            }
        }
    }
}

/// One page from what the run folder holds now; returns where the job stands.
async fn write_page(
    loc: &osrt_store::Location,
    out: &Path,
    label: &str,
    every: u64,
) -> Result<Live> {
    let text = osrt_run::metrics_log::read_all(loc)
        .await?
        .unwrap_or_default();
    let job: JobView = match read_file(loc, JOB_FILE).await? {
        Some(b) => serde_json::from_slice(&b)
            .with_context(|| format!("{}: not a job state", loc.describe(&loc.path(JOB_FILE))))?,
        None => JobView::default(),
    };
    let now = osrt_run::unix_now();
    let live = Live::of(&text, job, now);
    let summary = RunSummary::parse(&text, &loc.describe(&loc.path(METRICS_FILE)))?;
    let mut strips = Vec::new();
    if let Some(e) = live.newest_eval {
        for name in EVAL_PICTURES {
            if let Some(png) = read_file(loc, &eval_picture(e.step, name)).await? {
                let file = format!("{name}.png");
                osrt_sweep::write_bytes(&out.join(&file), &png)?;
                strips.push((
                    format!("validation at step {}: {}", e.step, caption(name)),
                    file,
                ));
            }
        }
    }
    let refresh = (!live.job.is_over()).then_some(every);
    let note = format!(
        "{} Page written {} from {}{}.",
        live.note(),
        utc(now),
        loc.display,
        refresh.map_or(String::new(), |s| format!("; it reloads every {s} s"))
    );
    html::write(
        out,
        &Report {
            title: format!("run {label}"),
            note,
            rows: &[],
            curves: &[summary.curve(label)],
            strips,
            refresh_s: refresh,
        },
    )?;
    eprintln!(
        "report: step {}, {}, {}",
        live.step,
        live.newest_eval
            .map_or("no validation yet".into(), |e| format!(
                "validation at step {}",
                e.step
            )),
        utc(now)
    );
    Ok(live)
}
