//! Write/read round trips, projection, row groups.

use crate::tiny_scenes;
use osrt_dataset::{Columns, ReadStats, RowGroupRef, SplitReader, SplitWriter, WriterOptions};
use osrt_store::Location;
use std::sync::Arc;

async fn write(
    loc: &Location,
    scenes: Vec<osrt_dataset::Scene>,
    per_rg: usize,
    rg_per_file: usize,
) {
    let mut w = SplitWriter::new(
        loc.clone(),
        WriterOptions {
            scenes_per_row_group: per_rg,
            row_groups_per_file: rg_per_file,
            ..Default::default()
        },
    );
    w.push(scenes).await.unwrap();
    w.finish().await.unwrap();
}

#[tokio::test]
async fn round_trip_in_memory() {
    let scenes = tiny_scenes(5, 16);
    let loc = Location::parse("memory://io-roundtrip/train").unwrap();
    write(&loc, scenes.clone(), 2, 8).await;
    let back = SplitReader::open(loc)
        .await
        .unwrap()
        .read_all(Columns::ALL)
        .await
        .unwrap();
    assert_eq!(back, scenes);
}

#[tokio::test]
async fn round_trip_on_local_files() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = tiny_scenes(4, 12);
    let loc = Location::parse(dir.path().join("val").to_str().unwrap()).unwrap();
    write(&loc, scenes.clone(), 3, 8).await;
    assert!(dir.path().join("val/part-00000.parquet").is_file());
    let url = format!("file://{}", dir.path().join("val").display());
    let back = SplitReader::open(Location::parse(&url).unwrap())
        .await
        .unwrap()
        .read_all(Columns::ALL)
        .await
        .unwrap();
    assert_eq!(back, scenes);
}

#[tokio::test]
async fn row_groups_are_listed_and_read_one_at_a_time() {
    let scenes = tiny_scenes(10, 8);
    let loc = Location::parse("memory://io-rowgroups/train").unwrap();
    write(&loc, scenes.clone(), 3, 2).await;
    let r = SplitReader::open(loc).await.unwrap();
    let names: Vec<_> = r.files().iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["part-00000.parquet", "part-00001.parquet"]);
    let rgs = r.row_groups().await.unwrap();
    let rg = |file: &str, index, num_rows| RowGroupRef {
        file: file.into(),
        index,
        num_rows,
    };
    assert_eq!(
        rgs,
        vec![
            rg("part-00000.parquet", 0, 3),
            rg("part-00000.parquet", 1, 3),
            rg("part-00001.parquet", 0, 3),
            rg("part-00001.parquet", 1, 1),
        ]
    );
    let last = r.read_row_group(&rgs[3], Columns::ALL).await.unwrap();
    assert_eq!(last, vec![scenes[9].clone()]);
    let third = r.read_row_group(&rgs[2], Columns::ALL).await.unwrap();
    assert_eq!(third, scenes[6..9].to_vec());
    let err = r
        .read_row_group(&rg("part-00001.parquet", 5, 1), Columns::ALL)
        .await
        .unwrap_err();
    assert!(
        err.to_string()
            .contains("row group 5 requested, the file has 2"),
        "{err}"
    );
    // A listing that no longer matches the file (replaced since it was listed) is an
    // error naming the file, not a short shard.
    let err = r
        .read_row_group(&rg("part-00001.parquet", 1, 4), Columns::ALL)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("part-00001.parquet") && err.contains("listed with 4 scenes, 1 decoded"),
        "{err}"
    );
}

/// A rank reads only its rows of a shared row group: the selected scenes, in row order,
/// exactly as the whole group's read gives them.
#[tokio::test]
async fn selected_rows_of_a_row_group_are_read_alone() {
    let scenes = tiny_scenes(12, 8);
    let loc = Location::parse("memory://io-rows/train").unwrap();
    write(&loc, scenes.clone(), 6, 2).await;
    let r = SplitReader::open(loc).await.unwrap();
    let rgs = r.row_groups().await.unwrap();
    for rows in [vec![0u64], vec![1, 2, 5], vec![0, 1, 2, 3, 4, 5], vec![5]] {
        let got = r.read_rows(&rgs[1], &rows, Columns::ALL).await.unwrap();
        let want: Vec<_> = rows
            .iter()
            .map(|&i| scenes[6 + i as usize].clone())
            .collect();
        assert_eq!(got, want, "rows {rows:?}");
    }
    for bad in [vec![2u64, 1], vec![3, 3], vec![6]] {
        let err = r
            .read_rows(&rgs[0], &bad, Columns::ALL)
            .await
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("part-00000.parquet")
                && err.contains("must increase and lie below its 6 rows"),
            "{bad:?}: {err}"
        );
    }
}

