//! `osrt render`: novel views of one scene along a camera path, with the slot segmentation
//! beside each frame, and scene editing (drop a slot, add one from another scene).

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use osrt_dataset::{Camera, Columns, Scene};
use osrt_model::{add_slot, drop_slot};
use osrt_store::Location;
use osrt_sweep::picture_files::{write_gif, write_png};
use osrt_trainer::pictures::{rgb_image, rgb8_image, segmentation_image, strip};
use osrt_trainer::render::{encode_scene, orbit, render_view, scene_camera};
use osrt_trainer::{LoadedRun, TestTime, device::DeviceSpec, load_run, load_run_on};
use serde_json::json;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Motion {
    /// A full circle about the scene at the first input camera's height and distance.
    Orbit,
    /// The dataset's own cameras of the scene (ground truth shown beside each frame).
    Views,
}

#[derive(Args)]
pub struct RenderArgs {
    /// Run folder or URL (its newest committed checkpoint renders).
    #[arg(long)]
    pub run: String,
    /// Scene id in the split.
    #[arg(long)]
    pub scene: u64,
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Dataset (default: the one the run trained on).
    #[arg(long)]
    pub data: Option<String>,
    #[arg(long, value_enum, default_value_t = Motion::Orbit)]
    pub motion: Motion,
    /// Frames along an orbit.
    #[arg(long, default_value_t = 24)]
    pub frames: usize,
    /// Rendered image size in pixels (default: the dataset's).
    #[arg(long)]
    pub size: Option<u32>,
    /// Nearest-neighbour upscaling of the written pictures.
    #[arg(long, default_value_t = 4)]
    pub scale: u32,
    /// Scene editing: render without slot K (0-based).
    #[arg(long)]
    pub drop_slot: Option<usize>,
    /// Scene editing: add slot K of scene SCENE (same split), as `SCENE:K`.
    #[arg(long, value_parser = parse_add_slot)]
    pub add_slot: Option<(u64, usize)>,
    /// Output folder (frame-NNN.png, render.gif, render.json).
    #[arg(long)]
    pub out: PathBuf,
    /// Where the model runs: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
}

fn parse_add_slot(s: &str) -> std::result::Result<(u64, usize), String> {
    let (scene, k) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected SCENE:K, e.g. 12:3"))?;
    Ok((
        scene
            .parse()
            .map_err(|_| format!("`{scene}` is not a scene id"))?,
        k.parse()
            .map_err(|_| format!("`{k}` is not a slot index"))?,
    ))
}

/// The first `limit` scenes (all if `None`) of `split`, with masks.
async fn load_scenes(data: &str, split: &str, limit: Option<usize>) -> Result<Vec<Scene>> {
    let loc = Location::parse(data)?;
    let columns = Columns {
        masks: true,
        objects: false,
    };
    osrt_dataset::load_split(&loc, split, columns, limit)
        .await
        .with_context(|| format!("reading {data}/{split}"))
}

/// Scenes `ids` of `split`, in the order asked; a missing id is an error naming the split's
/// id range.
async fn find_scenes(data: &str, split: &str, ids: &[u64]) -> Result<Vec<Scene>> {
    let scenes = load_scenes(data, split, None).await?;
    ids.iter()
        .map(|&id| {
            scenes
                .iter()
                .find(|s| s.id == id)
                .cloned()
                .with_context(|| {
                    let lo = scenes.iter().map(|s| s.id).min().unwrap_or(0);
                    let hi = scenes.iter().map(|s| s.id).max().unwrap_or(0);
                    format!(
                        "{data}/{split} has no scene {id} ({} scenes, ids {lo}..={hi})",
                        scenes.len()
                    )
                })
        })
        .collect()
}

/// What a render wrote.
pub struct Rendered {
    pub frames: Vec<PathBuf>,
    pub gif: PathBuf,
    /// Share of pixels each slot is assigned over all frames (unedited scene).
    pub slot_share: Option<Vec<f64>>,
}

