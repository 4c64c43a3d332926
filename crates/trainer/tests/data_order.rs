//! The scenes and rays of a step do not depend on how many workers share it: ranks of
//! 1, 2, 3 and 5 workers, each reading its share of a real Parquet split through its
//! own feed, together draw exactly the batches one worker draws, step after step —
//! through a step that straddles two shuffle windows and into the next epoch.

use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    Batch, BatchConfig, InputSelection, SplitReader, TargetViews, WriterOptions, build_batch_each,
    generator::SplitSizes, generator::generate_dataset,
};
use osrt_store::Location;
use osrt_trainer::feed::Feed;
use osrt_trainer::shard::{EpochPlan, scene_rng, share};
use rand::Rng;
use std::sync::Arc;

const BATCH: usize = 12;

/// What one rank's share of a step draws: its scenes, input pixels, target rays and
/// colours, and the next number of each scene's stream (from which the slot noise and
/// ray offsets are drawn).
#[derive(Debug, PartialEq)]
struct Draws {
    ids: Vec<u64>,
    inputs: Vec<f32>,
    origins: Vec<f32>,
    directions: Vec<f32>,
    rgb: Vec<f32>,
    pixels: Vec<(u32, u32)>,
    next: Vec<u64>,
}

impl Draws {
    fn join(parts: Vec<Draws>) -> Draws {
        let mut all = Draws {
            ids: vec![],
            inputs: vec![],
            origins: vec![],
            directions: vec![],
            rgb: vec![],
            pixels: vec![],
            next: vec![],
        };
        for p in parts {
            all.ids.extend(p.ids);
            all.inputs.extend(p.inputs);
            all.origins.extend(p.origins);
            all.directions.extend(p.directions);
            all.rgb.extend(p.rgb);
            all.pixels.extend(p.pixels);
            all.next.extend(p.next);
        }
        all
    }

    fn of(batch: Batch, next: Vec<u64>) -> Draws {
        Draws {
            ids: batch.scene_ids,
            inputs: batch.input_images,
            origins: batch.target_origins,
            directions: batch.target_directions,
            rgb: batch.target_rgb,
            pixels: batch.target_pixels,
            next,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_worker_count_draws_the_same_scenes_and_rays() {
    let dir = tempfile::tempdir().unwrap();
    let data = Location::parse(dir.path().to_str().unwrap()).unwrap();
    let gen_cfg = GeneratorConfig {
        image_size: 8,
        antialias: 1,
        ..GeneratorConfig::clevr_lite()
    };
    let sizes = SplitSizes {
        train: 1300,
        val: 1,
        test: 1,
    };
    let opts = WriterOptions {
        scenes_per_row_group: 13,
        row_groups_per_file: 8,
        ..Default::default()
    };
    generate_dataset(&data, &gen_cfg, 3, sizes, opts, false)
        .await
        .unwrap();
    let groups = Arc::new(
        SplitReader::open(data.join("train"))
            .await
            .unwrap()
            .row_groups()
            .await
            .unwrap(),
    );
    let cfg = BatchConfig {
        input_views: 2,
        input_selection: InputSelection::Random,
        target_views: TargetViews::All,
        rays_per_scene: Some(20),
        with_masks: false,
        salient_fraction: 0.25,
        ray_frame: Default::default(),
        input_stride: 1,
    };
    let seed = 11;
    let epochs: Vec<Arc<EpochPlan>> = (0..2)
        .map(|e| Arc::new(EpochPlan::new(&groups, seed, e, BATCH).unwrap()))
        .collect();
    let plan = &epochs[0];
    assert_eq!(plan.steps, 1300 / BATCH as u64);
    assert_eq!(plan.windows.len(), 2, "{:?}", plan.windows);
    let straddling = (0..plan.steps)
        .find(|&k| {
            let p = plan.positions(k, &(0..BATCH));
            plan.window_of(p.start) != plan.window_of(p.end - 1)
        })
        .expect("a step across the windows' boundary");

    // The steps checked: the first, both sides of the window boundary, the epoch's last,
    // and the first two of the next epoch (global step numbers).
    let steps = plan.steps;
    let checked = [
        0,
        1,
        straddling - 1,
        straddling,
        straddling + 1,
        steps - 1,
        steps,
        steps + 1,
    ];
    let mut reference: Vec<Draws> = Vec::new();
    for world in [1, 2, 3, 5] {
        let mut feeds: Vec<Vec<Feed>> = epochs
            .iter()
            .map(|p| {
                (0..world)
                    .map(|r| {
                        Feed::new(
                            data.clone(),
                            groups.clone(),
                            p.clone(),
                            share(BATCH, world, r),
                        )
                    })
                    .collect()
            })
            .collect();
        for (i, &step) in checked.iter().enumerate() {
            let (e, k) = ((step / steps) as usize, step % steps);
            let mut parts = Vec::new();
            for feed in feeds[e].iter_mut() {
                let scenes = feed.scenes(k).await.unwrap();
                let mut rngs: Vec<_> = scenes.iter().map(|s| scene_rng(seed, step, s.id)).collect();
                let batch = build_batch_each(&scenes, &cfg, &mut rngs).unwrap();
                let next = rngs.iter_mut().map(|r| r.random::<u64>()).collect();
                parts.push(Draws::of(batch, next));
            }
            let joined = Draws::join(parts);
            assert_eq!(joined.ids.len(), BATCH);
            if world == 1 {
                reference.push(joined);
            } else {
                assert!(
                    joined == reference[i],
                    "{world} workers, step {step}: other scenes or rays than 1 worker's"
                );
            }
        }
    }
    // The epochs take different scenes in a different order, every scene once each.
    assert_ne!(reference[0].ids, reference[6].ids);
    let mut ids: Vec<u64> = (0..steps)
        .flat_map(|k| plan.positions(k, &(0..BATCH)))
        .map(|p| plan.order[p])
        .map(|s| s.group as u64 * 13 + s.row)
        .collect();
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len() as u64, steps * BATCH as u64);
}
