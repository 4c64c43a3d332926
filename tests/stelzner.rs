//! Models of stelzner/osrt (PyTorch) in and out, against files PyTorch itself wrote
//! (tests/fixtures/stelzner/write.py: a small model in the peer's layout, its checkpoint
//! after 3 Adam steps, a batch, the model's outputs on it, and its weights after one more
//! Adam step). Run through the `osrt` binary as a user runs it.

mod common;

use common::{bin, osrt};
use osrt_dataset::Batch;
use osrt_dataset::import::npy::{Values, parse_npy};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/stelzner")
}

fn fixture(name: &str) -> PathBuf {
    fixtures().join(name)
}

/// The by-hand check against the peer's own classes: a folder of the same files written
/// with its code (docs/interop.md), named by `OSRT_PEER_FIXTURE`.
fn peer_fixtures() -> PathBuf {
    PathBuf::from(std::env::var("OSRT_PEER_FIXTURE").expect(
        "OSRT_PEER_FIXTURE names a folder of files written with the peer's code (docs/interop.md)",
    ))
}

fn arrays(path: &Path) -> BTreeMap<String, (Vec<usize>, Vec<f32>)> {
    use std::io::Read;
    // Entry by entry: the peer-size weights hold 83 M values.
    let mut zip = zip::ZipArchive::new(std::fs::File::open(path).unwrap()).unwrap();
    (0..zip.len())
        .map(|i| {
            let mut e = zip.by_index(i).unwrap();
            let name = e.name().unwrap().trim_end_matches(".npy").to_string();
            let mut bytes = Vec::new();
            e.read_to_end(&mut bytes).unwrap();
            let a = parse_npy(&bytes, &name).unwrap();
            let Values::Numbers(v) = a.values else {
                panic!("{name}: text")
            };
            (name, (a.shape, v.into_iter().map(|x| x as f32).collect()))
        })
        .collect()
}

/// `‖a − b‖ / ‖b‖` in f64.
fn rel_l2(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let d: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    let n: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    (d / n).sqrt()
}

fn import(run: &Path, model: &Path) -> std::process::Output {
    import_with(run, model, &fixture("config.yaml"))
}

fn import_with(run: &Path, model: &Path, config: &Path) -> std::process::Output {
    Command::new(bin())
        .args(["import-checkpoint", "--from", "stelzner-osrt"])
        .arg(model)
        .arg("--config")
        .arg(config)
        .arg("--run")
        .arg(run)
        .output()
        .unwrap()
}

#[test]
fn a_pytorch_checkpoint_imports_predicts_as_pytorch_and_exports_to_the_same_bits() {
    imports_predicts_and_exports(&fixtures(), false);
}

#[test]
#[ignore = "by hand: needs OSRT_PEER_FIXTURE, files written with the peer's own code"]
fn the_peers_own_checkpoint_imports_predicts_as_the_peer_and_exports() {
    imports_predicts_and_exports(&peer_fixtures(), true);
}

#[tokio::test(flavor = "multi_thread")]
#[ignore = "by hand: needs OSRT_PEER_FIXTURE, files written with the peer's own code"]
async fn fine_tuning_continues_the_peers_own_adam() {
    continues_adam(&peer_fixtures()).await;
}

