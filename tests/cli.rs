//! The `osrt` binary end to end: generate a dataset, inspect it, and read it back with an
//! independent Parquet implementation (pyarrow).

mod common;

use common::{bin, osrt, read_jsonl};
use std::path::Path;
use std::process::{Command, Stdio};

fn generate(dir: &Path) {
    osrt(&[
        "data",
        "generate",
        "--preset",
        "clevr-lite",
        "--out",
        dir.to_str().unwrap(),
        "--train",
        "40",
        "--val",
        "6",
        "--test",
        "5",
        "--seed",
        "3",
        "--image-size",
        "24",
        "--scenes-per-row-group",
        "8",
    ]);
}

#[test]
fn generate_then_inspect() {
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path());
    let sheet = dir.path().join("sheet.png");
    let out = osrt(&[
        "data",
        "inspect",
        dir.path().to_str().unwrap(),
        "--json",
        "--sheet",
        sheet.to_str().unwrap(),
    ]);
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["splits"]["train"]["scenes"], 40);
    assert_eq!(report["splits"]["train"]["row_groups"], 5);
    assert_eq!(report["splits"]["test"]["scenes"], 5);
    assert_eq!(report["splits"]["val"]["views_histogram"]["3"], 6);
    assert_eq!(report["manifest"]["generator"]["seed"], 3);
    let objects: u64 = report["splits"]["train"]["objects_histogram"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| {
            let k: u64 = k.parse().unwrap();
            assert!((3..=6).contains(&k));
            v.as_u64().unwrap()
        })
        .sum();
    assert_eq!(objects, 40);
    let img = image::open(&sheet).unwrap();
    // 6 scenes by default: 6 rows of 24 px + padding; 3 views + 3 masks across.
    assert_eq!((img.width(), img.height()), (6 * 26 + 2, 6 * 26 + 2));
}

#[test]
fn bad_arguments_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "data",
            "generate",
            "--preset",
            "nope",
            "--out",
            dir.path().to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown preset `nope`"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(["data", "inspect", dir.path().to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("is empty"), "{err}");
    // Device and precision are checked before any worker starts.
    for (args, want) in [
        (vec!["--device", "tpu"], "expected cpu, cuda or cuda:N"),
        (vec!["--precision", "fp8"], "expected f32 or bf16"),
        (
            vec!["--precision", "bf16", "--kernels", "composed"],
            "composed ops are the f32 reference",
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
            .arg("train")
            .args(&args)
            .args(["--data", dir.path().to_str().unwrap()])
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(want), "{args:?}: {err}");
    }
    // check-device on the CPU compares f32 only, and says so where bf16 is asked for.
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "check-device",
            "--device",
            "cpu",
            "--precisions",
            "f32,bf16",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--precisions bf16 needs a GPU"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "check-device",
            "--device",
            "cpu",
            "--presets",
            "tiny",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let precisions: Vec<&str> = (v["steps"].as_array().unwrap().iter())
        .map(|s| s["precision"].as_str().unwrap())
        .collect();
    assert_eq!(precisions, ["f32", "f32"], "fused and composed, f32 only");
    // The plumbing on the CPU: the gradient's staging, exact, and a step with recomputed
    // activations against one keeping them.
    let pipes = v["plumbing"].as_array().unwrap();
    assert_eq!(pipes.len(), 2);
    assert_eq!(pipes[0]["check"], "staged gradient round trip");
    assert_eq!(pipes[1]["check"], "recomputed activations");
    for p in pipes {
        assert_eq!(p["pass"], true, "{p}");
    }
    // Without the `cuda` feature a GPU preset is one clear error, not a worker restart loop.
    if !cfg!(feature = "cuda") {
        let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
            .args(["train", "--preset", "clevr-lite-gpu", "--max-steps", "1"])
            .args(["--data", dir.path().to_str().unwrap()])
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("scripts/build-cuda.sh"), "{err}");
    }
}

