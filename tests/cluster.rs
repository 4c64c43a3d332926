//! The cluster end to end, with real processes on loopback: `osrt train` (coordinator in
//! process + worker processes), and `osrt coordinator` / `osrt worker` started separately
//! the way pods start them, then killed.

mod common;

use common::*;
use osrt_store::Location;
use std::path::Path;
use std::time::{Duration, Instant};

/// `osrt train` of the tiny preset with 2 workers × 1 thread.
fn train_env(
    data: &str,
    run: &str,
    steps: u64,
    extra: &[&str],
    env: &[(String, String)],
) -> std::process::Output {
    let steps = steps.to_string();
    let mut args = vec![
        "train",
        "--preset",
        "tiny",
        "--workers",
        "2",
        "--threads",
        "1",
        "--data",
        data,
        "--run",
        run,
        "--max-steps",
        &steps,
    ];
    args.extend(extra);
    osrt_env(&args, env)
}

fn train(data: &Path, run: &Path, steps: u64, extra: &[&str]) {
    let _ = train_env(
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        steps,
        extra,
        &[],
    );
}

fn losses(run: &Path) -> Vec<(u64, f64)> {
    read_jsonl(&run.join("metrics.jsonl"))
        .iter()
        .filter(|r| r.get("loss").is_some())
        .map(|r| (r["step"].as_u64().unwrap(), r["loss"].as_f64().unwrap()))
        .collect()
}

fn checkpoint_bytes(run: &Path, step: u64, file: &str) -> Vec<u8> {
    std::fs::read(checkpoint_file(run, step, file)).unwrap()
}

#[test]
fn two_workers_train_agree_and_commit_a_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    train(&data, &run, 30, &[]);
    let l = losses(&run);
    assert_eq!(l.len(), 30, "one training record per step (log_every = 1)");
    assert!(l.iter().all(|(_, x)| x.is_finite()));
    let first: f64 = l[..5].iter().map(|x| x.1).sum::<f64>() / 5.0;
    let last: f64 = l[25..].iter().map(|x| x.1).sum::<f64>() / 5.0;
    assert!(
        last < first,
        "loss should fall: first 5 {first}, last 5 {last}"
    );
    let records = read_jsonl(&run.join("metrics.jsonl"));
    assert!(
        records
            .iter()
            .filter(|r| r.get("loss").is_some())
            .all(|r| r["workers"] == 2)
    );
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done");
    assert_eq!(job["restarts"], 0);
    // Rank 0 recorded the parameter count (the coordinator builds no model).
    let info = read_json(&run.join("run.json")).unwrap();
    let tiny = osrt_trainer::Trainer::new(
        osrt_trainer::JobConfig::preset("tiny").unwrap(),
        osrt_trainer::device::DeviceSpec::Cpu.open().unwrap(),
    )
    .unwrap();
    assert_eq!(
        info["parameters"].as_u64(),
        Some(tiny.num_parameters() as u64)
    );
    // hash_every = 1 in the tiny preset: both replicas' hashes agreed after every step.
    assert_eq!(job["hash_checks"], 30, "{job}");
    assert_eq!(job["last_checkpoint"], 30);
    let loc = Location::parse(run.to_str().unwrap()).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(osrt_run::checkpoint::verify(&loc, 30))
        .expect("the final checkpoint verifies");
    // Retention: the newest 3 (keep_last) plus the best by validation FG-ARI at most.
    let kept = rt.block_on(osrt_run::checkpoint::list_steps(&loc)).unwrap();
    assert!(kept.len() <= 4 && kept[..3] == [30, 25, 20], "{kept:?}");
}

/// Micro-batches between real processes: each worker runs its share of the step's 4
/// scenes as 2 passes of 1, sums their gradients and takes one all-reduce per optimiser
/// step (counted in the collective's debug log: the weights' broadcast, then one per
/// step); the replicas stay bit-identical and the records say how the share was cut.
#[test]
fn two_workers_with_micro_batches_reduce_once_per_step_and_agree() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let env = [(
        "RUST_LOG".to_string(),
        "osrt_collective=debug,warn".to_string(),
    )];
    let out = train_env(
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        8,
        &["--micro-batch-size", "1"],
        &env,
    );
    let log = String::from_utf8_lossy(&out.stderr);
    for rank in 0..2 {
        let reduces = log
            .lines()
            .filter(|l| l.contains("all-reduce") && l.contains(&format!("rank={rank} ")))
            .count();
        assert_eq!(
            reduces,
            1 + 8,
            "rank {rank}: a broadcast and one per step:\n{log}"
        );
    }
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["hash_checks"], 8, "{job}");
    let records = read_jsonl(&run.join("metrics.jsonl"));
    let train: Vec<_> = records.iter().filter(|r| r.get("loss").is_some()).collect();
    assert_eq!(train.len(), 8);
    assert!(train.iter().all(|r| r["micro_batches"] == 2), "{train:?}");
    assert!(losses(&run).iter().all(|(_, x)| x.is_finite()));
}

