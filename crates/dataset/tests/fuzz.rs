//! Generated inputs for every reader of foreign bytes: `.npy` and `.npz`, TFRecord framing
//! and the `tf.train.Example`s inside it, and the footers of Parquet parts. Each property
//! holds that the reader returns a value or an error and never panics (an overflow, an
//! out-of-bounds slice or an `expect` on hostile input would), and, where the input is
//! valid, that it reads back what was written. `cargo test` runs a bounded number of
//! cases (`PROPTEST_CASES`, default 256 per property, a quarter of it for Parquet); a
//! longer run by hand is `PROPTEST_CASES=100000 cargo test -p osrt-dataset --test fuzz`.

use osrt_dataset::import::Source;
use osrt_dataset::import::kubric::{KubricSource, tf};
use osrt_dataset::import::npy::{Values, parse_npy, read_npz};
use osrt_dataset::import::tfrecord::{index_file, read_record};
use proptest::prelude::*;
use prost::Message;
use std::io::{Cursor, Write};

// --- .npy and .npz -----------------------------------------------------------------------

/// A version-1 `.npy` file of `header` (any text) and `data`.
fn npy(header: &str, data: &[u8]) -> Vec<u8> {
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(data);
    out
}

fn descr() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("<f8".to_string()),
        Just("<f4".to_string()),
        Just("|u1".to_string()),
        Just("<i8".to_string()),
        Just("<U4".to_string()),
        Just("|b1".to_string()),
        "[<>|=]?[a-zA-Z]?[0-9]{0,20}",
        any::<String>(),
    ]
}

fn shape() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::collection::vec(0usize..6, 0..4).prop_map(|d| {
            let inner: Vec<String> = d.iter().map(|x| x.to_string()).collect();
            format!("({},)", inner.join(", "))
        }),
        prop::collection::vec(any::<u64>(), 0..4)
            .prop_map(|d| format!("{d:?}").replace('[', "(").replace(']', ")")),
        "[(),0-9 x-]{0,30}",
    ]
}

