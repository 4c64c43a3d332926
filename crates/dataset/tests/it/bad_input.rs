//! Bad input gets a clear error naming the file (and scene where known), never a panic
//! or silently wrong data.

use crate::tiny_scenes;
use arrow::array::{ArrayRef, Int32Array, RecordBatch, UInt64Array};
use arrow::datatypes::{DataType, Field, Schema};
use object_store::ObjectStoreExt;
use osrt_dataset::{
    Columns, DatasetError, Scene, SplitReader, SplitWriter, VERSION_KEY, WriterOptions,
    scenes_to_batch,
};
use osrt_store::Location;
use parquet::arrow::ArrowWriter;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use std::sync::Arc;

fn parquet_bytes(batch: &RecordBatch, version: Option<&str>) -> Vec<u8> {
    let props = WriterProperties::builder()
        .set_key_value_metadata(
            version.map(|v| vec![KeyValue::new(VERSION_KEY.into(), v.to_string())]),
        )
        .build();
    let mut buf = Vec::new();
    let mut w = ArrowWriter::try_new(&mut buf, batch.schema(), Some(props)).unwrap();
    w.write(batch).unwrap();
    w.close().unwrap();
    buf
}

/// A fresh split `memory://bad-{name}/train` holding `bytes` as its one file.
async fn split_of(name: &str, bytes: Vec<u8>) -> Location {
    let loc = Location::parse(&format!("memory://bad-{name}/train")).unwrap();
    loc.store
        .put(&loc.path("part-00000.parquet"), bytes.into())
        .await
        .unwrap();
    loc
}

/// Puts one file into a fresh split and returns the error of reading the split back.
async fn read_error(name: &str, bytes: Vec<u8>) -> String {
    let loc = split_of(name, bytes).await;
    let err = match SplitReader::open(loc).await {
        Err(e) => e,
        Ok(r) => r
            .read_all(Columns::ALL)
            .await
            .expect_err("reading must fail"),
    };
    let msg = err.to_string();
    assert!(
        msg.contains(&format!("memory://bad-{name}/train")),
        "error must name the file: {msg}"
    );
    msg
}

fn good_bytes(scenes: &[Scene]) -> Vec<u8> {
    parquet_bytes(&scenes_to_batch(scenes).unwrap(), Some("1"))
}

#[tokio::test]
async fn truncated_file() {
    let bytes = good_bytes(&tiny_scenes(2, 8));
    let msg = read_error("truncated", bytes[..bytes.len() / 2].to_vec()).await;
    assert!(
        msg.contains("part-00000.parquet") && msg.contains("Parquet error"),
        "{msg}"
    );
}

#[tokio::test]
async fn corrupt_file() {
    let mut bytes = good_bytes(&tiny_scenes(2, 8));
    // Clobber the footer length and magic.
    let n = bytes.len();
    for b in &mut bytes[n - 8..] {
        *b = 0x5a;
    }
    let msg = read_error("corrupt", bytes).await;
    assert!(msg.contains("part-00000.parquet"), "{msg}");
    // Garbage in the middle of the data pages is caught too (decompression or decode).
    let mut bytes = good_bytes(&tiny_scenes(2, 8));
    let mid = bytes.len() / 3;
    for b in &mut bytes[mid..mid + 64] {
        *b ^= 0xff;
    }
    let loc = Location::parse("memory://bad-corrupt-middle/train").unwrap();
    loc.store
        .put(&loc.path("part-00000.parquet"), bytes.into())
        .await
        .unwrap();
    let got = SplitReader::open(loc)
        .await
        .unwrap()
        .read_all(Columns::ALL)
        .await;
    match got {
        Err(e) => assert!(e.to_string().contains("part-00000.parquet"), "{e}"),
        // A flipped byte inside raw image bytes can decode fine; it must then still be a
        // structurally valid scene, never a panic.
        Ok(s) => assert_eq!(s.len(), 2),
    }
}