/// Imports `dir/model.pt` (config `dir/config.yaml`), predicts `dir/inputs.npz` against
/// `dir/expected.npz`, exports and imports again. `paper_widths`: the peer's classes can
/// build the model, so export needs no `--any-widths`.
fn imports_predicts_and_exports(fixtures: &Path, paper_widths: bool) {
    let fixture = |name: &str| fixtures.join(name);
    let import = |run: &Path, model: &Path| import_with(run, model, &fixture("config.yaml"));
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = import(&run, &fixture("model.pt"));
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        said.contains("at step 3") && said.contains("moments: imported"),
        "{said}"
    );
    // Importing over an existing run is refused and changes nothing.
    let again = import(&run, &fixture("model.pt"));
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("config.toml: exists"));

    let pred = dir.path().join("pred.npz");
    let (run_s, pred_s) = (run.to_str().unwrap(), pred.to_str().unwrap());
    let inputs = fixture("inputs.npz");
    osrt(&[
        "predict",
        "--run",
        run_s,
        "--inputs",
        inputs.to_str().unwrap(),
        "--out",
        pred_s,
    ]);
    let (got, want, given) = (
        arrays(&pred),
        arrays(&fixture("expected.npz")),
        arrays(&inputs),
    );
    for name in ["rgb", "slot_weights", "slots"] {
        assert_eq!(got[name].0, want[name].0, "{name}");
        let e = rel_l2(&got[name].1, &want[name].1);
        eprintln!("{name}: relative L2 {e:e} against PyTorch");
        assert!(e < 1e-5, "{name}: relative L2 error {e:e} against PyTorch");
    }
    // The inputs come back as given.
    for name in [
        "input_images",
        "input_directions",
        "target_origins",
        "target_rgb",
    ] {
        assert_eq!(got[name], given[name], "{name}");
    }
    // NumPy reads the archive (an independent reader of our writer).
    let check = Command::new("python3")
        .args([
            "-c",
            "import numpy as np, sys; a = np.load(sys.argv[1]); \
               assert a['rgb'].dtype == np.float32 and a['slot_weights'].shape[:-1] == a['rgb'].shape[:-1]; \
               assert abs(a['slot_weights'].sum(-1) - 1).max() < 1e-5; print('ok')",
            pred_s,
        ])
        .output()
        .unwrap();
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stderr)
    );

    // Out and back in: the same bits. Export refuses widths the peer's classes do not build.
    let st = dir.path().join("model.safetensors");
    let st_s = st.to_str().unwrap();
    let mut export = vec!["export-checkpoint", "--to", "stelzner-osrt", run_s, st_s];
    if !paper_widths {
        let refused = Command::new(bin()).args(&export).output().unwrap();
        let err = String::from_utf8_lossy(&refused.stderr);
        assert!(
            !refused.status.success() && err.contains("model widths"),
            "{err}"
        );
        export.push("--any-widths");
    }
    let said = osrt(&export);
    assert!(String::from_utf8_lossy(&said.stdout).contains("load_state_dict"));
    let run2 = dir.path().join("run2");
    let out = import(&run2, &st);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let step = import_step(&run);
    let a = std::fs::read(common::checkpoint_file(&run, step, "model.safetensors")).unwrap();
    let b = std::fs::read(common::checkpoint_file(&run2, 0, "model.safetensors")).unwrap();
    assert_eq!(a, b, "weights after export and re-import");
}

/// The batch of `inputs.npz` as osrt's training batch.
fn batch(given: &BTreeMap<String, (Vec<usize>, Vec<f32>)>) -> Batch {
    let (shape, images) = given["input_images"].clone();
    let (s, v, h, w) = (shape[0], shape[1], shape[2], shape[3]);
    let r = given["target_origins"].0[1];
    Batch {
        scene_ids: (0..s as u64).collect(),
        batch_size: s,
        input_views: v,
        height: h,
        width: w,
        input_images: images,
        input_origins: given["input_origins"].1.clone(),
        input_directions: given["input_directions"].1.clone(),
        rays_per_scene: r,
        target_origins: given["target_origins"].1.clone(),
        target_directions: given["target_directions"].1.clone(),
        target_rgb: given["target_rgb"].1.clone(),
        target_masks: None,
        target_pixels: vec![(0, 0); s * r],
    }
}

/// The step of a run folder's one checkpoint.
fn import_step(run: &Path) -> u64 {
    let steps = import_steps(run);
    assert_eq!(steps.len(), 1, "{steps:?}");
    steps[0]
}

#[tokio::test(flavor = "multi_thread")]
async fn fine_tuning_continues_the_peers_adam() {
    continues_adam(&fixtures()).await;
}

