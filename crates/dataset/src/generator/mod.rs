//! The built-in scene generator: procedural CLEVR-like scenes (spheres, cubes, cylinders;
//! 8 colours, 2 sizes, 2 materials) on a floor under a light with shadows, rendered by
//! [`tracer`] with instance masks and cameras, and written as a dataset.
//!
//! Determinism: scene `i` of split `s` draws from its own ChaCha RNG seeded by
//! `(seed, s, i)`, so the bytes do not depend on thread count, chunking or the other
//! splits' sizes; scenes are written in index order.

pub mod tracer;

use crate::camera::{Camera, Intrinsics};
use crate::error::{DatasetError, Result};
use crate::manifest::{GeneratorInfo, Manifest};
use crate::math::Vec3;
use crate::scene::{ObjectMeta, Scene, View};
use crate::writer::{SplitWriter, WriterOptions};
use indicatif::{ProgressBar, ProgressStyle};
use osrt_store::Location;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use tracer::{Lighting, Material, Object, Shape, World};

/// CLEVR's eight colours (sRGB as in CLEVR's `properties.json`).
pub const COLORS: [(&str, [u8; 3]); 8] = [
    ("gray", [87, 87, 87]),
    ("red", [173, 35, 35]),
    ("blue", [42, 75, 215]),
    ("green", [29, 105, 20]),
    ("brown", [129, 74, 25]),
    ("purple", [129, 38, 192]),
    ("cyan", [41, 208, 208]),
    ("yellow", [255, 238, 51]),
];
pub const SIZES: [(&str, f64); 2] = [("large", 0.7), ("small", 0.35)];
pub const SHAPES: [(&str, Shape); 3] = [
    ("sphere", Shape::Sphere),
    ("cube", Shape::Cube),
    ("cylinder", Shape::Cylinder),
];
pub const MATERIALS: [(&str, Material); 2] =
    [("rubber", Material::Rubber), ("metal", Material::Metal)];

/// Where the cameras of a scene are.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CameraRig {
    /// CLEVR-3D: the original CLEVR camera rotated about the vertical axis by fixed angles.
    Fixed {
        azimuths_deg: Vec<f64>,
        /// Azimuth of the first view (CLEVR's camera sits at about −41°).
        base_azimuth_deg: f64,
        horizontal_distance: f64,
        height: f64,
    },
    /// Cameras drawn on a hemisphere, looking at a jittered point near the origin.
    Hemisphere {
        views: usize,
        distance: [f64; 2],
        elevation_deg: [f64; 2],
        target_jitter: f64,
    },
}

impl CameraRig {
    /// The same rig with `n` cameras: fixed rigs spread them evenly in azimuth (so 3 gives
    /// CLEVR-3D's 0°, 120°, 240°), hemisphere rigs draw `n`.
    pub fn with_views(self, n: usize) -> Self {
        match self {
            CameraRig::Fixed {
                base_azimuth_deg,
                horizontal_distance,
                height,
                ..
            } => CameraRig::Fixed {
                azimuths_deg: (0..n).map(|i| 360.0 * i as f64 / n as f64).collect(),
                base_azimuth_deg,
                horizontal_distance,
                height,
            },
            CameraRig::Hemisphere {
                distance,
                elevation_deg,
                target_jitter,
                ..
            } => CameraRig::Hemisphere {
                views: n,
                distance,
                elevation_deg,
                target_jitter,
            },
        }
    }

    fn num_views(&self) -> usize {
        match self {
            CameraRig::Fixed { azimuths_deg, .. } => azimuths_deg.len(),
            CameraRig::Hemisphere { views, .. } => *views,
        }
    }
}

/// Everything that defines a generated dataset besides its seed and split sizes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GeneratorConfig {
    pub preset: String,
    pub image_size: u32,
    /// Inclusive range of objects per scene.
    pub objects: [u32; 2],
    pub cameras: CameraRig,
    pub fov_deg: f64,
    /// Objects are placed with footprint centres in `[-extent, extent]²`.
    pub extent: f64,
    /// Minimum gap between object footprints.
    pub min_gap: f64,
    /// Every object must cover at least this many mask pixels in some view (scaled from
    /// 64×64); a layout that hides an object is redrawn.
    pub min_visible_pixels: u32,
    /// Supersampling per side (1 = off).
    pub antialias: u32,
    pub vary_floor: bool,
    pub vary_light: bool,
}

impl GeneratorConfig {
    /// The CLEVR camera's field of view: focal 35 mm on a 32 mm sensor.
    const CLEVR_FOV_DEG: f64 = 49.1;