#[tokio::test]
async fn file_of_another_schema() {
    let schema = Arc::new(Schema::new(vec![Field::new("x", DataType::Int32, false)]));
    let batch = RecordBatch::try_new(
        schema,
        vec![Arc::new(Int32Array::from(vec![1, 2])) as ArrayRef],
    )
    .unwrap();
    let msg = read_error("schema", parquet_bytes(&batch, Some("1"))).await;
    assert!(
        msg.contains("not an osrt scene file") && msg.contains("missing column `scene_id`"),
        "{msg}"
    );
    // Without our version key it is refused before the columns are even looked at.
    let msg = read_error("nokey", parquet_bytes(&batch, None)).await;
    assert!(msg.contains(VERSION_KEY), "{msg}");
}

#[tokio::test]
async fn file_of_another_version() {
    let batch = scenes_to_batch(&tiny_scenes(1, 8)).unwrap();
    let msg = read_error("version", parquet_bytes(&batch, Some("99"))).await;
    assert!(
        msg.contains("schema version 99") && msg.contains("reads versions 1 to 2"),
        "{msg}"
    );
}

#[tokio::test]
async fn missing_column() {
    // A scene file whose views lack `intrinsics`.
    let batch = scenes_to_batch(&tiny_scenes(1, 8)).unwrap();
    let views = batch
        .column_by_name("views")
        .unwrap()
        .as_any()
        .downcast_ref::<arrow::array::ListArray>()
        .unwrap();
    let s = views
        .values()
        .as_any()
        .downcast_ref::<arrow::array::StructArray>()
        .unwrap();
    let keep: Vec<usize> = (0..s.num_columns())
        .filter(|&i| s.fields()[i].name() != "intrinsics")
        .collect();
    let fields: arrow::datatypes::Fields = keep.iter().map(|&i| s.fields()[i].clone()).collect();
    let cols: Vec<ArrayRef> = keep.iter().map(|&i| s.column(i).clone()).collect();
    let s2 = arrow::array::StructArray::new(fields.clone(), cols, None);
    let item = Arc::new(Field::new("element", DataType::Struct(fields), false));
    let l2 =
        arrow::array::ListArray::new(item.clone(), views.offsets().clone(), Arc::new(s2), None);
    let schema = Arc::new(Schema::new(vec![
        Field::new("scene_id", DataType::UInt64, false),
        Field::new("views", DataType::List(item), false),
    ]));
    let ids: ArrayRef = Arc::new(UInt64Array::from(vec![0]));
    let b2 = RecordBatch::try_new(schema, vec![ids, Arc::new(l2)]).unwrap();
    let msg = read_error("missing", parquet_bytes(&b2, Some("1"))).await;
    assert!(msg.contains("missing column `views.intrinsics`"), "{msg}");
}

#[tokio::test]
async fn image_of_the_wrong_length() {
    let mut scenes = tiny_scenes(2, 8);
    scenes[1].id = 41;
    scenes[1].views[2].image.truncate(100);
    let msg = read_error("imagelen", good_bytes(&scenes)).await;
    assert!(
        msg.contains("scene 41, view 2") && msg.contains("image has 100 bytes, expected 192"),
        "{msg}"
    );
    // The writer refuses it in the first place.
    let mut w = SplitWriter::new(
        Location::parse("memory://bad-imagelen-w/train").unwrap(),
        WriterOptions::default(),
    );
    let e = w.push(scenes).await.unwrap_err();
    assert!(
        matches!(
            e,
            DatasetError::InvalidView {
                scene_id: 41,
                view: 2,
                ..
            }
        ),
        "{e}"
    );
}