/// A job whose share of the batch does not fit the machine in one pass runs in the
/// largest micro-batch that does, chosen by `osrt train` from the memory estimate and
/// said in one line: here a limit between the estimates for passes of 4 and of 5 scenes.
#[test]
fn a_share_that_does_not_fit_runs_in_the_largest_micro_batch_that_does() {
    use osrt_trainer::footprint::{estimate, with_headroom};
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let mut job = osrt_trainer::JobConfig::preset("tiny").unwrap();
    job.train.batch_size = 32;
    // Two workers of one thread on this machine, on the dataset's 8×8 images.
    let need = |micro: usize| {
        let mut j = job.clone();
        j.train.micro_batch_size = Some(micro);
        2.0 * with_headroom(estimate(&j, [8, 8], 2, 1).unwrap().total())
    };
    assert!(need(4) < need(5) && need(5) < need(16));
    let limit_gib = (need(4) + need(5)) / 2.0 / (1u64 << 30) as f64;
    let env = [("OSRT_MEMORY_LIMIT_GIB".to_string(), format!("{limit_gib}"))];
    let out = train_env(
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        2,
        &["--batch-size", "32"],
        &env,
    );
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(
        log.contains("a worker's share of 16 scenes does not fit in one pass: micro-batches of 4"),
        "{log}"
    );
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    let records = read_jsonl(&run.join("metrics.jsonl"));
    let train: Vec<_> = records.iter().filter(|r| r.get("loss").is_some()).collect();
    assert!(
        !train.is_empty() && train.iter().all(|r| r["micro_batches"] == 4),
        "{train:?}"
    );
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains("micro_batch_size = 4"), "{config}");
}

/// The GPU's graph on the CPU (`--kernels device`) stages each worker's gradient for the
/// ring bucket by bucket as a GPU does (`osrt_trainer::staging`): between real processes
/// the replicas stay bit-identical (the parameter hash after every step) and the loss
/// falls.
#[test]
fn two_workers_on_the_gpus_graph_stage_their_gradients() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let env = [("RUST_LOG".to_string(), "osrt_worker=info,warn".to_string())];
    let args = ["--kernels", "device"];
    let out = train_env(
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        16,
        &args,
        &env,
    );
    let log = String::from_utf8_lossy(&out.stderr);
    let staged = log.matches("the gradient crosses to the ring and back bucket by bucket");
    assert_eq!(
        staged.count(),
        2,
        "each worker stages its gradient once made:\n{log}"
    );
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done");
    assert_eq!(job["restarts"], 0);
    assert_eq!(job["hash_checks"], 16, "{job}");
    let l = losses(&run);
    assert_eq!(l.len(), 16);
    let first: f64 = l[..4].iter().map(|x| x.1).sum::<f64>() / 4.0;
    let last: f64 = l[12..].iter().map(|x| x.1).sum::<f64>() / 4.0;
    assert!(
        last < first,
        "loss should fall: first 4 {first}, last 4 {last}"
    );
}

#[test]
fn resume_is_bit_identical_to_a_straight_run() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let straight = dir.path().join("straight");
    let split = dir.path().join("split");
    train(&data, &straight, 12, &[]);
    train(&data, &split, 6, &[]);
    train(&data, &split, 12, &["--resume"]);
    for file in ["model.safetensors", "optimizer.safetensors"] {
        assert!(
            checkpoint_bytes(&straight, 12, file) == checkpoint_bytes(&split, 12, file),
            "{file} differs after resume"
        );
    }
    // Same data order: every step's loss (a function of the batch) is identical.
    assert_eq!(losses(&straight), losses(&split));
    let job = read_json(&split.join("job.json")).unwrap();
    assert_eq!(job["state"], "done");
    assert_eq!(job["generation"], 2, "the resume is a second generation");
    // TensorBoard sees both invocations' records once each, pictures included.
    let tb = check_tensorboard(&split);
    assert_eq!(tb["train_steps"], 12, "{tb}");
    assert_eq!(tb["eval_steps"], serde_json::json!([0, 6, 12]), "{tb}");
}

#[test]
fn a_budget_horizon_is_measured_recorded_and_reruns_to_the_bit() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let budget = dir.path().join("budget");
    let (d, b) = (data.to_str().unwrap(), budget.to_str().unwrap());
    // A deadline and no step limit: rank 0 measures the horizon over the warm-up (2 steps).
    osrt_env(
        &[
            "train",
            "--preset",
            "tiny",
            "--workers",
            "2",
            "--threads",
            "1",
            "--data",
            d,
            "--run",
            b,
            "--max-minutes",
            "0.2",
            "--horizon",
            "budget",
        ],
        &[],
    );
    let info = read_json(&budget.join("run.json")).unwrap();
    let h = info["horizon"]
        .as_u64()
        .expect("the measured horizon is in run.json");
    let job = read_json(&budget.join("job.json")).unwrap();
    let last = job["last_checkpoint"].as_u64().unwrap();
    assert!(h > 2 && last > 2, "horizon {h}, last step {last}");
    let state = read_json(&checkpoint_file(&budget, last, "state.json")).unwrap();
    assert_eq!(state["horizon"].as_u64(), Some(h), "{state}");
    // Every step after the warm-up decayed towards the floor at the horizon (the tiny
    // preset: peak 1e-3, 2 warm-up steps, floor 0.16 × the peak).
    let records = read_jsonl(&budget.join("metrics.jsonl"));
    let lrs: Vec<(u64, f64)> = records
        .iter()
        .filter_map(|r| Some((r["step"].as_u64()?, r.get("lr")?.as_f64()?)))
        .collect();
    assert_eq!(lrs.len() as u64, last, "one training record per step");
    for &(step, lr) in &lrs {
        let s = step - 1;
        let want = if s < 2 {
            1e-3 * (s + 1) as f64 / 2.0
        } else {
            1e-3 * 0.16f64.powf(((s - 2) as f64 / (h - 2) as f64).min(1.0))
        };
        assert!(
            (lr - want).abs() <= 1e-9 * want,
            "step {step}: lr {lr}, want {want}"
        );
    }
    // The same config given the recorded horizon takes the same steps to the bit.
    let rerun = dir.path().join("rerun");
    train(&data, &rerun, last, &["--horizon", &h.to_string()]);
    for file in ["model.safetensors", "optimizer.safetensors"] {
        assert!(
            checkpoint_bytes(&budget, last, file) == checkpoint_bytes(&rerun, last, file),
            "{file} differs in the rerun with horizon {h}"
        );
    }
}

