//! `osrt data import` on a dataset in ObSuRF's release format written by an independent
//! writer (tests/python/make_obsurf.py: numpy and Pillow), read back with osrt's reader,
//! pyarrow and Pillow, then trained on and evaluated.

mod common;

use common::osrt;
use osrt_dataset::import::npy::{Values, read_npz};
use osrt_dataset::{Columns, Scene, load_split};
use osrt_store::Location;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Runs the Python writer `script` (tests/python/) into `dir/name`; returns that folder.
fn python_fixture(script: &str, dir: &Path, name: &str, args: &[&str]) -> PathBuf {
    let src = dir.join(name);
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/python")
        .join(script);
    let out = Command::new("python3")
        .arg(&path)
        .arg(&src)
        .args(args)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "{script} failed (scripts/test installs numpy, Pillow, protobuf and crc32c): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    src
}

/// The release folder the Python writer makes, with `scenes` scenes.
fn release(dir: &Path, scenes: usize) -> PathBuf {
    python_fixture("make_obsurf.py", dir, "release", &[&scenes.to_string()])
}

fn import(src: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    import_as("clevr3d", src, out, extra)
}

fn import_as(format: &str, src: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "data",
        "import",
        "--format",
        format,
        src.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--split",
        "train=0..8,val=8..10,test=10..12",
        "--scenes-per-part",
        "3",
    ];
    args.extend(extra);
    Command::new(common::bin()).args(&args).output().unwrap()
}

fn read(data: &Path, split: &str) -> Vec<Scene> {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let loc = Location::parse(data.to_str().unwrap()).unwrap();
    rt.block_on(load_split(&loc, split, Columns::ALL, None))
        .unwrap()
}

fn numbers(v: &Values) -> &[f64] {
    match v {
        Values::Numbers(n) => n,
        Values::Text(_) => panic!("numbers expected"),
    }
}

/// Pixels, masks, cameras (positions, intrinsics, every pixel's ray against the Python
/// writer's own rays, the centre ray through the origin), objects and the split
/// assignment by scene index all come through; CLEVR-3D's default filter leaves out the
/// 7-object scene.
#[test]
fn an_obsurf_release_imports_with_its_pixels_cameras_and_objects() {
    let dir = tempfile::tempdir().unwrap();
    let src = release(dir.path(), 12);
    let data = dir.path().join("data");
    let out = import(&src, &data, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta = read_npz(
        std::fs::File::open(src.join("metadata.npz")).unwrap(),
        "metadata",
        &["camera_pos", "3d_coords", "shape"],
    )
    .unwrap();
    let camera_pos = numbers(&meta["camera_pos"].values);
    let coords = numbers(&meta["3d_coords"].values);
    let shape = numbers(&meta["shape"].values);
    let rays = read_npz(
        zip_of(&src.join("expected_rays.npy")),
        "rays",
        &["expected_rays"],
    )
    .unwrap();
    let rays = numbers(&rays["expected_rays"].values);
    let (w, h) = (32usize, 24usize);
    for (split, ids) in [
        ("train", vec![0, 1, 2, 3, 4, 6, 7]),
        ("val", vec![8, 9]),
        ("test", vec![10, 11]),
    ] {
        let scenes = read(&data, split);
        assert_eq!(
            scenes.iter().map(|s| s.id).collect::<Vec<_>>(),
            ids,
            "{split}"
        );
        for s in &scenes {
            let id = s.id as usize;
            assert_eq!(s.views.len(), 3);
            for (v, view) in s.views.iter().enumerate() {
                let png = image::open(src.join(format!("images/img_{id}_{v}.png"))).unwrap();
                assert_eq!(
                    view.image,
                    png.into_rgb8().into_raw(),
                    "scene {id} view {v}"
                );
                let spelling = if id == 3 { "mask" } else { "masks" };
                let mask = image::open(src.join(format!("masks/{spelling}_{id}_{v}.png")))
                    .unwrap()
                    .into_luma8()
                    .into_raw();
                assert_eq!(view.mask.as_ref(), Some(&mask), "scene {id} view {v}");
                let c = &view.camera;
                let p = &camera_pos[(id * 3 + v) * 3..(id * 3 + v) * 3 + 3];
                for (ours, theirs) in c.position.iter().zip(p) {
                    assert!((*ours as f64 - theirs).abs() < 1e-5);
                }
                let k = c.intrinsics;
                assert_eq!((k.fx, k.fy, k.cx, k.cy), (35.0, 35.0, 16.0, 12.0));
                // The optical axis (the ray through the principal point) hits the origin.
                // (atan2 of |a × b| and a · b: acos near 1 would lose the precision.)
                let a = [c.rotation[0][2], c.rotation[1][2], c.rotation[2][2]].map(f64::from);
                let b = [-p[0], -p[1], -p[2]];
                let cross = [
                    a[1] * b[2] - a[2] * b[1],
                    a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0],
                ];
                let sin = cross.iter().map(|x| x * x).sum::<f64>().sqrt();
                let cos: f64 = (0..3).map(|i| a[i] * b[i]).sum();
                let angle = sin.atan2(cos);
                assert!(
                    angle < 1e-4,
                    "scene {id} view {v}: the axis misses by {angle} rad"
                );
                let ours = osrt_dataset::rays::view_rays(c, w as u32, h as u32);
                let base = (id * 3 + v) * h * w * 3;
                let theirs = &rays[base..base + h * w * 3];
                let worst = ours
                    .directions
                    .iter()
                    .zip(theirs)
                    .map(|(a, b)| (*a as f64 - b).abs())
                    .fold(0.0, f64::max);
                assert!(worst < 1e-5, "scene {id} view {v}: rays differ by {worst}");
            }
            let objects = s.objects.as_ref().unwrap();
            let present = shape[id * 8..id * 8 + 8]
                .iter()
                .filter(|&&x| x > 0.0)
                .count();
            assert_eq!(objects.len(), present, "scene {id}");
            for (k, o) in objects.iter().enumerate() {
                for j in 0..3 {
                    let want = coords[(id * 8 + k) * 3 + j];
                    assert!((o.position[j] as f64 - want).abs() < 1e-5);
                }
                assert!(["rubber", "metal"].contains(&o.material.as_str()), "{o:?}");
                assert_eq!(o.shape, format!("{}", shape[id * 8 + k] as i64));
            }
        }
    }
}