/// Durations and counts out of range are refused by the flag's name before anything runs:
/// `Duration::from_secs_f64` panicked on a negative timeout (the coordinator's after it
/// had taken the run folder's lease), a NaN budget never stopped the job, and an infinite
/// one was saved as `null`, no deadline at all.
#[test]
fn flags_out_of_range_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let (data, r) = (dir.path().to_str().unwrap(), run.to_str().unwrap());
    let coordinator = [
        "coordinator",
        "--data",
        data,
        "--run",
        r,
        "--listen",
        "127.0.0.1:0",
    ];
    let train = ["train", "--data", data, "--run", r];
    let cases: [(Vec<&str>, &str); 7] = [
        (
            vec![
                "worker",
                "--coordinator",
                "http://127.0.0.1:9",
                "--coordinator-timeout-s=-1",
            ],
            "--coordinator-timeout-s",
        ),
        (
            [&coordinator[..], &["--max-steps", "1", "--linger-s=-1"]].concat(),
            "--linger-s",
        ),
        (
            [&coordinator[..], &["--max-minutes", "NaN"]].concat(),
            "--max-minutes",
        ),
        (
            [&train[..], &["--max-minutes", "NaN"]].concat(),
            "--max-minutes",
        ),
        (
            [&train[..], &["--max-minutes", "inf"]].concat(),
            "--max-minutes",
        ),
        (
            [&train[..], &["--eval-every-s", "1e30"]].concat(),
            "--eval-every-s",
        ),
        ([&train[..], &["--workers", "0"]].concat(), "--workers"),
    ];
    for (args, flag) in cases {
        let out = Command::new(bin())
            .args(&args)
            .env("OSRT_TOKEN", "flags-test-token")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            err.contains(flag) && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
    assert!(!run.exists(), "a refused command wrote its run folder");
}