    /// 3–6 objects, 3 views at CLEVR-3D's fixed rotations (0°, 120°, 240°), 64×64.
    pub fn clevr_lite() -> Self {
        Self {
            preset: "clevr-lite".into(),
            image_size: 64,
            objects: [3, 6],
            cameras: CameraRig::Fixed {
                azimuths_deg: vec![0.0, 120.0, 240.0],
                base_azimuth_deg: -41.0,
                horizontal_distance: 9.9,
                height: 5.35,
            },
            fov_deg: Self::CLEVR_FOV_DEG,
            extent: 3.0,
            min_gap: 0.15,
            min_visible_pixels: 6,
            antialias: 2,
            vary_floor: false,
            vary_light: false,
        }
    }

    /// 8–16 objects, 10 views on a hemisphere at varying distance and elevation, varied
    /// floor colour and light.
    pub fn hard_lite() -> Self {
        Self {
            preset: "hard-lite".into(),
            image_size: 64,
            objects: [8, 16],
            cameras: CameraRig::Hemisphere {
                views: 10,
                distance: [9.0, 14.0],
                elevation_deg: [20.0, 65.0],
                target_jitter: 0.5,
            },
            fov_deg: 55.0,
            extent: 3.6,
            min_gap: 0.1,
            min_visible_pixels: 4,
            antialias: 2,
            vary_floor: true,
            vary_light: true,
        }
    }

    /// Like `clevr-lite` with 7–10 objects: an out-of-distribution test set.
    pub fn ood() -> Self {
        Self {
            preset: "ood".into(),
            objects: [7, 10],
            extent: 3.4,
            ..Self::clevr_lite()
        }
    }

    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "clevr-lite" => Ok(Self::clevr_lite()),
            "hard-lite" => Ok(Self::hard_lite()),
            "ood" => Ok(Self::ood()),
            other => Err(DatasetError::Generator(format!(
                "unknown preset `{other}`: expected one of {}",
                Self::PRESETS.join(", ")
            ))),
        }
    }

    pub const PRESETS: [&'static str; 3] = ["clevr-lite", "hard-lite", "ood"];

    /// The box every object of a scene lies in, with the floor under it: footprints reach
    /// `extent` plus the largest object's reach (a cube's corner, `r·√2`), objects stand
    /// up to `2r` tall, and a 0.25 slab below `z = 0` holds the floor's surface.
    pub fn scene_bounds(&self) -> [[f32; 3]; 2] {
        let r = SIZES.iter().map(|s| s.1).fold(0.0, f64::max);
        let xy = (self.extent + r * std::f64::consts::SQRT_2) as f32;
        [[-xy, -xy, -0.25], [xy, xy, (2.0 * r + 0.1) as f32]]
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(DatasetError::Generator(m));
        if self.image_size == 0 || self.image_size > 4096 {
            return bad(format!("image size {} outside 1..=4096", self.image_size));
        }
        if self.objects[0] > self.objects[1] || self.objects[1] > 254 {
            return bad(format!(
                "objects range {:?} must be ordered and ≤ 254",
                self.objects
            ));
        }
        if self.cameras.num_views() == 0 {
            return bad("a scene needs at least one camera".into());
        }
        if !(self.fov_deg > 1.0 && self.fov_deg < 170.0) {
            return bad(format!(
                "field of view {}° outside (1°, 170°)",
                self.fov_deg
            ));
        }
        Ok(())
    }
}

/// Scenes per split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitSizes {
    pub train: u64,
    pub val: u64,
    pub test: u64,
}

impl SplitSizes {
    pub fn iter(&self) -> impl Iterator<Item = (&'static str, u64)> {
        [
            ("train", self.train),
            ("val", self.val),
            ("test", self.test),
        ]
        .into_iter()
    }
}

/// SplitMix64: decorrelates the (seed, split, index) triple into one RNG seed.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The RNG of scene `index` in `split`.
pub fn scene_rng(seed: u64, split: &str, index: u64) -> ChaCha8Rng {
    let tag = split.bytes().fold(0u64, |h, b| mix(h ^ b as u64));
    ChaCha8Rng::seed_from_u64(mix(mix(seed) ^ tag).wrapping_add(mix(index)))
}

fn srgb_to_linear(c: [u8; 3]) -> Vec3 {
    let f = |v: u8| (v as f64 / 255.0).powf(2.2);
    Vec3::new(f(c[0]), f(c[1]), f(c[2]))
}