/// `expected_rays.npy` wrapped as a one-entry .npz (stored), for `read_npz`.
fn zip_of(npy: &Path) -> std::io::Cursor<Vec<u8>> {
    use std::io::Write;
    let mut buf = std::io::Cursor::new(Vec::new());
    let mut z = zip::ZipWriter::new(&mut buf);
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    z.start_file("expected_rays.npy", opts).unwrap();
    z.write_all(&std::fs::read(npy).unwrap()).unwrap();
    z.finish().unwrap();
    buf.set_position(0);
    buf
}

/// An interrupted import re-run with the same options writes only the missing parts
/// (byte for byte what a whole run writes); other options are refused; pyarrow reads the
/// PNG split and Pillow decodes it to the source pixels; the data trains and evaluates.
#[test]
fn an_import_resumes_reads_in_pyarrow_and_trains() {
    let dir = tempfile::tempdir().unwrap();
    let src = release(dir.path(), 12);
    let data = dir.path().join("data");
    assert!(import(&src, &data, &[]).status.success());
    let part = data.join("train/part-00001.parquet");
    let whole = std::fs::read(&part).unwrap();
    let kept = data.join("train/part-00000.parquet");
    let written_at = std::fs::metadata(&kept).unwrap().modified().unwrap();
    std::fs::remove_file(&part).unwrap();
    assert!(import(&src, &data, &[]).status.success());
    assert_eq!(
        std::fs::read(&part).unwrap(),
        whole,
        "the missing part is written again"
    );
    let after = std::fs::metadata(&kept).unwrap().modified().unwrap();
    assert_eq!(after, written_at, "a finished part is kept, not rewritten");
    // MSN-Easy reads the same release format without CLEVR-3D's 6-object filter.
    let easy = dir.path().join("easy");
    assert!(import_as("msn-easy", &src, &easy, &[]).status.success());
    let ids: Vec<u64> = read(&easy, "train").iter().map(|s| s.id).collect();
    assert_eq!(ids, (0..8).collect::<Vec<_>>(), "scene 5 (7 objects) kept");
    let other = import(&src, &data, &["--max-objects", "3"]);
    assert!(!other.status.success());
    let err = String::from_utf8_lossy(&other.stderr);
    assert!(
        err.contains("import.json") && err.contains("other options"),
        "{err}"
    );
    // Another release with the same options would mix two datasets' parts: refused,
    // naming both sources; nothing of the first import is touched.
    let second = python_fixture("make_obsurf.py", dir.path(), "release2", &["12"]);
    std::fs::remove_file(&part).unwrap();
    let mixed = import(&second, &data, &[]);
    assert!(!mixed.status.success());
    let err = String::from_utf8_lossy(&mixed.stderr);
    assert!(
        err.contains("release2") && err.contains(src.canonicalize().unwrap().to_str().unwrap()),
        "{err}"
    );
    assert!(!part.exists(), "no part written from the other source");
    assert!(
        import(&src, &data, &[]).status.success(),
        "the first source finishes it"
    );

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_png_split.py");
    let out = Command::new("python3")
        .arg(&script)
        .args([data.to_str().unwrap(), "train", src.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "pyarrow/Pillow check failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("\"views\": 21"));

    let run = dir.path().join("run");
    osrt(&[
        "train",
        "--preset",
        "tiny",
        "--data",
        data.to_str().unwrap(),
        "--run",
        run.to_str().unwrap(),
        "--max-steps",
        "20",
        "--workers",
        "1",
    ]);
    let out = osrt(&["eval", "--run", run.to_str().unwrap(), "--json"]);
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(r["psnr"].as_f64().unwrap().is_finite(), "{r}");
    assert_eq!(r["scenes"], 2, "the imported test split: {r}");
    let protocol = r["protocol"].as_str().unwrap();
    assert!(
        protocol.contains("input: view 0;") && protocol.contains("every pixel of every other view"),
        "{protocol}"
    );
}