/// pyarrow reads what we wrote (`scripts/test` installs pyarrow).
#[test]
fn pyarrow_reads_generated_splits() {
    let have = Command::new("python3")
        .args(["-c", "import pyarrow"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    assert!(
        have,
        "python3 has no pyarrow: run the tests with scripts/test, which installs it"
    );
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path());
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_parquet.py");
    for (split, n) in [("train", "40"), ("val", "6"), ("test", "5")] {
        let out = Command::new("python3")
            .arg(&script)
            .args([dir.path().to_str().unwrap(), split, n])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "pyarrow check of {split} failed:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

#[test]
fn train_then_eval_a_tiny_run() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    osrt(&[
        "data",
        "generate",
        "--out",
        data.to_str().unwrap(),
        "--train",
        "12",
        "--val",
        "4",
        "--test",
        "3",
        "--image-size",
        "8",
        "--antialias",
        "1",
    ]);
    for decoder in ["slot_mixer", "transformer"] {
        let run = dir.path().join(format!("run-{decoder}"));
        osrt(&[
            "train",
            "--preset",
            "tiny",
            "--decoder",
            decoder,
            "--data",
            data.to_str().unwrap(),
            "--run",
            run.to_str().unwrap(),
            "--max-steps",
            "3",
            "--workers",
            "1",
        ]);
        let records = read_jsonl(&run.join("metrics.jsonl"));
        let train: Vec<_> = records.iter().filter(|r| r.get("loss").is_some()).collect();
        let evals: Vec<_> = records.iter().filter(|r| r.get("psnr").is_some()).collect();
        assert_eq!(train.len(), 3, "log_every = 1 in the tiny preset");
        for r in &train {
            for key in ["step", "wall_s", "loss", "scenes_per_s"] {
                assert!(r[key].is_number(), "{key} missing in {r}");
            }
        }
        assert_eq!(evals.first().unwrap()["step"], 0);
        assert_eq!(evals.last().unwrap()["step"], 3);
        for key in ["psnr", "fg_ari", "fg_ari_2d", "ari"] {
            assert!(evals.last().unwrap().get(key).is_some(), "{key}");
        }
        assert!(
            run.join("checkpoints/step-000000003/MANIFEST.json")
                .is_file()
        );
        assert!(run.join("config.toml").is_file());

        let out = osrt(&["eval", "--run", run.to_str().unwrap(), "--json"]);
        let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(r["scenes"], 3);
        assert!(r["psnr"].as_f64().unwrap().is_finite());
        assert!(r["render_fps"].as_f64().unwrap() > 0.0);
        if decoder == "transformer" {
            // No slot weights: no segmentation numbers, and the text output says so.
            assert!(r["fg_ari"].is_null() && r["ari"].is_null());
            assert_eq!(r["segmentation"], false);
            let text =
                String::from_utf8(osrt(&["eval", "--run", run.to_str().unwrap()]).stdout).unwrap();
            assert!(text.contains("n/a (decoder has no slot weights)"), "{text}");
        } else {
            assert!(r["fg_ari"].as_f64().is_some() && r["ari"].as_f64().is_some());
        }
    }
    // More workers than the batch has scenes: the launcher starts as many as it feeds
    // (the ring used to form and then fail the job).
    let run = dir.path().join("run-capped");
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "train",
            "--preset",
            "tiny",
            "--data",
            data.to_str().unwrap(),
            "--run",
        ])
        .arg(&run)
        .args([
            "--max-steps",
            "2",
            "--workers",
            "3",
            "--batch-size",
            "2",
            "--threads",
            "1",
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("3 workers asked for") && err.contains("starting 2"),
        "{err}"
    );
    let records = read_jsonl(&run.join("metrics.jsonl"));
    assert!(records.iter().any(|r| r["workers"] == 2), "a ring of 2");
    // A coordinator asked to wait for more workers than its batch feeds is refused.
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "coordinator",
            "--preset",
            "tiny",
            "--data",
            data.to_str().unwrap(),
            "--run",
        ])
        .arg(dir.path().join("run-never"))
        .args([
            "--listen",
            "127.0.0.1:0",
            "--min-workers",
            "9",
            "--max-steps",
            "1",
        ])
        .env("OSRT_TOKEN", "test-token-0123456789abcdef")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("min_workers = 9 can never gather"), "{err}");
    assert!(
        !dir.path().join("run-never/lease.json").exists(),
        "the lease is released"
    );
    assert!(
        !dir.path().join("run-never/config.toml").exists(),
        "nothing written"
    );
    // Training into a folder that holds a run is refused, not overwritten.
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args([
            "train",
            "--preset",
            "tiny",
            "--data",
            data.to_str().unwrap(),
            "--run",
        ])
        .arg(dir.path().join("run-slot_mixer"))
        .args(["--max-steps", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("is done; pass --resume"), "{err}");

    // A relative --data is recorded as an absolute path, so evaluation started from
    // another directory (this test's) still finds the run's dataset.
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .current_dir(dir.path())
        .args([
            "train", "--preset", "tiny", "--data", "data", "--run", "run-rel",
        ])
        .args(["--max-steps", "1", "--workers", "1"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run = dir.path().join("run-rel");
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("run.json")).unwrap()).unwrap();
    let recorded = Path::new(info["data"].as_str().unwrap());
    assert!(recorded.is_absolute(), "{info}");
    assert_eq!(
        recorded.canonicalize().unwrap(),
        data.canonicalize().unwrap()
    );
    let out = osrt(&["eval", "--run", run.to_str().unwrap(), "--json"]);
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["scenes"], 3);

    // The dataset moved away: the error names the run's dataset and the way out, and
    // `--data` evaluates on it where it is now.
    let moved = dir.path().join("data-moved");
    std::fs::rename(&data, &moved).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(["eval", "--run", run.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("the dataset run")
            && err.contains(recorded.to_str().unwrap())
            && err.contains("pass --data"),
        "{err}"
    );
    let out = osrt(&[
        "eval",
        "--run",
        run.to_str().unwrap(),
        "--data",
        moved.to_str().unwrap(),
        "--json",
    ]);
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["scenes"], 3);
}

