//! The train step: flat gradients in a fixed order, applying external gradients, skipping
//! non-finite steps, and learning on a tiny problem.

use candle_core::Device;
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    BatchConfig, InputSelection, Scene, TargetViews, build_batch, generator::generate_scene,
};
use osrt_trainer::{ApplyOutcome, JobConfig, Trainer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn scenes(n: u64) -> Vec<Scene> {
    let cfg = GeneratorConfig {
        image_size: 8,
        antialias: 1,
        ..GeneratorConfig::clevr_lite()
    };
    (0..n)
        .map(|i| generate_scene(&cfg, 1, "train", i).unwrap())
        .collect()
}

fn batch(scenes: &[Scene], seed: u64) -> osrt_dataset::Batch {
    let refs: Vec<&Scene> = scenes.iter().collect();
    let cfg = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::All,
        rays_per_scene: Some(32),
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    build_batch(&refs, &cfg, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap()
}

fn tiny() -> JobConfig {
    JobConfig::preset("tiny").unwrap()
}

#[test]
fn gradients_are_one_flat_buffer_in_sorted_parameter_order() {
    let t = Trainer::new(tiny(), Device::Cpu).unwrap();
    let data = scenes(2);
    let g = t
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    assert_eq!(g.grads.len(), t.num_parameters());
    assert_eq!(g.samples, 2);
    assert!(g.loss.is_finite() && g.loss > 0.0);
    // Same seed, same data → the same bytes (determinism of one step).
    let t2 = Trainer::new(tiny(), Device::Cpu).unwrap();
    let g2 = t2
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    assert_eq!(g.grads, g2.grads);
    // The segment of each parameter sits at its offset in sorted-name order.
    let names: Vec<String> = t.params.vars().into_iter().map(|(n, _)| n).collect();
    let mut sorted = names.clone();
    sorted.sort();
    assert_eq!(names, sorted);
}

#[test]
fn applying_a_flat_gradient_equals_applying_the_local_one() {
    let data = scenes(2);
    let mut a = Trainer::new(tiny(), Device::Cpu).unwrap();
    let mut b = Trainer::new(tiny(), Device::Cpu).unwrap();
    let g = a
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    // b receives the gradient "over the network": a copy of the bytes.
    let bytes: Vec<u8> = g.grads.iter().flat_map(|x| x.to_le_bytes()).collect();
    let received: Vec<f32> = bytes
        .chunks(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert!(matches!(
        a.apply(g.loss, g.grads).unwrap(),
        ApplyOutcome::Applied { .. }
    ));
    assert!(matches!(
        b.apply(g.loss, received).unwrap(),
        ApplyOutcome::Applied { .. }
    ));
    assert_eq!(a.params.flatten().unwrap(), b.params.flatten().unwrap());
    assert_ne!(
        a.params.flatten().unwrap(),
        Trainer::new(tiny(), Device::Cpu)
            .unwrap()
            .params
            .flatten()
            .unwrap()
    );
}

#[test]
fn non_finite_steps_are_skipped_and_counted() {
    let data = scenes(2);
    let mut t = Trainer::new(tiny(), Device::Cpu).unwrap();
    let before = t.params.flatten().unwrap();
    let g = t
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    let mut bad = g.grads.clone();
    bad[3] = f32::NAN;
    assert_eq!(
        t.apply(g.loss, bad).unwrap(),
        ApplyOutcome::Skipped {
            reason: "non-finite gradient"
        }
    );
    assert_eq!(
        t.apply(f64::INFINITY, g.grads.clone()).unwrap(),
        ApplyOutcome::Skipped {
            reason: "non-finite loss"
        }
    );
    assert_eq!(
        t.params.flatten().unwrap(),
        before,
        "a skipped step must not touch the weights"
    );
    assert_eq!((t.skipped_total, t.skipped_in_a_row, t.step), (2, 2, 2));
    assert!(matches!(
        t.apply(g.loss, g.grads).unwrap(),
        ApplyOutcome::Applied { .. }
    ));
    assert_eq!(t.skipped_in_a_row, 0);
}

/// A finite gradient of 1e30 squares past f32's range: the second moment would be ∞
/// while every weight stays finite. The step is skipped; the moments stay finite.
#[test]
fn a_gradient_that_overflows_the_second_moment_is_skipped() {
    let data = scenes(2);
    let mut t = Trainer::new(tiny(), Device::Cpu).unwrap();
    let g = t
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    let mut huge = g.grads.clone();
    huge[0] = 1e30;
    assert_eq!(
        t.apply(g.loss, huge).unwrap(),
        ApplyOutcome::Skipped {
            reason: "non-finite updated weight or moment"
        }
    );
    let (m, v) = t.opt.moments().unwrap();
    assert!(m.iter().chain(&v).all(|x| x.is_finite()));
    assert_eq!(t.opt.t(), 0);
}

#[test]
fn an_absurd_learning_rate_never_writes_a_non_finite_weight() {
    let data = scenes(2);
    let mut job = tiny();
    job.train.lr = 1e38;
    job.train.warmup_steps = 0;
    let mut t = Trainer::new(job, Device::Cpu).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for i in 0..6 {
        let g = t.gradients(&batch(&data, i), &mut rng).unwrap();
        let _ = t.apply(g.loss, g.grads).unwrap();
        assert!(
            t.params.flatten().unwrap().iter().all(|p| p.is_finite()),
            "step {i}"
        );
    }
    assert!(
        t.skipped_total > 0,
        "lr 1e38 must have produced skipped steps"
    );
}

#[test]
fn clipping_bounds_the_applied_gradient_norm() {
    let data = scenes(2);
    let mut job = tiny();
    job.train.clip_norm = Some(1e-3);
    let mut t = Trainer::new(job, Device::Cpu).unwrap();
    let g = t
        .gradients(&batch(&data, 0), &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    let norm = osrt_trainer::optim::global_norm(&g.grads);
    match t.apply(g.loss, g.grads).unwrap() {
        ApplyOutcome::Applied { grad_norm, .. } => assert_eq!(grad_norm, norm),
        other => panic!("{other:?}"),
    }
}

#[test]
fn the_loss_falls_when_fitting_one_batch() {
    let data = scenes(2);
    let mut job = tiny();
    job.train.lr = 3e-3;
    let mut t = Trainer::new(job, Device::Cpu).unwrap();
    let b = batch(&data, 0);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let first = t.gradients(&b, &mut rng).unwrap().loss;
    let mut last = first;
    for _ in 0..60 {
        let g = t.gradients(&b, &mut rng).unwrap();
        last = g.loss;
        t.apply(g.loss, g.grads).unwrap();
    }
    assert!(last < 0.5 * first, "loss {first} → {last}");
}

#[test]
fn learning_rate_schedule_warms_up_then_decays() {
    let t = osrt_trainer::TrainConfig::reference();
    assert!((t.lr_at(0) - 1e-4 / 5000.0).abs() < 1e-15);
    assert!((t.lr_at(4999) - 1e-4).abs() < 1e-15);
    assert!((t.lr_at(5000) - 1e-4).abs() < 1e-15);
    assert!((t.lr_at(5000 + 4_000_000) - 1.6e-5).abs() < 1e-12);
}

#[test]
fn presets_round_trip_through_toml() {
    for name in ["clevr-lite-cpu", "tiny", "paper"] {
        let job = JobConfig::preset(name).unwrap();
        let back = JobConfig::from_toml("mem", &job.to_toml()).unwrap();
        assert_eq!(back, job);
    }
    let err = JobConfig::from_toml("bad.toml", "[train]\nlr = 'x'")
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.toml"), "{err}");
    assert!(JobConfig::preset("huge").is_err());
}

/// In f32 and in bf16 (the fused kernels' bf16 products where the CPU has a unit for
/// them): the same seed gives the same weights, bit for bit; another seed others.
#[test]
fn same_seed_same_weights_after_several_steps() {
    use osrt_kernels::Precision;
    let data = scenes(3);
    let run = |seed: u64, precision: Precision| {
        let mut job = tiny();
        job.train.seed = seed;
        job.train.precision = precision;
        job.model.slot_attention.init = osrt_model::slot_attention::SlotInit::Random;
        let mut t = Trainer::new(job, Device::Cpu).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for i in 0..4 {
            let g = t.gradients(&batch(&data, i), &mut rng).unwrap();
            t.apply(g.loss, g.grads).unwrap();
        }
        t.params.flatten().unwrap()
    };
    for p in [Precision::F32, Precision::Bf16] {
        let a = run(5, p);
        assert_eq!(
            a,
            run(5, p),
            "{p}: same seed must give bit-identical weights"
        );
        assert_ne!(a, run(6, p), "{p}");
    }
    if osrt_kernels::cpu_bf16_products().is_some() {
        assert_ne!(
            run(5, Precision::F32),
            run(5, Precision::Bf16),
            "the bf16 products ran"
        );
    }
}

/// The fused ops (LayerNorm, GELU, bias add with hand-written backward passes) change
/// speed, not training: a short seeded run takes the same loss curve with them as with
/// candle's composed ops (`train.kernels`), to float tolerance, whatever the calling
/// thread's own setting; and so does the GPU's graph built on the CPU (`device`: the
/// attention, convolution and MLP nodes, the one-node LayerNorm, softmax and bias).
#[test]
fn fused_ops_leave_the_loss_curve_unchanged() {
    use osrt_kernels::Kernels;
    let data = scenes(4);
    for preset in ["tiny", "clevr-lite-cpu"] {
        let run = |kernels: Kernels| {
            let mut job = JobConfig::preset(preset).unwrap();
            job.train.batch_size = 2;
            job.train.kernels = kernels;
            // The calling thread's switch says the opposite: the job's value wins.
            let other = match kernels {
                Kernels::Fused => Kernels::Composed,
                Kernels::Composed | Kernels::Device => Kernels::Fused,
            };
            osrt_kernels::with_kernels(other, || {
                let mut t = Trainer::new(job.clone(), Device::Cpu).unwrap();
                let mut rng = ChaCha8Rng::seed_from_u64(5);
                let mut losses = Vec::new();
                for step in 0..6 {
                    let b = batch(&data[(step % 2) * 2..(step % 2) * 2 + 2], step as u64);
                    let g = t.gradients(&b, &mut rng).unwrap();
                    losses.push(g.loss);
                    t.apply(g.loss, g.grads).unwrap();
                }
                (losses, t.params.flatten().unwrap())
            })
        };
        let (fused, w_fused) = run(Kernels::Fused);
        for other in [Kernels::Composed, Kernels::Device] {
            let (losses, w) = run(other);
            assert_ne!(w_fused, w, "{other}: the two kernel sets really both ran");
            for (step, (a, b)) in fused.iter().zip(&losses).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-4 * b.abs().max(1e-3),
                    "{preset} step {step}: loss {a} fused vs {b} {other}"
                );
            }
            let worst = w_fused
                .iter()
                .zip(&w)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(
                worst < 1e-4,
                "{preset}: weights differ by {worst} from {other}'s after 6 steps"
            );
        }
    }
}

/// The step's backward pass runs in segments (encoder CNN, transformer, slot attention,
/// decoder; `osrt_kernels::cut`) so that each segment's activations are freed before the
/// next; its gradients are those of the whole graph's single backward pass, to the bit,
/// with each kind of ops.
#[test]
fn the_segmented_backward_gives_the_whole_graphs_gradients() {
    use osrt_kernels::Kernels;
    use osrt_trainer::BatchTensors;
    let data = scenes(2);
    let b = batch(&data, 3);
    for kernels in [Kernels::Fused, Kernels::Composed, Kernels::Device] {
        let mut cfg = tiny();
        cfg.train.kernels = kernels;
        let t = Trainer::new(cfg, Device::Cpu).unwrap();
        let cut = t.gradients(&b, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
        let whole = osrt_kernels::with_kernels(kernels, || {
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let x = BatchTensors::new(&b, &Device::Cpu).unwrap();
            let noise = t.slot_noise(b.batch_size, &mut rng).unwrap();
            let offsets = t
                .model
                .ray_offsets(b.batch_size, b.rays_per_scene, &mut rng)
                .unwrap();
            let slots = t
                .model
                .encode(&x.images, &x.origins, &x.directions, noise.as_ref())
                .unwrap();
            let out = t
                .model
                .decode_with(
                    &slots.slots,
                    &x.target_origins,
                    &x.target_directions,
                    offsets.as_ref(),
                )
                .unwrap();
            let loss = (&out.rgb - &x.target_rgb).unwrap().sqr().unwrap();
            let grads = loss.mean_all().unwrap().backward().unwrap();
            let mut flat = Vec::new();
            for (_, var) in t.params.vars() {
                match grads.get(var.as_tensor()) {
                    Some(g) => flat.extend(g.flatten_all().unwrap().to_vec1::<f32>().unwrap()),
                    None => flat.extend(std::iter::repeat_n(0.0, var.elem_count())),
                }
            }
            flat
        });
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&cut.grads), bits(&whole), "{kernels:?}");
        assert!(whole.iter().any(|g| *g != 0.0));
    }
}

/// With `train.recompute` the forward pass keeps no activations of the transformer blocks,
/// the convolutions and the render MLP, and the backward pass makes them again: the same
/// gradients, to the bit with the fused ops and the device graph (f32 and bf16), to
/// rounding with candle's composed ops, with each decoder and the unposed encoder.
#[test]
fn recomputed_activations_give_the_kept_ones_gradients() {
    use osrt_kernels::{Kernels, Precision};
    let data = scenes(2);
    let b = batch(&data, 3);
    let cases = [
        ("tiny", Kernels::Fused, Precision::F32),
        ("tiny", Kernels::Composed, Precision::F32),
        ("tiny", Kernels::Device, Precision::F32),
        ("tiny", Kernels::Device, Precision::Bf16),
        ("clevr-lite-cpu", Kernels::Device, Precision::Bf16),
        ("clevr-lite-cpu", Kernels::Fused, Precision::F32),
    ];
    let decoders = [
        "slot_mixer",
        "transformer",
        "spatial_broadcast",
        "volumetric",
    ];
    for (preset, kernels, precision) in cases {
        for (decoder, unposed) in decoders
            .iter()
            .map(|d| (d, false))
            .chain([(&"slot_mixer", true)])
        {
            let mut cfg = JobConfig::preset(preset).unwrap();
            cfg.train.kernels = kernels;
            cfg.train.precision = precision;
            cfg.model = cfg.model.with_decoder(decoder).unwrap();
            if let osrt_model::decoder::Config::Volumetric(v) = &mut cfg.model.decoder {
                v.bounds = Some(GeneratorConfig::clevr_lite().scene_bounds());
            }
            if unposed {
                cfg.model.encoder.poses = osrt_model::encoder::Poses::Unposed;
            }
            let grads = |recompute: bool| {
                let mut cfg = cfg.clone();
                cfg.train.recompute = recompute;
                let t = Trainer::new(cfg, Device::Cpu).unwrap();
                let g = t.gradients(&b, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
                (g.loss, g.grads)
            };
            let (kept, recomputed) = (grads(false), grads(true));
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let case = format!("{preset} {kernels:?} {precision:?} {decoder} unposed {unposed}");
            assert_eq!(kept.0.to_bits(), recomputed.0.to_bits(), "{case}");
            assert!(kept.1.iter().any(|g| *g != 0.0), "{case}");
            // A block of candle's ops (composed, and the device graph's) reads its input
            // twice (LayerNorm, residual), so the query of the decoders with a render MLP,
            // read by the first block and the render MLP, sums three gradients: in
            // another order when the render MLP is a recomputed segment of its own, the
            // same up to rounding. Everywhere else, the same bits.
            let shared_query = matches!(*decoder, "slot_mixer" | "volumetric");
            if kernels == Kernels::Fused || !shared_query {
                assert_eq!(bits(&kept.1), bits(&recomputed.1), "{case}");
                continue;
            }
            let scale = kept.1.iter().fold(0f32, |m, g| m.max(g.abs()));
            for (i, (a, b)) in kept.1.iter().zip(&recomputed.1).enumerate() {
                assert!((a - b).abs() <= 1e-6 * scale, "{case}: [{i}] {a} vs {b}");
            }
        }
    }
}

/// A share run as micro-batches of 1, 2, 3 or 4 scenes (the last one smaller) gives the
/// whole share's loss and gradient to rounding, for every kernel choice and decoder: each
/// micro-batch's mean is weighted by its scenes, and the random numbers (slot noise, a
/// volumetric decoder's ray offsets) are the whole share's, drawn once. A micro-batch as
/// large as the share is the unset setting, to the bit.
#[test]
fn micro_batches_give_the_whole_batchs_gradient() {
    use osrt_kernels::{Kernels, Precision};
    let data = scenes(6);
    let b = batch(&data, 3);
    for kernels in [Kernels::Fused, Kernels::Composed, Kernels::Device] {
        for decoder in [
            "slot_mixer",
            "transformer",
            "spatial_broadcast",
            "volumetric",
        ] {
            let mut cfg = tiny();
            cfg.train.kernels = kernels;
            cfg.train.precision = Precision::F32;
            cfg.model = cfg.model.with_decoder(decoder).unwrap();
            if let osrt_model::decoder::Config::Volumetric(v) = &mut cfg.model.decoder {
                v.bounds = Some(GeneratorConfig::clevr_lite().scene_bounds());
            }
            let grads = |micro: Option<usize>| {
                let mut cfg = cfg.clone();
                cfg.train.micro_batch_size = micro;
                let t = Trainer::new(cfg, Device::Cpu).unwrap();
                let g = t.gradients(&b, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
                assert_eq!(g.samples, 6);
                (g.loss, g.grads)
            };
            let case = format!("{kernels:?} {decoder}");
            let whole = grads(None);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let one_pass = grads(Some(6));
            assert_eq!(whole.0.to_bits(), one_pass.0.to_bits(), "{case}");
            assert_eq!(bits(&whole.1), bits(&one_pass.1), "{case}");
            let norm = |v: &[f32]| v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
            assert!(norm(&whole.1) > 0.0, "{case}");
            for m in [1, 2, 3, 4] {
                let (loss, g) = grads(Some(m));
                assert!(
                    (loss - whole.0).abs() <= 1e-6 * whole.0.abs(),
                    "{case} m={m}: loss {loss} vs {}",
                    whole.0
                );
                let diff: Vec<f32> = g.iter().zip(&whole.1).map(|(a, b)| a - b).collect();
                let rel = norm(&diff) / norm(&whole.1);
                assert!(rel <= 1e-6, "{case} m={m}: relative L2 {rel:e}");
            }
        }
    }
}

/// On the CPU a step's passes go into the flat host gradient segment by segment, as each
/// backward pass makes them (the store never holds a whole pass's gradients beside the
/// sum); the sums are those of adding each pass's whole per-parameter gradients (the
/// path of a gradient kept on the device), to the bit, with the backward pass in a few
/// segments and in many (recomputed blocks, a parameter read by several of them).
#[test]
fn passes_summed_as_they_are_made_give_the_per_parameter_sums() {
    use osrt_kernels::{Kernels, Precision};
    let data = scenes(6);
    let b = batch(&data, 3);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for kernels in [Kernels::Fused, Kernels::Composed, Kernels::Device] {
        for recompute in [false, true] {
            for m in [2, 4] {
                let mut cfg = tiny();
                cfg.train.kernels = kernels;
                cfg.train.precision = Precision::F32;
                cfg.train.recompute = recompute;
                cfg.train.micro_batch_size = Some(m);
                let t = Trainer::new(cfg, Device::Cpu).unwrap();
                let host = t.gradients(&b, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
                let kept = t
                    .gradients_kept(&b, &mut ChaCha8Rng::seed_from_u64(5), true)
                    .unwrap();
                assert!(kept.grads.host().is_none(), "kept on the device");
                let kept_loss = kept.loss;
                let kept = kept.grads.into_host().unwrap();
                let case = format!("{kernels:?} recompute={recompute} m={m}");
                assert_eq!(host.grads.len(), kept.len(), "{case}");
                assert_eq!(bits(&host.grads), bits(&kept), "{case}");
                assert_eq!(host.loss.to_bits(), kept_loss.to_bits(), "{case}");
            }
        }
    }
}