/// The shards the Python writer makes (MSN-Hard's TFDS layout), and its expected values.
fn kubric_release(dir: &Path) -> PathBuf {
    python_fixture("make_kubric.py", dir, "kubric", &[])
}

fn npy_numbers(path: &Path) -> Vec<f64> {
    let a =
        osrt_dataset::import::npy::parse_npy(&std::fs::read(path).unwrap(), "expected").unwrap();
    numbers(&a.values).to_vec()
}

/// MSN-Hard shards import with the shards' own splits, every camera's pixels, masks
/// (`clip(instance, 1, 34) − 1`), position (`−Rᵀt`) and ray against the Python writer's;
/// depth and category images are left alone; a flipped payload byte is an error naming
/// the shard and the record, and `--split` does not apply.
#[test]
fn msn_hard_shards_import_with_their_cameras_and_checksums() {
    let dir = tempfile::tempdir().unwrap();
    let src = kubric_release(dir.path());
    let data = dir.path().join("data");
    let run = |src: &Path, out: &Path, extra: &[&str]| {
        let mut args = vec!["data", "import", "--format", "msn-hard"];
        args.push(src.to_str().unwrap());
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(extra);
        Command::new(common::bin()).args(&args).output().unwrap()
    };
    let out = run(&src, &data, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let images = npy_numbers(&src.join("expected_images.npy"));
    let masks = npy_numbers(&src.join("expected_masks.npy"));
    let positions = npy_numbers(&src.join("expected_positions.npy"));
    let rays = npy_numbers(&src.join("expected_rays.npy"));
    let (w, h, px) = (20usize, 16usize, 320usize);
    for (split, ids) in [
        ("train", vec![0, 1, 2, 3, 4]),
        ("val", vec![5]),
        ("test", vec![6, 7]),
    ] {
        let scenes = read(&data, split);
        assert_eq!(
            scenes.iter().map(|s| s.id).collect::<Vec<_>>(),
            ids,
            "{split}"
        );
        for s in &scenes {
            assert_eq!(s.views.len(), 10);
            for (k, v) in s.views.iter().enumerate() {
                let at = s.id as usize * 10 + k;
                assert_eq!((v.width, v.height), (w as u32, h as u32));
                let want: Vec<u8> = images[at * px * 3..(at + 1) * px * 3]
                    .iter()
                    .map(|&x| x as u8)
                    .collect();
                assert_eq!(v.image, want, "scene {} camera {k}", s.id);
                let want: Vec<u8> = masks[at * px..(at + 1) * px]
                    .iter()
                    .map(|&x| x as u8)
                    .collect();
                assert_eq!(v.mask.as_ref(), Some(&want), "scene {} camera {k}", s.id);
                for j in 0..3 {
                    let d = (v.camera.position[j] as f64 - positions[at * 3 + j]).abs();
                    assert!(d < 1e-4, "scene {} camera {k}: position off by {d}", s.id);
                }
                let ours = osrt_dataset::rays::view_rays(&v.camera, w as u32, h as u32);
                let worst = ours
                    .directions
                    .iter()
                    .zip(&rays[at * px * 3..(at + 1) * px * 3])
                    .map(|(a, b)| (*a as f64 - b).abs())
                    .fold(0.0, f64::max);
                assert!(
                    worst < 1e-5,
                    "scene {} camera {k}: rays off by {worst}",
                    s.id
                );
            }
        }
    }
    let limited = run(&src, &dir.path().join("sample"), &["--limit", "2"]);
    assert!(limited.status.success());
    assert_eq!(read(&dir.path().join("sample"), "train").len(), 2);
    let split = run(&src, &dir.path().join("x"), &["--split", "train=0..2"]);
    assert!(
        String::from_utf8_lossy(&split.stderr).contains("--split"),
        "split refused"
    );

    let broken = dir.path().join("broken");
    std::fs::create_dir(&broken).unwrap();
    for f in std::fs::read_dir(&src).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, broken.join(f.file_name().unwrap())).unwrap();
    }
    let shard = broken.join("msn-train.tfrecord-00001-of-00002");
    let mut bytes = std::fs::read(&shard).unwrap();
    bytes[100] ^= 0x40;
    std::fs::write(&shard, bytes).unwrap();
    let out = run(&broken, &dir.path().join("y"), &[]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("msn-train.tfrecord-00001-of-00002") && err.contains("CRC-32C"),
        "{err}"
    );
}