/// The GPU's bf16 graph runs on the CPU for measuring it (`--kernels device --precision
/// bf16`: bf16 products, the convolution node's bf16 unfolding); bf16 with the CPU's fused
/// kernels runs too (their own bf16 products); with candle's composed ops it is refused.
#[test]
fn bench_model_runs_the_gpus_bf16_graph_on_the_cpu() {
    let dir = tempfile::tempdir().unwrap();
    let out_json = dir.path().join("model.json");
    let args = |kernels: &'static str| {
        [
            "bench",
            "model",
            "--step-only",
            "--presets",
            "tiny",
            "--kernels",
            kernels,
            "--precision",
            "bf16",
            "--steps",
            "1",
            "--threads",
            "1",
            "--out",
        ]
    };
    for kernels in ["device", "fused"] {
        let mut a = args(kernels).to_vec();
        a.push(out_json.to_str().unwrap());
        osrt(&a);
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&out_json).unwrap()).unwrap();
        let s = &v["1"]["steps"][0];
        assert_eq!(
            (s["precision"].as_str(), s["kernels"].as_str()),
            (Some("bf16"), Some(kernels)),
            "{s}"
        );
        assert!(s["median_step_s"].as_f64().unwrap() > 0.0, "{s}");
        assert!(s["peak_heap_gib"].as_f64().unwrap() > 0.0, "{s}");
    }
    let mut a = args("composed").to_vec();
    a.push(out_json.to_str().unwrap());
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(&a)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("composed ops are the f32 reference"), "{err}");
}

/// The fused CPU kernels' bf16 step takes the unit this CPU has: its ledger holds bf16
/// products and the packing's casts where `osrt_kernels::cpu_bf16_products` names a unit,
/// f32 products and no casts where it names none; with `OSRT_CPU_BF16=off` (the dispatch
/// told there is no unit) f32 on any CPU.
#[test]
fn fused_bf16_products_follow_the_cpus_units() {
    let dir = tempfile::tempdir().unwrap();
    let here = osrt_kernels::cpu_bf16_products().is_some();
    for (env, bf16) in [
        (vec![], here),
        (vec![("OSRT_CPU_BF16".into(), "off".into())], false),
    ] {
        let (_, v) = ledger_of_tiny(dir.path(), "fused", "bf16", &env);
        let step = v["1"]["ledgers"][0]["totals"]
            .as_array()
            .unwrap()
            .last()
            .unwrap()
            .clone();
        assert_eq!(step["kind"], "step");
        let flops = |ty: &str| step["flops"][ty].as_f64().unwrap_or(0.0);
        assert!(flops("f32") > 0.0 || flops("bf16") > 0.0, "{step}");
        // Every product of the step, the slot attention's one-node products included.
        assert_eq!(
            (flops("bf16") > 0.0, flops("f32") == 0.0),
            (bf16, bf16),
            "{env:?}: {step}"
        );
        let casts = step["bytes"]["cast"].as_u64().unwrap_or(0);
        assert_eq!(casts > 0, bf16, "{env:?}: {step}");
    }
}