/// Renders `scene` (and its edited version, if any) from `cameras` into `out`.
#[allow(clippy::too_many_arguments)]
fn render_frames(
    loaded: &LoadedRun,
    scene: &Scene,
    donor: Option<(&Scene, usize)>,
    drop: Option<usize>,
    cameras: &[(Camera, Option<&osrt_dataset::View>)],
    size: (u32, u32),
    scale: u32,
    out: &Path,
) -> Result<Rendered> {
    let model = &loaded.trainer.model;
    let (views, stride) = (loaded.job.train.input_views, loaded.job.train.input_stride);
    let seed = loaded.job.train.seed;
    let slots = encode_scene(model, scene, views, stride, seed)?;
    let k = slots.dim(1)?;
    let mut edited = None;
    if let Some(j) = drop {
        if j >= k {
            bail!("--drop-slot {j}: the model has {k} slots (0..{k})");
        }
        edited = Some(drop_slot(&slots, j)?);
    }
    if let Some((other, j)) = donor {
        if j >= k {
            bail!(
                "--add-slot {}:{j}: the model has {k} slots (0..{k})",
                other.id
            );
        }
        let theirs = encode_scene(model, other, views, stride, seed)?;
        edited = Some(add_slot(edited.as_ref().unwrap_or(&slots), &theirs, j)?);
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let bar = if std::io::stderr().is_terminal() {
        indicatif::ProgressBar::new(cameras.len() as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] frame {pos}/{len}",
            )
            .expect("a valid progress template"),
        )
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut pictures = Vec::new();
    let mut paths = Vec::new();
    let mut counts = vec![0u64; k];
    let mut has_labels = true;
    for (i, (camera, truth)) in cameras.iter().enumerate() {
        let mut panels = Vec::new();
        if let Some(v) = truth {
            panels.push(
                rgb8_image(v.width, v.height, v.image.clone())
                    .context("a dataset view's image does not match its size")?,
            );
        }
        for (s, tally) in [(Some(&slots), true), (edited.as_ref(), false)] {
            let Some(s) = s else { continue };
            let camera = scene_camera(model, scene, camera);
            let f = render_view(model, s, &camera, size.0, size.1)?;
            panels.push(rgb_image(f.width, f.height, &f.decoded.rgb));
            match &f.decoded.labels {
                Some(l) => {
                    if tally {
                        for &x in l {
                            counts[x as usize] += 1;
                        }
                    }
                    panels.push(segmentation_image(f.width, f.height, l));
                }
                None => has_labels = false,
            }
        }
        let picture = strip(&panels, scale);
        let path = out.join(format!("frame-{i:03}.png"));
        write_png(&path, &picture)?;
        paths.push(path);
        pictures.push(picture);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let gif = out.join("render.gif");
    write_gif(&gif, &pictures, 120)?;
    let total: u64 = counts.iter().sum();
    let slot_share = (has_labels && total > 0)
        .then(|| counts.iter().map(|&c| c as f64 / total as f64).collect());
    Ok(Rendered {
        frames: paths,
        gif,
        slot_share,
    })
}

/// `camera` of a `from`-sized view with its intrinsics rescaled to render at `to`.
fn rescaled(mut camera: Camera, from: (u32, u32), to: (u32, u32)) -> Camera {
    let sx = to.0 as f32 / from.0 as f32;
    let sy = to.1 as f32 / from.1 as f32;
    camera.intrinsics.fx *= sx;
    camera.intrinsics.cx *= sx;
    camera.intrinsics.fy *= sy;
    camera.intrinsics.cy *= sy;
    camera
}

pub async fn render(a: RenderArgs) -> Result<()> {
    if a.motion == Motion::Orbit && a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let loaded = load_run_on(&a.run, &TestTime::default(), a.device)
        .await
        .with_context(|| format!("loading run {}", a.run))?;
    let data = a.data.clone().unwrap_or_else(|| loaded.info.data.clone());
    let mut ids = vec![a.scene];
    if let Some((other, _)) = a.add_slot {
        ids.push(other);
    }
    let scenes = find_scenes(&data, &a.split, &ids).await?;
    let scene = &scenes[0];
    let first = &scene.views[0];
    let size = a.size.map_or((first.width, first.height), |s| (s, s));
    let cameras: Vec<(Camera, Option<&osrt_dataset::View>)> = match a.motion {
        Motion::Orbit => orbit(&first.camera, a.frames)?
            .into_iter()
            .map(|c| (c, None))
            .collect(),
        // Ground truth only fits beside the frame at the dataset's own size.
        Motion::Views => scene
            .views
            .iter()
            .map(|v| (v.camera, (size == (v.width, v.height)).then_some(v)))
            .collect(),
    };
    let cameras: Vec<_> = cameras
        .into_iter()
        .map(|(c, v)| (rescaled(c, (first.width, first.height), size), v))
        .collect();
    let donor = a.add_slot.map(|(_, k)| (&scenes[1], k));
    // With the run's kernels (`train.kernels`), as its evaluations were.
    let r = osrt_kernels::with_kernels(loaded.job.train.kernels, || {
        render_frames(
            &loaded,
            scene,
            donor,
            a.drop_slot,
            &cameras,
            size,
            a.scale,
            &a.out,
        )
    })?;
    let layout = {
        let mut p = Vec::new();
        if a.motion == Motion::Views && cameras.iter().all(|c| c.1.is_some()) {
            p.push("ground truth");
        }
        p.extend(["render", "slots"]);
        if a.drop_slot.is_some() || a.add_slot.is_some() {
            p.extend(["edited render", "edited slots"]);
        }
        p
    };
    let meta = json!({
        "run": a.run,
        "checkpoint_step": loaded.step,
        "data": data,
        "split": a.split,
        "scene": a.scene,
        "motion": format!("{:?}", a.motion).to_lowercase(),
        "size": [size.0, size.1],
        "drop_slot": a.drop_slot,
        "add_slot": a.add_slot.map(|(s, k)| json!({"scene": s, "slot": k})),
        "panels": layout,
        "frames": r.frames.iter().map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned())).collect::<Vec<_>>(),
        "slot_pixel_share": r.slot_share,
    });
    let meta_path = a.out.join("render.json");
    std::fs::write(&meta_path, serde_json::to_string_pretty(&meta)?)
        .with_context(|| format!("writing {}", meta_path.display()))?;
    println!(
        "{} frames ({}) in {}; animation {}",
        r.frames.len(),
        layout.join(" | "),
        a.out.display(),
        r.gif.display()
    );
    if let Some(share) = &r.slot_share {
        let s: Vec<String> = share
            .iter()
            .enumerate()
            .map(|(k, f)| format!("{k}: {:.0}%", 100.0 * f))
            .collect();
        println!("pixels per slot: {}", s.join(", "));
    }
    Ok(())
}

