//! The step's memory estimate (`osrt_trainer::footprint`, what `osrt train` checks before
//! a job starts) against the step's counted peak heap (`osrt bench model`, the binary's
//! counting allocator), for the `tiny`, `clevr-lite-cpu` and `paper` (batch 2) presets at
//! two image sizes each, and for the GPU's graph built on the CPU (`--kernels device`, the
//! count a GPU job prints) in f32 and bf16, with and without the activations recomputed
//! (`--recompute`), and for passes of 2 scenes summed into the step's gradient as each
//! backward segment ends (`--micro-batch-size`): within 25 %.

mod common;

use common::osrt;

fn estimate_and_peak(preset: &str, size: u32, extra: &[&str]) -> (f64, f64) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("model.json");
    let size = size.to_string();
    let mut args = vec![
        "bench",
        "model",
        "--step-only",
        "--steps",
        "1",
        "--threads",
        "2",
        "--presets",
        preset,
        "--image-size",
        &size,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    osrt(&args);
    let figures: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let s = &figures["2"]["steps"][0];
    let f = |k: &str| s[k].as_f64().unwrap_or_else(|| panic!("{k} missing: {s}"));
    (f("estimated_peak_gib"), f("peak_heap_gib"))
}

#[test]
fn the_memory_estimate_is_within_a_quarter_of_the_measured_peak() {
    let cases: [(&str, u32, &[&str]); 11] = [
        ("tiny", 32, &[]),
        ("tiny", 64, &[]),
        ("clevr-lite-cpu", 32, &[]),
        ("clevr-lite-cpu", 64, &[]),
        ("paper", 64, &["--batch-size", "2"]),
        ("paper", 128, &["--batch-size", "2"]),
        (
            "paper",
            128,
            &[
                "--batch-size",
                "4",
                "--micro-batch-size",
                "2",
                "--recompute",
            ],
        ),
        ("clevr-lite-cpu", 64, &["--kernels", "device"]),
        (
            "clevr-lite-cpu",
            64,
            &["--kernels", "device", "--precision", "bf16"],
        ),
        ("clevr-lite-cpu", 64, &["--recompute"]),
        (
            "clevr-lite-cpu",
            64,
            &["--kernels", "device", "--precision", "bf16", "--recompute"],
        ),
    ];
    let mut report = Vec::new();
    for (preset, size, extra) in cases {
        let (estimate, peak) = estimate_and_peak(preset, size, extra);
        report.push(format!(
            "{preset} {size}px {extra:?}: estimate {estimate:.3} GiB, peak {peak:.3} GiB"
        ));
        assert!(
            (estimate / peak - 1.0).abs() <= 0.25,
            "{}",
            report.join("\n")
        );
    }
    eprintln!("{}", report.join("\n"));
}
