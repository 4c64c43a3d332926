//! The job as the coordinator receives it ([`spec`]), and the check before it starts that
//! its step fits in memory ([`memory_check`]), choosing micro-batches where asked.

use anyhow::{Context, Result, bail};
use osrt_coordinator::JobSpec;
use osrt_proto::auth::Token;
use osrt_run::cluster_config::ClusterOverrides;
use osrt_run::unix_now;
use osrt_trainer::JobConfig;

fn job_id() -> String {
    format!("job-{}", &Token::generate().as_str()[..12])
}

/// A relative local path made absolute against the current directory (URLs and absolute
/// paths unchanged): the run records where its data is, and `osrt eval`, `render` and
/// `report` read that record later, from wherever they are started. "URL" by the same
/// rule as `Location::parse`: anything with `://`.
fn absolute_local(data: &str) -> Result<String> {
    let path = std::path::Path::new(data);
    if data.contains("://") || path.is_absolute() {
        return Ok(data.to_string());
    }
    let cwd = std::env::current_dir().context("resolving the dataset path")?;
    Ok(cwd.join(path).to_string_lossy().into_owned())
}

/// What [`memory_check`] may do about a job that does not fit.
#[derive(Debug, Clone, Copy, Default)]
pub struct MemoryCheck {
    /// Run it anyway (`--skip-memory-check`).
    pub skip: bool,
    /// Give a job without `train.micro_batch_size` the largest micro-batch that fits.
    pub pick_micro_batch: bool,
}

/// Prints the estimated peak memory of one worker's step (`world` workers, `threads`
/// threads each) on the dataset's images, and refuses a job whose `here` workers on this
/// machine need more memory than it has, unless `check.skip` — or, with
/// `check.pick_micro_batch`, runs its share in the largest micro-batches that fit (and
/// says so). Only the fused CPU step's estimate is checked against measured peaks
/// (`tests/memory_estimate.rs`): for the others an excess is a warning.
pub async fn memory_check(
    job: &mut JobConfig,
    data: &str,
    (here, world): (usize, usize),
    threads: usize,
    check: MemoryCheck,
) -> Result<()> {
    let skip = check.skip;
    let Ok(manifest) = osrt_dataset::Manifest::read(&osrt_store::Location::parse(data)?).await
    else {
        // The workers report a missing or unreadable dataset with its reason.
        return Ok(());
    };
    let image = manifest.image_size;
    let fit_of = |job: &JobConfig| osrt_trainer::footprint::check(job, image, world, threads, here);
    let Some(mut fit) = fit_of(job) else {
        eprintln!("no memory estimate for this model (a volumetric decoder)");
        return Ok(());
    };
    eprintln!("{}", fit.memory.describe());
    if here == 0 {
        return Ok(());
    }
    if let Some(size) = fit.micro.filter(|_| check.pick_micro_batch && !skip)
        && job.train.micro_batch_size.is_none()
    {
        job.train.micro_batch_size = Some(size);
        if let Some(picked) = fit_of(job) {
            fit = picked;
        }
        eprintln!(
            "a worker's share of {} scenes does not fit in one pass: micro-batches of {size} \
             (--micro-batch-size {size}; the same step, one all-reduce): {}",
            fit.memory.share,
            fit.memory.describe()
        );
    }
    match fit.verdict {
        Ok(None) => Ok(()),
        Ok(Some(why)) => {
            eprintln!("warning: {why}");
            Ok(())
        }
        Err(why) if skip => {
            eprintln!("warning (--skip-memory-check): {why}");
            Ok(())
        }
        Err(why) => bail!("{why}"),
    }
}

/// The job as the coordinator receives it, the command line's overrides applied; a
/// volumetric decoder's scene box, unless the job sets one, is read from the dataset's
/// manifest here, so the run's saved config carries it.
pub async fn spec(
    mut job: JobConfig,
    data: &str,
    run: &str,
    max_steps: Option<u64>,
    max_minutes: Option<f64>,
) -> Result<JobSpec> {
    if let osrt_model::decoder::Config::Volumetric(v) = &job.model.decoder
        && v.bounds.is_none()
    {
        let manifest = osrt_dataset::Manifest::read(&osrt_store::Location::parse(data)?)
            .await
            .with_context(|| format!("reading the manifest of {data} for the scene's box"))?;
        job.resolve_scene_bounds(&manifest, data)?;
    }
    job.validate()?;
    // The flags are checked as they are parsed; a sweep file's budget arrives here.
    if let Some(m) = max_minutes {
        crate::flags::check_minutes(m).map_err(|why| anyhow::anyhow!("max_minutes {why}"))?;
    }
    Ok(JobSpec {
        job_id: job_id(),
        job_toml: job.to_toml(),
        cluster: job.cluster,
        data: absolute_local(data)?,
        run: run.to_string(),
        max_steps,
        deadline_unix_s: max_minutes.map(|m| unix_now() + m * 60.0),
        cluster_overrides: ClusterOverrides::default(),
    })
}