/// `osrt bench model --render-only` times the decoders' renders (the volumetric one with
/// and without box culling) and no train step
/// (the loop for render A/B runs); with `--step-only` as well it is refused.
#[test]
fn bench_model_render_only_times_renders_alone() {
    let dir = tempfile::tempdir().unwrap();
    let out_json = dir.path().join("model.json");
    osrt(&[
        "bench",
        "model",
        "--render-only",
        "--slots",
        "2",
        "--threads",
        "1",
        "--out",
        out_json.to_str().unwrap(),
    ]);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out_json).unwrap()).unwrap();
    let one = &v["1"];
    assert_eq!(one["steps"].as_array().unwrap().len(), 0, "{v}");
    let renders = one["renders"].as_array().unwrap();
    let decoders: Vec<&str> = renders
        .iter()
        .map(|r| r["decoder"].as_str().unwrap())
        .collect();
    assert_eq!(
        decoders,
        [
            "slot_mixer",
            "spatial_broadcast",
            "transformer",
            "volumetric",
            "volumetric_no_cull"
        ],
        "{v}"
    );
    assert!(
        renders
            .iter()
            .all(|r| r["slots"] == 2 && r["fps"].as_f64().unwrap() > 0.0),
        "{v}"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(["bench", "model", "--render-only", "--step-only"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot be used with"), "{err}");
}

/// `--profile` times the step's op kinds, forward and backward, with either kernels: the
/// tiny preset's step has its transformer blocks (fused: one op each; composed: their
/// LayerNorms, attention and MLPs) and its convolutions, every call counted and timed,
/// and the ops alone take no more than a few times the whole passes (each is timed apart).
#[test]
fn bench_model_profile_times_each_op_kind() {
    let dir = tempfile::tempdir().unwrap();
    for (kernels, must) in [
        ("fused", &["block", "conv2d"][..]),
        (
            "composed",
            &["attention", "conv2d", "layer_norm", "mlp"][..],
        ),
    ] {
        let out_json = dir.path().join(format!("{kernels}.json"));
        let out = osrt(&[
            "bench",
            "model",
            "--profile",
            "--presets",
            "tiny",
            "--kernels",
            kernels,
            "--steps",
            "2",
            "--threads",
            "1",
            "--out",
            out_json.to_str().unwrap(),
        ]);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(text.contains("ops alone"), "{text}");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&out_json).unwrap()).unwrap();
        let p = &v["1"]["profiles"][0];
        assert_eq!(p["kernels"], kernels, "{p}");
        let ops = p["ops"].as_array().unwrap();
        let kinds: Vec<&str> = ops.iter().map(|o| o["kind"].as_str().unwrap()).collect();
        for k in must {
            assert!(kinds.contains(k), "{kernels}: no {k} in {kinds:?}");
        }
        let f = |o: &serde_json::Value, k: &str| o[k].as_f64().unwrap();
        assert!(ops.iter().all(|o| f(o, "forward_s") > 0.0
            && f(o, "backward_s") >= 0.0
            && o["calls"].as_u64().unwrap() >= 1));
        // The binary counts its heap: every call keeps at least its output, and holds
        // at least that at its peak.
        assert!(
            ops.iter()
                .all(|o| f(o, "kept_bytes") > 0.0 && f(o, "peak_bytes") >= f(o, "kept_bytes")),
            "{p}"
        );
        let ops_s: f64 = ops
            .iter()
            .map(|o| o["calls"].as_f64().unwrap() * (f(o, "forward_s") + f(o, "backward_s")))
            .sum();
        // The per-kind table counts every call once.
        let calls = |v: &serde_json::Value| -> u64 {
            v.as_array()
                .unwrap()
                .iter()
                .map(|o| o["calls"].as_u64().unwrap())
                .sum()
        };
        assert_eq!(calls(&p["kinds"]), calls(&p["ops"]), "{p}");
        let step_s = f(p, "forward_s") + f(p, "backward_s");
        // The step's own memory: its forward pass leaves its graph held, and the passes
        // peak at least there.
        assert!(f(p, "step_kept_bytes") > 0.0, "{p}");
        assert!(f(p, "step_peak_bytes") >= f(p, "step_kept_bytes"), "{p}");
        assert!(step_s > 0.0 && ops_s > 0.0 && ops_s < 5.0 * step_s, "{p}");
    }
}