#[test]
fn a_torn_or_corrupt_checkpoint_is_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 32);
    let run = dir.path().join("run");
    train(&data, &run, 15, &[]);
    // Corrupt step 15 (one byte of the weights) and tear step 10 (no manifest).
    let model = checkpoint_file(&run, 15, "model.safetensors");
    let mut bytes = std::fs::read(&model).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 0x55;
    std::fs::write(&model, bytes).unwrap();
    std::fs::remove_file(run.join("checkpoints/step-000000010/MANIFEST.json")).unwrap();
    let out = osrt(&["eval", "--run", run.to_str().unwrap(), "--split", "test"]);
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("(step 5)"),
        "evaluated the newest verified one: {text}"
    );
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("SHA-256"), "the corrupt one is named: {err}");
    assert!(err.contains("torn"), "the torn one is named: {err}");
    // A resume starts from step 5 as well, and finishes.
    train(&data, &run, 8, &["--resume"]);
    let l = losses(&run);
    assert_eq!(l.last().unwrap().0, 8);
    assert!(l.windows(2).all(|w| w[0].0 < w[1].0), "one timeline: {l:?}");
}

/// A worker of a micro-batched job killed mid-way: the survivor restarts alone within the
/// heartbeat timeout and keeps the job's global batch of 4 scenes, now its whole share in
/// 4 passes of 1 instead of 2 (the records say so).
#[test]
fn a_killed_worker_does_not_hang_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let config = dir.path().join("job.toml");
    let mut job = osrt_trainer::JobConfig::preset("tiny").unwrap();
    job.train.micro_batch_size = Some(1);
    std::fs::write(&config, job.to_toml()).unwrap();
    let port = free_port();
    // A deadline, not a step count, ends this job: it runs long enough to be killed
    // mid-way on any machine.
    let mut coord = coordinator(
        port,
        &data,
        &run,
        &[
            "--config",
            config.to_str().unwrap(),
            "--max-minutes",
            "0.25",
            "--min-workers",
            "1",
            "--max-workers",
            "2",
        ],
    );
    let _a = worker(port);
    let mut b = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["generation"] == 1 && j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    b.0.kill().unwrap();
    let killed = Instant::now();
    let j = wait_job(&run, Duration::from_secs(60), |j| {
        j["generation"].as_u64().unwrap() >= 2
    });
    // Heartbeat timeout of the tiny preset: 3 s; the survivor restarts, it does not hang.
    assert!(
        killed.elapsed() < Duration::from_secs(10),
        "new generation after {:?}: {j}",
        killed.elapsed()
    );
    let status = coord.wait_for_exit(Duration::from_secs(120));
    assert!(status.success(), "coordinator: {status}");
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert!(job["restarts"].as_u64().unwrap() >= 1);
    let l = losses(&run);
    assert_eq!(Some(l.last().unwrap().0), job["last_checkpoint"].as_u64());
    assert!(l.windows(2).all(|w| w[0].0 < w[1].0), "one timeline");
    // After the loss the survivor trained alone, on the same global batch.
    let records = read_jsonl(&run.join("metrics.jsonl"));
    let train: Vec<_> = records.iter().filter(|r| r.get("loss").is_some()).collect();
    assert!(
        train.iter().any(|r| r["workers"] == 1),
        "a 1-worker generation"
    );
    for r in &train {
        let workers = r["workers"].as_u64().unwrap();
        assert_eq!(
            workers * r["micro_batches"].as_u64().unwrap(),
            4,
            "passes of 1 scene make the batch of 4: {r}"
        );
    }
}

