//! The generator: masks agree with images, occlusion, determinism, presets.

use crate::tiny_config;
use osrt_dataset::generator::tracer::{Lighting, Material, Object, Shape, World, render};
use osrt_dataset::generator::{COLORS, GeneratorConfig};
use osrt_dataset::math::Vec3;
use osrt_dataset::{Camera, Intrinsics};
use osrt_dataset::{
    WriterOptions, generator::SplitSizes, generator::generate_dataset, generator::generate_scene,
};
use osrt_store::Location;

fn lighting() -> Lighting {
    Lighting {
        direction: Vec3::new(-0.4, -0.5, 0.77).normalized(),
        color: Vec3::new(1.0, 1.0, 1.0),
        ambient: 0.3,
        floor: Vec3::new(0.32, 0.32, 0.32),
        sky: Vec3::new(0.6, 0.65, 0.72),
    }
}

fn sphere(x: f64, y: f64, r: f64, color: Vec3) -> Object {
    Object {
        shape: Shape::Sphere,
        material: Material::Rubber,
        color,
        position: Vec3::new(x, y, 0.0),
        radius: r,
        yaw: 0.0,
    }
}

fn chroma(p: &[u8]) -> i32 {
    *p.iter().max().unwrap() as i32 - *p.iter().min().unwrap() as i32
}

#[test]
fn masks_agree_with_the_image() {
    let k = Intrinsics::from_fov(49.1f64.to_radians(), 48, 48);
    let cam = Camera::look_at(Vec3::new(7.5, -6.5, 5.3), Vec3::ZERO, k).unwrap();
    for (shape, yaw) in [
        (Shape::Sphere, 0.0),
        (Shape::Cube, 0.6),
        (Shape::Cylinder, 0.0),
    ] {
        let world = World {
            objects: vec![Object {
                shape,
                yaw,
                ..sphere(0.0, 0.0, 0.7, Vec3::new(0.8, 0.02, 0.02))
            }],
            lighting: lighting(),
        };
        let r = render(&world, &cam, 48, 48, 1);
        let object: Vec<usize> = (0..48 * 48).filter(|&i| r.mask[i] == 1).collect();
        assert!(
            object.len() > 30,
            "{shape:?}: {} object pixels",
            object.len()
        );
        // Object pixels are red; background pixels (floor, shadow, sky) are near grey.
        let red = object
            .iter()
            .filter(|&&i| {
                let p = &r.image[3 * i..3 * i + 3];
                p[0] as i32 > p[1] as i32 + 40 && p[0] as i32 > p[2] as i32 + 40
            })
            .count();
        assert!(
            red as f64 > 0.9 * object.len() as f64,
            "{shape:?}: {red} of {} red",
            object.len()
        );
        for i in (0..48 * 48).filter(|&i| r.mask[i] == 0) {
            let p = &r.image[3 * i..3 * i + 3];
            assert!(
                chroma(p) <= 30,
                "{shape:?}: background pixel {i} has colour {p:?}"
            );
        }
        // The object's projected centre is inside its mask.
        let (x, y) = cam.project(Vec3::new(0.0, 0.0, 0.7)).unwrap();
        assert_eq!(r.mask[y as usize * 48 + x as usize], 1);
    }
}

#[test]
fn masks_are_occlusion_correct() {
    let k = Intrinsics::from_fov(40f64.to_radians(), 33, 33);
    let cam = Camera::look_at(Vec3::new(0.0, -10.0, 0.5), Vec3::new(0.0, 0.0, 0.5), k).unwrap();
    let far = sphere(0.0, 2.0, 0.5, Vec3::new(0.0, 0.0, 0.8));
    let near = sphere(0.0, -2.0, 0.5, Vec3::new(0.8, 0.0, 0.0));
    // Object order must not matter: the nearer one owns the centre pixel either way.
    for (objects, near_id) in [(vec![far, near], 2), (vec![near, far], 1)] {
        let world = World {
            objects,
            lighting: lighting(),
        };
        let r = render(&world, &cam, 33, 33, 1);
        assert_eq!(r.mask[16 * 33 + 16], near_id);
    }
}