/// `osrt bench model --ledger` of the `tiny` preset at batch 2 on one thread with
/// `kernels` and `precision` (and `env`): its printed report and its JSON.
fn ledger_of_tiny(
    dir: &Path,
    kernels: &str,
    precision: &str,
    env: &[(String, String)],
) -> (String, serde_json::Value) {
    let out_json = dir.join(format!("{kernels}-{precision}.json"));
    let out = common::osrt_env(
        &[
            "bench",
            "model",
            "--ledger",
            "--presets",
            "tiny",
            "--kernels",
            kernels,
            "--precision",
            precision,
            "--threads",
            "1",
            "--batch-size",
            "2",
            "--out",
            out_json.to_str().unwrap(),
        ],
        env,
    );
    let v = serde_json::from_str(&std::fs::read_to_string(&out_json).unwrap()).unwrap();
    (String::from_utf8_lossy(&out.stdout).into_owned(), v)
}

/// `--ledger` enters one step's products, casts and copies per op kind: the tiny preset's
/// step on the fused CPU kernels has f32 products and no casts; on the device graph in
/// bf16 every product is on bf16 operands (the report says so) and casts appear; the
/// step's totals are the kinds' sums.
#[test]
fn bench_model_ledger_enters_each_products_types() {
    let dir = tempfile::tempdir().unwrap();
    for (kernels, precision) in [("fused", "f32"), ("device", "bf16")] {
        let (text, v) = ledger_of_tiny(dir.path(), kernels, precision, &[]);
        assert!(text.contains("costliest products"), "{text}");
        assert_eq!(
            text.contains("every product on bf16 operands"),
            precision == "bf16",
            "{text}"
        );
        let l = &v["1"]["ledgers"][0];
        let totals = l["totals"].as_array().unwrap();
        let (step, kinds) = totals.split_last().unwrap();
        assert_eq!(step["kind"], "step");
        let flops = |t: &serde_json::Value, ty: &str| t["flops"][ty].as_f64().unwrap_or(0.0);
        let other = if precision == "bf16" { "f32" } else { "bf16" };
        assert!(
            flops(step, precision) > 0.0 && flops(step, other) == 0.0,
            "{step}"
        );
        let sum: f64 = kinds.iter().map(|k| flops(k, precision)).sum();
        assert!((sum - flops(step, precision)).abs() <= 1e-9 * sum, "{l}");
        let products = |t: &serde_json::Value| t["products"].as_u64().unwrap();
        assert_eq!(kinds.iter().map(products).sum::<u64>(), products(step));
        let casts = step["bytes"]["cast"].as_u64().unwrap_or(0);
        assert_eq!(casts > 0, precision == "bf16", "{step}");
    }
}