#[tokio::test]
async fn projection_skips_mask_and_object_bytes() {
    let scenes = tiny_scenes(8, 32);
    let loc = Location::parse("memory://io-projection/train").unwrap();
    write(&loc, scenes.clone(), 8, 1).await;
    let r = SplitReader::open(loc.clone()).await.unwrap();
    let rg = &r.row_groups().await.unwrap()[0];

    let read = |cols| {
        let r = r.clone();
        let rg = rg.clone();
        async move {
            let stats = Arc::new(ReadStats::default());
            let s = r
                .read_row_group_with_stats(&rg, cols, stats.clone())
                .await
                .unwrap();
            (s, stats.bytes())
        }
    };
    let (with, bytes_with) = read(Columns::ALL).await;
    let (without, bytes_without) = read(Columns::TRAIN).await;
    assert!(
        with.iter()
            .all(|s| s.views.iter().all(|v| v.mask.is_some()))
    );
    assert!(with.iter().all(|s| s.objects.is_some()));
    assert!(
        without
            .iter()
            .all(|s| s.views.iter().all(|v| v.mask.is_none()))
    );
    assert!(without.iter().all(|s| s.objects.is_none()));
    for (a, b) in with.iter().zip(&without) {
        assert_eq!(a.views.len(), b.views.len());
        assert_eq!(a.views[0].image, b.views[0].image);
        assert_eq!(a.views[0].camera, b.views[0].camera);
    }

    // The bytes saved must be at least the compressed size of the mask column chunk.
    let file = object_store::ObjectStoreExt::get(&*loc.store, &loc.path("part-00000.parquet"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let meta = parquet::file::serialized_reader::SerializedFileReader::new(file).unwrap();
    let md = parquet::file::reader::FileReader::metadata(&meta);
    let mask_bytes: i64 = md
        .row_group(0)
        .columns()
        .iter()
        .filter(|c| c.column_path().string().ends_with("mask"))
        .map(|c| c.compressed_size())
        .sum();
    assert!(mask_bytes > 0);
    assert!(
        bytes_with - bytes_without >= mask_bytes as u64,
        "with masks {bytes_with} B, without {bytes_without} B, mask column {mask_bytes} B"
    );
}

#[tokio::test]
async fn rays_and_batches_from_read_scenes() {
    use osrt_dataset::{BatchConfig, InputSelection, TargetViews, build_batch};
    use rand::SeedableRng;
    let scenes = tiny_scenes(3, 8);
    let refs: Vec<_> = scenes.iter().collect();
    let cfg = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::Random,
        target_views: TargetViews::All,
        rays_per_scene: Some(50),
        with_masks: true,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let b = build_batch(&refs, &cfg, &mut rng).unwrap();
    assert_eq!(b.input_images.len(), 3 * 8 * 8 * 3);
    assert_eq!(b.target_rgb.len(), 3 * 50 * 3);
    assert_eq!(b.target_masks.as_ref().unwrap().len(), 150);
    // Sampled rays are distinct pixels and their colours are the stored pixels.
    for (s, scene) in scenes.iter().enumerate() {
        let px = &b.target_pixels[s * 50..(s + 1) * 50];
        let mut uniq = px.to_vec();
        uniq.sort();
        uniq.dedup();
        assert_eq!(uniq.len(), 50);
        for (k, &(v, p)) in px.iter().enumerate() {
            let view = &scene.views[v as usize];
            let want = view.image[3 * p as usize] as f32 / 255.0;
            assert_eq!(b.target_rgb[(s * 50 + k) * 3], want);
        }
    }
    // Same seed → same batch; another seed → another sample.
    let mut rng2 = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    assert_eq!(build_batch(&refs, &cfg, &mut rng2).unwrap(), b);
    let mut rng3 = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    assert_ne!(
        build_batch(&refs, &cfg, &mut rng3).unwrap().target_pixels,
        b.target_pixels
    );

    // Whole-view evaluation batches take every pixel of the non-input views, in order.
    let eval = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::NonInput,
        rays_per_scene: None,
        with_masks: true,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    let e = build_batch(&refs, &eval, &mut rng).unwrap();
    assert_eq!(e.rays_per_scene, 2 * 64);
    assert_eq!(e.target_pixels[0], (1, 0));
    assert_eq!(e.target_pixels[64], (2, 0));

    // Too many rays is a clear error, not padding.
    let too_many = BatchConfig {
        rays_per_scene: Some(10_000),
        ..cfg
    };
    let err = build_batch(&refs, &too_many, &mut rng)
        .unwrap_err()
        .to_string();
    assert!(err.contains("10000 target rays requested"), "{err}");
}

#[test]
fn salient_sampling_draws_more_object_rays_without_reading_masks() {
    use osrt_dataset::{BatchConfig, InputSelection, TargetViews, build_batch};
    use rand::SeedableRng;
    let scenes = tiny_scenes(6, 24);
    let refs: Vec<_> = scenes.iter().collect();
    let cfg = |f: f32| BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::All,
        rays_per_scene: Some(200),
        with_masks: true,
        salient_fraction: f,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    let share = |f: f32| {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let b = build_batch(&refs, &cfg(f), &mut rng).unwrap();
        for s in 0..6 {
            let mut px = b.target_pixels[s * 200..(s + 1) * 200].to_vec();
            px.sort();
            px.dedup();
            assert_eq!(px.len(), 200, "rays must stay distinct pixels");
        }
        let m = b.target_masks.unwrap();
        m.iter().filter(|&&id| id != 0).count() as f64 / m.len() as f64
    };
    let (uniform, salient) = (share(0.0), share(0.5));
    assert!(
        salient > 2.0 * uniform,
        "object share {uniform} uniform vs {salient} salient"
    );
}

/// PNG storage gives back the raw scenes pixel for pixel (file sizes are a matter for
/// `osrt bench data`: zstd already shrinks flat-shaded raw renders well), in files that say so (schema
/// version 2 and the codec key; raw files stay version 1 without one), whose `image` and
/// `mask` bytes are standalone PNGs of the view's size.
#[tokio::test]
async fn png_storage_gives_back_the_same_scenes() {
    use osrt_dataset::ImageCodec;
    use parquet::file::reader::{FileReader, SerializedFileReader};
    let scenes = tiny_scenes(5, 24);
    let dir = tempfile::tempdir().unwrap();
    for codec in [ImageCodec::Raw, ImageCodec::Png] {
        let path = dir.path().join(codec.to_string());
        let loc = Location::parse(path.to_str().unwrap()).unwrap();
        let mut w = SplitWriter::new(
            loc.clone(),
            WriterOptions {
                scenes_per_row_group: 2,
                codec,
                ..Default::default()
            },
        );
        w.push(scenes.clone()).await.unwrap();
        w.finish().await.unwrap();
        let back = SplitReader::open(loc)
            .await
            .unwrap()
            .read_all(Columns::ALL)
            .await;
        assert_eq!(back.unwrap(), scenes, "{codec}");
        let file = std::fs::File::open(path.join("part-00000.parquet")).unwrap();
        let meta = SerializedFileReader::new(file).unwrap();
        let kv: Vec<(String, Option<String>)> = meta
            .metadata()
            .file_metadata()
            .key_value_metadata()
            .unwrap()
            .iter()
            .filter(|k| k.key.starts_with("osrt."))
            .map(|k| (k.key.clone(), k.value.clone()))
            .collect();
        let want = match codec {
            ImageCodec::Raw => vec![("osrt.scene_schema_version".into(), Some("1".into()))],
            ImageCodec::Png => vec![
                ("osrt.scene_schema_version".into(), Some("2".into())),
                ("osrt.image_codec".into(), Some("png".into())),
            ],
        };
        assert_eq!(kv, want, "{codec}");
    }
    let (image, mask) = osrt_dataset::codec::encode_view(&scenes[0].views[0]).unwrap();
    let img = image::load_from_memory(&image).unwrap().into_rgb8();
    assert_eq!(img.dimensions(), (24, 24));
    assert_eq!(img.into_raw(), scenes[0].views[0].image);
    let m = image::load_from_memory(&mask.unwrap())
        .unwrap()
        .into_luma8();
    assert_eq!(Some(m.into_raw()), scenes[0].views[0].mask);
}

#[test]
fn strided_inputs_are_the_whole_views_pixels_and_rays_at_the_stride() {
    use osrt_dataset::{BatchConfig, InputSelection, TargetViews, build_batch};
    use rand::SeedableRng;
    let scenes = tiny_scenes(2, 9);
    let refs: Vec<_> = scenes.iter().collect();
    let cfg = |input_stride| BatchConfig {
        input_views: 2,
        input_selection: InputSelection::First,
        target_views: TargetViews::All,
        rays_per_scene: None,
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride,
    };
    let rng = || rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let whole = build_batch(&refs, &cfg(1), &mut rng()).unwrap();
    for stride in [2, 4] {
        let b = build_batch(&refs, &cfg(stride), &mut rng()).unwrap();
        // stelzner/osrt's `x[s/2::s, s/2::s]`: pixels s/2, s/2 + s, … of each axis.
        let kept: Vec<usize> = (stride / 2..9).step_by(stride).collect();
        assert_eq!((b.height, b.width), (kept.len(), kept.len()));
        let mut k = 0;
        for scene_view in 0..2 * 2 {
            for &y in &kept {
                for &x in &kept {
                    let at = (scene_view * 81 + y * 9 + x) * 3;
                    for (got, whole) in [
                        (&b.input_images, &whole.input_images),
                        (&b.input_origins, &whole.input_origins),
                        (&b.input_directions, &whole.input_directions),
                    ] {
                        assert_eq!(got[k * 3..k * 3 + 3], whole[at..at + 3]);
                    }
                    k += 1;
                }
            }
        }
        assert_eq!(k * 3, b.input_images.len());
        // Targets keep every pixel.
        assert_eq!(b.target_rgb, whole.target_rgb);
        assert_eq!(b.target_directions, whole.target_directions);
    }
    let err = build_batch(&refs, &cfg(0), &mut rng())
        .unwrap_err()
        .to_string();
    assert!(err.contains("input stride 0"), "{err}");
}
