//! The figures of `osrt bench model` for people: each step's times and memory, the
//! profile's op kinds, the renders' speeds, and the ratios between them.

use super::BenchModelArgs;
use osrt_bench::model::{ModelReport, ProfileFigures, StepFigures};

/// One step's profile (`--profile`): op kinds, then the costliest distinct calls.
fn print_profile(p: &ProfileFigures) {
    let (fwd, bwd) = (p.forward_s, p.backward_s);
    println!(
        "  profile of {} (batch {}, {} view(s), {} rays, {} px) on {}, {}, {} kernels: \
         forward {:.1} ms, backward {:.1} ms (medians of the whole step's passes)",
        p.preset,
        p.batch_size,
        p.input_views,
        p.rays_per_scene,
        p.image_size,
        p.device,
        p.precision,
        p.kernels,
        fwd * 1e3,
        bwd * 1e3,
    );
    println!(
        "    {:<12} {:>6} {:>11} {:>11} {:>11} {:>9} {:>10} {:>14}",
        "op",
        "calls",
        "forward ms",
        "backward ms",
        "total ms",
        "% of step",
        "kept MiB",
        "largest peak"
    );
    let (step, mib) = (fwd + bwd, |b: f64| b / (1u64 << 20) as f64);
    let (mut sf, mut sb, mut sk) = (0.0, 0.0, 0.0);
    for k in &p.kinds {
        let (of, ob) = (k.forward_s, k.backward_s);
        let kept = k.kept_bytes.unwrap_or(0) as f64;
        (sf, sb, sk) = (sf + of, sb + ob, sk + kept);
        println!(
            "    {:<12} {:>6} {:>11.2} {:>11.2} {:>11.2} {:>8.1}% {:>10.1} {:>10.1} MiB",
            k.kind,
            k.calls,
            of * 1e3,
            ob * 1e3,
            (of + ob) * 1e3,
            100.0 * (of + ob) / step,
            mib(kept),
            mib(k.peak_bytes.unwrap_or(0) as f64),
        );
    }
    if let (Some(kept), Some(peak)) = (p.step_kept_bytes, p.step_peak_bytes) {
        println!(
            "    the step's forward pass left {:.1} MiB held (the batch and the graph), its \
             passes peaked {:.1} MiB above their start",
            mib(kept as f64),
            mib(peak as f64)
        );
    }
    println!(
        "    {:<12} {:>6} {:>11.2} {:>11.2} {:>11.2} {:>8.1}% {:>10.1}   (the rest: ops \
         between these, gradient accumulation)",
        "ops alone",
        "",
        sf * 1e3,
        sb * 1e3,
        (sf + sb) * 1e3,
        100.0 * (sf + sb) / step,
        mib(sk),
    );
    println!("    costliest calls (calls × (forward + backward); calls × kept):");
    for o in p.ops.iter().take(8) {
        let n = o.calls as f64;
        println!(
            "      {:>9.2} ms {:>9.1} MiB  {} × {}",
            n * (o.forward_s + o.backward_s) * 1e3,
            mib(n * o.kept_bytes.unwrap_or(0) as f64),
            n,
            o.signature
        );
    }
}

/// One step's figures of `osrt bench model`, for people.
fn print_step(s: &StepFigures) {
    let ms = |x: f64| x * 1e3;
    println!(
        "  train step {:<16} {:<8} {:>8.1} ms median ({:.1} scenes/s; fwd+bwd {:.1} ms; {} params, batch {}, {} view(s), {} rays, {}px, {} {}{})",
        s.preset,
        s.kernels,
        ms(s.median_step_s),
        s.scenes_per_s,
        ms(s.median_forward_backward_s),
        s.parameters,
        s.batch_size,
        s.input_views,
        s.rays_per_scene,
        s.image_size,
        s.device,
        s.precision,
        match (s.recompute, s.micro_batch_size) {
            (true, Some(m)) => format!(", activations recomputed, passes of {m}"),
            (true, None) => ", activations recomputed".into(),
            (false, Some(m)) => format!(", passes of {m}"),
            (false, None) => String::new(),
        },
    );
    let gib = |g: Option<f64>| match g {
        Some(g) => format!("{g:.2} GiB"),
        None => "not counted".into(),
    };
    println!(
        "    optimiser {:.1} ms median; peak heap {}, peak resident {}; estimated peak {}",
        ms(s.median_optimizer_s),
        gib(s.peak_heap_gib),
        gib(s.peak_rss_gib),
        gib(s.estimated_peak_gib),
    );
    if s.skipped_steps > 0 {
        println!(
            "    SKIPPED {} of the timed steps: {}",
            s.skipped_steps,
            s.skip_reason.as_deref().unwrap_or("")
        );
    }
    if s.peak_gib.is_some() {
        println!("    peak device memory {}", gib(s.peak_gib));
    }
    if s.median_gradient_transfer_s > 0.0 {
        println!(
            "    gradient device → host → device through the all-reduce's staging \
             (paid by each of ≥ 2 workers beside the ring, not in the step above): \
             {:.2} ms median ({:.1} % of the step)",
            ms(s.median_gradient_transfer_s),
            100.0 * s.median_gradient_transfer_s / s.median_step_s
        );
    }
    if let Some(e) = &s.gradient_transfer_error {
        println!("    GRADIENT ROUND TRIP FAILED: {e}");
    }
}

/// The figures of `osrt bench model`, for people.
pub(super) fn print_model_report(a: &BenchModelArgs, report: &[(usize, ModelReport)]) {
    for (threads, v) in report {
        println!("{threads} thread(s):");
        for p in &v.profiles {
            print_profile(p);
        }
        for l in &v.ledgers {
            super::ledger::print_ledger(l);
        }
        for s in &v.steps {
            print_step(s);
        }
        for p in &a.presets {
            let t = |fused: bool| {
                v.steps
                    .iter()
                    .find(|s| &s.preset == p && s.fused == fused)
                    .map(|s| s.median_step_s)
            };
            if let (Some(f), Some(c)) = (t(true), t(false)) {
                println!("  {p}: fused ops make the step {:.2}× as fast", c / f);
            }
        }
        for r in &v.renders {
            println!(
                "  render {:<18} {:>3} slots {:>9.1} fps",
                r.decoder, r.slots, r.fps
            );
        }
        for &k in &a.slots {
            let fps = |d: &str| {
                v.renders
                    .iter()
                    .find(|r| r.decoder == d && r.slots == k)
                    .map(|r| r.fps)
            };
            if let (Some(sm), Some(sb)) = (fps("slot_mixer"), fps("spatial_broadcast")) {
                println!(
                    "  Slot Mixer / spatial broadcast at {k} slots: {:.1}×",
                    sm / sb
                );
            }
            if let (Some(sm), Some(v)) = (fps("slot_mixer"), fps("volumetric")) {
                println!("  Slot Mixer / volumetric at {k} slots: {:.1}×", sm / v);
            }
            if let (Some(v), Some(all)) = (fps("volumetric"), fps("volumetric_no_cull")) {
                println!("  box culling: volumetric {:.2}× as fast with it", v / all);
            }
        }
    }
}
