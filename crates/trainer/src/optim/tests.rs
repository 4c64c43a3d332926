use super::*;
use candle_core::{Device, Tensor, Var};

const HYPER: Hyperparams = Hyperparams {
    beta1: 0.9,
    beta2: 0.999,
    eps: 1e-8,
    weight_decay: 0.01,
};

/// Deterministic values in [-0.5, 0.5).
fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        })
        .collect()
}

/// Parameters of the given sizes, on `dev`.
fn vars(sizes: &[usize], dev: &Device) -> Vec<Var> {
    sizes
        .iter()
        .enumerate()
        .map(|(i, &n)| {
            Var::from_tensor(&Tensor::from_vec(values(n, i as u64), n, dev).unwrap()).unwrap()
        })
        .collect()
}

fn flat(vars: &[Var]) -> Vec<f32> {
    vars.iter()
        .flat_map(|v| v.as_tensor().to_vec1::<f32>().unwrap())
        .collect()
}

/// The arithmetic, element by element, as the reference the in-place paths must match.
fn reference(p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &[f32], k: &StepConsts) {
    for i in 0..p.len() {
        (p[i], m[i], v[i]) = adamw_element(p[i], g[i], m[i], v[i], k);
    }
}

#[test]
fn first_adam_step_moves_each_weight_by_lr() {
    // With bias correction, step 1 is lr · sign(g) (up to ε).
    let h = Hyperparams {
        eps: 1e-12,
        weight_decay: 0.0,
        ..HYPER
    };
    let k = StepConsts::new(&h, 1, 0.1);
    for (g, want) in [(0.5, 0.9), (-2.0, 1.1), (1e-3, 0.9)] {
        let (p, _, _) = adamw_element(1.0, g, 0.0, 0.0, &k);
        assert!((p - want).abs() < 1e-5, "{g}: {p}");
    }
}

#[test]
fn weight_decay_is_decoupled() {
    let h = Hyperparams {
        weight_decay: 0.5,
        ..HYPER
    };
    // Zero gradient: only decay, 2 − 0.1·0.5·2 = 1.9.
    let (p, _, _) = adamw_element(2.0, 0.0, 0.0, 0.0, &StepConsts::new(&h, 1, 0.1));
    assert!((p - 1.9).abs() < 1e-6);
}

/// The host's in-place update gives the element-wise reference's bits, step after step,
/// over parameters that span several parallel tasks.
#[test]
fn the_host_update_in_place_gives_the_reference_bits() {
    let sizes = [3, 70_000, 1, 40_000];
    let n: usize = sizes.iter().sum();
    let vs = vars(&sizes, &Device::Cpu);
    let mut opt = AdamW::new(n, HYPER);
    let (mut p, mut m, mut v) = (flat(&vs), vec![0f32; n], vec![0f32; n]);
    for step in 0..4 {
        let g: Vec<f32> = values(n, 100 + step)
            .iter()
            .map(|x| x * 10f32.powi(step as i32 - 2))
            .collect();
        let lr = 1e-3 * (step + 1) as f64;
        let k = StepConsts::new(&HYPER, step + 1, lr);
        reference(&mut p, &mut m, &mut v, &g, &k);
        let s = GradSummary::of(&g);
        assert!(opt.step(&vs, 7, &g, s.max_abs, lr).unwrap());
        assert_eq!(flat(&vs), p, "step {step}");
        assert_eq!((&opt.m, &opt.v), (&m, &v), "step {step}");
    }
    assert_eq!(opt.t, 4);
}