#[test]
fn a_restarted_coordinator_resumes_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let args = ["--max-minutes", "0.2", "--min-workers", "2"];
    let mut coord = coordinator(port, &data, &run, &args);
    let mut a = worker(port);
    let mut b = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    coord.0.kill().unwrap();
    let _ = coord.0.wait();
    std::thread::sleep(Duration::from_millis(500));
    // Killed: its lease is taken over without watching it for renewals.
    let restart: Vec<&str> = args.iter().copied().chain(["--take-over"]).collect();
    let mut coord = coordinator(port, &data, &run, &restart);
    let status = coord.wait_for_exit(Duration::from_secs(120));
    assert!(status.success(), "restarted coordinator: {status}");
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert!(job["generation"].as_u64().unwrap() >= 2, "{job}");
    assert!(job["last_checkpoint"].as_u64().unwrap() > 10, "{job}");
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    assert!(b.wait_for_exit(Duration::from_secs(30)).success());
    // The steps replayed after the restart have one value each in TensorBoard, and the
    // records of the second generation say it was a restart.
    let tb = check_tensorboard(&run);
    assert_eq!(
        tb["train_steps"].as_u64(),
        Some(losses(&run).len() as u64),
        "{tb}"
    );
    let restarts: Vec<u64> = read_jsonl(&run.join("metrics.jsonl"))
        .iter()
        .filter_map(|r| r.get("loss").map(|_| r["restarts"].as_u64().unwrap_or(0)))
        .collect();
    assert_eq!(restarts.first(), Some(&0));
    assert_eq!(restarts.last(), job["restarts"].as_u64().as_ref(), "{job}");
}

/// A second coordinator on the folder of a live job is refused, naming the holder, and
/// changes nothing there: the live job ends with one training record per step and every
/// checkpoint it committed verifying.
#[test]
fn a_second_coordinator_on_a_live_run_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let args = ["--max-steps", "400", "--min-workers", "1"];
    let mut coord = coordinator(port, &data, &run, &args);
    let mut a = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    let started = Instant::now();
    let listen = format!("127.0.0.1:{}", free_port());
    let second = std::process::Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(["coordinator", "--preset", "tiny", "--data"])
        .arg(&data)
        .arg("--run")
        .arg(&run)
        .args(["--listen", &listen, "--max-steps", "400", "--resume"])
        .env("OSRT_TOKEN", TOKEN)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(
        !second.status.success(),
        "the second coordinator was not refused"
    );
    assert!(
        err.contains("another coordinator drives this run folder") && err.contains("pid"),
        "{err}"
    );
    assert!(
        started.elapsed() < Duration::from_secs(30),
        "{:?}",
        started.elapsed()
    );
    assert!(
        coord.0.try_wait().unwrap().is_none(),
        "the live job stopped"
    );
    assert!(coord.wait_for_exit(Duration::from_secs(180)).success());
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(
        job["generation"], 1,
        "one generation: nobody else drove the folder"
    );
    let steps: Vec<u64> = losses(&run).iter().map(|(s, _)| *s).collect();
    let mut unique = steps.clone();
    unique.dedup();
    assert_eq!(steps, unique, "one training record per step");
    assert!(steps.windows(2).all(|w| w[0] < w[1]), "{steps:?}");
    let loc = Location::parse(run.to_str().unwrap()).unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let committed = rt.block_on(osrt_run::checkpoint::list_steps(&loc)).unwrap();
    assert!(!committed.is_empty());
    for step in committed {
        rt.block_on(osrt_run::checkpoint::verify(&loc, step))
            .unwrap_or_else(|e| panic!("checkpoint {step}: {e}"));
    }
    assert!(
        !run.join("lease.json").exists(),
        "the lease is released at the end"
    );
}

/// A worker whose device this build cannot open never joins, saying why, and the job
/// goes on with the others (it used to be a config error that failed the whole job).
#[test]
fn a_worker_that_cannot_open_its_device_stays_out_and_the_job_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let mut coord = coordinator(
        port,
        &data,
        &run,
        &["--max-steps", "20", "--min-workers", "1"],
    );
    let mut a = worker(port);
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "worker",
            "--coordinator",
            &format!("http://127.0.0.1:{port}"),
        ])
        .args([
            "--listen",
            "127.0.0.1:0",
            "--device",
            if cfg!(feature = "cuda") {
                "cuda:99"
            } else {
                "cuda"
            },
        ])
        .env("OSRT_TOKEN", TOKEN)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("device: cuda"), "{err}");
    assert!(coord.wait_for_exit(Duration::from_secs(120)).success());
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
}

fn signal(p: &Proc, sig: &str) {
    let pid = p.0.id().to_string();
    let s = std::process::Command::new("kill")
        .args([&format!("-{sig}"), &pid])
        .status()
        .unwrap();
    assert!(s.success(), "kill -{sig} {pid}");
}

/// A worker paused while the coordinator is killed and restarted holds an id of the
/// old coordinator; the other worker registers with the new one first. The new
/// coordinator must not hand out the paused worker's id again (it once did: the paused
/// worker's calls were taken for the other's, it never registered again, and the job
/// waited forever for its second member).
#[test]
fn a_worker_paused_across_a_coordinator_restart_registers_again() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let args = ["--max-minutes", "0.3", "--min-workers", "2"];
    let mut coord = coordinator(port, &data, &run, &args);
    let mut a = worker(port);
    // `a` registers first: it holds the first id the coordinator issues.
    std::thread::sleep(Duration::from_millis(1500));
    let mut b = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    signal(&a, "STOP");
    coord.0.kill().unwrap();
    let _ = coord.0.wait();
    std::thread::sleep(Duration::from_millis(500));
    // Killed: its lease is taken over without watching it for renewals.
    let restart: Vec<&str> = args.iter().copied().chain(["--take-over"]).collect();
    let mut coord = coordinator(port, &data, &run, &restart);
    // `b` finds the new coordinator and registers while `a` sleeps.
    std::thread::sleep(Duration::from_secs(4));
    signal(&a, "CONT");
    let status = coord.wait_for_exit(Duration::from_secs(120));
    assert!(status.success(), "restarted coordinator: {status}");
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    assert!(b.wait_for_exit(Duration::from_secs(30)).success());
}

