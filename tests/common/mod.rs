//! Helpers shared by the end-to-end tests: run the `osrt` binary, read JSON lines, start
//! a coordinator and workers as separate processes the way a cluster's pods do.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_osrt")
}

/// Runs `osrt args…` and asserts success.
pub fn osrt(args: &[&str]) -> Output {
    osrt_env(args, &[])
}

pub fn read_jsonl(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

pub fn read_json(path: &Path) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(path).ok()?;
    serde_json::from_str(&text).ok()
}

/// TensorBoard's own readers agree with `RUN/metrics.jsonl`: every record's figures at
/// its step, one value per tag and step, each validation's pictures
/// (`tests/python/check_tensorboard.py`). Returns the script's summary.
pub fn check_tensorboard(run: &Path) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_tensorboard.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(run)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "check_tensorboard.py {}: {}",
        run.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A small dataset for cluster tests: 8×8 views, 8 scenes per row group.
pub fn tiny_dataset(dir: &Path, train: usize) -> PathBuf {
    let data = dir.join("data");
    tiny_dataset_at(data.to_str().unwrap(), train, &[]);
    data
}

/// The same at any location (`s3://…` with the server's variables in `env`).
pub fn tiny_dataset_at(out: &str, train: usize, env: &[(String, String)]) {
    tiny_dataset_with(out, train, &[], env);
}

/// [`tiny_dataset_at`] with more `osrt data generate` arguments (`--views 6`, …).
pub fn tiny_dataset_with(out: &str, train: usize, extra: &[&str], env: &[(String, String)]) {
    let train = train.to_string();
    let mut args = vec![
        "data",
        "generate",
        "--out",
        out,
        "--train",
        &train,
        "--val",
        "4",
        "--test",
        "4",
        "--image-size",
        "8",
        "--antialias",
        "1",
        "--scenes-per-row-group",
        "8",
    ];
    args.extend(extra);
    osrt_env(&args, env);
}

/// Trains the `tiny` preset for `steps` steps on one single-threaded worker into `run`,
/// with `extra` train flags.
pub fn train_tiny(data: &Path, run: &Path, steps: u64, extra: &[&str]) -> Output {
    let (data, run, steps) = (
        data.to_str().unwrap(),
        run.to_str().unwrap(),
        steps.to_string(),
    );
    let mut args = vec![
        "train",
        "--preset",
        "tiny",
        "--data",
        data,
        "--run",
        run,
        "--workers",
        "1",
        "--threads",
        "1",
        "--max-steps",
        &steps,
    ];
    args.extend_from_slice(extra);
    osrt(&args)
}

/// The file of a local run's checkpoint at `step` that holds `name` (`model.safetensors`,
/// …): the object its manifest names (each writer's files have names of their own).
pub fn checkpoint_file(run: &Path, step: u64, name: &str) -> std::path::PathBuf {
    let dir = run.join(format!("checkpoints/step-{step:09}"));
    let manifest = read_json(&dir.join("MANIFEST.json")).expect("a committed checkpoint");
    let entry = manifest["files"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["name"] == name)
        .unwrap_or_else(|| panic!("{name} not in {manifest}"));
    dir.join(entry["object"].as_str().unwrap_or(name))
}

/// A free loopback port (bound and released; the race is harmless in tests).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

pub const TOKEN: &str = "test-token-0123456789abcdef";