/// Imports `dir/model.pt`, takes one step on `dir/inputs.npz` at its `lr`, and compares the
/// weights with `dir/after_step.npz` (the peer's `torch.optim.Adam` step).
async fn continues_adam(fixtures: &Path) {
    let fixture = |name: &str| fixtures.join(name);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = import_with(&run, &fixture("model.pt"), &fixture("config.yaml"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let loaded = osrt_trainer::load_run(run.to_str().unwrap()).await.unwrap();
    // The peer's step after the fixture's: Adam at lr 1e-3 on the batch's mean squared error.
    let given = arrays(&fixture("inputs.npz"));
    let lr = given["lr"].1[0] as f64;
    let mut job = loaded.job.clone();
    (job.train.lr, job.train.warmup_steps, job.train.decay_rate) = (lr, 0, 1.0);
    let mut trainer = osrt_trainer::Trainer::new(
        job.clone(),
        osrt_trainer::device::DeviceSpec::Cpu.open().unwrap(),
    )
    .unwrap();
    let loc = osrt_store::Location::parse(run.to_str().unwrap()).unwrap();
    let state = osrt_trainer::checkpoint::load(&loc, 3, &mut trainer)
        .await
        .unwrap();
    assert_eq!((state.step, trainer.opt.t()), (3, 3));
    let before = trainer.params.flatten().unwrap();
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let g = trainer.gradients(&batch(&given), &mut rng).unwrap();
    trainer.apply(g.loss, g.grads).unwrap();
    let params = trainer
        .params
        .vars()
        .into_iter()
        .map(|(n, v)| {
            let t = v.as_tensor();
            (
                n,
                (
                    t.dims().to_vec(),
                    t.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                ),
            )
        })
        .collect();
    let ours = osrt_interop::stelzner::export(&job.model, &params, true).unwrap();
    let peer = arrays(&fixture("after_step.npz"));
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for x in &ours {
        assert_eq!(x.shape, peer[&x.name].0, "{}", x.name);
        a.extend(&x.values);
        b.extend(&peer[&x.name].1);
    }
    let e = rel_l2(&a, &b);
    eprintln!("weights after one Adam step: relative L2 {e:e} against torch.optim.Adam");
    assert!(
        e < 1e-6,
        "weights after one step: relative L2 {e:e} against torch.optim.Adam"
    );
    // The update itself, not only the weights, is the peer's.
    let after = trainer.params.flatten().unwrap();
    let moved = rel_l2(&after, &before);
    eprintln!("the step moved the weights by {moved:e} (relative L2)");
    assert!(moved > 1e-5, "the step moved the weights by {moved:e} only");
}

#[test]
fn bad_files_end_in_errors_naming_the_file_and_the_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let fail = |model: &Path| -> String {
        let out = import(&dir.path().join("run"), model);
        assert!(!out.status.success());
        assert!(
            !dir.path().join("run").exists(),
            "a refused import left a run folder"
        );
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let err = fail(&fixture("wrong_arch.pt"));
    for want in [
        "wrong_arch.pt",
        "missing `decoder.mixing_block.to_q.weight` [24, 180]",
        "missing `decoder.mixing_block.to_k.weight` [24, 24]",
        "unexpected `decoder.allocation_transformer.output_mlp.0.weight` [4, 180]",
    ] {
        assert!(err.contains(want), "{want} not in: {err}");
    }
    let err = fail(&fixture("not_a_state_dict.pt"));
    assert!(
        err.contains("not_a_state_dict.pt") && err.contains("a list of 3 items"),
        "{err}"
    );
    // A pickle that would call `print` is read as data: nothing runs, and it is refused.
    let out = import(&dir.path().join("run"), &fixture("code.pt"));
    assert!(!out.status.success());
    let (said, err) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(
        !said.contains("code ran") && !err.contains("code ran"),
        "{said}{err}"
    );
    assert!(
        err.contains("code.pt") && err.contains("an object of __builtin__.print"),
        "{err}"
    );
    // A truncated file.
    let bytes = std::fs::read(fixture("model.pt")).unwrap();
    let cut = dir.path().join("cut.pt");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = fail(&cut);
    assert!(err.contains("cut.pt") && err.contains("truncated"), "{err}");
    // A storage cut short inside an intact archive names the tensor.
    let short = dir.path().join("short.pt");
    rewrite_entry(&fixture("model.pt"), &short, "data/0", |b| {
        b[..b.len() / 2].to_vec()
    });
    let err = fail(&short);
    assert!(
        err.contains("short.pt") && err.contains("tensor `"),
        "{err}"
    );
}

/// Copies the zip `from` to `to` with the entry ending in `suffix` changed by `f`.
fn rewrite_entry(from: &Path, to: &Path, suffix: &str, f: impl Fn(&[u8]) -> Vec<u8>) {
    use std::io::{Read, Write};
    let mut zin = zip::ZipArchive::new(std::fs::File::open(from).unwrap()).unwrap();
    let mut zout = zip::ZipWriter::new(std::fs::File::create(to).unwrap());
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for i in 0..zin.len() {
        let mut e = zin.by_index(i).unwrap();
        let name = e.name().unwrap().to_string();
        let mut bytes = Vec::new();
        e.read_to_end(&mut bytes).unwrap();
        let bytes = if name.ends_with(suffix) {
            f(&bytes)
        } else {
            bytes
        };
        zout.start_file(name, opts).unwrap();
        zout.write_all(&bytes).unwrap();
    }
    zout.finish().unwrap();
}

#[test]
fn an_imported_model_evaluates_renders_and_fine_tunes_like_any_run() {
    let dir = tempfile::tempdir().unwrap();
    let data = common::tiny_dataset(dir.path(), 8);
    let (run, data_s) = (dir.path().join("run"), data.to_str().unwrap());
    let run_s = run.to_str().unwrap();
    let model = fixture("model.pt");
    // As the peer's runs/clevr3d: input views point-sampled to half size.
    let config = dir.path().join("config.yaml");
    let text = std::fs::read_to_string(fixture("config.yaml")).unwrap();
    let text = text.replace(
        "  num_points: 10\n",
        "  num_points: 10\n  kwargs:\n    downsample: 1\n",
    );
    assert!(text.contains("downsample"));
    std::fs::write(&config, text).unwrap();
    osrt(&[
        "import-checkpoint",
        "--from",
        "stelzner-osrt",
        model.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--run",
        run_s,
        "--data",
        data_s,
    ]);
    // A page before any record of this folder: the imported model's render.
    let page = dir.path().join("page");
    osrt(&["report", run_s, "--out", page.to_str().unwrap()]);
    assert!(page.join("index.html").exists() && page.join("render.png").exists());
    let eval = osrt(&["eval", "--run", run_s, "--split", "val", "--json"]);
    let r: serde_json::Value = serde_json::from_slice(&eval.stdout).unwrap();
    assert!(r["psnr"].as_f64().unwrap().is_finite(), "{r}");
    let pred = dir.path().join("p.npz");
    osrt(&[
        "predict",
        "--run",
        run_s,
        "--split",
        "val",
        "--scenes",
        "1..3",
        "--out",
        pred.to_str().unwrap(),
    ]);
    let got = arrays(&pred);
    assert_eq!(got["scene_ids"].0, vec![2]);
    assert_eq!(got["slot_weights"].0[0], 2);
    // 8 × 8 views: the inputs at stride 2, the targets whole.
    assert_eq!(got["input_images"].0[2..], [4, 4, 3]);
    assert_eq!(got["rgb"].0[2..], [8, 8, 3]);
    let toml = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(toml.contains("input_stride = 2"), "{toml}");
    let frames = dir.path().join("render");
    osrt(&[
        "render",
        "--run",
        run_s,
        "--split",
        "val",
        "--scene",
        "0",
        "--frames",
        "2",
        "--out",
        frames.to_str().unwrap(),
    ]);
    // A plain `train` would start over beside the imported checkpoint: refused.
    let train = [
        "train",
        "--run",
        run_s,
        "--data",
        data_s,
        "--workers",
        "1",
        "--threads",
        "1",
    ];
    let out = Command::new(bin())
        .args(train)
        .args(["--max-steps", "5"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("pass --resume"),
        "{err}"
    );
    // `--resume` continues from it: the job's first step is the peer's step 3.
    osrt(&[&train[..], &["--resume", "--max-steps", "5"]].concat());
    assert_eq!(import_steps(&run), vec![3, 5]);
    let metrics = common::read_jsonl(&run.join("metrics.jsonl"));
    assert!(
        metrics.iter().all(|m| m["step"].as_u64().unwrap() > 3),
        "{metrics:?}"
    );
}

/// The steps of a run folder's checkpoints, in order.
fn import_steps(run: &Path) -> Vec<u64> {
    let mut steps: Vec<u64> = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|e| {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            name.trim_start_matches("step-").parse().unwrap()
        })
        .collect();
    steps.sort();
    steps
}