/// SIGTERM stops a worker gracefully: it tells the coordinator it leaves and exits with
/// an error of its own (not killed by the signal); the job goes on once a replacement
/// joins.
#[test]
fn a_worker_stopped_by_sigterm_tells_the_coordinator_and_exits() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let args = ["--max-steps", "300", "--min-workers", "2"];
    let mut coord = coordinator(port, &data, &run, &args);
    let mut a = worker(port);
    let mut b = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    signal(&b, "TERM");
    let status = b.wait_for_exit(Duration::from_secs(10));
    assert_eq!(status.signal(), None, "handled, not killed: {status}");
    assert!(!status.success());
    let _b = worker(port);
    assert!(coord.wait_for_exit(Duration::from_secs(120)).success());
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    // One restart: the stopped worker left at once, so the next generation did not count
    // it (a dead member would have failed that generation too).
    assert_eq!(job["restarts"], 1, "{job}");
}

/// SIGTERM stops the coordinator gracefully: it writes what it holds (job state and every
/// record it received) and exits on its own, not killed by the signal.
#[test]
fn a_coordinator_stopped_by_sigterm_writes_what_it_holds() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let mut coord = coordinator(port, &data, &run, &["--max-minutes", "1"]);
    let _w = worker(port);
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 20)
    });
    signal(&coord, "TERM");
    let status = coord.wait_for_exit(Duration::from_secs(10));
    assert_eq!(status.signal(), None, "handled, not killed: {status}");
    let job = read_json(&run.join("job.json")).unwrap();
    let last = losses(&run).last().unwrap().0;
    assert!(
        last >= job["last_checkpoint"].as_u64().unwrap(),
        "records up to step {last}, checkpoint {job}"
    );
}

