//! The paper's variants as the trainer runs them. Up-OSRT's defining property: moving
//! every camera of a scene by one rigid motion changes neither its batch nor the model's
//! outputs. V-OSRT: the scene box comes from the dataset's manifest, and a training step
//! with it is deterministic and finite.

use candle_core::{Device, Tensor};
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::math::Vec3;
use osrt_dataset::{
    Batch, BatchConfig, InputSelection, Manifest, RayFrame, Scene, TargetViews, build_batch,
    generator::generate_scene,
};
use osrt_model::encoder::Poses;
use osrt_model::{Osrt, Params};
use osrt_trainer::{BatchTensors, JobConfig, Trainer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn scene() -> Scene {
    let cfg = GeneratorConfig {
        image_size: 16,
        antialias: 1,
        cameras: GeneratorConfig::clevr_lite().cameras.with_views(4),
        ..GeneratorConfig::clevr_lite()
    };
    generate_scene(&cfg, 3, "test", 0).unwrap()
}

/// The scene with every camera moved by `x ↦ M x + c`: a rotation of 40° about the axis
/// (1, 2, 3) and a shift — the same scene, elsewhere in the world.
fn moved(scene: &Scene) -> Scene {
    let a = Vec3::new(1.0, 2.0, 3.0).normalized();
    let (s, c) = 40f64.to_radians().sin_cos();
    let rotate = |v: Vec3| v * c + a.cross(v) * s + a * (a.dot(v) * (1.0 - c));
    let mut out = scene.clone();
    for v in &mut out.views {
        let cam = &mut v.camera;
        cam.position = (rotate(cam.position()) + Vec3::new(3.0, -1.0, 2.0)).to_f32();
        let cols: Vec<[f32; 3]> = (0..3).map(|j| rotate(cam.axis(j)).to_f32()).collect();
        for (j, col) in cols.iter().enumerate() {
            for (i, x) in col.iter().enumerate() {
                cam.rotation[i][j] = *x;
            }
        }
        cam.validate().unwrap();
    }
    out
}

fn batch(scene: &Scene, frame: RayFrame) -> Batch {
    let cfg = BatchConfig {
        input_views: 2,
        input_selection: InputSelection::First,
        target_views: TargetViews::NonInput,
        rays_per_scene: None,
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: frame,
        input_stride: 1,
    };
    build_batch(&[scene], &cfg, &mut ChaCha8Rng::seed_from_u64(0)).unwrap()
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Colours and slot weights of every target ray of `b`.
fn outputs(model: &Osrt, b: &Batch) -> Vec<f32> {
    let t = BatchTensors::new(b, &Device::Cpu).unwrap();
    let s = model
        .encode(&t.images, &t.origins, &t.directions, None)
        .unwrap();
    let out = model
        .decode(&s.slots, &t.target_origins, &t.target_directions)
        .unwrap();
    let flat = |x: &Tensor| x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    [flat(&out.rgb), flat(&out.weights.unwrap())].concat()
}

fn model(poses: Poses) -> Osrt {
    let mut cfg = JobConfig::preset("tiny").unwrap().model;
    cfg.encoder.poses = poses;
    Osrt::new(&cfg, Params::new(7).var_builder(&Device::Cpu)).unwrap()
}

#[test]
fn up_osrt_is_invariant_to_a_rigid_motion_of_the_whole_scene() {
    let (a, b) = (scene(), moved(&scene()));
    // The batches: rays in the first input camera's frame do not move.
    let (ba, bb) = (
        batch(&a, RayFrame::FirstInput),
        batch(&b, RayFrame::FirstInput),
    );
    assert!(max_diff(&ba.target_origins, &bb.target_origins) < 1e-4);
    assert!(max_diff(&ba.target_directions, &bb.target_directions) < 1e-5);
    assert_eq!(ba.input_images, bb.input_images);
    // The outputs: colours and slot weights of every target pixel.
    let up = model(Poses::Unposed);
    let d = max_diff(&outputs(&up, &ba), &outputs(&up, &bb));
    assert!(d < 1e-4, "Up-OSRT outputs moved by {d}");
    // The same motion does move a posed model's world-frame rays and outputs: the
    // comparison above can fail.
    let posed = model(Poses::Absolute);
    let (wa, wb) = (batch(&a, RayFrame::World), batch(&b, RayFrame::World));
    assert!(max_diff(&wa.target_origins, &wb.target_origins) > 0.5);
    let d = max_diff(&outputs(&posed, &wa), &outputs(&posed, &wb));
    assert!(d > 1e-3, "a posed model's outputs moved by only {d}");
}

#[test]
fn the_volumetric_box_comes_from_the_manifest() {
    let mut job = JobConfig::preset("tiny").unwrap();
    job.model = job.model.with_decoder("volumetric").unwrap();
    // A dataset that records no box (an import) is refused by name…
    let bare = Manifest::new([16, 16], [4, 4], [1, 2]);
    let e = job
        .clone()
        .resolve_scene_bounds(&bare, "imports/x")
        .unwrap_err();
    assert!(e.to_string().contains("model.decoder.bounds"), "{e}");
    assert!(e.to_string().contains("imports/x"), "{e}");
    // …a generated one derives it from its generator settings…
    let mut generated = bare.clone();
    generated.generator = Some(osrt_dataset::GeneratorInfo {
        preset: "clevr-lite".into(),
        seed: 0,
        settings: serde_json::to_value(GeneratorConfig::clevr_lite()).unwrap(),
    });
    let mut j = job.clone();
    j.resolve_scene_bounds(&generated, "data").unwrap();
    let osrt_model::decoder::Config::Volumetric(v) = &j.model.decoder else {
        unreachable!()
    };
    let b = GeneratorConfig::clevr_lite().scene_bounds();
    assert_eq!(v.bounds, Some(b));
    // …and every object of a generated scene lies inside it.
    for o in scene().objects.unwrap() {
        let (lo, hi) = (b[0], b[1]);
        assert!(lo[0] < o.position[0] && o.position[0] < hi[0], "{o:?}");
        assert!(lo[1] < o.position[1] && o.position[1] < hi[1], "{o:?}");
    }
    // Up-OSRT's relative rays and a world-frame box do not mix.
    j.model.encoder.poses = Poses::Unposed;
    assert!(j.validate().unwrap_err().to_string().contains("unposed"));
}

/// Training steps of both variants: finite, and the same bytes from the same seed.
#[test]
fn variant_steps_are_finite_and_deterministic() {
    for variant in ["unposed", "volumetric"] {
        let mut job = JobConfig::preset("tiny").unwrap();
        match variant {
            "unposed" => job.model.encoder.poses = Poses::Unposed,
            _ => {
                job.model = job.model.with_decoder("volumetric").unwrap();
                let osrt_model::decoder::Config::Volumetric(v) = &mut job.model.decoder else {
                    unreachable!()
                };
                v.bounds = Some(GeneratorConfig::clevr_lite().scene_bounds());
            }
        }
        let frame = osrt_trainer::ray_frame(&job.model);
        let cfg = BatchConfig {
            input_views: 1,
            input_selection: InputSelection::Random,
            target_views: TargetViews::All,
            rays_per_scene: Some(32),
            with_masks: false,
            salient_fraction: 0.0,
            ray_frame: frame,
            input_stride: 1,
        };
        let s = scene();
        let step = || {
            let mut t = Trainer::new(job.clone(), Device::Cpu).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            for _ in 0..3 {
                let b = build_batch(&[&s, &s], &cfg, &mut rng).unwrap();
                let g = t.gradients(&b, &mut rng).unwrap();
                assert!(g.loss.is_finite() && g.grads.iter().all(|x| x.is_finite()));
                t.apply(g.loss, g.grads).unwrap();
            }
            t.params.flatten().unwrap()
        };
        assert_eq!(step(), step(), "{variant}");
    }
}
