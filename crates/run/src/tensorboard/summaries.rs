//! From metrics records to TensorBoard summaries: each record's figures as scalars, an
//! evaluation's pictures as images.

use super::proto::summary;
use crate::records::{MetricsRecord, TrainRecord};

fn scalar(tag: &str, v: f64) -> Option<summary::Value> {
    v.is_finite().then(|| summary::Value {
        tag: tag.into(),
        value: Some(summary::value::Value::SimpleValue(v as f32)),
    })
}

/// A PNG's size from its header (`None`: not a PNG).
fn png_size(png: &[u8]) -> Option<(i32, i32)> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    if png.len() < 24 || &png[..8] != SIGNATURE || &png[12..16] != b"IHDR" {
        return None;
    }
    let w = u32::from_be_bytes(png[16..20].try_into().ok()?);
    let h = u32::from_be_bytes(png[20..24].try_into().ok()?);
    Some((i32::try_from(w).ok()?, i32::try_from(h).ok()?))
}

/// An image summary of PNG bytes (`None`: not a PNG).
pub fn image(tag: &str, png: Vec<u8>) -> Option<summary::Value> {
    let (width, height) = png_size(&png)?;
    Some(summary::Value {
        tag: tag.into(),
        value: Some(summary::value::Value::Image(summary::Image {
            height,
            width,
            colorspace: 3,
            encoded_image_string: png,
        })),
    })
}

/// The scalar summaries of a record. `previous`: the training record before it (the
/// step time is the train seconds between the two over their steps). Non-finite figures
/// (a window whose every step was skipped) are left out: TensorBoard draws no NaN.
pub fn scalars(record: &MetricsRecord, previous: Option<&TrainRecord>) -> Vec<summary::Value> {
    let mut v = Vec::new();
    match record {
        MetricsRecord::Train(r) => {
            v.push(scalar("train/loss", r.loss));
            v.push(scalar("train/lr", r.lr));
            v.push(scalar("train/scenes_per_s", r.scenes_per_s));
            if let Some(p) = previous.filter(|p| p.step < r.step) {
                let s = (r.train_s - p.train_s) / (r.step - p.step) as f64;
                v.push(scalar("train/step_s", s));
            }
            v.push(r.grad_norm.and_then(|g| scalar("train/grad_norm", g)));
            v.push(scalar("train/skipped_steps", r.skipped as f64));
            v.push(scalar("train/epoch", r.epoch as f64));
            v.push(scalar("train/workers", r.workers as f64));
            v.push(r.peak_rss_mb.and_then(|m| scalar("train/peak_rss_mb", m)));
            v.push(scalar("job/restarts", r.restarts as f64));
        }
        MetricsRecord::Eval(r) => {
            v.push(scalar("eval/psnr", r.psnr));
            v.push(
                r.baseline_psnr
                    .and_then(|x| scalar("eval/baseline_psnr", x)),
            );
            v.push(r.fg_ari.and_then(|x| scalar("eval/fg_ari", x)));
            v.push(r.fg_ari_2d.and_then(|x| scalar("eval/fg_ari_2d", x)));
            v.push(r.ari.and_then(|x| scalar("eval/ari", x)));
            v.push(scalar("eval/render_fps", r.render_fps));
            for o in &r.by_objects {
                let tag = format!("eval/fg_ari_by_objects/{}", o.objects);
                v.push(o.fg_ari.and_then(|x| scalar(&tag, x)));
            }
        }
    }
    v.into_iter().flatten().collect()
}
