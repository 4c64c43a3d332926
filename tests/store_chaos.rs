//! A 2-worker job whose every process opens its stores through a store that misbehaves
//! (`OSRT_FAULT_STORE`, `osrt_store::chaos`: reads of optimizer files that time out,
//! slow puts, create-only puts of checkpoint files answered `AlreadyExists` after they
//! went through), with its coordinator killed and restarted, must keep the run folder's
//! rule: every checkpoint committed at or before the point the restarted coordinator
//! continues from is still there and verifies, every checkpoint left verifies, and
//! `metrics.jsonl` holds every step once.

mod common;

use common::*;
use osrt_run::checkpoint;
use osrt_store::Location;
use std::collections::BTreeSet;
use std::path::Path;
use std::time::{Duration, Instant};

const STEPS: u64 = 300;
const FAULTS: &str =
    "seed=11,reads=optimizer.,read_p=0.3,creates=checkpoints/,create_p=0.3,put_delay_ms=30";

fn job_file(dir: &Path) -> std::path::PathBuf {
    let mut job = osrt_trainer::JobConfig::preset("tiny").unwrap();
    let c = &mut job.cluster;
    c.min_workers = 2;
    c.max_workers = 2;
    c.max_restarts = 1000;
    c.heartbeat_timeout_s = 3.0;
    c.join_grace_s = 0.5;
    c.checkpoint_every = 10;
    // Retention retires nothing: every checkpoint committed stays unless discarded as
    // an abandoned timeline's.
    c.keep_last = 1000;
    let path = dir.join("job.toml");
    std::fs::write(&path, job.to_toml()).unwrap();
    path
}

/// Steps of the checkpoint folders that hold a manifest now.
fn committed(run: &Path) -> BTreeSet<u64> {
    let Ok(dirs) = std::fs::read_dir(run.join("checkpoints")) else {
        return BTreeSet::new();
    };
    dirs.flatten()
        .filter(|d| d.path().join(checkpoint::MANIFEST).exists())
        .filter_map(|d| d.file_name().to_str()?.strip_prefix("step-")?.parse().ok())
        .collect()
}

fn last_record(run: &Path) -> u64 {
    read_jsonl(&run.join("metrics.jsonl"))
        .iter()
        .filter_map(|r| r["step"].as_u64())
        .max()
        .unwrap_or(0)
}

#[test]
fn a_job_on_a_misbehaving_store_keeps_every_checkpoint_and_record() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let job = job_file(dir.path());
    let run = dir.path().join("run");
    let env = [("OSRT_FAULT_STORE".to_string(), FAULTS.to_string())];
    let port = free_port();
    let steps = STEPS.to_string();
    let args = ["--config", job.to_str().unwrap(), "--max-steps", &steps];
    let mut coord = coordinator_env(port, &data, &run, &args, &env);
    let addr = format!("http://127.0.0.1:{port}");
    let mut workers: Vec<Proc> = (0..2).map(|_| worker_env(&addr, &env)).collect();

    // Every checkpoint seen committed before the coordinator dies, and the point a
    // coordinator restarted from the run folder's files continues from.
    let mut seen = BTreeSet::new();
    let t = Instant::now();
    while read_json(&run.join("job.json"))
        .and_then(|j| j["last_checkpoint"].as_u64())
        .is_none_or(|c| c < 100)
    {
        seen.extend(committed(&run));
        assert!(t.elapsed() < Duration::from_secs(60), "no checkpoint 100");
        std::thread::sleep(Duration::from_millis(20));
    }
    signal_kill(&coord);
    let _ = coord.0.wait();
    seen.extend(committed(&run));
    let recorded = read_json(&run.join("job.json")).unwrap()["last_checkpoint"]
        .as_u64()
        .unwrap();
    let bound = checkpoint::resume_bound(Some(last_record(&run)), Some(recorded));
    let restart: Vec<&str> = args.iter().copied().chain(["--take-over"]).collect();
    let mut coord = coordinator_env(port, &data, &run, &restart, &env);
    assert!(
        coord.wait_for_exit(Duration::from_secs(120)).success(),
        "the restarted coordinator failed"
    );
    for w in &mut workers {
        assert!(w.wait_for_exit(Duration::from_secs(30)).success());
    }
    let job_json = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job_json["state"], "done", "{job_json}");

    let now = committed(&run);
    let lost: Vec<u64> = seen
        .iter()
        .copied()
        .filter(|s| *s <= bound && !now.contains(s))
        .collect();
    assert!(
        lost.is_empty(),
        "checkpoints lost: {lost:?} (bound {bound})"
    );
    let loc = Location::parse(run.to_str().unwrap()).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    for s in &now {
        rt.block_on(checkpoint::check(&loc, *s))
            .unwrap_or_else(|e| panic!("checkpoint {s}: {e}"));
    }
    assert!(now.contains(&STEPS), "no final checkpoint: {now:?}");
    let steps: Vec<u64> = read_jsonl(&run.join("metrics.jsonl"))
        .iter()
        .filter(|r| r.get("loss").is_some())
        .map(|r| r["step"].as_u64().unwrap())
        .collect();
    assert_eq!(steps, (1..=STEPS).collect::<Vec<_>>());
    eprintln!(
        "{} checkpoints committed before the kill, resume bound {bound}, {} at the end; {} restarts",
        seen.len(),
        now.len(),
        job_json["restarts"]
    );
}

fn signal_kill(p: &Proc) {
    let s = std::process::Command::new("kill")
        .args(["-KILL", &p.0.id().to_string()])
        .status()
        .unwrap();
    assert!(s.success());
}