/// A zip of `entries`, deflated.
fn npz(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    for (name, data) in entries {
        zip.start_file(name.as_str(), opts).unwrap();
        zip.write_all(data).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

/// The properties' settings: `PROPTEST_CASES` (256 by default) cases, or a `1 / share`
/// of them, nothing written to disk on failure (the failing case is printed).
fn config(share: u32) -> ProptestConfig {
    let default = ProptestConfig::default();
    ProptestConfig {
        cases: (default.cases / share).max(1),
        failure_persistence: None,
        ..default
    }
}

proptest! {
    #![proptest_config(config(1))]

    #[test]
    fn any_bytes_parse_as_npy_or_fail(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_npy(&bytes, "f.npy");
        let mut magic = b"\x93NUMPY".to_vec();
        magic.extend(&bytes);
        let _ = parse_npy(&magic, "f.npy");
    }

    /// Headers of any dtype and shape text before any amount of data: a value whose
    /// element count is the shape's product, or an error naming the file.
    #[test]
    fn npy_headers_of_any_dtype_and_shape(
        d in descr(), s in shape(), fortran in any::<bool>(),
        data in prop::collection::vec(any::<u8>(), 0..256),
    ) {
        let header = format!(
            "{{'descr': '{d}', 'fortran_order': {}, 'shape': {s}, }}\n",
            if fortran { "True" } else { "False" }
        );
        match parse_npy(&npy(&header, &data), "f.npy") {
            Ok(a) => {
                let n: usize = a.shape.iter().product();
                let len = match &a.values {
                    Values::Numbers(v) => v.len(),
                    Values::Text(v) => v.len(),
                };
                prop_assert_eq!(len, n);
            }
            Err(e) => prop_assert!(e.to_string().contains("f.npy"), "{}", e),
        }
    }

    /// A valid archive with bytes flipped anywhere: the arrays, or an error naming it.
    #[test]
    fn npz_archives_with_flipped_bytes(
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 0..6),
        wanted_b in any::<bool>(),
    ) {
        let values: Vec<u8> = (0..64u8).collect();
        let a = npy("{'descr': '<f8', 'fortran_order': False, 'shape': (8,), }\n", &values);
        let b = npy("{'descr': '|u1', 'fortran_order': False, 'shape': (4, 4), }\n", &values[..16]);
        let mut bytes = npz(&[("a.npy".into(), a), ("b.npy".into(), b)]);
        for (at, x) in &flips {
            let i = at.index(bytes.len());
            bytes[i] ^= x;
        }
        let wanted: &[&str] = if wanted_b { &["a", "b"] } else { &["a"] };
        match read_npz(Cursor::new(&bytes), "m.npz", wanted) {
            Ok(arrays) => prop_assert!(arrays.keys().all(|k| wanted.contains(&k.as_str()))),
            Err(e) => prop_assert!(e.to_string().contains("m.npz"), "{}", e),
        }
    }

    #[test]
    fn any_bytes_read_as_npz_or_fail(bytes in prop::collection::vec(any::<u8>(), 0..1024)) {
        let _ = read_npz(Cursor::new(&bytes), "m.npz", &["a"]);
        let mut zipped = b"PK\x03\x04".to_vec();
        zipped.extend(&bytes);
        let _ = read_npz(Cursor::new(&zipped), "m.npz", &["a"]);
    }
}

// --- TFRecord and tf.train.Example --------------------------------------------------------

fn masked_crc(data: &[u8]) -> u32 {
    const CRC32C: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
    let c = CRC32C.checksum(data);
    c.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// A TFRecord of `payload` whose length field says `len` (checksums valid).
fn record(payload: &[u8], len: u64) -> Vec<u8> {
    let l = len.to_le_bytes();
    let mut out = l.to_vec();
    out.extend(masked_crc(&l).to_le_bytes());
    out.extend(payload);
    out.extend(masked_crc(payload).to_le_bytes());
    out
}

/// A file of `bytes` in a fresh folder, named as an MSN-Hard training shard.
fn shard(bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("msn-train.tfrecord-00000-of-00001");
    std::fs::write(&path, bytes).unwrap();
    (dir, path)
}

/// A small PNG (valid, or its first `keep` bytes).
fn png(w: u32, h: u32, grey: bool, keep: usize) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    if grey {
        image::GrayImage::new(w, h)
            .write_to(&mut out, image::ImageFormat::Png)
            .unwrap();
    } else {
        image::RgbImage::new(w, h)
            .write_to(&mut out, image::ImageFormat::Png)
            .unwrap();
    }
    let mut v = out.into_inner();
    v.truncate(keep);
    v
}

/// Any value a feature of an Example might hold: PNGs (whole, cut, of odd sizes), floats
/// and integers of any count.
fn feature() -> impl Strategy<Value = tf::Feature> {
    use tf::feature::Kind;
    let kind = prop_oneof![
        (1u32..6, 1u32..6, any::<bool>(), 0usize..200).prop_map(|(w, h, g, keep)| {
            Kind::BytesList(tf::BytesList {
                value: vec![png(w, h, g, keep).into()],
            })
        }),
        prop::collection::vec(prop::collection::vec(any::<u8>(), 0..16), 0..3).prop_map(|v| {
            Kind::BytesList(tf::BytesList {
                value: v.into_iter().map(Into::into).collect(),
            })
        }),
        prop::collection::vec(prop_oneof![any::<f32>(), -2f32..2.0], 0..12)
            .prop_map(|value| Kind::FloatList(tf::FloatList { value })),
        prop::collection::vec(any::<i64>(), 0..3)
            .prop_map(|value| Kind::Int64List(tf::Int64List { value })),
    ];
    prop::option::weighted(0.95, kind).prop_map(|kind| tf::Feature { kind })
}

const CAMERA_KEYS: [&str; 6] = [
    "color_image",
    "instance_image",
    "intrinsics/K",
    "extrinsics/R",
    "extrinsics/t",
    "intrinsics/image_width",
];

/// What a real Example holds under `key` for a 4×3 camera.
fn valid_feature(key: &str) -> tf::Feature {
    use tf::feature::Kind;
    let floats = |value: Vec<f32>| Kind::FloatList(tf::FloatList { value });
    let kind = match key {
        "color_image" => Kind::BytesList(tf::BytesList {
            value: vec![png(4, 3, false, usize::MAX).into()],
        }),
        "instance_image" => Kind::BytesList(tf::BytesList {
            value: vec![png(4, 3, true, usize::MAX).into()],
        }),
        "intrinsics/K" => floats(vec![4.0, 0.0, 2.0, 0.0, 4.0, 1.5, 0.0, 0.0, 1.0]),
        "extrinsics/R" => floats(vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
        "extrinsics/t" => floats(vec![0.0, 0.0, 5.0]),
        _ => Kind::Int64List(tf::Int64List { value: vec![4] }),
    };
    tf::Feature { kind: Some(kind) }
}

/// An Example of up to three cameras, each feature missing, valid, or of any other
/// kind and value (mostly valid, so that the readers get past the first check).
fn example() -> impl Strategy<Value = tf::Example> {
    let slot = prop_oneof![
        1 => Just(None),
        6 => Just(Some(None)),
        2 => feature().prop_map(|f| Some(Some(f))),
    ];
    (
        1usize..=3,
        prop::collection::vec(slot, 3 * CAMERA_KEYS.len()),
    )
        .prop_map(|(cams, slots)| {
            let mut feature = std::collections::HashMap::new();
            for (i, s) in slots.into_iter().enumerate() {
                let (k, key) = (i / CAMERA_KEYS.len(), CAMERA_KEYS[i % CAMERA_KEYS.len()]);
                let value = match s {
                    None => continue,
                    Some(None) => valid_feature(key),
                    Some(Some(f)) => f,
                };
                if k < cams {
                    feature.insert(format!("cameras/camera_{k}/{key}"), value);
                }
            }
            tf::Example {
                features: Some(tf::Features { feature }),
            }
        })
}

proptest! {
    #![proptest_config(config(1))]

    /// Any bytes as a shard: indexed and read, or an error naming the file.
    #[test]
    fn any_bytes_index_as_tfrecord_or_fail(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let (_dir, path) = shard(&bytes);
        match index_file(&path) {
            Ok(records) => {
                for (i, r) in records.iter().enumerate() {
                    let _ = read_record(r, i);
                }
            }
            Err(e) => prop_assert!(e.to_string().contains("msn-train"), "{}", e),
        }
    }

    /// Valid framing whose length fields lie by any amount (checksums valid): payloads
    /// read back where the lengths are true, errors where not.
    #[test]
    fn tfrecord_lengths_that_lie(
        payloads in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..40), 1..4),
        lie in prop::option::of((any::<prop::sample::Index>(), any::<u64>())),
    ) {
        let mut bytes = Vec::new();
        let liar = lie.map(|(i, len)| (i.index(payloads.len()), len));
        for (i, p) in payloads.iter().enumerate() {
            let len = match liar {
                Some((j, len)) if j == i => len,
                _ => p.len() as u64,
            };
            bytes.extend(record(p, len));
        }
        let (_dir, path) = shard(&bytes);
        let read = index_file(&path).and_then(|rs| {
            rs.iter().enumerate().map(|(i, r)| read_record(r, i)).collect::<Result<Vec<_>, _>>()
        });
        match (read, liar) {
            (Ok(got), None) => prop_assert_eq!(got, payloads),
            (Ok(_), Some((j, len))) => prop_assert_eq!(len, payloads[j].len() as u64),
            (Err(e), lie) => {
                prop_assert!(lie.is_some(), "honest records refused: {}", e);
                prop_assert!(e.to_string().contains("msn-train"), "{}", e);
            }
        }
    }

    /// Example payloads with bytes flipped: protobuf decoding refuses or reads them.
    #[test]
    fn examples_with_flipped_bytes(
        ex in example(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4),
    ) {
        let mut payload = ex.encode_to_vec();
        if !payload.is_empty() {
            for (at, x) in &flips {
                let i = at.index(payload.len());
                payload[i] ^= x;
            }
        }
        let (dir, _path) = shard(&record(&payload, payload.len() as u64));
        if let Ok(src) = KubricSource::open(dir.path()) {
            let _ = src.scene(0);
        }
    }
}