fn cameras(cfg: &GeneratorConfig, rng: &mut ChaCha8Rng) -> Result<Vec<Camera>> {
    let k = Intrinsics::from_fov(cfg.fov_deg.to_radians(), cfg.image_size, cfg.image_size);
    let mut out = Vec::new();
    match &cfg.cameras {
        CameraRig::Fixed {
            azimuths_deg,
            base_azimuth_deg,
            horizontal_distance,
            height,
        } => {
            for a in azimuths_deg {
                let az = (base_azimuth_deg + a).to_radians();
                let pos = Vec3::new(
                    horizontal_distance * az.cos(),
                    horizontal_distance * az.sin(),
                    *height,
                );
                out.push(Camera::look_at(pos, Vec3::ZERO, k).map_err(DatasetError::Generator)?);
            }
        }
        CameraRig::Hemisphere {
            views,
            distance,
            elevation_deg,
            target_jitter,
        } => {
            for _ in 0..*views {
                let az = rng.random_range(0.0..2.0 * PI);
                let el = rng
                    .random_range(elevation_deg[0]..=elevation_deg[1])
                    .to_radians();
                let r = rng.random_range(distance[0]..=distance[1]);
                let pos = Vec3::new(
                    r * el.cos() * az.cos(),
                    r * el.cos() * az.sin(),
                    r * el.sin(),
                );
                let target = Vec3::new(
                    rng.random_range(-target_jitter..=*target_jitter),
                    rng.random_range(-target_jitter..=*target_jitter),
                    0.0,
                );
                out.push(Camera::look_at(pos, target, k).map_err(DatasetError::Generator)?);
            }
        }
    }
    Ok(out)
}

fn lighting(cfg: &GeneratorConfig, rng: &mut ChaCha8Rng) -> Lighting {
    let (az, el): (f64, f64) = if cfg.vary_light {
        (
            rng.random_range(0.0..2.0 * PI),
            rng.random_range(35f64..75.0).to_radians(),
        )
    } else {
        (-2.3, 55f64.to_radians())
    };
    let color = if cfg.vary_light {
        Vec3::new(
            rng.random_range(0.85..=1.0),
            rng.random_range(0.85..=1.0),
            rng.random_range(0.85..=1.0),
        )
    } else {
        Vec3::new(1.0, 1.0, 1.0)
    };
    let floor = if cfg.vary_floor {
        let g = rng.random_range(0.15..0.55);
        Vec3::new(
            g * rng.random_range(0.7..=1.3),
            g * rng.random_range(0.7..=1.3),
            g * rng.random_range(0.7..=1.3),
        )
    } else {
        Vec3::new(0.32, 0.32, 0.32)
    };
    Lighting {
        direction: Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()),
        color,
        ambient: 0.3,
        floor,
        sky: Vec3::new(0.6, 0.65, 0.72),
    }
}

