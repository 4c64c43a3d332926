//! The Kubernetes manifests in deploy/k8s: validated offline against the API schemas
//! (kubernetes-validate --strict), and run the way their pods run — the same binary, the
//! same arguments and the same environment variables (values for loopback and a local
//! S3-compatible server substituted) — until the job completes.

mod common;

use common::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn k8s_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/k8s")
}

fn manifests() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(k8s_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .filter(|p| p.file_name().unwrap() != "kustomization.yaml")
        .collect();
    v.sort();
    v
}

/// `Some(output)`, or `None` when the validator is missing outside CI.
fn validate(files: &[PathBuf]) -> Option<std::process::Output> {
    let out = Command::new("python3")
        .args(["-m", "kubernetes_validate", "--strict"])
        .args(files)
        .output()
        .expect("python3");
    if String::from_utf8_lossy(&out.stderr).contains("No module named kubernetes_validate") {
        assert!(
            std::env::var_os("CI").is_none(),
            "kubernetes-validate missing in CI"
        );
        eprintln!("skipped: kubernetes-validate not installed");
        return None;
    }
    Some(out)
}

#[test]
fn manifests_validate_strictly_and_a_broken_one_is_rejected() {
    let files = manifests();
    assert!(files.len() >= 4, "{files:?}");
    let Some(out) = validate(&files) else { return };
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{text}");
    for kind in [
        "deployment/osrt-coordinator",
        "job/osrt-workers",
        "service/osrt-workers",
    ] {
        assert!(text.contains(kind), "{kind} validated: {text}");
    }
    // The check can fail: a misspelt field and a wrongly typed one are rejected.
    let dir = tempfile::tempdir().unwrap();
    let workers = std::fs::read_to_string(k8s_dir().join("workers.yaml")).unwrap();
    for (what, broken) in [
        (
            "unknown field",
            workers.replace("backoffLimit: 0", "backofLimit: 0"),
        ),
        (
            "wrong type",
            workers.replace("parallelism: 2", "parallelism: two"),
        ),
    ] {
        assert_ne!(broken, workers, "{what}: the substitution applied");
        let path = dir.path().join("workers.yaml");
        std::fs::write(&path, broken).unwrap();
        let out = validate(&[path]).unwrap();
        assert!(!out.status.success(), "{what} was accepted");
    }
}

/// The environment of a rendered container, with `overrides` replacing manifest values.
/// Every overridden name must exist in the manifest: the test uses its variables.
fn pod_env(
    rendered: &serde_json::Value,
    overrides: &BTreeMap<&str, String>,
    field_refs: &BTreeMap<&str, String>,
) -> Vec<(String, String)> {
    let env = rendered["env"].as_object().unwrap();
    for k in overrides.keys() {
        assert!(env.contains_key(*k), "the manifest has no variable {k}");
    }
    let mut out: Vec<(String, String)> = Vec::new();
    for (k, v) in env {
        let value = if let Some(o) = overrides.get(k.as_str()) {
            o.clone()
        } else if let Some(path) = v.get("fieldRef").and_then(|p| p.as_str()) {
            field_refs
                .get(path)
                .unwrap_or_else(|| panic!("no value for fieldRef {path}"))
                .clone()
        } else {
            v["value"].as_str().unwrap().to_string()
        };
        // Kubernetes expands $(VAR) from variables defined before.
        let expanded = out.iter().fold(value, |acc, (name, val)| {
            acc.replace(&format!("$({name})"), val)
        });
        out.push((k.clone(), expanded));
    }
    out
}

/// Starts the binary as the pod would: its args, exactly `env` (plus PATH), nothing else.
fn start_pod(rendered: &serde_json::Value, env: Vec<(String, String)>) -> Proc {
    let args: Vec<String> = serde_json::from_value(rendered["args"].clone()).unwrap();
    Proc(
        Command::new(bin())
            .args(&args)
            .env_clear()
            .env("PATH", std::env::var("PATH").unwrap_or_default())
            .envs(env)
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    )
}

