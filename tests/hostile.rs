//! Hostile and broken inputs, written by an independent writer (tests/python/make_hostile.py:
//! numpy, Pillow, zlib, protobuf, crc32c, pyarrow), fed to the
//! commands a user runs on them: `osrt data import` for the release formats, `osrt data
//! inspect` for Parquet parts. Each must end within 30 s and 1.5 GB of resident memory,
//! measured from outside (tests/python/run_bounded.py), in exit 1 with a message naming
//! the broken file, or, where the broken part is one the reader never needs, in a correct
//! import that trains. Never a panic, a hang or a silent acceptance.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

const SECONDS: f64 = 30.0;
const MAX_RSS_BYTES: u64 = 1_500_000_000;

fn python(script: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/python")
        .join(script)
}

/// How one run ended, as run_bounded.py reports it.
#[derive(Debug)]
struct Ended {
    code: Option<i64>,
    signal: Option<i64>,
    timed_out: bool,
    seconds: f64,
    max_rss_bytes: u64,
    stderr: String,
}

impl Ended {
    fn from_json(v: serde_json::Value) -> Self {
        Self {
            code: v["code"].as_i64(),
            signal: v["signal"].as_i64(),
            timed_out: v["timed_out"].as_bool().unwrap(),
            seconds: v["seconds"].as_f64().unwrap(),
            max_rss_bytes: v["max_rss_bytes"].as_u64().unwrap(),
            stderr: v["stderr"].as_str().unwrap().to_string(),
        }
    }
}

/// `osrt args` under run_bounded.py's 30 s limit.
fn bounded(args: &[&str]) -> Ended {
    let out = Command::new("python3")
        .arg(python("run_bounded.py"))
        .arg(SECONDS.to_string())
        .arg("--")
        .arg(bin())
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("python3");
    assert!(
        out.status.success(),
        "run_bounded.py: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ended::from_json(serde_json::from_slice(&out.stdout).unwrap())
}

struct Case {
    command: String,
    expect: String,
    names: String,
    why: String,
}

/// The command line of `case` on its input `src`, writing to `out`.
fn command_of<'a>(case: &'a Case, src: &'a str, out: &'a str) -> Vec<&'a str> {
    match case.command.as_str() {
        "import clevr3d" => vec![
            "data",
            "import",
            "--format",
            "clevr3d",
            src,
            "--out",
            out,
            "--split",
            "train=0..6,val=6..7,test=7..8",
        ],
        "import msn-hard" => vec!["data", "import", "--format", "msn-hard", src, "--out", out],
        "inspect" => vec!["data", "inspect", src, "--sheet", out],
        other => panic!("unknown command {other}"),
    }
}

/// What is wrong with how a case ended, if anything.
fn verdict(name: &str, case: &Case, e: &Ended) -> Option<String> {
    let tail = e
        .stderr
        .lines()
        .rev()
        .take(6)
        .collect::<Vec<_>>()
        .join(" | ");
    if e.timed_out || e.seconds >= SECONDS {
        return Some(format!("{name}: still running after {SECONDS} s"));
    }
    if e.max_rss_bytes >= MAX_RSS_BYTES {
        return Some(format!("{name}: {} bytes resident", e.max_rss_bytes));
    }
    if e.stderr.contains("panicked") {
        return Some(format!("{name}: panicked: {tail}"));
    }
    match case.expect.as_str() {
        "ok" if e.code == Some(0) => None,
        "error" if e.code == Some(1) && e.stderr.contains(&case.names) => None,
        "error" if e.code == Some(1) => Some(format!(
            "{name}: the error does not name {}: {tail}",
            case.names
        )),
        _ => Some(format!(
            "{name} ({}): expected {}, ended with code {:?}, signal {:?}: {tail}",
            case.why, case.expect, e.code, e.signal
        )),
    }
}

#[test]
fn hostile_inputs_end_in_clear_errors_within_bounds() {
    let dir = tempfile::tempdir().unwrap();
    // The Parquet cases break parts of a dataset osrt wrote.
    let base = dir.path().join("parquet");
    osrt(&[
        "data",
        "generate",
        "--out",
        base.to_str().unwrap(),
        "--train",
        "8",
        "--val",
        "4",
        "--test",
        "4",
        "--image-size",
        "16",
        "--scenes-per-row-group",
        "4",
    ]);
    let cases = dir.path().join("cases");
    let made = Command::new("python3")
        .arg(python("make_hostile.py"))
        .arg(&cases)
        .arg(&base)
        .output()
        .expect("python3");
    assert!(
        made.status.success(),
        "make_hostile.py (scripts/test installs numpy, Pillow, protobuf, crc32c, pyarrow): {}",
        String::from_utf8_lossy(&made.stderr)
    );
    let names: Vec<String> = serde_json::from_slice(&made.stdout).unwrap();
    assert!(names.len() >= 25, "{names:?}");

    let mut failures = Vec::new();
    let mut trained = 0;
    for name in &names {
        let root = cases.join(name);
        let c = read_json(&root.join("case.json")).unwrap();
        let field = |k: &str| c[k].as_str().unwrap().to_string();
        let case = Case {
            command: field("command"),
            expect: field("expect"),
            names: field("names"),
            why: field("why"),
        };
        let (src, out) = (root.join("src"), root.join("out"));
        let args = command_of(&case, src.to_str().unwrap(), out.to_str().unwrap());
        let ended = bounded(&args);
        eprintln!(
            "{name}: code {:?} in {:.2} s, {} MiB resident",
            ended.code,
            ended.seconds,
            ended.max_rss_bytes >> 20
        );
        if let Some(problem) = verdict(name, &case, &ended) {
            failures.push(problem);
        } else if case.expect == "ok" {
            // The import is correct where it claims to be: it trains.
            let run = root.join("run");
            osrt(&[
                "train",
                "--preset",
                "tiny",
                "--data",
                out.to_str().unwrap(),
                "--run",
                run.to_str().unwrap(),
                "--max-steps",
                "2",
                "--workers",
                "1",
            ]);
            trained += 1;
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(trained >= 1, "no case was expected to import and train");
}