#[tokio::test]
async fn non_finite_and_degenerate_cameras() {
    let mut scenes = tiny_scenes(1, 8);
    scenes[0].id = 7;
    scenes[0].views[1].camera.position[0] = f32::INFINITY;
    let msg = read_error("nonfinite", good_bytes(&scenes)).await;
    assert!(
        msg.contains("scene 7, view 1") && msg.contains("non-finite"),
        "{msg}"
    );

    let mut scenes = tiny_scenes(1, 8);
    // A zero forward axis: no viewing direction.
    for row in scenes[0].views[0].camera.rotation.iter_mut() {
        row[2] = 0.0;
    }
    let msg = read_error("zerodir", good_bytes(&scenes)).await;
    assert!(
        msg.contains("view 0") && msg.contains("not orthonormal"),
        "{msg}"
    );

    let mut scenes = tiny_scenes(1, 8);
    scenes[0].views[0].camera.rotation[0][0] *= 1.5;
    let msg = read_error("nonortho", good_bytes(&scenes)).await;
    assert!(msg.contains("not orthonormal"), "{msg}");
}

#[tokio::test]
async fn empty_split() {
    // No files at all.
    let loc = Location::parse("memory://bad-empty/train").unwrap();
    let e = SplitReader::open(loc).await.unwrap_err();
    assert!(matches!(e, DatasetError::EmptySplit { .. }), "{e}");
    assert!(e.to_string().contains("memory://bad-empty/train"));
    // A file with zero scenes.
    let batch = scenes_to_batch(&[]).unwrap();
    let loc = Location::parse("memory://bad-empty-rows/train").unwrap();
    loc.store
        .put(
            &loc.path("part-00000.parquet"),
            parquet_bytes(&batch, Some("1")).into(),
        )
        .await
        .unwrap();
    let e = SplitReader::open(loc)
        .await
        .unwrap()
        .row_groups()
        .await
        .unwrap_err();
    assert!(matches!(e, DatasetError::EmptySplit { .. }), "{e}");
    // A local directory without the split folder.
    let dir = tempfile::tempdir().unwrap();
    let e = SplitReader::open(Location::parse(dir.path().join("val").to_str().unwrap()).unwrap())
        .await
        .unwrap_err();
    assert!(e.to_string().contains("is empty"), "{e}");
}

#[tokio::test]
async fn scene_without_views() {
    let mut scenes = tiny_scenes(1, 8);
    scenes[0].views.clear();
    let msg = read_error("noviews", good_bytes(&scenes)).await;
    assert!(msg.contains("scene 0") && msg.contains("no views"), "{msg}");
}

#[tokio::test]
async fn bad_manifest() {
    let loc = Location::parse("memory://bad-manifest/ds").unwrap();
    loc.store
        .put(
            &loc.path("manifest.json"),
            bytes::Bytes::from_static(b"{\"schema_version\": 1").into(),
        )
        .await
        .unwrap();
    let e = osrt_dataset::Manifest::read(&loc)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("manifest memory://bad-manifest/ds/manifest.json"),
        "{e}"
    );
}

/// Image dimensions whose byte count overflows 64 bits are an error, not a panic.
#[test]
fn image_dimensions_that_overflow() {
    let mut v = tiny_scenes(1, 8)[0].views[0].clone();
    v.width = u32::MAX;
    v.height = u32::MAX;
    let e = v.validate().unwrap_err();
    assert!(e.contains("too large"), "{e}");
}

/// A footer whose row counts cannot be true (negative, or more rows than the file has
/// bytes) is an error naming the file, never an allocation of that size.
#[tokio::test]
async fn footers_that_lie_about_their_row_count() {
    use parquet::file::metadata::{ParquetMetaDataReader, ParquetMetaDataWriter};
    let good = good_bytes(&tiny_scenes(2, 4));
    let footer_len = u32::from_le_bytes(good[good.len() - 8..good.len() - 4].try_into().unwrap());
    let data_end = good.len() - 8 - footer_len as usize;
    for (name, rows) in [("negative-rows", -1i64), ("huge-rows", i64::MAX / 2)] {
        let md = ParquetMetaDataReader::new()
            .parse_and_finish(&bytes::Bytes::from(good.clone()))
            .unwrap();
        let mut b = md.into_builder();
        let groups = b
            .take_row_groups()
            .into_iter()
            .map(|g| g.into_builder().set_num_rows(rows).build().unwrap())
            .collect();
        let md = b.set_row_groups(groups).build();
        let mut crafted = good[..data_end].to_vec();
        ParquetMetaDataWriter::new(&mut crafted, &md)
            .finish()
            .unwrap();
        let e = SplitReader::open(split_of(name, crafted).await)
            .await
            .unwrap()
            .row_groups()
            .await
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&format!("memory://bad-{name}/train/part-00000.parquet"))
                && e.contains(&format!("declares {rows} rows")),
            "{e}"
        );
    }
}