#[test]
fn the_pods_command_lines_run_the_job_against_s3() {
    let Some(s3) = S3Server::start(&["osrt"]) else {
        return;
    };
    let out = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/render_pods.py"))
        .arg(k8s_dir())
        .output()
        .unwrap();
    if out.status.code() == Some(77) && std::env::var_os("CI").is_none() {
        eprintln!("skipped: PyYAML not installed");
        return;
    }
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let pods: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let coord = &pods["coordinator"];
    let worker = &pods["worker"];
    let s3_env: BTreeMap<&str, String> = s3
        .env()
        .into_iter()
        .map(|(k, v)| {
            (
                match k.as_str() {
                    "AWS_ENDPOINT" => "AWS_ENDPOINT",
                    "AWS_ALLOW_HTTP" => "AWS_ALLOW_HTTP",
                    "AWS_ACCESS_KEY_ID" => "AWS_ACCESS_KEY_ID",
                    "AWS_SECRET_ACCESS_KEY" => "AWS_SECRET_ACCESS_KEY",
                    other => panic!("unexpected {other}"),
                },
                v,
            )
        })
        .collect();
    // The dataset goes where the job config says it is (16×16: the preset samples 512
    // target rays from 3 views).(16×16: the preset samples 512
    // target rays from 3 views).
    let data_url = coord["env"]["OSRT_DATA"]["value"]
        .as_str()
        .unwrap()
        .to_string();
    let run_url = coord["env"]["OSRT_RUN"]["value"]
        .as_str()
        .unwrap()
        .to_string();
    osrt_env(
        &[
            "data",
            "generate",
            "--out",
            &data_url,
            "--train",
            "64",
            "--val",
            "4",
            "--test",
            "4",
            "--image-size",
            "16",
            "--antialias",
            "1",
            "--scenes-per-row-group",
            "8",
        ],
        &s3.env(),
    );
    // The ConfigMap's job.toml, as the pod's volume mount would present it.
    let dir = tempfile::tempdir().unwrap();
    let files = coord["files"].as_object().unwrap();
    let config_path = coord["env"]["OSRT_CONFIG"]["value"].as_str().unwrap();
    let job_toml = files[config_path].as_str().unwrap();
    let local_config = dir.path().join("job.toml");
    std::fs::write(&local_config, job_toml).unwrap();

    let port = free_port();
    let mut o = s3_env.clone();
    o.insert("OSRT_TOKEN", TOKEN.to_string());
    o.insert("OSRT_CONFIG", local_config.to_str().unwrap().to_string());
    o.insert("OSRT_LISTEN", format!("127.0.0.1:{port}"));
    o.insert("OSRT_MAX_STEPS", "4".into());
    o.insert("OSRT_LINGER_S", "2".into());
    let env = pod_env(coord, &o, &BTreeMap::new());
    let mut coordinator = start_pod(coord, env);
    let n = worker["parallelism"].as_u64().unwrap();
    let mut workers = Vec::new();
    for index in 0..n {
        let mut o = s3_env.clone();
        o.insert("OSRT_TOKEN", TOKEN.to_string());
        o.insert("OSRT_COORDINATOR", format!("http://127.0.0.1:{port}"));
        // All pods share one host here: any free port, and loopback instead of the
        // headless Service's DNS name.
        o.insert("OSRT_WORKER_LISTEN", "127.0.0.1:0".into());
        o.insert("OSRT_ADVERTISE", "127.0.0.1".into());
        let fields = BTreeMap::from([(
            "metadata.annotations['batch.kubernetes.io/job-completion-index']",
            index.to_string(),
        )]);
        let env = pod_env(worker, &o, &fields);
        let threads = env.iter().find(|(k, _)| k == "OSRT_THREADS").unwrap();
        assert_eq!(threads.1, "2", "threads follow limits.cpu");
        workers.push(start_pod(worker, env));
    }
    let status = coordinator.wait_for_exit(Duration::from_secs(180));
    assert!(status.success(), "coordinator pod: {status}");
    for w in &mut workers {
        let s = w.wait_for_exit(Duration::from_secs(30));
        assert!(s.success(), "worker pod: {s}");
    }
    // The job's state, read back from the bucket.
    let env = s3.env();
    let out = osrt_env(
        &["eval", "--run", &run_url, "--split", "test", "--json"],
        &env,
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(r["psnr"].as_f64().unwrap().is_finite());
}