/// The device optimiser (run here on CPU tensors, across several buckets) gives the
/// host's bits, step after step, weight decay and bias correction included.
#[test]
fn the_device_update_gives_the_host_update_bits() {
    // Two buckets and a parameter larger than one.
    let sizes = [1000, (1 << 22) - 1000, 5, (1 << 22) + 3];
    let n: usize = sizes.iter().sum();
    let dev = Device::Cpu;
    let (host_vars, dev_vars) = (vars(&sizes, &dev), vars(&sizes, &dev));
    let mut host = AdamW::new(n, HYPER);
    let mut device = DeviceAdamW::new(n, HYPER, &dev).unwrap();
    for step in 0..3 {
        let g: Vec<f32> = values(n, 200 + step)
            .iter()
            .map(|x| x * 10f32.powi(step as i32 - 1))
            .collect();
        let lr = 1e-3 * (step + 1) as f64;
        let s = GradSummary::of(&g);
        assert!(host.step(&host_vars, 1, &g, s.max_abs, lr).unwrap());
        let gt = Tensor::from_slice(&g, n, &dev).unwrap();
        assert!(device.step(&dev_vars, 1, &gt, s.max_abs, lr).unwrap());
        assert!(flat(&dev_vars) == flat(&host_vars), "step {step}");
        assert!(device.m.to_vec1::<f32>().unwrap() == host.m, "step {step}");
        assert!(device.v.to_vec1::<f32>().unwrap() == host.v, "step {step}");
    }
    // Clipping: the host scales each element as it updates, the device gets the scaled
    // gradient; the same bits.
    let g = values(n, 300);
    let scale = 0.37f32;
    let s = GradSummary::of(&g);
    let lr = 2e-3;
    assert!(
        host.step_scaled(&host_vars, 1, &g, scale, s.max_abs * scale, lr)
            .unwrap()
    );
    let scaled: Vec<f32> = g.iter().map(|x| x * scale).collect();
    assert_eq!(GradSummary::of(&scaled).max_abs, s.max_abs * scale);
    let gt = (Tensor::from_slice(&g, n, &dev).unwrap() * scale as f64).unwrap();
    assert!(
        device
            .step(&dev_vars, 1, &gt, s.max_abs * scale, lr)
            .unwrap()
    );
    assert!(flat(&dev_vars) == flat(&host_vars), "clipped step");
    assert!(device.m.to_vec1::<f32>().unwrap() == host.m, "clipped step");
    assert_eq!(device.t, host.t);
}

/// The maxima as bit patterns: magnitudes of finite values, +∞ for any NaN or negative
/// second moment, whatever the sign or payload.
#[test]
fn maxima_from_bits() {
    let m = MaximaBits::of(-3.0, 2.0, 5.0)
        .max(MaximaBits::of(1.0, -2.5, 0.0))
        .decode();
    assert_eq!(
        m,
        Maxima {
            p: 3.0,
            m: 2.5,
            v: 5.0
        }
    );
    let nan = -f32::NAN;
    for (p, mm, v) in [(nan, 0.0, 0.0), (0.0, f32::NAN, 0.0), (0.0, 0.0, -1e-30)] {
        let d = Maxima::of(p, mm, v);
        assert!(
            [d.p, d.m, d.v].contains(&f32::INFINITY),
            "{p} {mm} {v}: {d:?}"
        );
    }
    assert_eq!(Maxima::of(0.0, 0.0, f32::NAN).v, f32::INFINITY);
    assert_eq!(Maxima::of(f32::INFINITY, 0.0, 0.0).p, f32::INFINITY);
}

/// An update whose second moment overflows f32 (a huge finite gradient), or whose
/// weights would, is refused on both sides with nothing changed; a large gradient that
/// still fits goes through.
#[test]
fn an_update_that_would_overflow_changes_nothing() {
    let dev = Device::Cpu;
    for (g_bad, lr, accepted) in [
        (1e19f32, 1e-3, true),
        (1e30, 1e-3, false),
        (0.1, 1e40, false),
    ] {
        let (hv, dv) = (vars(&[4], &dev), vars(&[4], &dev));
        let before = flat(&hv);
        let mut host = AdamW::new(4, HYPER);
        let mut device = DeviceAdamW::new(4, HYPER, &dev).unwrap();
        let g = [0.1, g_bad, -0.2, 0.0];
        let gt = Tensor::new(&g, &dev).unwrap();
        let s = GradSummary::of(&g);
        assert_eq!(
            host.step(&hv, 0, &g, s.max_abs, lr).unwrap(),
            accepted,
            "{g_bad} {lr}"
        );
        assert_eq!(
            device.step(&dv, 0, &gt, s.max_abs, lr).unwrap(),
            accepted,
            "{g_bad} {lr}"
        );
        if !accepted {
            assert_eq!(flat(&hv), before);
            assert_eq!(flat(&dv), before);
            assert_eq!((host.m.as_slice(), host.t), ([0f32; 4].as_slice(), 0));
            assert_eq!(device.m.to_vec1::<f32>().unwrap(), vec![0f32; 4]);
            assert_eq!(device.t, 0);
        }
    }
}