/// Writes to a local folder are synced before they count: `strace` sees an fsync of
/// every file `osrt data generate` writes (the three splits' parts and the manifest) and
/// of every file a training job's run folder depends on (each checkpoint object with its
/// manifest, `job.json`, `metrics.jsonl`), and of their folders. Without strace (or where
/// it may not trace) the test fails, unless `OSRT_TEST_NO_STRACE=1` asks to skip it.
#[test]
fn local_writes_are_synced() {
    // Installed, and allowed to trace here (containers may forbid ptrace).
    let traces = Command::new("strace")
        .args(["-f", "-o", "/dev/null", "true"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !traces {
        assert!(
            std::env::var_os("OSRT_TEST_NO_STRACE").is_some(),
            "strace is not installed or may not trace here: install it (scripts/test does \
             where apt-get may) or set OSRT_TEST_NO_STRACE=1 to skip this check knowingly"
        );
        eprintln!("SKIPPED (OSRT_TEST_NO_STRACE): the fsync check");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let generate = [
        "data",
        "generate",
        "--preset",
        "clevr-lite",
        "--train",
        "4",
        "--val",
        "1",
        "--test",
        "1",
        "--image-size",
        "8",
        "--out",
    ];
    let synced = synced_paths(dir.path(), &generate, &data);
    let mut wanted: Vec<std::path::PathBuf> = ["train", "val", "test"]
        .iter()
        .map(|s| data.join(s).join("part-00000.parquet"))
        .collect();
    wanted.push(data.join("manifest.json"));
    wanted.extend(["train", "val", "test"].iter().map(|s| data.join(s)));
    assert_synced(&synced, &wanted);

    let run = dir.path().join("run");
    let train = [
        "train",
        "--preset",
        "tiny",
        "--workers",
        "1",
        "--threads",
        "1",
        "--max-steps",
        "5",
        "--data",
        data.to_str().unwrap(),
        "--run",
    ];
    let synced = synced_paths(dir.path(), &train, &run);
    let step = run.join("checkpoints/step-000000005");
    let mut wanted = vec![step.join("MANIFEST.json"), step.clone()];
    for name in ["model.safetensors", "optimizer.safetensors", "state.json"] {
        wanted.push(common::checkpoint_file(&run, 5, name));
    }
    wanted.extend([run.join("job.json"), run.join("metrics.jsonl")]);
    assert_synced(&synced, &wanted);
}

/// Runs `osrt args… out` under strace; returns the paths of the files and folders it
/// synced (`fsync`/`fdatasync` that returned 0).
fn synced_paths(dir: &Path, args: &[&str], out: &Path) -> Vec<String> {
    // One log per thread (`-ff`): a call another thread interrupts is not split into
    // "unfinished" and "resumed" lines.
    let logs = tempfile::tempdir_in(dir).unwrap();
    let status = Command::new("strace")
        .args(["-f", "-ff", "-y", "-e", "trace=fsync,fdatasync", "-o"])
        .arg(logs.path().join("trace"))
        .arg(bin())
        .args(args)
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "osrt {args:?} under strace");
    // `fsync(7</tmp/…/manifest.json#12>) = 0`: with -y, the path behind each descriptor.
    let mut synced = Vec::new();
    for log in std::fs::read_dir(logs.path()).unwrap() {
        let text = std::fs::read_to_string(log.unwrap().path()).unwrap();
        synced.extend(
            text.lines()
                .filter(|l| {
                    (l.contains("fsync(") || l.contains("fdatasync(")) && l.ends_with("= 0")
                })
                .filter_map(|l| Some(l.split_once('<')?.1.rsplit_once(">)")?.0.to_string())),
        );
    }
    synced
}

/// Every path of `wanted` was synced: itself, or the temporary file it was renamed from
/// (`PATH#N`, how a local store writes).
fn assert_synced(synced: &[String], wanted: &[std::path::PathBuf]) {
    for w in wanted {
        let w = std::fs::canonicalize(w).unwrap_or_else(|e| panic!("{}: {e}", w.display()));
        let w = w.to_str().unwrap();
        let hit = synced
            .iter()
            .any(|s| s == w || s.strip_prefix(w).is_some_and(|rest| rest.starts_with('#')));
        assert!(hit, "{w} was not synced; synced:\n{}", synced.join("\n"));
    }
}

/// `osrt bench data` times write and read+decode per image size and codec (cropped
/// renders for non-square sizes) and sets them against what training consumes.
#[test]
fn bench_data_covers_every_size_and_codec() {
    let dir = tempfile::tempdir().unwrap();
    let out_json = dir.path().join("data.json");
    osrt(&[
        "bench",
        "data",
        "--scenes",
        "2",
        "--repeats",
        "1",
        "--sizes",
        "16x12,8x8",
        "--out",
        out_json.to_str().unwrap(),
    ]);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out_json).unwrap()).unwrap();
    let cases = v["cases"].as_array().unwrap();
    let seen: Vec<(u64, u64, &str)> = cases
        .iter()
        .map(|c| {
            (
                c["image_size"].as_u64().unwrap(),
                c["image_height"].as_u64().unwrap(),
                c["codec"].as_str().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        seen,
        [
            (16, 12, "raw"),
            (16, 12, "png"),
            (8, 8, "raw"),
            (8, 8, "png")
        ],
        "{v}"
    );
    assert!(
        cases
            .iter()
            .all(|c| c["read_with_masks"]["scenes_per_s"].as_f64().unwrap() > 0.0)
    );
    assert_eq!(v["training_consumes_scenes_per_s"], 2048.0);
}
