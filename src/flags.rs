//! Value parsers of the command line's durations and counts. clap puts the flag's name
//! before the reason (`invalid value '-1' for '--linger-s <LINGER_S>': …`) and refuses
//! the value before anything runs: no lease taken, no file written, no panic in
//! `Duration::from_secs_f64` later. The bounds are the job config's
//! (`osrt_run::cluster_config`): durations at most a year, workers at most `MAX_WORKERS`.

use osrt_run::cluster_config::{MAX_CHUNK_FLOATS, MAX_DURATION_S, MAX_WORKERS, MIN_CHUNK_FLOATS};
use std::ops::RangeInclusive;

/// More compute threads than any machine has cores.
const MAX_THREADS: usize = 4096;

fn number(s: &str) -> Result<f64, String> {
    s.trim()
        .parse::<f64>()
        .map_err(|e| format!("expected a number ({e})"))
}

fn count(s: &str, range: RangeInclusive<usize>) -> Result<usize, String> {
    let v: usize = s
        .trim()
        .parse()
        .map_err(|e| format!("expected a whole number ({e})"))?;
    if !range.contains(&v) {
        return Err(format!(
            "must be in {}..={}, got {v}",
            range.start(),
            range.end()
        ));
    }
    Ok(v)
}

/// Seconds, zero or more, finite, at most a year.
pub fn seconds(s: &str) -> Result<f64, String> {
    let v = number(s)?;
    osrt_run::cluster_config::duration_s(v, false)?;
    Ok(v)
}

/// Seconds, more than zero, finite, at most a year.
pub fn positive_seconds(s: &str) -> Result<f64, String> {
    let v = number(s)?;
    osrt_run::cluster_config::duration_s(v, true)?;
    Ok(v)
}

/// Milliseconds, more than zero, finite, at most a year.
pub fn positive_millis(s: &str) -> Result<f64, String> {
    let v = number(s)?;
    osrt_run::cluster_config::duration_s(v / 1e3, true).map_err(|_| {
        format!(
            "must be a positive, finite number of milliseconds, at most {} (a year); got {v:?}",
            MAX_DURATION_S * 1e3
        )
    })?;
    Ok(v)
}

/// A job's wall-clock budget in minutes: [`check_minutes`].
pub fn minutes(s: &str) -> Result<f64, String> {
    check_minutes(number(s)?)
}

/// Minutes of a job's wall-clock budget: positive, finite, at most a year. NaN would
/// never stop the job. Infinity is refused rather than taken for "no limit": the
/// deadline is kept in `job.json`, and JSON has no infinity (it was written as `null`,
/// which reads back as no deadline at all); a job without a time limit leaves the budget
/// out and gives a step limit.
pub fn check_minutes(v: f64) -> Result<f64, String> {
    let most = MAX_DURATION_S / 60.0;
    if v.is_finite() && v > 0.0 && v <= most {
        return Ok(v);
    }
    Err(format!(
        "must be a positive, finite number of minutes, at most {most} (a year); got {v:?} \
         (for no time limit, leave it out and give --max-steps)"
    ))
}

/// A number of workers: 1 to `MAX_WORKERS`.
pub fn workers(s: &str) -> Result<usize, String> {
    count(s, 1..=MAX_WORKERS)
}

/// A number of compute threads: 1 to 4096.
pub fn threads(s: &str) -> Result<usize, String> {
    count(s, 1..=MAX_THREADS)
}

/// Floats per collective chunk: the job config's `cluster.chunk_floats` range.
pub fn chunk_floats(s: &str) -> Result<usize, String> {
    count(s, MIN_CHUNK_FLOATS..=MAX_CHUNK_FLOATS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_counts_out_of_range_are_refused() {
        for bad in ["-1", "NaN", "inf", "-inf", "1e30", "x", ""] {
            assert!(seconds(bad).is_err(), "{bad}");
            assert!(positive_seconds(bad).is_err(), "{bad}");
            assert!(minutes(bad).is_err(), "{bad}");
            assert!(positive_millis(bad).is_err(), "{bad}");
        }
        assert_eq!(seconds("0"), Ok(0.0));
        assert!(positive_seconds("0").is_err());
        assert!(minutes("0").is_err());
        assert_eq!(minutes("0.2"), Ok(0.2));
        assert_eq!(minutes("525600"), Ok(525_600.0));
        assert!(minutes("525601").is_err());
        assert!(minutes("inf").unwrap_err().contains("--max-steps"));
        for bad in ["0", "-1", "1025", "1.5", "99999999999999999999999"] {
            assert!(workers(bad).is_err(), "{bad}");
        }
        assert_eq!(workers("1024"), Ok(1024));
        assert!(threads("0").is_err());
        assert!(chunk_floats("1").is_err());
        assert!(chunk_floats("262145").is_err());
        assert_eq!(chunk_floats("262144"), Ok(262_144));
    }
}
