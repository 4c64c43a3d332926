//! Model-level tests: parameter counts, gradient flow, finite-difference gradient checks
//! (in f64) and extreme inputs. The paper's variants (Up-OSRT, V-OSRT) have their own
//! checks in [`variants`].

mod variants;

use crate::decoder;
use crate::decoder::DecoderOutput;
use crate::encoder::{Poses, RayInput};
use crate::nn::{Block, TransformerConfig};
use crate::params::{Params, normal_samples};
use crate::ray_encoding::RayEncoding;
use crate::slot_attention::{SlotAttention, SlotGradient, SlotInit};
use crate::{Config, Osrt, add_slot, drop_slot};
use candle_core::{DType, Device, Result, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const CPU: Device = Device::Cpu;

fn randn(shape: &[usize], seed: u64, dtype: DType) -> Tensor {
    let n = shape.iter().product();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Tensor::from_vec(normal_samples(&mut rng, n), shape, &CPU)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// Inputs of a small scene batch: images in [0,1], camera rays looking at the origin.
struct Inputs {
    images: Tensor,
    origins: Tensor,
    dirs: Tensor,
    t_origins: Tensor,
    t_dirs: Tensor,
    target: Tensor,
}

fn unit_dirs(shape: &[usize], seed: u64, dtype: DType) -> Tensor {
    let d = randn(shape, seed, DType::F64);
    let n = d
        .sqr()
        .unwrap()
        .sum_keepdim(candle_core::D::Minus1)
        .unwrap()
        .sqrt()
        .unwrap();
    d.broadcast_div(&n).unwrap().to_dtype(dtype).unwrap()
}

fn inputs(b: usize, v: usize, hw: usize, r: usize, cam_dist: f64, dtype: DType) -> Inputs {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let img: Vec<f32> = (0..b * v * hw * hw * 3).map(|_| rng.random()).collect();
    let images = Tensor::from_vec(img, (b, v, hw, hw, 3), &CPU)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    let origins = (unit_dirs(&[b, v, hw, hw, 3], 1, DType::F64) * cam_dist)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    let t_origins = (unit_dirs(&[b, r, 3], 2, DType::F64) * cam_dist)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    let tgt: Vec<f32> = (0..b * r * 3).map(|_| rng.random()).collect();
    Inputs {
        images,
        origins,
        dirs: unit_dirs(&[b, v, hw, hw, 3], 3, dtype),
        t_origins,
        t_dirs: unit_dirs(&[b, r, 3], 4, dtype),
        target: Tensor::from_vec(tgt, (b, r, 3), &CPU)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    }
}

fn noise(cfg: &Config, b: usize, dtype: DType) -> Option<Tensor> {
    (cfg.slot_attention.init == SlotInit::Random).then(|| {
        randn(
            &[b, cfg.slot_attention.num_slots, cfg.slot_attention.slot_dim],
            5,
            dtype,
        )
    })
}

fn run(model: &Osrt, x: &Inputs) -> Result<(DecoderOutput, Tensor)> {
    let slots = model.encode(
        &x.images,
        &x.origins,
        &x.dirs,
        noise(&model.cfg, x.images.dim(0)?, x.images.dtype()).as_ref(),
    )?;
    let out = model.decode(&slots.slots, &x.t_origins, &x.t_dirs)?;
    let loss = (&out.rgb - &x.target)?.sqr()?.mean_all()?;
    Ok((out, loss))
}

/// A box that holds every camera of [`inputs`] at distance ≤ 3: every ray hits it.
const TEST_BOUNDS: decoder::volumetric::Bounds = [[-4.0; 3], [4.0; 3]];

/// The model with a volumetric decoder of 4 points per ray in [`TEST_BOUNDS`].
fn volumetric(base: Config) -> Config {
    let mut c = base.with_decoder("volumetric").unwrap();
    if let decoder::Config::Volumetric(v) = &mut c.decoder {
        v.bounds = Some(TEST_BOUNDS);
        v.samples = 4;
    }
    c
}

/// Every decoder with every slot init and ray input, then Up-OSRT (unposed encoder).
fn decoder_variants(base: Config) -> Vec<(String, Config)> {
    let mut out = Vec::new();
    for kind in [
        "slot_mixer",
        "spatial_broadcast",
        "transformer",
        "volumetric",
    ] {
        for (init, ray_input) in [
            (SlotInit::Learned, RayInput::Concat),
            (SlotInit::Random, RayInput::Concat),
            (SlotInit::Tokens, RayInput::Concat),
            (SlotInit::Learned, RayInput::Add),
        ] {
            let mut c = match kind {
                "volumetric" => volumetric(base.clone()),
                _ => base.clone().with_decoder(kind).unwrap(),
            };
            c.slot_attention.init = init;
            c.encoder.ray_input = ray_input;
            out.push((format!("{kind}/{init:?}/{ray_input:?}"), c));
        }
    }
    let mut unposed = base;
    unposed.encoder.poses = Poses::Unposed;
    out.push(("slot_mixer/unposed".into(), unposed));
    out
}

/// The flat tensor view of the parameters (what a GPU's optimiser updates) holds the
/// host buffer's values in the same order, and writing one back sets every parameter;
/// a buffer of the wrong length is refused.
#[test]
fn flat_parameter_tensors_round_trip_in_the_fixed_order() {
    let p = Params::new(3);
    Osrt::new(&Config::tiny(), p.var_builder(&CPU)).unwrap();
    let flat = p.flatten().unwrap();
    assert_eq!(p.flatten_tensor().unwrap().to_vec1::<f32>().unwrap(), flat);
    let doubled: Vec<f32> = flat.iter().map(|x| 2.0 * x + 1.0).collect();
    p.load_flat_tensor(&Tensor::from_slice(&doubled, doubled.len(), &CPU).unwrap())
        .unwrap();
    assert_eq!(p.flatten().unwrap(), doubled);
    let short = Tensor::zeros(flat.len() - 1, DType::F32, &CPU).unwrap();
    assert!(p.load_flat_tensor(&short).is_err());
}

#[test]
fn paper_preset_has_the_papers_parameter_count() {
    let p = Params::new(0);
    Osrt::new(&Config::paper(), p.var_builder(&CPU)).unwrap();
    let n = p.num_elements() as f64;
    let paper = 81e6;
    eprintln!("paper preset: {n} parameters");
    assert!(
        (n - paper).abs() / paper < 0.03,
        "paper preset has {n} parameters, expected 81 M ± 3%"
    );
}

#[test]
fn every_parameter_of_every_variant_gets_a_gradient() {
    for (name, cfg) in decoder_variants(Config::tiny()) {
        let p = Params::new(1);
        let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
        let x = inputs(2, 2, 4, 5, 3.0, DType::F32);
        let (_, loss) = run(&model, &x).unwrap();
        let grads = loss.backward().unwrap();
        for (pname, var) in p.vars() {
            let g = grads
                .get(var.as_tensor())
                .unwrap_or_else(|| panic!("{name}: `{pname}` has no gradient"));
            let v = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(
                v.iter().all(|x| x.is_finite()),
                "{name}: `{pname}` has a non-finite gradient"
            );
            assert!(
                v.iter().any(|&x| x != 0.0),
                "{name}: `{pname}` has an all-zero gradient"
            );
        }
    }
}

/// Compares autograd with central differences on a few entries of every variable.
fn gradcheck(vars: &[(String, Var)], f: &dyn Fn() -> Result<Tensor>, per_var: usize) {
    let loss = f().unwrap();
    let grads = loss.backward().unwrap();
    let h = 1e-6;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for (name, var) in vars {
        let g = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("`{name}` has no gradient"));
        let g = g.flatten_all().unwrap().to_vec1::<f64>().unwrap();
        let base = var
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        for _ in 0..per_var.min(base.len()) {
            let i = rng.random_range(0..base.len());
            let eval = |delta: f64| {
                let mut v = base.clone();
                v[i] += delta;
                var.set(&Tensor::from_vec(v, var.shape(), &CPU).unwrap())
                    .unwrap();
                f().unwrap().to_scalar::<f64>().unwrap()
            };
            let numeric = (eval(h) - eval(-h)) / (2.0 * h);
            var.set(&Tensor::from_vec(base.clone(), var.shape(), &CPU).unwrap())
                .unwrap();
            let tol = 1e-5 + 1e-4 * numeric.abs().max(g[i].abs());
            assert!(
                (numeric - g[i]).abs() <= tol,
                "`{name}`[{i}]: autograd {} vs finite difference {numeric}",
                g[i]
            );
        }
    }
}

#[test]
fn gradcheck_ray_encoding() {
    let enc = RayEncoding::new(Config::tiny().ray_encoding, DType::F64, &CPU).unwrap();
    let o = Var::from_tensor(&randn(&[2, 3, 3], 1, DType::F64)).unwrap();
    let d = Var::from_tensor(&unit_dirs(&[2, 3, 3], 2, DType::F64)).unwrap();
    let w = randn(&[2, 3, enc.dim()], 3, DType::F64);
    let f = || {
        enc.forward(o.as_tensor(), d.as_tensor())?
            .mul(&w)?
            .sum_all()
    };
    gradcheck(
        &[
            ("origins".into(), o.clone()),
            ("directions".into(), d.clone()),
        ],
        &f,
        6,
    );
}

/// The one-pass kernel (rays without gradients) against the composed ops it replaces:
/// ordinary rays, huge origins (angles up to ~1e9 rad) and non-finite values.
#[test]
fn ray_encoding_kernel_matches_the_composed_version() {
    for cfg in [Config::cpu().ray_encoding, Config::paper().ray_encoding] {
        let enc = RayEncoding::new(cfg, DType::F32, &CPU).unwrap();
        let d = unit_dirs(&[2, 5, 7, 3], 11, DType::F32);
        for (scale, tol) in [(3.0, 2e-6), (1e5, 2e-6)] {
            let o = (randn(&[2, 5, 7, 3], 12, DType::F32) * scale).unwrap();
            let fast = enc.forward(&o, &d).unwrap();
            let slow = enc.forward_composed(&o, &d).unwrap();
            assert_eq!(fast.dims(), slow.dims());
            let diff = (&fast - &slow)
                .unwrap()
                .abs()
                .unwrap()
                .flatten_all()
                .unwrap()
                .max(0)
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            assert!(
                diff <= tol,
                "scale {scale}: max |kernel − composed| = {diff:e}"
            );
        }
        let bad = Tensor::new(&[[f32::INFINITY, f32::NAN, 0.0]], &CPU).unwrap();
        let d1 = Tensor::new(&[[0f32, 0.0, 1.0]], &CPU).unwrap();
        let out: Vec<f32> = enc
            .forward(&bad, &d1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        // The sines and cosines of the infinite and the NaN axis are NaN, no others.
        let nan = out.iter().filter(|v| v.is_nan()).count();
        assert_eq!(nan, 4 * enc.config().origin_octaves, "NaN count");
    }
}

#[test]
fn gradcheck_encoder_block() {
    let p = Params::new(2);
    let cfg = TransformerConfig {
        layers: 1,
        heads: 2,
        head_dim: 3,
        mlp_hidden: 7,
    };
    let block = Block::new(6, 6, &cfg, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
    let x = randn(&[2, 4, 6], 4, DType::F64);
    let w = randn(&[2, 4, 6], 5, DType::F64);
    let f = || block.forward(&x, None)?.mul(&w)?.sum_all();
    gradcheck(&p.vars(), &f, 4);
}

#[test]
fn gradcheck_slot_attention() {
    for init in [SlotInit::Learned, SlotInit::Random, SlotInit::Tokens] {
        let p = Params::new(3);
        let mut cfg = Config::tiny().slot_attention;
        cfg.init = init;
        let sa = SlotAttention::new(&cfg, 5, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
        let x = randn(&[2, 6, 5], 6, DType::F64);
        let z = randn(&[2, cfg.num_slots, cfg.slot_dim], 7, DType::F64);
        let w = randn(&[2, cfg.num_slots, cfg.slot_dim], 8, DType::F64);
        let f = || sa.forward(&x, Some(&z))?.slots.mul(&w)?.sum_all();
        gradcheck(&p.vars(), &f, 3);
    }
}

/// Each parameter's name and gradient (`None`: no gradient reached it).
type NamedGradients = Vec<(String, Option<Vec<f64>>)>;

/// One slot-attention forward (learned init) under a weighted sum: the slots' values and
/// each parameter's gradient.
fn slot_gradients(gradient: SlotGradient, iterations: usize) -> (Vec<f64>, NamedGradients) {
    let p = Params::new(3);
    let mut cfg = Config::tiny().slot_attention;
    (cfg.iterations, cfg.gradient) = (iterations, gradient);
    let sa = SlotAttention::new(&cfg, 5, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
    let x = randn(&[2, 6, 5], 6, DType::F64);
    let w = randn(&[2, cfg.num_slots, cfg.slot_dim], 8, DType::F64);
    let slots = sa.forward(&x, None).unwrap().slots;
    let g = slots
        .mul(&w)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let mut grads: Vec<_> = p
        .vars()
        .into_iter()
        .map(|(name, v)| (name, g.get(v.as_tensor()).map(flat)))
        .collect();
    grads.sort_by(|a, b| a.0.cmp(&b.0));
    (flat(&slots), grads)
}

#[test]
fn slot_gradients_keep_the_values_and_cut_the_paths_they_name() {
    let (full_v, full) = slot_gradients(SlotGradient::Full, 3);
    let (implicit_v, implicit) = slot_gradients(SlotGradient::Implicit, 3);
    let (bilevel_v, bilevel) = slot_gradients(SlotGradient::Bilevel, 3);
    assert!(
        full_v == implicit_v && full_v == bilevel_v,
        "the forward values are the same"
    );
    let is_init = |name: &str| name.ends_with("init_slots");
    assert!(
        full.iter().any(|(n, _)| is_init(n)),
        "learned init has init_slots"
    );
    let zero = |g: &Option<Vec<f64>>| g.as_ref().is_none_or(|g| g.iter().all(|x| *x == 0.0));
    for (((name, f), (_, i)), (_, b)) in full.iter().zip(&implicit).zip(&bilevel) {
        if is_init(name) {
            // Implicit: nothing reaches the initial slots; bilevel: the last iteration's.
            assert!(
                zero(i),
                "{name}: implicit gives the initial slots no gradient"
            );
            assert!(
                !zero(b) && b != f,
                "{name}: bilevel passes the last iteration's gradient"
            );
        } else {
            // Both differentiate the last iteration only, with the same inputs.
            assert_eq!(
                i, b,
                "{name}: implicit and bilevel agree off the initial slots"
            );
        }
    }
    assert!(
        full.iter().zip(&implicit).any(|((_, f), (_, i))| f != i),
        "cutting the earlier iterations changes some gradient"
    );
    // With one iteration there is nothing to cut: bilevel is full, to the bit.
    assert_eq!(
        slot_gradients(SlotGradient::Bilevel, 1),
        slot_gradients(SlotGradient::Full, 1)
    );
    assert_eq!("bilevel".parse::<SlotGradient>(), Ok(SlotGradient::Bilevel));
    assert!(
        "exact"
            .parse::<SlotGradient>()
            .unwrap_err()
            .contains("full, implicit or bilevel")
    );
}

#[test]
fn gradcheck_decoders_and_loss() {
    // The full model (encoder, slot attention, each decoder) under the MSE loss.
    // Every third of the 17 variants: each decoder, slot init and ray input once (the
    // unposed encoder is checked in `variants`).
    for (name, cfg) in decoder_variants(Config::tiny()).into_iter().step_by(3) {
        let p = Params::new(4);
        let model = Osrt::new(&cfg, p.var_builder_dtype(DType::F64, &CPU)).unwrap();
        let x = inputs(1, 1, 4, 3, 2.0, DType::F64);
        let f = || run(&model, &x).map(|(_, l)| l);
        eprintln!("gradcheck {name}");
        gradcheck(&p.vars(), &f, 2);
    }
}

fn assert_sane(name: &str, out: &DecoderOutput, k: usize) {
    let rgb = out.rgb.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert!(
        rgb.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)),
        "{name}: rgb out of [0,1] or non-finite"
    );
    if let Some(w) = &out.weights {
        assert_eq!(w.dim(2).unwrap(), k);
        let w = w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(
            w.iter().all(|v| v.is_finite() && *v >= 0.0),
            "{name}: bad slot weights"
        );
    }
}

#[test]
fn extreme_inputs_give_finite_outputs() {
    for (name, cfg) in decoder_variants(Config::tiny()) {
        let p = Params::new(5);
        let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
        let k = cfg.slot_attention.num_slots;
        let base = inputs(2, 2, 4, 5, 3.0, DType::F32);
        // Black, white and constant images (a scene with zero objects is a constant one).
        for fill in [0.0f32, 1.0, 0.37] {
            let x = Inputs {
                images: (base.images.zeros_like().unwrap() + fill as f64).unwrap(),
                ..inputs(2, 2, 4, 5, 3.0, DType::F32)
            };
            assert_sane(
                &format!("{name} fill {fill}"),
                &run(&model, &x).unwrap().0,
                k,
            );
        }
        // Identical input tokens: one pixel repeated, same ray everywhere.
        let one_ray = base
            .origins
            .narrow(2, 0, 1)
            .unwrap()
            .narrow(3, 0, 1)
            .unwrap()
            .broadcast_as(base.origins.shape())
            .unwrap()
            .contiguous()
            .unwrap();
        let one_dir = base
            .dirs
            .narrow(2, 0, 1)
            .unwrap()
            .narrow(3, 0, 1)
            .unwrap()
            .broadcast_as(base.dirs.shape())
            .unwrap()
            .contiguous()
            .unwrap();
        let x = Inputs {
            origins: one_ray,
            dirs: one_dir,
            images: (base.images.zeros_like().unwrap() + 0.5).unwrap(),
            ..inputs(2, 2, 4, 5, 3.0, DType::F32)
        };
        assert_sane(
            &format!("{name} identical tokens"),
            &run(&model, &x).unwrap().0,
            k,
        );
        // Cameras very near and very far.
        for dist in [1e-3, 1e4] {
            assert_sane(
                &format!("{name} camera at {dist}"),
                &run(&model, &inputs(2, 2, 4, 5, dist, DType::F32))
                    .unwrap()
                    .0,
                k,
            );
        }
        // A single ray, batch of one.
        assert_sane(
            &format!("{name} single ray"),
            &run(&model, &inputs(1, 1, 4, 1, 3.0, DType::F32)).unwrap().0,
            k,
        );
    }
}

#[test]
fn one_and_many_slots_and_huge_attention_logits() {
    for slots in [1usize, 64] {
        for (name, mut cfg) in decoder_variants(Config::tiny()) {
            cfg.slot_attention.num_slots = slots;
            let p = Params::new(6);
            let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
            assert_sane(
                &format!("{name} {slots} slots"),
                &run(&model, &inputs(1, 1, 4, 3, 3.0, DType::F32)).unwrap().0,
                slots,
            );
        }
    }
    // Attention logits ×1e4: scale every query projection by 1e4.
    for (name, cfg) in decoder_variants(Config::tiny()) {
        let p = Params::new(7);
        let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
        for (pname, v) in p.vars() {
            if pname.ends_with("q.weight")
                || pname.ends_with("to_q.weight")
                || pname.ends_with("mix_q.weight")
            {
                v.set(&(v.as_tensor() * 1e4).unwrap()).unwrap();
            }
        }
        let x = inputs(2, 1, 4, 5, 3.0, DType::F32);
        let (out, loss) = run(&model, &x).unwrap();
        assert_sane(
            &format!("{name} logits ×1e4"),
            &out,
            cfg.slot_attention.num_slots,
        );
        let grads = loss.backward().unwrap();
        for (pname, v) in p.vars() {
            if let Some(g) = grads.get(v.as_tensor()) {
                let g = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                assert!(
                    g.iter().all(|x| x.is_finite()),
                    "{name}: `{pname}` gradient non-finite at logits ×1e4"
                );
            }
        }
    }
}

#[test]
fn initialisation_is_deterministic_and_order_independent() {
    let a = Params::new(42);
    Osrt::new(&Config::tiny(), a.var_builder(&CPU)).unwrap();
    let b = Params::new(42);
    Osrt::new(&Config::tiny(), b.var_builder(&CPU)).unwrap();
    assert_eq!(a.flatten().unwrap(), b.flatten().unwrap());
    let c = Params::new(43);
    Osrt::new(&Config::tiny(), c.var_builder(&CPU)).unwrap();
    assert_ne!(a.flatten().unwrap(), c.flatten().unwrap());
    // Names are sorted: the flat order is fixed.
    let names: Vec<String> = a.vars().into_iter().map(|(n, _)| n).collect();
    let mut sorted = names.clone();
    sorted.sort();
    assert_eq!(names, sorted);
    // Round trip through the flat buffer.
    let flat = c.flatten().unwrap();
    a.load_flat(&flat).unwrap();
    assert_eq!(a.flatten().unwrap(), flat);
}

#[test]
fn scene_editing_changes_the_slot_set() {
    let p = Params::new(8);
    let model = Osrt::new(&Config::tiny(), p.var_builder(&CPU)).unwrap();
    let x = inputs(1, 1, 4, 6, 3.0, DType::F32);
    let slots = model
        .encode(&x.images, &x.origins, &x.dirs, None)
        .unwrap()
        .slots;
    let dropped = drop_slot(&slots, 1).unwrap();
    assert_eq!(dropped.dims(), &[1, 2, 8]);
    let out = model.decode(&dropped, &x.t_origins, &x.t_dirs).unwrap();
    assert_eq!(out.weights.unwrap().dims(), &[1, 6, 2]);
    let added = add_slot(&slots, &dropped, 0).unwrap();
    assert_eq!(added.dims(), &[1, 4, 8]);
    assert!(drop_slot(&slots, 3).is_err());
    assert!(add_slot(&slots, &dropped, 2).is_err());
}

#[test]
fn cpu_preset_size() {
    let p = Params::new(0);
    Osrt::new(&Config::cpu(), p.var_builder(&CPU)).unwrap();
    let n = p.num_elements();
    eprintln!("cpu preset: {n} parameters");
    assert!(
        (500_000..3_000_000).contains(&n),
        "cpu preset has {n} parameters"
    );
}

#[test]
fn ray_input_add_refuses_sides_not_divisible_by_the_stride() {
    let mut cfg = Config::tiny();
    cfg.encoder.ray_input = RayInput::Add;
    let p = Params::new(1);
    let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
    let err = run(&model, &inputs(1, 1, 5, 3, 3.0, DType::F32))
        .err()
        .expect("a 5×5 image with stride 2 is refused")
        .to_string();
    assert!(err.contains("divisible by the CNN stride 2"), "{err}");
}

/// Why `RayInput::Add` exists: at initialisation, the SLSR tokens of two different images
/// seen along the same rays differ far more when the CNN reads RGB alone.
#[test]
fn ray_input_add_lets_the_image_through_at_initialisation() {
    let token_change = |ray_input: RayInput| -> f32 {
        let mut cfg = Config::cpu();
        cfg.encoder.ray_input = ray_input;
        let p = Params::new(0);
        let model = Osrt::new(&cfg, p.var_builder(&CPU)).unwrap();
        let a = inputs(1, 1, 32, 1, 3.0, DType::F32);
        // Same rays, another image: the first one turned upside down and mirrored.
        let img_b = a.images.flip(&[2, 3]).unwrap();
        let tokens = |img: &Tensor| {
            model
                .encoder
                .forward(&model.rays, img, &a.origins, &a.dirs)
                .unwrap()
        };
        let (ta, tb) = (tokens(&a.images), tokens(&img_b));
        let rel = (&ta - &tb).unwrap().sqr().unwrap().sum_all().unwrap();
        let norm = ta.sqr().unwrap().sum_all().unwrap();
        (rel.to_scalar::<f32>().unwrap() / norm.to_scalar::<f32>().unwrap()).sqrt()
    };
    let (concat, add) = (token_change(RayInput::Concat), token_change(RayInput::Add));
    eprintln!("relative token change: concat {concat:.4}, add {add:.4}");
    assert!(add > 3.0 * concat, "concat {concat}, add {add}");
}
