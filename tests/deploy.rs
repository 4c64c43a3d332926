//! The Kubernetes manifests in deploy/k8s: validated offline against the API schemas
//! (kubernetes-validate --strict), and run the way their pods run — the same binary, the
//! same arguments and the same environment variables (values for loopback and a local
//! S3-compatible server substituted) — until the job completes. The GPU overlay,
//! deploy/k8s-gpu, is built as `kubectl apply -k` builds it and validated the same way;
//! its pods are not run (no GPU here), but its workers are shown to be the CPU workers
//! plus `--device cuda` on one GPU each.

mod common;

use common::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn k8s_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/k8s")
}

fn k8s_gpu_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/k8s-gpu")
}

fn python_helper(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/python")
        .join(name)
}

fn output_text(out: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
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

/// The strict validator's verdict on `files` (`scripts/test` installs kubernetes-validate).
fn validate(files: &[PathBuf]) -> std::process::Output {
    let out = Command::new("python3")
        .args(["-m", "kubernetes_validate", "--strict"])
        .args(files)
        .output()
        .expect("python3");
    assert!(
        !String::from_utf8_lossy(&out.stderr).contains("No module named kubernetes_validate"),
        "python3 has no kubernetes-validate: run the tests with scripts/test, which installs it"
    );
    out
}

#[test]
fn manifests_validate_strictly_and_a_broken_one_is_rejected() {
    let files = manifests();
    assert!(files.len() >= 4, "{files:?}");
    let out = validate(&files);
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
        let out = validate(&[path]);
        assert!(!out.status.success(), "{what} was accepted");
    }
}

/// `kubectl kustomize DIR`: the resources `kubectl apply -k DIR` creates, built by
/// tests/python/kustomize_lite.py (checked against kubectl itself where it is installed)
/// into `out`/built.yaml.
fn kustomize_build(dir: &Path, out: &Path) -> PathBuf {
    let mut cmd = Command::new("python3");
    cmd.arg(python_helper("kustomize_lite.py")).arg(dir);
    let kubectl = Command::new("kubectl")
        .args(["version", "--client"])
        .output()
        .is_ok_and(|o| o.status.success());
    if kubectl {
        cmd.arg("--check-kubectl");
    }
    let built = cmd.output().expect("python3");
    assert_ne!(
        built.status.code(),
        Some(77),
        "python3 has no PyYAML: run the tests with scripts/test, which installs it"
    );
    assert!(
        built.status.success(),
        "building {}: {}",
        dir.display(),
        output_text(&built)
    );
    let path = out.join("built.yaml");
    std::fs::write(&path, &built.stdout).unwrap();
    path
}

/// Copies the files (not subfolders) of `from` into a new folder `to`.
fn copy_files(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, to.join(path.file_name().unwrap())).unwrap();
        }
    }
}

#[test]
fn gpu_overlay_validates_strictly_and_a_broken_one_is_rejected() {
    // The base and the overlay, each as `kubectl apply -k` would create it.
    for dir in [k8s_dir(), k8s_gpu_dir()] {
        let tmp = tempfile::tempdir().unwrap();
        let out = validate(&[kustomize_build(&dir, tmp.path())]);
        let text = output_text(&out);
        assert!(out.status.success(), "{}: {text}", dir.display());
        for kind in [
            "configmap/osrt-job",
            "deployment/osrt-coordinator",
            "service/osrt-coordinator",
            "job/osrt-workers",
            "service/osrt-workers",
        ] {
            assert!(text.contains(kind), "{kind} validated: {text}");
        }
    }
    // The check can fail: a misspelt field and a wrongly typed one in the overlay's
    // patch reach the built Job and are rejected (the copy keeps the layout: the
    // overlay names its base as ../k8s).
    let patch = std::fs::read_to_string(k8s_gpu_dir().join("workers-gpu.yaml")).unwrap();
    for (what, broken) in [
        (
            "unknown field",
            patch.replace("tolerations:", "toleration:"),
        ),
        (
            "wrong type",
            patch.replace("nvidia.com/gpu: 1", "nvidia.com/gpu: [1]"),
        ),
    ] {
        assert_ne!(broken, patch, "{what}: the substitution applied");
        let tmp = tempfile::tempdir().unwrap();
        copy_files(&k8s_dir(), &tmp.path().join("k8s"));
        copy_files(&k8s_gpu_dir(), &tmp.path().join("k8s-gpu"));
        std::fs::write(tmp.path().join("k8s-gpu/workers-gpu.yaml"), broken).unwrap();
        let built = kustomize_build(&tmp.path().join("k8s-gpu"), tmp.path());
        let out = validate(&[built]);
        assert!(!out.status.success(), "{what} was accepted");
    }
}