/// On a local run folder `metrics.jsonl` grows by appends: the file is never replaced
/// (a rewrite through the store is a new file under the same name) while no record is
/// dropped.
#[test]
fn metrics_jsonl_grows_in_place() {
    use std::os::unix::fs::MetadataExt;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let mut coord = coordinator(port, &data, &run, &["--max-minutes", "0.1"]);
    let mut w = worker(port);
    let path = run.join("metrics.jsonl");
    let t = Instant::now();
    let inode = loop {
        if let Ok(m) = std::fs::metadata(&path) {
            break m.ino();
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no metrics.jsonl");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(coord.wait_for_exit(Duration::from_secs(120)).success());
    assert!(w.wait_for_exit(Duration::from_secs(30)).success());
    assert_eq!(
        std::fs::metadata(&path).unwrap().ino(),
        inode,
        "replaced, not appended"
    );
    let steps: Vec<u64> = losses(&run).iter().map(|(s, _)| *s).collect();
    assert!(steps.len() > 10, "{} steps", steps.len());
    assert_eq!(steps, (1..=steps.len() as u64).collect::<Vec<_>>());
}

/// A TCP proxy in front of the coordinator whose connections can be cut.
struct CutProxy {
    port: u16,
    conns: std::sync::Arc<std::sync::Mutex<Vec<std::net::TcpStream>>>,
}

impl CutProxy {
    fn to(target: u16) -> Self {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let conns = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let held = conns.clone();
        std::thread::spawn(move || {
            for client in listener.incoming().flatten() {
                let Ok(server) = std::net::TcpStream::connect(("127.0.0.1", target)) else {
                    continue;
                };
                let pipe = |mut from: std::net::TcpStream, mut to: std::net::TcpStream| {
                    std::thread::spawn(move || {
                        let _ = std::io::copy(&mut from, &mut to);
                        let _ = to.shutdown(std::net::Shutdown::Both);
                    });
                };
                let mut h = held.lock().unwrap();
                h.push(client.try_clone().unwrap());
                h.push(server.try_clone().unwrap());
                pipe(client.try_clone().unwrap(), server.try_clone().unwrap());
                pipe(server, client);
            }
        });
        Self { port, conns }
    }

    /// Resets every open connection (calls in flight fail; clients reconnect).
    fn cut(&self) {
        for s in self.conns.lock().unwrap().drain(..) {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }
}

/// A worker whose connection to the coordinator is cut every 300 ms: reports that fail
/// are delivered later (and before any checkpoint after them), so `metrics.jsonl` still
/// has one training record per step. The job is given as long as it keeps making
/// progress (a loaded machine runs it several times slower than an idle one); the
/// worker's log must show failed reports, or the test would prove nothing.
#[test]
fn records_of_failed_reports_are_delivered_later() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let log = dir.path().join("worker.log");
    let port = free_port();
    let proxy = CutProxy::to(port);
    let mut coord = coordinator(port, &data, &run, &["--max-steps", "400"]);
    let mut w = worker_logging_to(&format!("http://127.0.0.1:{}", proxy.port), &log, &[]);
    let (mut seen, mut since) = (0, Instant::now());
    let status = loop {
        if let Some(s) = coord.0.try_wait().unwrap() {
            break s;
        }
        let bytes = std::fs::read_to_string(run.join("metrics.jsonl")).map_or(0, |m| m.len());
        if bytes > seen {
            (seen, since) = (bytes, Instant::now());
        }
        assert!(
            since.elapsed() < Duration::from_secs(60),
            "metrics.jsonl did not grow for 60 s ({seen} bytes); the worker's log:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(300));
        proxy.cut();
    };
    assert!(status.success(), "coordinator: {status}");
    assert!(w.wait_for_exit(Duration::from_secs(30)).success());
    let steps: Vec<u64> = losses(&run).iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, (1..=400).collect::<Vec<_>>());
    let failed = std::fs::read_to_string(&log)
        .unwrap()
        .matches("progress report failed")
        .count();
    assert!(
        failed > 0,
        "no progress report failed: the cuts missed them"
    );
}

/// A worker whose machine cannot hold the job's step (here: a 1 MiB limit) leaves the job
/// before allocating anything, saying why; with no other worker the job fails after its
/// wait timeout.
#[test]
fn a_worker_without_the_memory_for_the_step_leaves_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    let config = dir.path().join("job.toml");
    let mut job = osrt_trainer::JobConfig::preset("tiny").unwrap();
    job.cluster.wait_timeout_s = 3.0;
    std::fs::write(&config, job.to_toml()).unwrap();
    let port = free_port();
    let config = config.to_str().unwrap();
    let mut coord = coordinator(port, &data, &run, &["--config", config, "--max-steps", "3"]);
    let log = dir.path().join("worker.log");
    let limit = [("OSRT_MEMORY_LIMIT_GIB".to_string(), "0.001".to_string())];
    let mut w = worker_logging_to(&format!("http://127.0.0.1:{port}"), &log, &limit);
    assert!(!w.wait_for_exit(Duration::from_secs(60)).success());
    let said = std::fs::read_to_string(&log).unwrap();
    assert!(
        said.contains("this worker's machine cannot hold the job's step"),
        "{said}"
    );
    assert!(said.contains("OSRT_MEMORY_LIMIT_GIB=0.001"), "{said}");
    assert!(!coord.wait_for_exit(Duration::from_secs(60)).success());
    let checkpoints = std::fs::read_dir(run.join("checkpoints"));
    assert!(
        checkpoints.map_or(true, |mut d| d.next().is_none()),
        "a step was taken"
    );
}

/// A step the device cannot hold (a device out-of-memory error, injected through
/// `OSRT_FAULT_DEVICE_OOM` so that it happens on a CPU too) ends the job at once with a
/// message naming the step, its estimate and what to change, instead of restarting into
/// the same error until the restart budget is spent.
#[test]
fn a_step_out_of_device_memory_ends_the_job_with_the_cause() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    let t = std::time::Instant::now();
    let out = std::process::Command::new(bin())
        .args([
            "train",
            "--preset",
            "tiny",
            "--data",
            data.to_str().unwrap(),
        ])
        .args([
            "--run",
            run.to_str().unwrap(),
            "--max-steps",
            "50",
            "--workers",
            "1",
        ])
        .env("OSRT_FAULT_DEVICE_OOM", "1")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(t.elapsed() < Duration::from_secs(60), "{:?}", t.elapsed());
    for part in [
        "out of memory on Cpu",
        "CUDA_ERROR_OUT_OF_MEMORY",
        "4 scene(s), 1 input view(s) at 8×8 px",
        "estimated peak host RAM",
        "Set train.micro_batch_size below 4 (--micro-batch-size",
        "Lower train.batch_size",
    ] {
        assert!(said.contains(part), "{part}: {said}");
    }
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["restarts"], 0, "restarted into the same error: {job}");
    let m = job["message"].as_str().unwrap();
    assert!(m.contains("out of memory on Cpu"), "{m}");
}

/// A resumed job that no worker joins fails after `cluster.wait_timeout_s` with a
/// message that says so, instead of waiting forever.
#[test]
fn a_job_no_worker_joins_fails_after_the_wait_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    let config = dir.path().join("job.toml");
    let mut job = osrt_trainer::JobConfig::preset("tiny").unwrap();
    job.cluster.wait_timeout_s = 2.0;
    std::fs::write(&config, job.to_toml()).unwrap();
    let port = free_port();
    let config = config.to_str().unwrap();
    let mut coord = coordinator(port, &data, &run, &["--config", config, "--max-steps", "3"]);
    let status = coord.wait_for_exit(Duration::from_secs(60));
    assert!(!status.success());
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "failed", "{job}");
    let m = job["message"].as_str().unwrap();
    assert!(m.contains("cluster.wait_timeout_s"), "{m}");
}