/// A strip of the run's renders of `scene`'s dataset views (truth | render | slots per
/// view, one row per view stacked into one picture) for reports; returns its path.
/// `data` defaults to the dataset the run trained on.
pub async fn report_strip(
    run: &str,
    data: Option<&str>,
    split: &str,
    out: &Path,
) -> Result<PathBuf> {
    let loaded = load_run(run).await?;
    let data = data.unwrap_or(&loaded.info.data);
    let scenes = load_scenes(data, split, Some(1)).await?;
    let scene = scenes
        .first()
        .with_context(|| format!("{data}/{split} has no scenes"))?;
    let model = &loaded.trainer.model;
    let slots = encode_scene(
        model,
        scene,
        loaded.job.train.input_views,
        loaded.job.train.input_stride,
        loaded.job.train.seed,
    )?;
    let mut panels = Vec::new();
    for v in &scene.views {
        panels.push(
            rgb8_image(v.width, v.height, v.image.clone())
                .context("a dataset view's image does not match its size")?,
        );
        let camera = scene_camera(model, scene, &v.camera);
        let f = render_view(model, &slots, &camera, v.width, v.height)?;
        panels.push(rgb_image(f.width, f.height, &f.decoded.rgb));
        if let Some(l) = &f.decoded.labels {
            panels.push(segmentation_image(f.width, f.height, l));
        }
    }
    let path = out.to_path_buf();
    write_png(&path, &strip(&panels, 3))?;
    Ok(path)
}