/// A PNG file whose pictures do not fit their rows (another size, RGB where a grey mask
/// belongs, bytes that are no PNG) is refused naming the file, scene and view.
#[tokio::test]
async fn png_views_that_do_not_fit_their_rows_are_refused() {
    use osrt_dataset::{CODEC_KEY, ImageCodec, scenes_to_batch_with};
    // A file of `scenes` (raw bytes, or PNG-coded) that names a codec in version `v`.
    let coded = |scenes: &[Scene], raw: bool, v: &str| {
        let batch = if raw {
            scenes_to_batch(scenes).unwrap()
        } else {
            scenes_to_batch_with(scenes, ImageCodec::Png).unwrap()
        };
        let props = WriterProperties::builder()
            .set_key_value_metadata(Some(vec![
                KeyValue::new(VERSION_KEY.into(), v.to_string()),
                KeyValue::new(CODEC_KEY.into(), "png".to_string()),
            ]))
            .build();
        let mut buf = Vec::new();
        let mut w = ArrowWriter::try_new(&mut buf, batch.schema(), Some(props)).unwrap();
        w.write(&batch).unwrap();
        w.close().unwrap();
        buf
    };
    let png_file = |scenes: &[Scene], raw: bool| coded(scenes, raw, "2");
    let scenes = tiny_scenes(2, 8);
    // Raw bytes where PNGs belong.
    let msg = read_error("png-raw", png_file(&scenes, true)).await;
    assert!(
        msg.contains("not a readable PNG") && msg.contains("scene"),
        "{msg}"
    );
    // Rows whose bytes are PNGs (written as they are), one of them not fitting.
    let as_png = |scenes: &[Scene]| -> Vec<Scene> {
        let mut out = scenes.to_vec();
        for v in out.iter_mut().flat_map(|s| s.views.iter_mut()) {
            let (image, mask) = osrt_dataset::codec::encode_view(v).unwrap();
            (v.image, v.mask) = (image, mask);
        }
        out
    };
    let mut other = scenes[1].views[0].clone();
    (other.width, other.height) = (4, 16);
    let mut sized = as_png(&scenes);
    sized[1].views[0].image = osrt_dataset::codec::encode_view(&other).unwrap().0;
    let msg = read_error("png-size", png_file(&sized, true)).await;
    assert!(
        msg.contains("image PNG is 4x16, the view is 8x8") && msg.contains("scene 1"),
        "{msg}"
    );
    let mut rgb_mask = as_png(&scenes);
    rgb_mask[0].views[1].mask = Some(rgb_mask[0].views[1].image.clone());
    let msg = read_error("png-mask", png_file(&rgb_mask, true)).await;
    assert!(msg.contains("expected 8-bit grey"), "{msg}");
    assert_eq!(
        SplitReader::open(split_of("png-good", png_file(&as_png(&scenes), true)).await)
            .await
            .unwrap()
            .read_all(Columns::ALL)
            .await
            .unwrap(),
        scenes,
        "the same rows with fitting PNGs read back"
    );
    // The version-1 file that names a codec is refused too.
    let buf = coded(&scenes, true, "1");
    let msg = read_error("png-v1", buf).await;
    assert!(msg.contains("version 1 has no image codec"), "{msg}");
}