#[test]
fn calls_without_the_job_token_are_refused_and_health_answers() {
    use osrt_proto::v1::coordinator_client::CoordinatorClient;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    let port = free_port();
    let _coord = coordinator(port, &data, &run, &["--max-steps", "5"]);
    let addr = format!("http://127.0.0.1:{port}");
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let channel = loop {
            if let Ok(c) = tonic::transport::Endpoint::from_shared(addr.clone())
                .unwrap()
                .connect()
                .await
            {
                break c;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        let mut bare = CoordinatorClient::new(channel.clone());
        let e = bare
            .get_status(osrt_proto::v1::StatusRequest {})
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
        let wrong = osrt_proto::auth::Token::new("another-jobs-token-000").unwrap();
        let mut other = CoordinatorClient::with_interceptor(
            channel.clone(),
            osrt_proto::auth::AttachToken(wrong),
        );
        let e = other
            .register(osrt_proto::v1::RegisterRequest {
                protocol_version: osrt_proto::PROTOCOL_VERSION,
                name: "intruder".into(),
                collective_addr: "http://127.0.0.1:1".into(),
                threads: 1,
                instance: 0,
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
        let right = osrt_proto::auth::Token::new(TOKEN).unwrap();
        let mut ok =
            CoordinatorClient::with_interceptor(channel, osrt_proto::auth::AttachToken(right));
        let s = ok
            .get_status(osrt_proto::v1::StatusRequest {})
            .await
            .unwrap()
            .into_inner();
        assert_eq!(s.members.len(), 0, "the intruder was not registered");
        // A worker of another protocol version is refused at registration.
        let e = ok
            .register(osrt_proto::v1::RegisterRequest {
                protocol_version: 99,
                name: "old".into(),
                collective_addr: "http://127.0.0.1:1".into(),
                threads: 1,
                instance: 0,
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e}");
        // Messages up to 16 MiB are taken (a report of 10,000 records is several MiB,
        // past tonic's default of 4 MiB); larger ones are refused before they are decoded.
        let sized = |bytes: usize| osrt_proto::v1::RegisterRequest {
            protocol_version: 99,
            name: "x".repeat(bytes),
            collective_addr: "http://127.0.0.1:1".into(),
            threads: 1,
            instance: 0,
        };
        let e = ok.register(sized(6 << 20)).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::FailedPrecondition, "decoded: {e}");
        let e = ok.register(sized(17 << 20)).await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::OutOfRange, "{e}");
    });
    // An independent gRPC implementation (Python grpcio) asks the standard health
    // service, which needs no token.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_health.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(format!("127.0.0.1:{port}"))
        .output()
        .expect("python3");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "{stdout}{stderr} (scripts/test installs grpcio)"
    );
    assert!(stdout.contains("SERVING"), "{stdout}");
}

#[test]
fn checkpoints_to_and_resumes_from_s3() {
    let s3 = S3Server::start(&["osrt"]);
    let env = s3.env();
    tiny_dataset_at("s3://osrt/data", 32, &env);
    let run = "s3://osrt/runs/a";
    train_env("s3://osrt/data", run, 6, &[], &env);
    train_env("s3://osrt/data", run, 10, &["--resume"], &env);
    let out = osrt_env(&["eval", "--run", run, "--json"], &env);
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(r["psnr"].as_f64().unwrap().is_finite());
    // Read back through the store: the job finished at step 10 from the step-6 checkpoint.
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let store = object_store::aws::AmazonS3Builder::new()
            .with_endpoint(format!("http://127.0.0.1:{}", s3.port))
            .with_allow_http(true)
            .with_access_key_id("test")
            .with_secret_access_key("test")
            .with_region("us-east-1")
            .with_bucket_name("osrt")
            .build()
            .unwrap();
        let loc = Location::new(std::sync::Arc::new(store), "runs/a");
        let steps = osrt_run::checkpoint::list_steps(&loc).await.unwrap();
        assert_eq!(steps, vec![10, 6, 5], "{steps:?}");
        osrt_run::checkpoint::verify(&loc, 10).await.unwrap();
        // The manifest's create-only put is enforced by the server.
        use object_store::{PutMode, PutOptions};
        let path = loc.path("checkpoints/step-000000010/MANIFEST.json");
        let e = loc
            .store
            .put_opts(
                &path,
                "{}".into(),
                PutOptions {
                    mode: PutMode::Create,
                    ..Default::default()
                },
            )
            .await
            .unwrap_err();
        assert!(
            matches!(e, object_store::Error::AlreadyExists { .. }),
            "{e}"
        );
    });
}

#[test]
fn a_malformed_chunk_fails_its_round_and_the_job_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    // Rank 1 sends a chunk one float short in all-reduce 8 (step 7) of generation 1.
    let env = [("OSRT_FAULT_MALFORMED_CHUNK".to_string(), "1:8".to_string())];
    train_env(data.to_str().unwrap(), run.to_str().unwrap(), 20, &[], &env);
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["restarts"], 1, "one failed round, one restart: {job}");
    assert_eq!(job["generation"], 2);
    assert_eq!(job["last_checkpoint"], 20);
    let l = losses(&run);
    assert_eq!(
        l.iter().map(|x| x.0).collect::<Vec<_>>(),
        (1..=20).collect::<Vec<_>>()
    );
    // The replayed steps 6–7 of generation 2 reproduce generation 1's exactly (same
    // checkpoint, same data), so the curve is the one a clean run draws.
    let clean = dir.path().join("clean");
    train(&data, &clean, 20, &[]);
    assert_eq!(losses(&clean), l);
}