/// What the pods of the kustomization in `dir` run (tests/python/render_pods.py).
fn render_pods(dir: &Path) -> serde_json::Value {
    let out = Command::new("python3")
        .arg(python_helper("render_pods.py"))
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{} (scripts/test installs PyYAML)",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The GPU overlay's workers are the CPU workers (whose command lines the test below
/// runs) with the CUDA image, `--device cuda` and one GPU each; its coordinator is the
/// CPU one writing another run folder.
#[test]
fn gpu_workers_are_the_cpu_workers_with_one_gpu_each() {
    let (cpu, gpu) = (render_pods(&k8s_dir()), render_pods(&k8s_gpu_dir()));
    let (cw, gw) = (&cpu["worker"], &gpu["worker"]);

    // One GPU per pod, requested and limited; CPU and memory Guaranteed as well.
    let resources = &gw["resources"];
    for side in ["requests", "limits"] {
        let gpus = &resources[side]["nvidia.com/gpu"];
        assert!(
            gpus.as_u64() == Some(1) || gpus.as_str() == Some("1"),
            "{side}: nvidia.com/gpu = {gpus}"
        );
    }
    assert_eq!(resources["requests"], resources["limits"], "{resources}");
    let tolerated = gw["tolerations"].as_array().unwrap().iter().any(|t| {
        t["key"] == "nvidia.com/gpu" && t["operator"] == "Exists" && t["effect"] == "NoSchedule"
    });
    assert!(
        tolerated,
        "no nvidia.com/gpu toleration: {}",
        gw["tolerations"]
    );
    assert!(cw["tolerations"].as_array().unwrap().is_empty());

    // The CUDA build of the same version; the coordinator keeps the CPU image (the CUDA
    // binary needs the driver library, which only GPU pods get).
    let cpu_image = cw["image"].as_str().unwrap();
    assert_eq!(gw["image"], format!("{cpu_image}-cuda"));
    assert_eq!(gpu["coordinator"]["image"], cpu["coordinator"]["image"]);

    // The environment: the CPU worker's plus OSRT_DEVICE=cuda, threads following the
    // (larger) CPU limit.
    let mut genv = gw["env"].as_object().unwrap().clone();
    let cenv = cw["env"].as_object().unwrap();
    assert!(
        !cenv.contains_key("OSRT_DEVICE"),
        "the CPU workers set no device"
    );
    assert_eq!(
        genv.remove("OSRT_DEVICE"),
        Some(serde_json::json!({"value": "cuda"})),
        "the GPU workers run --device cuda"
    );
    let threads = genv.get_mut("OSRT_THREADS").unwrap();
    assert_eq!(threads["resourceFieldRef"], "limits.cpu");
    assert_eq!(threads["value"], resources["limits"]["cpu"]);
    threads["value"] = cenv["OSRT_THREADS"]["value"].clone();
    assert_eq!(&genv, cenv);
    for key in ["args", "files", "ports", "parallelism"] {
        assert_eq!(gw[key], cw[key], "{key}");
    }

    // The coordinator and the job config are the base's, with the GPU job's own run.
    let (cc, gc) = (&cpu["coordinator"], &gpu["coordinator"]);
    let mut genv = gc["env"].as_object().unwrap().clone();
    let mut cenv = cc["env"].as_object().unwrap().clone();
    let (grun, crun) = (genv.remove("OSRT_RUN"), cenv.remove("OSRT_RUN"));
    assert_ne!(grun, crun, "the GPU job writes its own run folder");
    assert_eq!(genv, cenv);
    for key in ["args", "files", "ports", "resources"] {
        assert_eq!(gc[key], cc[key], "{key}");
    }

    // OSRT_DEVICE is the variable of the worker's --device flag.
    let help = osrt(&["worker", "--help"]);
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(
        help.contains("--device") && help.contains("OSRT_DEVICE"),
        "{help}"
    );
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

/// deploy/make-certs.sh (the README's recipe) into `out`, for `workers` workers.
fn make_certs(out: &Path, workers: u64, extra: &[&str]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/make-certs.sh");
    let made = Command::new(script)
        .arg(out)
        .arg(workers.to_string())
        .args(extra)
        .output()
        .expect("bash");
    assert!(
        made.status.success(),
        "make-certs.sh: {}",
        output_text(&made)
    );
}

/// Checks that a rendered pod runs TLS from the Secret osrt-tls and probes a plaintext
/// health port, and sets `overrides` so that it runs here: the TLS files of `certs`, a
/// free health port on loopback (returned).
fn tls_and_health(
    rendered: &serde_json::Value,
    certs: &Path,
    overrides: &mut BTreeMap<&str, String>,
) -> u16 {
    let env = &rendered["env"];
    for (var, file) in [
        ("OSRT_TLS_CERT", "tls.crt"),
        ("OSRT_TLS_KEY", "tls.key"),
        ("OSRT_TLS_CA", "ca.crt"),
    ] {
        let path = env[var]["value"]
            .as_str()
            .unwrap_or_else(|| panic!("no {var}"));
        assert_eq!(
            rendered["secret_files"][path],
            format!("osrt-tls/{file}"),
            "{var} = {path} is not mounted from the Secret"
        );
        overrides.insert(var, certs.join(file).to_str().unwrap().to_string());
    }
    let health = env["OSRT_HEALTH_LISTEN"]["value"].as_str().unwrap();
    let health_port: u64 = health.rsplit(':').next().unwrap().parse().unwrap();
    let probes = rendered["probes"].as_object().unwrap();
    assert!(!probes.is_empty(), "no gRPC probes");
    for (kind, port) in probes {
        assert_eq!(port.as_u64(), Some(health_port), "{kind} asks another port");
    }
    let port = free_port();
    overrides.insert("OSRT_HEALTH_LISTEN", format!("127.0.0.1:{port}"));
    port
}

/// grpcio's plaintext health check of `services` at `addr` answers SERVING.
fn health_answers(addr: &str, services: &[&str]) {
    let out = Command::new("python3")
        .arg(python_helper("check_health.py"))
        .arg(addr)
        .args(services)
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "health at {addr}: {}",
        output_text(&out)
    );
}

/// The README's certificate names every address the manifests dial: the coordinator's
/// Service and each worker's stable DNS name, as server and client certificate.
#[test]
fn the_certificate_recipe_names_what_the_pods_dial() {
    let pods = render_pods(&k8s_dir());
    let worker = &pods["worker"];
    let n = worker["parallelism"].as_u64().unwrap();
    let dir = tempfile::tempdir().unwrap();
    make_certs(dir.path(), n, &[]);
    let show = Command::new("openssl")
        .args([
            "x509",
            "-noout",
            "-ext",
            "subjectAltName,extendedKeyUsage",
            "-in",
        ])
        .arg(dir.path().join("tls.crt"))
        .output()
        .expect("openssl (scripts/test installs it)");
    let text = output_text(&show);
    assert!(show.status.success(), "{text}");
    assert!(text.contains("TLS Web Server Authentication"), "{text}");
    assert!(text.contains("TLS Web Client Authentication"), "{text}");
    let coordinator = worker["env"]["OSRT_COORDINATOR"]["value"].as_str().unwrap();
    let host = coordinator
        .trim_start_matches("https://")
        .split(':')
        .next()
        .unwrap();
    let mut names = vec![host.to_string()];
    for index in 0..n {
        let fields = BTreeMap::from([(
            "metadata.annotations['batch.kubernetes.io/job-completion-index']",
            index.to_string(),
        )]);
        let env = pod_env(worker, &BTreeMap::new(), &fields);
        names.push(
            env.into_iter()
                .find(|(k, _)| k == "OSRT_ADVERTISE")
                .unwrap()
                .1,
        );
    }
    for name in names {
        assert!(
            text.contains(&format!("DNS:{name}")),
            "{name} not in {text}"
        );
    }
    let verify = Command::new("openssl")
        .args(["verify", "-CAfile"])
        .arg(dir.path().join("ca.crt"))
        .arg(dir.path().join("tls.crt"))
        .output()
        .unwrap();
    assert!(verify.status.success(), "{}", output_text(&verify));
}

#[test]
fn the_pods_command_lines_run_the_job_against_s3() {
    let s3 = S3Server::start(&["osrt"]);
    let pods = render_pods(&k8s_dir());
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

    // The README's certificates, with loopback's address added: the pods' TLS files.
    let certs = dir.path().join("tls");
    let n = worker["parallelism"].as_u64().unwrap();
    make_certs(&certs, n, &["IP:127.0.0.1"]);

    let port = free_port();
    let mut o = s3_env.clone();
    o.insert("OSRT_TOKEN", TOKEN.to_string());
    o.insert("OSRT_CONFIG", local_config.to_str().unwrap().to_string());
    o.insert("OSRT_LISTEN", format!("127.0.0.1:{port}"));
    o.insert("OSRT_MAX_STEPS", "4".into());
    o.insert("OSRT_LINGER_S", "2".into());
    let coord_health = tls_and_health(coord, &certs, &mut o);
    let env = pod_env(coord, &o, &BTreeMap::new());
    let mut coordinator = start_pod(coord, env);
    let mut workers = Vec::new();
    let mut worker_health = Vec::new();
    for index in 0..n {
        let mut o = s3_env.clone();
        o.insert("OSRT_TOKEN", TOKEN.to_string());
        worker_health.push(tls_and_health(worker, &certs, &mut o));
        // The manifest dials the coordinator over TLS.
        let dialled = worker["env"]["OSRT_COORDINATOR"]["value"].as_str().unwrap();
        assert!(dialled.starts_with("https://"), "{dialled}");
        o.insert("OSRT_COORDINATOR", format!("https://127.0.0.1:{port}"));
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
    // What the kubelet's probes ask: the plaintext health ports, answered by grpcio.
    health_answers(&format!("127.0.0.1:{coord_health}"), &[""]);
    health_answers(&format!("127.0.0.1:{}", worker_health[0]), &[""]);
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

/// The liveness probe's plaintext health port answers from the coordinator's start, not
/// only once the run folder is open: a restart that watches a lease (here one whose
/// holder is gone: 15 s) or verifies large checkpoints must not be killed by its probe.
#[test]
fn the_health_port_answers_while_the_run_folder_is_being_opened() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_dataset(dir.path(), 16);
    let run = dir.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    let lease = r#"{"holder":{"host":"gone","pid":1,"job_id":"job-gone","token":"gone-1",
        "started_unix_s":0},"renewals":3,"renewed_unix_s":0}"#;
    std::fs::write(run.join("lease.json"), lease).unwrap();
    let health = free_port();
    let health_addr = format!("127.0.0.1:{health}");
    let args = ["--max-steps", "10", "--health-listen", health_addr.as_str()];
    let mut coord = coordinator(free_port(), &data, &run, &args);
    let t = std::time::Instant::now();
    let answered = loop {
        let out = Command::new("python3")
            .arg(python_helper("check_health.py"))
            .args([health_addr.as_str(), ""])
            .output()
            .expect("python3");
        if out.status.success() {
            break t.elapsed();
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "no health answer while the lease is watched: {}",
            output_text(&out)
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(
        std::fs::read_to_string(run.join("lease.json"))
            .unwrap()
            .contains("job-gone"),
        "the lease was taken before the watch ended"
    );
    eprintln!(
        "health answered {:.1} s after the start",
        answered.as_secs_f64()
    );
    let _ = coord.0.kill();
    let _ = coord.0.wait();
}
