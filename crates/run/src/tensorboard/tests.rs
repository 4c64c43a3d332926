use super::frames::masked_crc;
use super::*;
use crate::records::{EvalRecord, MetricsRecord, ObjectCountRecord, TrainRecord};

fn train(step: u64, loss: f64, train_s: f64) -> MetricsRecord {
    MetricsRecord::Train(TrainRecord {
        micro_batches: 0,
        epoch: 1,
        grad_norm: Some(0.5),
        loss,
        lr: 1e-4,
        peak_rss_mb: None,
        restarts: 2,
        scenes_per_s: 10.0,
        skipped: 0,
        step,
        train_s,
        wall_s: train_s,
        workers: 2,
    })
}

fn value_of(e: &Event, tag: &str) -> Option<f32> {
    let Some(event::What::Summary(s)) = &e.what else {
        return None;
    };
    s.value
        .iter()
        .find(|v| v.tag == tag)
        .and_then(|v| match v.value {
            Some(summary::value::Value::SimpleValue(x)) => Some(x),
            _ => None,
        })
}

/// `(file name, data steps)` of every event file in `run/tb`, in name order.
async fn steps_by_file(run: &Location) -> Vec<(String, Vec<u64>)> {
    let dir = run.join(TB_DIR);
    let mut out = Vec::new();
    for name in list(&dir).await.unwrap() {
        let bytes = dir
            .store
            .get(&dir.path(&name))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
        let events = read_events(&name, &bytes).unwrap();
        assert!(
            matches!(&events[0].0.what, Some(event::What::FileVersion(v)) if v == FILE_VERSION),
            "{name} starts with its version"
        );
        out.push((
            name,
            events.iter().filter_map(|(e, _)| data_step(e)).collect(),
        ));
    }
    out
}

fn all_steps(files: &[(String, Vec<u64>)]) -> Vec<u64> {
    files.iter().flat_map(|f| f.1.clone()).collect()
}

#[test]
fn frames_read_back_and_a_torn_or_corrupt_tail_ends_the_read() {
    let mut bytes = Vec::new();
    for step in 0..3 {
        let e = Event {
            wall_time: 1.5,
            step,
            what: Some(event::What::Summary(Summary {
                value: scalars(&train(step as u64, 0.25, 1.0), None),
            })),
        };
        frame(&e.encode_to_vec(), &mut bytes);
    }
    let events = read_events("f", &bytes).unwrap();
    assert_eq!(events.len(), 3);
    assert_eq!(events[2].1, bytes.len());
    assert_eq!(value_of(&events[1].0, "train/loss"), Some(0.25));
    // Cut inside the last frame, and a flipped payload byte in the second.
    let (torn, bad) = scan_events(&bytes[..bytes.len() - 3]);
    assert_eq!((torn.len(), bad.map(|b| b.offset)), (2, Some(events[1].1)));
    let mut flipped = bytes.clone();
    flipped[events[0].1 + 14] ^= 1;
    let (read, bad) = scan_events(&flipped);
    assert_eq!(read.len(), 1);
    assert!(bad.unwrap().reason.contains("checksum"));
    // A length near 2⁶⁴ with a valid checksum is no frame, not an overflow.
    let huge = length_only(u64::MAX, &[0; 8]);
    let (read, bad) = scan_events(&huge);
    assert!(read.is_empty() && bad.is_some());
}

/// A frame header declaring `len` bytes, with its valid checksum, then `rest`.
fn length_only(len: u64, rest: &[u8]) -> Vec<u8> {
    let mut out = len.to_le_bytes().to_vec();
    out.extend_from_slice(&masked_crc(&len.to_le_bytes()).to_le_bytes());
    out.extend_from_slice(rest);
    out
}

/// Malformed files (a zero-length record two bytes short of its checksum, lengths past
/// the end, a header torn short, garbage) are errors naming the file, never a panic or
/// an allocation of the declared length.
#[test]
fn malformed_frames_are_errors_naming_the_file() {
    let mut whole = Vec::new();
    let e = Event {
        wall_time: 1.0,
        step: 3,
        what: Some(event::What::Summary(Summary {
            value: scalars(&train(3, 0.5, 1.0), None),
        })),
    };
    frame(&e.encode_to_vec(), &mut whole);
    let mut garbage_after = whole.clone();
    garbage_after.extend_from_slice(&[0xa5; 40]);
    let cases: [(&str, Vec<u8>, usize, &str); 6] = [
        (
            "zero-length",
            length_only(0, &[0, 0]),
            0,
            "record of 0 bytes",
        ),
        (
            "huge-length",
            length_only(1 << 62, &[1; 64]),
            0,
            "record of 4611686018427387904 bytes",
        ),
        (
            "past-the-end",
            length_only(100, &[1; 50]),
            0,
            "50 bytes follow",
        ),
        (
            "torn-header",
            whole[..7].to_vec(),
            0,
            "7 bytes of its 12-byte header",
        ),
        (
            "truncated",
            whole[..whole.len() - 1].to_vec(),
            0,
            "bytes follow",
        ),
        (
            "garbage-after",
            garbage_after,
            whole.len(),
            "checksum does not match",
        ),
    ];
    for (name, bytes, offset, want) in cases {
        let err = read_events(name, &bytes).unwrap_err().to_string();
        assert!(
            err.contains(name)
                && err.contains(&format!("from byte {offset}:"))
                && err.contains(want),
            "{name}: {err}"
        );
    }
    // The 14-byte file as found in a run folder.
    assert_eq!(length_only(0, &[0, 0]).len(), 14);
}