#[test]
fn a_job_runs_over_mutual_tls_and_plaintext_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/make_certs.py"))
        .arg(dir.path())
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "{} (scripts/test installs cryptography)",
        String::from_utf8_lossy(&out.stderr)
    );
    let pem = |f: &str| dir.path().join(f).to_str().unwrap().to_string();
    let env = vec![
        ("OSRT_TLS_CERT".to_string(), pem("cert.pem")),
        ("OSRT_TLS_KEY".to_string(), pem("key.pem")),
        ("OSRT_TLS_CA".to_string(), pem("ca.pem")),
    ];
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let port = free_port();
    let mut coord = coordinator_env(
        port,
        &data,
        &run,
        &["--max-steps", "8", "--min-workers", "2"],
        &env,
    );
    let url = format!("https://127.0.0.1:{port}");
    let mut a = worker_env(&url, &env);
    let mut b = worker_env(&url, &env);
    // A plaintext client gets no answer from the TLS port.
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        use osrt_proto::v1::coordinator_client::CoordinatorClient;
        tokio::time::sleep(Duration::from_millis(500)).await;
        let token = osrt_proto::auth::Token::new(TOKEN).unwrap();
        let channel = tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{port}"))
            .unwrap()
            .connect_lazy();
        let mut plain =
            CoordinatorClient::with_interceptor(channel, osrt_proto::auth::AttachToken(token));
        let r = tokio::time::timeout(
            Duration::from_secs(10),
            plain.get_status(osrt_proto::v1::StatusRequest {}),
        )
        .await;
        assert!(
            !matches!(r, Ok(Ok(_))),
            "a plaintext call to the TLS coordinator succeeded"
        );
    });
    assert!(coord.wait_for_exit(Duration::from_secs(120)).success());
    assert!(a.wait_for_exit(Duration::from_secs(30)).success());
    assert!(b.wait_for_exit(Duration::from_secs(30)).success());
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["hash_checks"], 8, "{job}");
}

/// The pids of `parent`'s child processes (Linux `/proc`).
fn children_of(parent: u32) -> Vec<u32> {
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            // `pid (comm) state ppid …`: the comm may hold spaces, so split after it.
            std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|s| {
                s.rsplit_once(')')
                    .and_then(|(_, rest)| rest.split_whitespace().nth(1)?.parse::<u32>().ok())
                    == Some(parent)
            })
        })
        .collect()
}

/// A local worker killed by SIGKILL twice at the same step of the job (what the kernel's
/// out-of-memory killer does to a worker whose step cannot fit) ends the job with the
/// cause, in `job.json` and in `osrt train`'s error, instead of being replaced forever.
/// The test kills every worker the launcher starts as soon as it appears.
#[test]
fn a_worker_killed_twice_at_one_step_ends_the_job_with_the_cause() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    let mut launcher = std::process::Command::new(bin());
    launcher
        .args([
            "train",
            "--preset",
            "tiny",
            "--workers",
            "1",
            "--max-steps",
            "50",
        ])
        .arg("--data")
        .arg(&data)
        .arg("--run")
        .arg(&run)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    let mut launcher = Proc(launcher.spawn().unwrap());
    let (start, mut killed) = (Instant::now(), 0);
    let status = loop {
        if let Some(s) = launcher.0.try_wait().unwrap() {
            break s;
        }
        for pid in children_of(launcher.0.id()) {
            let mut kill = std::process::Command::new("kill");
            kill.args(["-KILL", &pid.to_string()]);
            killed += usize::from(kill.status().is_ok_and(|s| s.success()));
        }
        assert!(start.elapsed() < Duration::from_secs(60), "still running");
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut launcher.0.stderr.take().unwrap(), &mut err).unwrap();
    assert!(!status.success(), "{err}");
    assert!(killed >= 2, "{killed} workers killed");
    assert!(
        err.contains("killed by SIGKILL twice while setting up the job's first step"),
        "{err}"
    );
    let job = read_json(&run.join("job.json")).unwrap();
    assert_eq!(job["state"], "failed", "{job}");
    assert!(
        job["message"]
            .as_str()
            .unwrap()
            .contains("out-of-memory killer"),
        "{job}"
    );
}

/// SIGTERM stops `osrt train` gracefully: its coordinator writes what it holds (every
/// record up to the last checkpoint) and releases the run folder's lease before the
/// process ends, so `--resume` starts at once.
#[test]
fn osrt_train_stopped_by_sigterm_waits_for_its_final_write() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 64);
    let run = dir.path().join("run");
    let mut launcher = std::process::Command::new(bin());
    launcher
        .args([
            "train",
            "--preset",
            "tiny",
            "--workers",
            "2",
            "--threads",
            "1",
        ])
        .args(["--max-minutes", "2", "--data"])
        .arg(&data)
        .arg("--run")
        .arg(&run)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null());
    let launcher = Proc(launcher.spawn().unwrap());
    wait_job(&run, Duration::from_secs(60), |j| {
        j["last_checkpoint"].as_u64().is_some_and(|s| s >= 10)
    });
    signal(&launcher, "TERM");
    let mut launcher = launcher;
    let status = launcher.wait_for_exit(Duration::from_secs(40));
    assert_eq!(status.signal(), None, "handled, not killed: {status}");
    assert!(
        !run.join("lease.json").exists(),
        "the lease was not released"
    );
    let job = read_json(&run.join("job.json")).unwrap();
    let last = losses(&run).last().unwrap().0;
    assert!(
        last >= job["last_checkpoint"].as_u64().unwrap(),
        "records up to step {last}, checkpoint {job}"
    );
}