/// Draws a non-overlapping layout of `n` objects; `None` when it does not fit.
fn layout(
    cfg: &GeneratorConfig,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> Option<(Vec<Object>, Vec<ObjectMeta>)> {
    let mut objects: Vec<Object> = Vec::with_capacity(n);
    let mut meta = Vec::with_capacity(n);
    for _ in 0..n {
        let (shape_name, shape) = SHAPES[rng.random_range(0..SHAPES.len())];
        let (size_name, radius) = SIZES[rng.random_range(0..SIZES.len())];
        let (color_name, rgb) = COLORS[rng.random_range(0..COLORS.len())];
        let (material_name, material) = MATERIALS[rng.random_range(0..MATERIALS.len())];
        let yaw = rng.random_range(0.0..2.0 * PI);
        // Footprint radius: cubes reach out to their corners.
        let reach = |s: Shape, r: f64| {
            if s == Shape::Cube {
                r * std::f64::consts::SQRT_2
            } else {
                r
            }
        };
        let mut placed = None;
        for _ in 0..100 {
            let x = rng.random_range(-cfg.extent..=cfg.extent);
            let y = rng.random_range(-cfg.extent..=cfg.extent);
            let ok = objects.iter().all(|o| {
                let dx = o.position.x - x;
                let dy = o.position.y - y;
                (dx * dx + dy * dy).sqrt()
                    >= reach(o.shape, o.radius) + reach(shape, radius) + cfg.min_gap
            });
            if ok {
                placed = Some((x, y));
                break;
            }
        }
        let (x, y) = placed?;
        objects.push(Object {
            shape,
            material,
            color: srgb_to_linear(rgb),
            position: Vec3::new(x, y, 0.0),
            radius,
            yaw,
        });
        meta.push(ObjectMeta {
            shape: shape_name.into(),
            color: color_name.into(),
            size: size_name.into(),
            material: material_name.into(),
            position: [x as f32, y as f32, 0.0],
            yaw: yaw as f32,
        });
    }
    Some((objects, meta))
}

/// Generates scene `index` of `split`. Pure: depends only on its arguments.
pub fn generate_scene(cfg: &GeneratorConfig, seed: u64, split: &str, index: u64) -> Result<Scene> {
    let mut rng = scene_rng(seed, split, index);
    let n = rng.random_range(cfg.objects[0]..=cfg.objects[1]) as usize;
    let cams = cameras(cfg, &mut rng)?;
    let light = lighting(cfg, &mut rng);
    let size = cfg.image_size;
    // Visibility threshold scales with image area (the configured value is for 64×64).
    let min_px = ((cfg.min_visible_pixels as f64) * (size as f64 / 64.0).powi(2))
        .ceil()
        .max(1.0) as usize;
    for _attempt in 0..200 {
        let Some((objects, meta)) = layout(cfg, n, &mut rng) else {
            continue;
        };
        let world = World {
            objects,
            lighting: light,
        };
        // Check visibility on masks first (cheap), render colour only for accepted layouts.
        let masks: Vec<Vec<u8>> = cams
            .iter()
            .map(|c| {
                let mut m = Vec::with_capacity((size * size) as usize);
                for v in 0..size {
                    for u in 0..size {
                        m.push(world.instance(c.position(), c.pixel_direction(u, v)));
                    }
                }
                m
            })
            .collect();
        let visible = (1..=n).all(|k| {
            masks
                .iter()
                .any(|m| m.iter().filter(|&&id| id as usize == k).count() >= min_px)
        });
        if !visible {
            continue;
        }
        let views = cams
            .iter()
            .map(|c| {
                let r = tracer::render(&world, c, size, size, cfg.antialias);
                View {
                    width: size,
                    height: size,
                    image: r.image,
                    mask: Some(r.mask),
                    camera: *c,
                }
            })
            .collect();
        return Ok(Scene {
            id: index,
            views,
            objects: Some(meta),
        });
    }
    Err(DatasetError::Generator(format!(
        "split {split}, scene {index}: no layout of {n} objects with every object visible \
         in 200 attempts (extent {} too small?)",
        cfg.extent
    )))
}

/// A bar of `total` `unit` with their rate and the time left (hidden when `shown` is
/// false): dataset generation and imports.
pub fn progress_bar(total: u64, shown: bool, unit: &str) -> ProgressBar {
    if !shown {
        return ProgressBar::hidden();
    }
    let b = ProgressBar::new(total);
    b.set_style(
        ProgressStyle::with_template(&format!(
            "{{msg:>6}} [{{bar:30}}] {{pos}}/{{len}} {unit} {{per_sec}} ETA {{eta}}"
        ))
        .expect("valid template")
        .progress_chars("=> "),
    );
    b
}

/// Generates all splits into `dataset` and writes `manifest.json` last, so a dataset with
/// a manifest is complete. Parallel over scenes (rayon), with a progress bar.
pub async fn generate_dataset(
    dataset: &Location,
    cfg: &GeneratorConfig,
    seed: u64,
    sizes: SplitSizes,
    opts: WriterOptions,
    progress: bool,
) -> Result<Manifest> {
    cfg.validate()?;
    let total: u64 = sizes.iter().map(|(_, n)| n).sum();
    let bar = progress_bar(total, progress, "scenes");
    let views = cfg.cameras.num_views() as u32;
    let mut manifest =
        Manifest::new([cfg.image_size; 2], [views, views], cfg.objects).with_codec(opts.codec);
    manifest.scene_bounds = Some(cfg.scene_bounds());
    manifest.generator = Some(GeneratorInfo {
        preset: cfg.preset.clone(),
        seed,
        settings: serde_json::to_value(cfg).expect("config serialises"),
    });
    // Chunks of whole row groups bound memory while keeping both cores busy.
    let chunk = (opts.scenes_per_row_group * 4).max(1) as u64;
    for (split, n) in sizes.iter() {
        bar.set_message(split);
        let mut writer = SplitWriter::new(dataset.join(split), opts);
        let mut start = 0;
        while start < n {
            let end = (start + chunk).min(n);
            let (cfg2, bar2) = (cfg.clone(), bar.clone());
            let scenes = tokio::task::spawn_blocking(move || {
                (start..end)
                    .into_par_iter()
                    .map(|i| {
                        let s = generate_scene(&cfg2, seed, split, i);
                        bar2.inc(1);
                        s
                    })
                    .collect::<Result<Vec<_>>>()
            })
            .await
            .map_err(|e| DatasetError::Generator(format!("generator task failed: {e}")))??;
            writer.push(scenes).await?;
            start = end;
        }
        let info = writer.finish().await?;
        manifest.splits.insert(split.to_string(), info);
    }
    bar.finish_and_clear();
    manifest.write(dataset).await?;
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn with_views_spreads_fixed_cameras_and_keeps_clevr_3d_at_three() {
        let rig = GeneratorConfig::clevr_lite().cameras;
        assert_eq!(rig.clone().with_views(3), rig);
        let CameraRig::Fixed { azimuths_deg, .. } = rig.with_views(6) else {
            panic!("still a fixed rig")
        };
        assert_eq!(azimuths_deg, vec![0.0, 60.0, 120.0, 180.0, 240.0, 300.0]);
        assert_eq!(
            GeneratorConfig::hard_lite()
                .cameras
                .with_views(4)
                .num_views(),
            4
        );
    }
}