/// Examples with any subset of the cameras' features, of any kinds and values, in a
/// valid shard: the import's source opens and reads the scene, or says which file. Some
/// of the generated Examples must read whole, or the property never reached the views'
/// checks.
#[test]
fn examples_of_any_features_read_or_fail() {
    let mut runner = proptest::test_runner::TestRunner::new(config(1));
    let whole = std::cell::Cell::new(0);
    runner
        .run(&example(), |ex| {
            let payload = ex.encode_to_vec();
            let (dir, _path) = shard(&record(&payload, payload.len() as u64));
            let scene = KubricSource::open(dir.path()).and_then(|src| src.scene(0));
            match scene {
                Ok(scene) => {
                    prop_assert!(!scene.views.is_empty());
                    whole.set(whole.get() + 1);
                }
                Err(e) => prop_assert!(e.to_string().contains("msn-train"), "{}", e),
            }
            Ok(())
        })
        .unwrap();
    assert!(whole.get() > 0, "no generated Example was read whole");
    eprintln!(
        "{} of {} generated Examples read whole",
        whole.get(),
        runner.config().cases
    );
}

// --- Parquet footers ----------------------------------------------------------------------

/// The bytes of a valid 4-scene training part (generated once).
fn valid_part() -> &'static [u8] {
    static PART: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    PART.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let cfg = osrt_dataset::generator::GeneratorConfig {
            image_size: 8,
            ..osrt_dataset::generator::GeneratorConfig::clevr_lite()
        };
        let sizes = osrt_dataset::generator::SplitSizes {
            train: 4,
            val: 1,
            test: 1,
        };
        let opts = osrt_dataset::WriterOptions {
            scenes_per_row_group: 2,
            ..Default::default()
        };
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let loc = osrt_store::Location::parse(dir.path().to_str().unwrap()).unwrap();
        rt.block_on(osrt_dataset::generator::generate_dataset(
            &loc, &cfg, 1, sizes, opts, false,
        ))
        .unwrap();
        std::fs::read(dir.path().join("train/part-00000.parquet")).unwrap()
    })
}