#[test]
fn generated_scenes_have_visible_labelled_objects() {
    let cfg = tiny_config(32);
    for i in 0..6 {
        let s = generate_scene(&cfg, 11, "train", i).unwrap();
        let objects = s.objects.as_ref().unwrap();
        assert!((3..=6).contains(&objects.len()));
        assert_eq!(s.views.len(), 3);
        for k in 1..=objects.len() as u8 {
            let px: usize = s
                .views
                .iter()
                .map(|v| v.mask.as_ref().unwrap().iter().filter(|&&m| m == k).count())
                .sum();
            assert!(px > 0, "scene {i}: object {k} invisible in every view");
        }
        for v in &s.views {
            assert!(
                v.mask
                    .as_ref()
                    .unwrap()
                    .iter()
                    .all(|&m| m as usize <= objects.len())
            );
        }
        // Colour check per object: the mean colour of its pixels is nearest its own
        // palette colour's hue class (ignoring grey, whose hue is undefined).
        for (k, o) in objects.iter().enumerate() {
            if o.color == "gray" || o.material == "metal" {
                continue;
            }
            let mut sum = [0f64; 3];
            let mut n = 0.0;
            for v in &s.views {
                for (p, &m) in v.mask.as_ref().unwrap().iter().enumerate() {
                    if m as usize == k + 1 {
                        for (c, acc) in sum.iter_mut().enumerate() {
                            *acc += v.image[3 * p + c] as f64;
                        }
                        n += 1.0;
                    }
                }
            }
            let mean = sum.map(|s| s / n);
            let dominant = (0..3).max_by(|&a, &b| mean[a].total_cmp(&mean[b])).unwrap();
            let palette = COLORS.iter().find(|(name, _)| *name == o.color).unwrap().1;
            let want = (0..3).max_by_key(|&c| palette[c]).unwrap();
            let tied = (0..3)
                .filter(|&c| palette[c] as i32 >= palette[want] as i32 - 10)
                .collect::<Vec<_>>();
            assert!(
                tied.contains(&dominant),
                "scene {i} object {k} ({}) mean {mean:?}",
                o.color
            );
        }
    }
}

#[test]
fn presets_have_their_shapes() {
    let hard = GeneratorConfig {
        image_size: 24,
        antialias: 1,
        ..GeneratorConfig::hard_lite()
    };
    let s = generate_scene(&hard, 1, "train", 0).unwrap();
    assert_eq!(s.views.len(), 10);
    assert!((8..=16).contains(&s.objects.unwrap().len()));
    // Hemisphere cameras vary in distance and elevation.
    let dists: Vec<f64> = s.views.iter().map(|v| v.camera.position().norm()).collect();
    assert!(
        dists.iter().cloned().fold(0.0, f64::max) - dists.iter().cloned().fold(f64::MAX, f64::min)
            > 0.5
    );
    let ood = GeneratorConfig {
        image_size: 24,
        antialias: 1,
        ..GeneratorConfig::ood()
    };
    let s = generate_scene(&ood, 1, "test", 0).unwrap();
    assert!((7..=10).contains(&s.objects.unwrap().len()));
    // clevr-lite cameras sit at fixed rotations 120° apart.
    let s = generate_scene(&crate::tiny_config(16), 1, "train", 0).unwrap();
    let az: Vec<f64> = s
        .views
        .iter()
        .map(|v| {
            (v.camera.position[1] as f64)
                .atan2(v.camera.position[0] as f64)
                .to_degrees()
        })
        .collect();
    let d1 = (az[1] - az[0]).rem_euclid(360.0);
    let d2 = (az[2] - az[1]).rem_euclid(360.0);
    assert!(
        (d1 - 120.0).abs() < 1e-3 && (d2 - 120.0).abs() < 1e-3,
        "{az:?}"
    );
    assert!(
        GeneratorConfig::preset("clevr-heavy")
            .unwrap_err()
            .to_string()
            .contains("unknown preset")
    );
}

async fn files(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for split in ["train", "val", "test"] {
        let mut names: Vec<_> = std::fs::read_dir(dir.join(split))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        names.sort();
        for p in names {
            out.push((
                p.display()
                    .to_string()
                    .replace(&dir.display().to_string(), ""),
                std::fs::read(&p).unwrap(),
            ));
        }
    }
    out.push((
        "manifest".into(),
        std::fs::read(dir.join("manifest.json")).unwrap(),
    ));
    out
}

#[tokio::test]
async fn same_seed_same_bytes_different_seed_different_bytes() {
    let cfg = tiny_config(16);
    let sizes = SplitSizes {
        train: 9,
        val: 3,
        test: 2,
    };
    let opts = WriterOptions {
        scenes_per_row_group: 4,
        row_groups_per_file: 2,
        ..Default::default()
    };
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    for (d, seed) in dirs.iter().zip([5, 5, 6]) {
        let loc = Location::parse(d.path().to_str().unwrap()).unwrap();
        generate_dataset(&loc, &cfg, seed, sizes, opts, false)
            .await
            .unwrap();
    }
    let a = files(dirs[0].path()).await;
    let b = files(dirs[1].path()).await;
    let c = files(dirs[2].path()).await;
    assert_eq!(a.len(), 2 + 1 + 1 + 1);
    assert!(a == b, "same seed must give identical files");
    let train = |f: &Vec<(String, Vec<u8>)>| {
        f.iter()
            .filter(|(n, _)| n.contains("train"))
            .map(|(_, b)| b.clone())
            .collect::<Vec<_>>()
    };
    assert_ne!(train(&a), train(&c), "another seed must give other scenes");
    // Scene content is independent of the split sizes (per-scene RNG streams).
    let s = generate_scene(&cfg, 5, "val", 2).unwrap();
    let r = osrt_dataset::SplitReader::open(
        Location::parse(dirs[0].path().join("val").to_str().unwrap()).unwrap(),
    )
    .await
    .unwrap();
    let all = r.read_all(osrt_dataset::Columns::ALL).await.unwrap();
    assert_eq!(all[2], s);
}
