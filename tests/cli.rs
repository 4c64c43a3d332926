//! The `osrt` binary end to end: generate a dataset, inspect it, and read it back with an
//! independent Parquet implementation (pyarrow).

use std::path::Path;
use std::process::Command;

fn osrt(args: &[&str]) -> std::process::Output {
    let out = Command::new(env!("CARGO_BIN_EXE_osrt"))
        .args(args)
        .output()
        .expect("run osrt");
    assert!(
        out.status.success(),
        "osrt {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

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
}

/// pyarrow reads what we wrote. CI installs pyarrow (`.ci/run`); elsewhere the test says
/// it is skipped rather than failing a machine without it.
#[test]
fn pyarrow_reads_generated_splits() {
    let have = Command::new("python3")
        .args(["-c", "import pyarrow"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    if !have {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must install pyarrow (.ci/run does)"
        );
        eprintln!("SKIPPED pyarrow_reads_generated_splits: python3 with pyarrow not found");
        return;
    }
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