/// A run folder whose newest event file is malformed opens: the damage is reported
/// naming the file, its readable events count, and new events go to a fresh file beside
/// it.
#[tokio::test]
async fn a_malformed_event_file_is_reported_and_a_fresh_one_begun() {
    let dir = tempfile::tempdir().unwrap();
    let tb = dir.path().join(TB_DIR);
    std::fs::create_dir_all(&tb).unwrap();
    let empty = format!("{NAME_PREFIX}{:016}{NAME_SUFFIX}", 1);
    std::fs::write(tb.join(&empty), length_only(0, &[0, 0])).unwrap();
    let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
    let (mut log, last) = EventLog::open(&run, true).await.unwrap();
    assert_eq!(last, None);
    let damaged: Vec<String> = log.damaged().iter().map(|e| e.to_string()).collect();
    assert_eq!(damaged.len(), 1, "{damaged:?}");
    assert!(
        damaged[0].contains(&empty) && damaged[0].contains("record of 0 bytes"),
        "{damaged:?}"
    );
    log.add(1, 1.0, scalars(&train(1, 0.1, 1.0), None));
    log.flush().await.unwrap();
    let names = list(&run.join(TB_DIR)).await.unwrap();
    assert_eq!(names.len(), 2, "{names:?}");
    assert_eq!(
        names[0], empty,
        "the damaged file is left beside the new one"
    );
    let fresh = std::fs::read(tb.join(&names[1])).unwrap();
    let steps: Vec<u64> = read_events(&names[1], &fresh)
        .unwrap()
        .iter()
        .filter_map(|(e, _)| data_step(e))
        .collect();
    assert_eq!(steps, [1]);
    drop(log);

    // A file whose whole frames are followed by a garbage length: its steps count, and
    // the cut a restarted coordinator makes (its last step's events may be short) takes
    // the damaged files with it.
    let newest = tb.join(&names[1]);
    let mut bytes = fresh.clone();
    bytes.extend_from_slice(&length_only(u64::MAX / 3, &[7; 20]));
    std::fs::write(&newest, bytes).unwrap();
    let (mut log, last) = EventLog::open(&run, true).await.unwrap();
    assert_eq!(last, Some(1));
    assert!(
        log.damaged()[0].to_string().contains(&names[1]),
        "{:?}",
        log.damaged()
    );
    log.cut_after(Some(0));
    for step in 1..=2 {
        log.add(step, 2.0, scalars(&train(step, 0.1, 2.0), None));
    }
    log.flush().await.unwrap();
    let files = steps_by_file(&run).await;
    assert_eq!(all_steps(&files), [1, 2]);
    assert_eq!(files.len(), 1, "{files:?}");
    assert!(
        EventLog::open(&run, true)
            .await
            .unwrap()
            .0
            .damaged()
            .is_empty()
    );
}

#[test]
fn records_become_scalars_with_non_finite_figures_left_out() {
    let prev = match train(10, 0.5, 2.0) {
        MetricsRecord::Train(t) => t,
        _ => unreachable!(),
    };
    let v = scalars(&train(20, f64::NAN, 4.0), Some(&prev));
    let tags: Vec<&str> = v.iter().map(|v| v.tag.as_str()).collect();
    assert!(!tags.contains(&"train/loss"), "a NaN loss is no point");
    let e = Event {
        wall_time: 0.0,
        step: 20,
        what: Some(event::What::Summary(Summary { value: v })),
    };
    assert_eq!(
        value_of(&e, "train/step_s"),
        Some(0.2),
        "(4 - 2) s over 10 steps"
    );
    assert_eq!(value_of(&e, "job/restarts"), Some(2.0));
    assert_eq!(value_of(&e, "train/grad_norm"), Some(0.5));
    let eval = MetricsRecord::Eval(EvalRecord {
        ari: None,
        baseline_psnr: Some(20.0),
        by_objects: vec![ObjectCountRecord {
            fg_ari: Some(0.75),
            objects: 3,
            scenes: 4,
        }],
        eval_scenes: 4,
        fg_ari: Some(0.5),
        fg_ari_2d: None,
        psnr: 25.0,
        ratio: None,
        render_fps: 3.0,
        step: 20,
        train_s: 4.0,
        wall_s: 5.0,
    });
    let tags: Vec<String> = scalars(&eval, None).into_iter().map(|v| v.tag).collect();
    assert_eq!(
        tags,
        [
            "eval/psnr",
            "eval/baseline_psnr",
            "eval/fg_ari",
            "eval/render_fps",
            "eval/fg_ari_by_objects/3"
        ]
    );
}

