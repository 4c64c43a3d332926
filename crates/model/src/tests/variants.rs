//! The paper's variants (§4.3): Up-OSRT (unposed encoder) and V-OSRT (volumetric
//! decoder): finite-difference gradient checks in f64, the compositing quadrature on its
//! own, and the inputs that stress each (identical or single input views; densities at 0
//! and 1e4; rays that miss, graze or run along the box).

use super::{CPU, Inputs, assert_sane, gradcheck, inputs, randn, run, unit_dirs, volumetric};
use crate::decoder::volumetric::{Bounds, Segment, box_segment, composite};
use crate::encoder::Poses;
use crate::params::Params;
use crate::{Config, Osrt};
use candle_core::{DType, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn unposed(base: Config) -> Config {
    let mut c = base;
    c.encoder.poses = Poses::Unposed;
    c
}

fn values(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

#[test]
fn gradcheck_unposed_and_volumetric_models() {
    for (name, cfg) in [
        ("unposed", unposed(Config::tiny())),
        ("volumetric", volumetric(Config::tiny())),
    ] {
        let p = Params::new(4);
        let model = Osrt::new(&cfg, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
        let x = inputs(1, 2, 4, 3, 2.0, DType::F64);
        let f = || run(&model, &x).map(|(_, l)| l);
        eprintln!("gradcheck {name}");
        gradcheck(&p.vars(), &f, 2);
    }
    // Jittered (training) sampling is differentiable the same way.
    let p = Params::new(5);
    let cfg = volumetric(Config::tiny());
    let model = Osrt::new(&cfg, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
    let x = inputs(1, 1, 4, 3, 2.0, DType::F64);
    let offsets = model
        .ray_offsets(1, 3, &mut ChaCha8Rng::seed_from_u64(1))
        .unwrap()
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap();
    let f = || {
        let s = model.encode(&x.images, &x.origins, &x.dirs, None)?;
        let out = model.decode_with(&s.slots, &x.t_origins, &x.t_dirs, Some(&offsets))?;
        (&out.rgb - &x.target)?.sqr()?.mean_all()
    };
    gradcheck(&p.vars(), &f, 2);
}

/// The quadrature alone, against finite differences in every input.
#[test]
fn gradcheck_compositing() {
    let (m, n, k) = (3, 5, 4);
    let sd = Var::from_tensor(&randn(&[m, n], 1, DType::F64).abs().unwrap()).unwrap();
    let rgb = Var::from_tensor(&randn(&[m, n, 3], 2, DType::F64)).unwrap();
    let w = Var::from_tensor(&randn(&[m, n, k], 3, DType::F64)).unwrap();
    let bg = Var::from_tensor(&randn(&[3], 4, DType::F64)).unwrap();
    let (pc, pw) = (randn(&[m, 3], 5, DType::F64), randn(&[m, k], 6, DType::F64));
    let f = || {
        let (c, s) = composite(
            sd.as_tensor(),
            rgb.as_tensor(),
            w.as_tensor(),
            bg.as_tensor(),
        )?;
        c.mul(&pc)?.sum_all()? + s.mul(&pw)?.sum_all()?
    };
    let vars = [
        ("sigma_delta".to_string(), sd.clone()),
        ("rgb".to_string(), rgb.clone()),
        ("weights".to_string(), w.clone()),
        ("background".to_string(), bg.clone()),
    ];
    gradcheck(&vars, &f, 6);
}

/// No density: the background, slot weights spread evenly. Density 1e4 everywhere: the
/// first point alone. Both with finite gradients.
#[test]
fn compositing_at_zero_and_huge_density() {
    let (m, n, k) = (2, 6, 3);
    let rgb = randn(&[m, n, 3], 7, DType::F32)
        .abs()
        .unwrap()
        .clamp(0f32, 1f32)
        .unwrap();
    let w = candle_nn::ops::softmax(&randn(&[m, n, k], 8, DType::F32), 2).unwrap();
    let bg = Tensor::new(&[0.2f32, 0.4, 0.6], &CPU).unwrap();
    for (density, expect_first) in [(0.0, false), (1e4, true)] {
        let sd =
            Var::from_tensor(&(Tensor::ones((m, n), DType::F32, &CPU).unwrap() * density).unwrap())
                .unwrap();
        let (c, s) = composite(sd.as_tensor(), &rgb, &w, &bg).unwrap();
        let (want_c, want_s) = if expect_first {
            (
                rgb.narrow(1, 0, 1).unwrap().squeeze(1).unwrap(),
                w.narrow(1, 0, 1).unwrap().squeeze(1).unwrap(),
            )
        } else {
            (
                bg.unsqueeze(0)
                    .unwrap()
                    .broadcast_as((m, 3))
                    .unwrap()
                    .contiguous()
                    .unwrap(),
                (Tensor::ones((m, k), DType::F32, &CPU).unwrap() / k as f64).unwrap(),
            )
        };
        for (got, want) in [(values(&c), values(&want_c)), (values(&s), values(&want_s))] {
            for (g, e) in got.iter().zip(&want) {
                assert!((g - e).abs() < 1e-6, "density {density}: {g} vs {e}");
            }
        }
        let loss = (c.sum_all().unwrap() + s.sqr().unwrap().sum_all().unwrap()).unwrap();
        let g = loss.backward().unwrap();
        assert!(
            values(g.get(sd.as_tensor()).unwrap())
                .iter()
                .all(|x| x.is_finite())
        );
    }
}

/// An infinite σδ at one point makes that point opaque: what lies before it composites
/// as usual, nothing after it counts, and nothing is NaN.
#[test]
fn an_infinite_density_is_an_opaque_point_not_a_nan() {
    let (m, n, k) = (1, 4, 2);
    let rgb = Tensor::new(
        &[[
            [0.1f32, 0.2, 0.3],
            [0.4, 0.5, 0.6],
            [0.7, 0.8, 0.9],
            [1.0, 1.0, 1.0],
        ]],
        &CPU,
    )
    .unwrap();
    let w = candle_nn::ops::softmax(&randn(&[m, n, k], 9, DType::F32), 2).unwrap();
    let bg = Tensor::new(&[0.2f32, 0.4, 0.6], &CPU).unwrap();
    let sd = Var::from_tensor(&Tensor::new(&[[0.5f32, 0.0, f32::INFINITY, 3.0]], &CPU).unwrap())
        .unwrap();
    let (c, s) = composite(sd.as_tensor(), &rgb, &w, &bg).unwrap();
    // Point 0 takes 1 − e^{−0.5} of the light, point 2 the rest.
    let a0 = 1.0 - (-0.5f32).exp();
    let (rgb_v, w_v) = (values(&rgb), values(&w));
    for ch in 0..3 {
        let want = a0 * rgb_v[ch] + (1.0 - a0) * rgb_v[6 + ch];
        assert!((values(&c)[ch] - want).abs() < 1e-6, "{:?}", values(&c));
    }
    for j in 0..k {
        let want = a0 * w_v[j] + (1.0 - a0) * w_v[2 * k + j];
        assert!((values(&s)[j] - want).abs() < 1e-6, "{:?}", values(&s));
    }
    let loss = (c.sum_all().unwrap() + s.sum_all().unwrap()).unwrap();
    let g = loss.backward().unwrap();
    assert!(
        values(g.get(sd.as_tensor()).unwrap())
            .iter()
            .all(|x| x.is_finite())
    );
}

#[test]
fn the_box_segment_is_the_ray_inside_the_box() {
    let b: Bounds = [[-1.0, -2.0, 0.0], [1.0, 2.0, 1.0]];
    let close = |s: Option<Segment>, near: f64, far: f64| {
        let s = s.expect("hits");
        assert!(
            (s.near - near).abs() < 1e-9 && (s.far - far).abs() < 1e-9,
            "{s:?}"
        );
    };
    // Along +x through the middle: enters at x = −1, leaves at x = 1.
    close(box_segment([-5.0, 0.0, 0.5], [1.0, 0.0, 0.0], &b), 4.0, 6.0);
    // From inside: starts at the origin of the ray.
    close(box_segment([0.0, 0.0, 0.5], [0.0, 0.0, 1.0], &b), 0.0, 0.5);
    // Diagonal.
    let d = 1.0 / 2f64.sqrt();
    close(
        box_segment([-2.0, 0.0, -1.0], [d, 0.0, d], &b),
        2f64.sqrt(),
        2.0 * 2f64.sqrt(),
    );
    // Misses: pointing away, passing beside, parallel outside a slab, behind the origin.
    assert_eq!(box_segment([-5.0, 0.0, 0.5], [-1.0, 0.0, 0.0], &b), None);
    assert_eq!(box_segment([-5.0, 3.0, 0.5], [1.0, 0.0, 0.0], &b), None);
    assert_eq!(box_segment([-5.0, 0.0, 2.0], [1.0, 0.0, 0.0], &b), None);
    // Grazing an edge (touching it at one point) is an empty segment: a miss.
    assert_eq!(box_segment([-2.0, 0.0, 1.0], [d, 0.0, d], &b), None);
}

/// Rays that miss the box render the background with even slot weights, whatever the
/// slots; a grazing ray, an axis-parallel ray and rays far away stay finite; with every
/// ray missing the decoder still answers (nothing to decode).
#[test]
fn volumetric_rays_that_miss_graze_or_run_along_the_box() {
    let mut cfg = volumetric(Config::tiny());
    if let crate::decoder::Config::Volumetric(v) = &mut cfg.decoder {
        v.bounds = Some([[-1.0; 3], [1.0; 3]]);
    }
    let k = cfg.slot_attention.num_slots;
    let p = Params::new(9);
    let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
    let x = inputs(1, 1, 4, 1, 3.0, DType::F32);
    let slots = model
        .encode(&x.images, &x.origins, &x.dirs, None)
        .unwrap()
        .slots;
    let other = (&slots * 3.0).unwrap();
    let rays = |o: &[[f32; 3]], d: &[[f32; 3]]| {
        let flat = |v: &[[f32; 3]]| {
            Tensor::from_vec(
                v.iter().flatten().copied().collect::<Vec<_>>(),
                (1, v.len(), 3),
                &CPU,
            )
            .unwrap()
        };
        (flat(o), flat(d))
    };
    let s = 1.0 / 2f32.sqrt();
    // 0: misses; 1: grazes the edge at (−1, ·, 1); 2: runs along the x axis through the
    // box; 3: hits head-on; 4: from 1e4 away, hits.
    let (o, d) = rays(
        &[
            [-5.0, 0.0, 3.0],
            [-2.0, 0.0, 0.0],
            [-5.0, 0.0, 0.0],
            [0.0, -5.0, 0.2],
            [1e4, 0.0, 0.0],
        ],
        &[
            [1.0, 0.0, 0.0],
            [s, 0.0, s],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [-1.0, 0.0, 0.0],
        ],
    );
    let a = model.decode(&slots, &o, &d).unwrap();
    let b = model.decode(&other, &o, &d).unwrap();
    assert_sane("box rays", &a, k);
    assert_sane("box rays, other slots", &b, k);
    let (ra, rb) = (values(&a.rgb), values(&b.rgb));
    let (wa, wb) = (
        values(a.weights.as_ref().unwrap()),
        values(b.weights.as_ref().unwrap()),
    );
    let bg =
        values(&candle_nn::ops::sigmoid(&Tensor::zeros(3, DType::F32, &CPU).unwrap()).unwrap());
    for ray in [0, 1] {
        assert_eq!(
            &ra[3 * ray..3 * ray + 3],
            &bg[..],
            "ray {ray} renders the background"
        );
        assert_eq!(&ra[3 * ray..3 * ray + 3], &rb[3 * ray..3 * ray + 3]);
        assert_eq!(&wa[k * ray..k * (ray + 1)], &wb[k * ray..k * (ray + 1)]);
    }
    assert_ne!(
        &ra[6..9],
        &rb[6..9],
        "a ray through the box depends on the slots"
    );
    // Every ray missing: nothing decoded, all background.
    let (o, d) = rays(&[[-5.0, 0.0, 3.0]; 2], &[[1.0, 0.0, 0.0]; 2]);
    let out = model.decode(&slots, &o, &d).unwrap();
    assert_eq!(values(&out.rgb), [bg.clone(), bg].concat());
    // Gradients stay finite through the mix of decoded and background rays.
    let loss = a.rgb.sqr().unwrap().sum_all().unwrap();
    let g = loss.backward().unwrap();
    for (name, var) in p.vars() {
        if let Some(g) = g.get(var.as_tensor()) {
            assert!(values(g).iter().all(|v| v.is_finite()), "`{name}`");
        }
    }
}

/// Up-OSRT sees no poses: identical input views, a single view, and images with rays
/// that differ (which it ignores) stay finite; the position embeddings refuse a feature
/// grid larger than they cover.
#[test]
fn unposed_inputs_at_the_edges() {
    let cfg = unposed(Config::tiny());
    let k = cfg.slot_attention.num_slots;
    let p = Params::new(10);
    let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
    let one = inputs(2, 1, 4, 5, 3.0, DType::F32);
    assert_sane("one view", &run(&model, &one).unwrap().0, k);
    let same = Inputs {
        images: one.images.repeat((1, 3, 1, 1, 1)).unwrap(),
        origins: one.origins.repeat((1, 3, 1, 1, 1)).unwrap(),
        dirs: one.dirs.repeat((1, 3, 1, 1, 1)).unwrap(),
        ..inputs(2, 1, 4, 5, 3.0, DType::F32)
    };
    assert_sane("identical views", &run(&model, &same).unwrap().0, k);
    // The input rays do not enter: other rays, the same slots.
    let moved = Inputs {
        origins: (unit_dirs(&[2, 3, 4, 4, 3], 77, DType::F32) * 50.0).unwrap(),
        dirs: unit_dirs(&[2, 3, 4, 4, 3], 78, DType::F32),
        ..same
    };
    let slots = |x: &Inputs| {
        values(
            &model
                .encode(&x.images, &x.origins, &x.dirs, None)
                .unwrap()
                .slots,
        )
    };
    let same = Inputs {
        images: one.images.repeat((1, 3, 1, 1, 1)).unwrap(),
        origins: one.origins.repeat((1, 3, 1, 1, 1)).unwrap(),
        dirs: one.dirs.repeat((1, 3, 1, 1, 1)).unwrap(),
        ..inputs(2, 1, 4, 5, 3.0, DType::F32)
    };
    assert_eq!(slots(&same), slots(&moved));
    // tiny's grid covers 16×16 tokens: 40×40 inputs at stride 2 give 20×20.
    let big = inputs(1, 1, 40, 2, 3.0, DType::F32);
    let err = run(&model, &big).err().expect("refused").to_string();
    assert!(err.contains("max_grid"), "{err}");
}