proptest! {
    // Each case writes and reads a whole part: a quarter of the cases.
    #![proptest_config(config(4))]

    /// A part whose footer (metadata and its length) has bytes flipped, or is cut short:
    /// the split reads, or fails naming the part; never a panic.
    #[test]
    fn parquet_footers_with_flipped_bytes(
        flips in prop::collection::vec((0usize..512, 1u8..=255), 1..6),
        cut in prop::option::weighted(0.2, 0usize..600),
    ) {
        let mut bytes = valid_part().to_vec();
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("train")).unwrap();
        let part = dir.path().join("train/part-00000.parquet");
        let n = bytes.len();
        for (back, x) in &flips {
            let i = n - 1 - back % n.min(512);
            bytes[i] ^= x;
        }
        if let Some(c) = cut {
            bytes.truncate(n.saturating_sub(c));
        }
        std::fs::write(&part, &bytes).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let split = osrt_store::Location::parse(dir.path().join("train").to_str().unwrap())
            .unwrap();
        let read = rt.block_on(async {
            let reader = osrt_dataset::SplitReader::open(split).await?;
            reader.read_all(osrt_dataset::Columns::TRAIN).await
        });
        if let Err(e) = read {
            prop_assert!(e.to_string().contains("part-00000.parquet"), "{}", e);
        }
    }
}