#[test]
fn images_carry_the_png_size_and_other_bytes_are_refused() {
    let img = image::RgbImage::from_pixel(5, 3, image::Rgb([1, 2, 3]));
    let mut png = std::io::Cursor::new(Vec::new());
    img.write_to(&mut png, image::ImageFormat::Png).unwrap();
    let v = image("eval/render", png.into_inner()).unwrap();
    let Some(summary::value::Value::Image(i)) = v.value else {
        panic!("an image")
    };
    assert_eq!((i.width, i.height, i.colorspace), (5, 3, 3));
    assert!(image("eval/render", b"GIF89a not a png at all".to_vec()).is_none());
}

/// Events are appended as they come; a cut leaves one value per step, renames what
/// shrank, and a reopened log knows its last step and repairs a torn tail.
async fn cut_and_reopen(run: Location, can_append: bool) {
    let (mut log, last) = EventLog::open(&run, can_append).await.unwrap();
    assert_eq!(last, None);
    for step in 1..=6 {
        log.add(step, 1.0, scalars(&train(step, 0.1, step as f64), None));
        log.flush().await.unwrap();
    }
    let files = steps_by_file(&run).await;
    assert_eq!(files.len(), 1, "{files:?}");
    assert_eq!(all_steps(&files), [1, 2, 3, 4, 5, 6]);
    let before = files[0].0.clone();
    // A generation replays from step 4.
    log.cut_after(Some(4));
    log.flush().await.unwrap();
    let files = steps_by_file(&run).await;
    assert_eq!(all_steps(&files), [1, 2, 3, 4]);
    assert!(files[0].0 > before, "a file that shrank has a later name");
    for step in 5..=8 {
        log.add(step, 2.0, scalars(&train(step, 0.2, step as f64), None));
    }
    log.flush().await.unwrap();
    assert_eq!(
        all_steps(&steps_by_file(&run).await),
        [1, 2, 3, 4, 5, 6, 7, 8]
    );
    drop(log);

    // A restarted coordinator: the last step is 8; it resumes from checkpoint 6.
    let (mut log, last) = EventLog::open(&run, can_append).await.unwrap();
    assert_eq!(last, Some(8));
    log.cut_after(Some(6));
    log.add(7, 3.0, scalars(&train(7, 0.3, 7.0), None));
    log.flush().await.unwrap();
    let files = steps_by_file(&run).await;
    assert_eq!(all_steps(&files), [1, 2, 3, 4, 5, 6, 7]);
    assert!(files.windows(2).all(|w| w[0].0 < w[1].0));
    drop(log);

    // Cutting everything leaves no file of ours.
    let (mut log, _) = EventLog::open(&run, can_append).await.unwrap();
    log.cut_after(None);
    log.flush().await.unwrap();
    assert!(steps_by_file(&run).await.is_empty());
}

#[tokio::test]
async fn a_local_log_appends_cuts_and_reopens() {
    let dir = tempfile::tempdir().unwrap();
    let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
    cut_and_reopen(run, true).await;
}

#[tokio::test]
async fn an_object_store_log_is_written_whole_and_cuts_the_same() {
    let store = std::sync::Arc::new(object_store::memory::InMemory::new());
    cut_and_reopen(Location::new(store, "run"), false).await;
}

#[tokio::test]
async fn a_torn_tail_left_by_a_crash_is_cut_when_reopened() {
    let dir = tempfile::tempdir().unwrap();
    let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
    let (mut log, _) = EventLog::open(&run, true).await.unwrap();
    for step in 1..=3 {
        log.add(step, 1.0, scalars(&train(step, 0.1, 1.0), None));
    }
    log.flush().await.unwrap();
    let name = steps_by_file(&run).await[0].0.clone();
    let file = dir.path().join(TB_DIR).join(&name);
    let len = std::fs::metadata(&file).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&file)
        .unwrap()
        .set_len(len - 5)
        .unwrap();
    let (mut log, last) = EventLog::open(&run, true).await.unwrap();
    assert_eq!(last, Some(2), "the torn event is not there");
    log.cut_after(Some(1));
    log.flush().await.unwrap();
    assert_eq!(all_steps(&steps_by_file(&run).await), [1]);
}