/// Kills the process when dropped, so a failing test leaves nothing running.
pub struct Proc(pub Child);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Proc {
    pub fn wait_for_exit(&mut self, limit: Duration) -> std::process::ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(s) = self.0.try_wait().unwrap() {
                return s;
            }
            assert!(
                start.elapsed() < limit,
                "process did not exit within {limit:?}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

pub fn coordinator(port: u16, data: &Path, run: &Path, extra: &[&str]) -> Proc {
    coordinator_env(port, data, run, extra, &[])
}

pub fn coordinator_env(
    port: u16,
    data: &Path,
    run: &Path,
    extra: &[&str],
    env: &[(String, String)],
) -> Proc {
    let mut cmd = Command::new(bin());
    cmd.envs(env.iter().map(|(k, v)| (k.as_str(), v.as_str())));
    cmd.args(["coordinator", "--preset", "tiny", "--data"])
        .arg(data)
        .arg("--run")
        .arg(run)
        .args(["--listen", &format!("127.0.0.1:{port}")])
        .args(extra)
        .env("OSRT_TOKEN", TOKEN)
        .stdout(Stdio::null());
    Proc(cmd.spawn().expect("start coordinator"))
}

pub fn worker(port: u16) -> Proc {
    worker_env(&format!("http://127.0.0.1:{port}"), &[])
}

pub fn worker_env(coordinator: &str, env: &[(String, String)]) -> Proc {
    Proc(
        worker_command(coordinator, env)
            .spawn()
            .expect("start worker"),
    )
}

/// A worker whose log (stderr) goes to `log`, for tests that read what it said.
pub fn worker_logging_to(coordinator: &str, log: &Path, env: &[(String, String)]) -> Proc {
    let file = std::fs::File::create(log).expect("worker log");
    let mut cmd = worker_command(coordinator, env);
    Proc(cmd.stderr(file).spawn().expect("start worker"))
}

fn worker_command(coordinator: &str, env: &[(String, String)]) -> Command {
    let mut cmd = Command::new(bin());
    cmd.envs(env.iter().map(|(k, v)| (k.as_str(), v.as_str())));
    cmd.args([
        "worker",
        "--coordinator",
        coordinator,
        "--listen",
        "127.0.0.1:0",
        "--threads",
        "1",
    ])
    .env("OSRT_TOKEN", TOKEN)
    .stdout(Stdio::null());
    cmd
}

/// Polls `RUN/job.json` until `pred` holds.
pub fn wait_job(
    run: &Path,
    limit: Duration,
    pred: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let start = Instant::now();
    loop {
        if let Some(j) = read_json(&run.join("job.json"))
            && pred(&j)
        {
            return j;
        }
        assert!(
            start.elapsed() < limit,
            "job state not reached within {limit:?}: {:?}",
            read_json(&run.join("job.json"))
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Runs `osrt args…` with extra environment variables and asserts success.
pub fn osrt_env(args: &[&str], env: &[(String, String)]) -> Output {
    let out = Command::new(bin())
        .args(args)
        .envs(env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .output()
        .expect("run osrt");
    assert!(
        out.status.success(),
        "osrt {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A local S3-compatible server (moto, which `scripts/test` installs) with the given
/// buckets.
pub struct S3Server {
    proc: Proc,
    pub port: u16,
}

impl S3Server {
    pub fn start(buckets: &[&str]) -> Self {
        use std::io::BufRead;
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/s3_server.py");
        let mut child = Command::new("python3")
            .arg(script)
            .args(buckets)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("python3");
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let Some(port) = line.strip_prefix("PORT ") else {
            let status = child.wait().unwrap();
            panic!("S3 server did not start ({status}; scripts/test installs moto): {line}");
        };
        let port = port.trim().parse().unwrap();
        Self {
            proc: Proc(child),
            port,
        }
    }

    /// Exactly the variables a pod gets from its Secret and ConfigMap.
    pub fn env(&self) -> Vec<(String, String)> {
        [
            ("AWS_ENDPOINT", format!("http://127.0.0.1:{}", self.port)),
            ("AWS_ALLOW_HTTP", "true".into()),
            ("AWS_ACCESS_KEY_ID", "test".into()),
            ("AWS_SECRET_ACCESS_KEY", "test".into()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect()
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        // Closing stdin stops the server; the Proc guard kills it if it lingers.
        drop(self.proc.0.stdin.take());
    }
}