/// The bound is refused where it cannot hold, and shown where it does; a state restored
/// with a NaN, an infinity or a negative second moment is never taken on trust.
#[test]
fn the_finiteness_bound() {
    let k = StepConsts::new(&HYPER, 1, 1e-3);
    let sane = Maxima {
        p: 10.0,
        m: 1.0,
        v: 1.0,
    };
    assert!(k.provably_finite(sane, 100.0));
    assert!(!k.provably_finite(sane, 1e25), "v overflows: 1e-3 · 1e50");
    assert!(
        !k.provably_finite(
            Maxima {
                p: f32::MAX,
                ..sane
            },
            1.0
        ),
        "p at the edge"
    );
    assert!(
        k.provably_finite(Maxima { p: 3e38, ..sane }, 1.0),
        "p near it, with room"
    );
    assert!(!k.provably_finite(Maxima::of(f32::NAN, 0.0, 0.0), 1.0));
    assert!(!k.provably_finite(Maxima::of(0.0, 0.0, -1.0), 1.0));
    assert!(!k.provably_finite(Maxima::of(0.0, f32::INFINITY, 0.0), 1.0));
    assert!(!k.provably_finite(sane, f32::NAN));
    let no_eps = StepConsts::new(&Hyperparams { eps: 0.0, ..HYPER }, 1, 1e-3);
    assert!(!no_eps.provably_finite(sane, 1.0));

    // Restored with a negative second moment: sqrt would give NaN, so the step is
    // checked element by element and refused.
    let dev = Device::Cpu;
    let hv = vars(&[2], &dev);
    let mut host = AdamW::new(2, HYPER);
    host.restore(vec![0.0; 2], vec![-1.0, 0.0], 3);
    assert!(!host.step(&hv, 0, &[0.0, 0.0], 0.0, 1e-3).unwrap());
    let mut device = DeviceAdamW::new(2, HYPER, &dev).unwrap();
    device.restore(vec![0.0; 2], vec![-1.0, 0.0], 3).unwrap();
    let g = Tensor::new(&[0f32, 0.0], &dev).unwrap();
    assert!(!device.step(&hv, 0, &g, 0.0, 1e-3).unwrap());
}

/// Non-finite values in the gradient show in its summary; the sum does not depend on
/// the thread count (fixed blocks) and matches an f64 sum closely.
#[test]
fn the_gradient_summary() {
    let g = values(300_000, 9);
    let s = GradSummary::of(&g);
    let plain: f64 = g.iter().map(|&x| x as f64 * x as f64).sum();
    assert!(
        (s.sum_sq - plain).abs() <= 1e-12 * plain,
        "{} vs {plain}",
        s.sum_sq
    );
    assert_eq!(s.max_abs, g.iter().fold(0f32, |a, &x| a.max(x.abs())));
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    assert_eq!(one.install(|| GradSummary::of(&g)), s);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut b = g.clone();
        b[123_456] = bad;
        assert!(!GradSummary::of(&b).finite(), "{bad}");
    }
    let huge = vec![f32::MAX; 1000];
    assert!(
        GradSummary::of(&huge).finite(),
        "squares of f32 values fit f64"
    );
}

#[test]
fn clipping_bounds_the_norm() {
    let mut g = vec![3.0f32, 4.0];
    let s = clip_scale(global_norm(&g), Some(1.0));
    g.iter_mut().for_each(|x| *x *= s);
    assert!((global_norm(&g) - 1.0).abs() < 1e-6);
    assert_eq!(
        clip_scale(0.5, Some(1.0)),
        1.0,
        "within the bound: unchanged"
    );
    assert_eq!(clip_scale(5.0, None), 1.0, "no bound");
    assert_eq!(clip_scale(0.0, Some(1.0)), 1.0);
}

/// The device summary (two-stage reductions over buckets) agrees with the host's: the
/// same maximum, the sum to f64 rounding; a NaN or an infinity anywhere is not finite.
#[test]
fn the_device_gradient_summary_agrees_with_the_host_and_sees_non_finite_values() {
    for n in [0, 5, 1024 * 3 + 17, device_adamw::BUCKET + 4099] {
        let g = values(n, 7);
        let host = GradSummary::of(&g);
        let dev =
            GradSummary::of_tensor(&Tensor::new(g.as_slice(), &Device::Cpu).unwrap()).unwrap();
        assert_eq!(dev.max_abs, host.max_abs, "n = {n}");
        assert!(
            (dev.sum_sq - host.sum_sq).abs() <= 1e-12 * host.sum_sq.max(1e-300),
            "n = {n}"
        );
    }
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut g = values(3000, 8);
        g[2999] = bad;
        let s = GradSummary::of_tensor(&Tensor::new(g.as_slice(), &Device::Cpu).unwrap()).unwrap();
        assert!(!s.finite(), "{bad}");
    }
}

#[test]
fn two_stage_reductions_equal_whole_tensor_reductions() {
    for n in [1, 1023, 2048, 5000] {
        let v = values(n, 9);
        let t = Tensor::new(v.as_slice(), &Device::Cpu).unwrap();
        let max = device_adamw::wide_max(&t)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert_eq!(max, v.iter().copied().fold(f32::MIN, f32::max));
        let sum = device_adamw::wide_sum(&t.to_dtype(candle_core::DType::F64).unwrap())
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        let want: f64 = v.iter().map(|&x| x as f64).sum();
        assert!((sum - want).abs() < 1e-9, "{sum} vs {want}");
    }
}