/// CLEVR-3D's own 320×240 views with the `tiny` preset: the encoder's self-attention over
/// 160 × 120 tokens needs tens of GiB, so on a 24 GiB machine `osrt train` refuses the
/// job with the figures and what to change, before the coordinator or any worker
/// starts (no run folder). Imported with `--resize 32x24` it trains.
#[test]
fn a_job_too_big_for_the_machine_is_refused_and_trains_resized() {
    let dir = tempfile::tempdir().unwrap();
    let train = |data: &Path, run: &Path| {
        Command::new(common::bin())
            .args([
                "train",
                "--preset",
                "tiny",
                "--workers",
                "1",
                "--max-steps",
                "2",
            ])
            .arg("--data")
            .arg(data)
            .arg("--run")
            .arg(run)
            // Below even one scene's pass at 320×240 (no micro-batch makes it fit).
            .env("OSRT_MEMORY_LIMIT_GIB", "8")
            .output()
            .unwrap()
    };
    let args = ["12", "320", "240", "32", "24"];
    let src = python_fixture("make_obsurf.py", dir.path(), "big", &args);
    let data = dir.path().join("big-data");
    let out = import(&src, &data, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run = dir.path().join("big-run");
    let out = train(&data, &run);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    for needle in [
        "OSRT_MEMORY_LIMIT_GIB=8 is 8.00 GiB",
        "at 320×240 px",
        "--batch-size",
        "--rays-per-scene",
    ] {
        assert!(err.contains(needle), "{needle:?} missing from: {err}");
    }
    assert!(!run.exists(), "the refused job made its run folder");

    let data = dir.path().join("small-data");
    let out = import(&src, &data, &["--resize", "32x24"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    check_resized(&src, &data);
    let run = dir.path().join("small-run");
    let out = train(&data, &run);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("at 32×24 px"), "{err}");
    // A resize that would enlarge is refused by name.
    let out = import(&src, &dir.path().join("big2"), &["--resize", "640x480"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("only shrinks"),
        "{err}"
    );
}

/// The 32×24 import of the 320×240 release `src`: each image as Pillow's area-averaging
/// BOX filter shrinks it (within 1 of 255: rounding), each mask pixel the source's id at
/// the centre of its 10 × 10 block, each pixel's ray the camera model's at 32×24.
fn check_resized(src: &Path, data: &Path) {
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(data.join("manifest.json")).unwrap())
            .unwrap();
    assert_eq!(m["image_size"], serde_json::json!([32, 24]), "{m}");
    let small = zip_of(&src.join("expected_small/rays.npy"));
    let rays = read_npz(small, "rays", &["expected_rays"]).unwrap();
    let rays = numbers(&rays["expected_rays"].values);
    for s in read(data, "train") {
        let id = s.id as usize;
        for (v, view) in s.views.iter().enumerate() {
            assert_eq!((view.width, view.height), (32, 24));
            let pil = image::open(src.join(format!("expected_small/img_{id}_{v}.png")))
                .unwrap()
                .into_rgb8()
                .into_raw();
            let worst = view
                .image
                .iter()
                .zip(&pil)
                .map(|(a, b)| a.abs_diff(*b))
                .max();
            assert!(
                worst <= Some(1),
                "scene {id} view {v}: {worst:?} from Pillow's BOX"
            );
            let spelling = if id == 3 { "mask" } else { "masks" };
            let mask = image::open(src.join(format!("masks/{spelling}_{id}_{v}.png")))
                .unwrap()
                .into_luma8();
            let ours = view.mask.as_ref().unwrap();
            for (i, id_here) in ours.iter().enumerate() {
                let (x, y) = ((i % 32) as u32, (i / 32) as u32);
                assert_eq!(*id_here, mask.get_pixel(10 * x + 5, 10 * y + 5).0[0]);
            }
            let ours = osrt_dataset::rays::view_rays(&view.camera, 32, 24);
            let base = (id * 3 + v) * 24 * 32 * 3;
            let worst = ours
                .directions
                .iter()
                .zip(&rays[base..base + 24 * 32 * 3])
                .map(|(a, b)| (*a as f64 - b).abs())
                .fold(0.0, f64::max);
            assert!(worst < 1e-5, "scene {id} view {v}: rays off by {worst}");
        }
    }
}
