//! Which job configs can run: bounds on every count and size, and the checks that name the
//! field a setting breaks.

use super::JobConfig;
use crate::error::{Result, TrainError};
use crate::lr_schedule::{Horizon, MAX_HORIZON};
use osrt_kernels::{Kernels, Precision};
use osrt_model::decoder::Config as DecoderConfig;
use osrt_model::encoder::Poses;
use osrt_model::nn::TransformerConfig;
use std::ops::RangeInclusive;

/// Upper bounds of the job's counts and sizes: far above any setting that trains (the
/// paper's widest layer has 3,072 units, its batch 256 scenes), and low enough that the
/// products of sizes the model, the batch builder and the memory estimate form in `usize`
/// stay inside it at ordinary image sizes. A model or step too large for the machine is
/// the memory check's to refuse.
const MAX_BATCH: usize = 1 << 16;
const MAX_RAYS_PER_SCENE: usize = 1 << 20;
const MAX_VIEWS: usize = 64;
const MAX_EVAL_SCENES: usize = 1 << 20;
const MAX_WIDTH: usize = 1 << 15;
const MAX_HEADS: usize = 256;
const MAX_LAYERS: usize = 256;
const MAX_SLOTS: usize = 1024;
const MAX_ITERATIONS: usize = 64;
/// Each block halves the feature map: 8 make a stride of 256.
const MAX_CONV_BLOCKS: usize = 8;
const MAX_GRID: usize = 4096;
const MAX_SAMPLES: usize = 4096;
/// Octave frequencies `2^o · π`, `o` from the start octave on: with starts in -32..=32
/// and at most 32 octaves, `o` stays within ±64, finite in f32 (and `start + o` in i32).
const MAX_OCTAVES: usize = 32;
const START_OCTAVES: RangeInclusive<i32> = -32..=32;

impl JobConfig {
    /// Rejects settings that cannot train, naming the field.
    pub fn validate(&self) -> Result<()> {
        self.validate_train()
            .and_then(|()| validate_model(&self.model))
            .map_err(|reason| TrainError::Config {
                path: "job config".into(),
                reason,
            })?;
        Ok(self.cluster.validate()?)
    }

    fn validate_train(&self) -> std::result::Result<(), String> {
        let t = &self.train;
        for (name, v, most) in [
            ("batch_size", t.batch_size, MAX_BATCH),
            ("rays_per_scene", t.rays_per_scene, MAX_RAYS_PER_SCENE),
            ("input_views", t.input_views, MAX_VIEWS),
            ("eval_scenes", t.eval_scenes, MAX_EVAL_SCENES),
        ] {
            within(&format!("train.{name}"), v, 1..=most)?;
        }
        if let Some(m) = t.micro_batch_size {
            within("train.micro_batch_size", m, 1..=MAX_BATCH)?;
        }
        // At most 2^8: stelzner/osrt's `downsample` is a power of two, and views are at
        // most a few thousand pixels wide.
        within("train.input_stride", t.input_stride, 1..=256)?;
        if let Horizon::Steps(h) = t.horizon
            && !(1..=MAX_HORIZON).contains(&h)
        {
            return Err(format!(
                "train.horizon must be fixed, budget or a step count in 1..={MAX_HORIZON}, got {h}"
            ));
        }
        for (name, v) in [
            ("log_every", t.log_every),
            ("max_consecutive_skips", t.max_consecutive_skips),
        ] {
            if v == 0 {
                return Err(format!("train.{name} must be positive"));
            }
        }
        for (name, v, positive) in [
            ("lr", t.lr, true),
            ("decay_steps", t.decay_steps, true),
            ("decay_rate", t.decay_rate, true),
            ("adam_eps", t.adam_eps, true),
            ("weight_decay", t.weight_decay, false),
            ("salient_fraction", f64::from(t.salient_fraction), false),
        ] {
            if !v.is_finite() || v < 0.0 || (positive && v == 0.0) {
                let want = if positive { "positive" } else { "non-negative" };
                return Err(format!("train.{name} must be {want} and finite, got {v:?}"));
            }
        }
        osrt_run::cluster_config::duration_s(t.eval_every_s, true)
            .map_err(|why| format!("train.eval_every_s {why}"))?;
        for (name, v) in [("beta1", t.beta1), ("beta2", t.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return Err(format!("train.{name} must be in [0, 1), got {v}"));
            }
        }
        if t.salient_fraction > 1.0 {
            return Err(format!(
                "train.salient_fraction must be at most 1, got {}",
                t.salient_fraction
            ));
        }
        if let Some(c) = t.clip_norm
            && !(c.is_finite() && c > 0.0)
        {
            return Err(format!(
                "train.clip_norm must be positive and finite, got {c}"
            ));
        }
        // On the CPU bf16 products are the fused kernels' (AMX or AVX512-BF16), or the
        // GPU's graph run there to measure it (kernels = "device").
        if t.precision == Precision::Bf16 && !t.device.is_cuda() && t.kernels == Kernels::Composed {
            return Err(
                "train.precision bf16 on the CPU runs with train.kernels = \"fused\" (bf16 \
                 products where the CPU has them) or \"device\" (the GPU's graph); candle's \
                 composed ops are the f32 reference there"
                    .into(),
            );
        }
        Ok(())
    }
}

/// `v` in `range`, or why not, naming the field.
fn within(name: &str, v: usize, range: RangeInclusive<usize>) -> std::result::Result<(), String> {
    if range.contains(&v) {
        return Ok(());
    }
    Err(format!(
        "{name} must be in {}..={}, got {v}",
        range.start(),
        range.end()
    ))
}

fn validate_transformer(name: &str, t: &TransformerConfig) -> std::result::Result<(), String> {
    within(&format!("{name}.layers"), t.layers, 0..=MAX_LAYERS)?;
    within(&format!("{name}.heads"), t.heads, 1..=MAX_HEADS)?;
    within(&format!("{name}.head_dim"), t.head_dim, 1..=MAX_WIDTH)?;
    within(&format!("{name}.mlp_hidden"), t.mlp_hidden, 1..=MAX_WIDTH)
}

/// The widths of an MLP's hidden layers: `at_least_one` where the decoder reads the first.
fn validate_widths(name: &str, w: &[usize], at_least_one: bool) -> std::result::Result<(), String> {
    let least = usize::from(at_least_one);
    within(&format!("{name} (its length)"), w.len(), least..=MAX_LAYERS)?;
    for (i, &v) in w.iter().enumerate() {
        within(&format!("{name}[{i}]"), v, 1..=MAX_WIDTH)?;
    }
    Ok(())
}

/// Every size of the model in range, and the combinations a model cannot be built with.
fn validate_model(m: &osrt_model::Config) -> std::result::Result<(), String> {
    let r = &m.ray_encoding;
    for (name, octaves, start) in [
        ("origin", r.origin_octaves, r.origin_start_octave),
        ("direction", r.direction_octaves, r.direction_start_octave),
    ] {
        within(
            &format!("model.ray_encoding.{name}_octaves"),
            octaves,
            0..=MAX_OCTAVES,
        )?;
        if !START_OCTAVES.contains(&start) {
            return Err(format!(
                "model.ray_encoding.{name}_start_octave must be in {}..={}, got {start}",
                START_OCTAVES.start(),
                START_OCTAVES.end()
            ));
        }
    }
    let e = &m.encoder;
    within(
        "model.encoder.conv_channels (its length)",
        e.conv_channels.len(),
        0..=MAX_CONV_BLOCKS,
    )?;
    for (i, &c) in e.conv_channels.iter().enumerate() {
        within(
            &format!("model.encoder.conv_channels[{i}]"),
            c,
            1..=MAX_WIDTH,
        )?;
    }
    within("model.encoder.dim", e.dim, 1..=MAX_WIDTH)?;
    within("model.encoder.max_grid", e.max_grid, 1..=MAX_GRID)?;
    validate_transformer("model.encoder.transformer", &e.transformer)?;
    let sa = &m.slot_attention;
    within(
        "model.slot_attention.num_slots",
        sa.num_slots,
        1..=MAX_SLOTS,
    )?;
    within("model.slot_attention.slot_dim", sa.slot_dim, 1..=MAX_WIDTH)?;
    within(
        "model.slot_attention.mlp_hidden",
        sa.mlp_hidden,
        1..=MAX_WIDTH,
    )?;
    within(
        "model.slot_attention.iterations",
        sa.iterations,
        1..=MAX_ITERATIONS,
    )?;
    if !(sa.eps.is_finite() && sa.eps > 0.0) {
        return Err(format!(
            "model.slot_attention.eps must be positive and finite, got {}",
            sa.eps
        ));
    }
    let d = "model.decoder";
    match &m.decoder {
        DecoderConfig::SlotMixer(c) => {
            within(&format!("{d}.query_hidden"), c.query_hidden, 1..=MAX_WIDTH)?;
            validate_transformer(&format!("{d}.allocation"), &c.allocation)?;
            validate_widths(&format!("{d}.render_hidden"), &c.render_hidden, false)?;
        }
        DecoderConfig::SpatialBroadcast(c) => {
            validate_widths(&format!("{d}.hidden"), &c.hidden, true)?;
        }
        DecoderConfig::Transformer(c) => {
            within(&format!("{d}.query_hidden"), c.query_hidden, 1..=MAX_WIDTH)?;
            validate_transformer(&format!("{d}.transformer"), &c.transformer)?;
            validate_widths(&format!("{d}.render_hidden"), &c.render_hidden, false)?;
        }
        DecoderConfig::Volumetric(c) => {
            within(&format!("{d}.samples"), c.samples, 1..=MAX_SAMPLES)?;
            within(&format!("{d}.query_hidden"), c.query_hidden, 1..=MAX_WIDTH)?;
            validate_transformer(&format!("{d}.allocation"), &c.allocation)?;
            validate_widths(&format!("{d}.render_hidden"), &c.render_hidden, false)?;
            if let Some([lo, hi]) = c.bounds
                && !(0..3).all(|k| lo[k].is_finite() && hi[k].is_finite() && lo[k] < hi[k])
            {
                return Err(format!(
                    "{d}.bounds must be finite with min < max on every axis, got {:?}",
                    [lo, hi]
                ));
            }
            if m.encoder.poses == Poses::Unposed {
                return Err(
                    "an unposed encoder (model.encoder.poses = \"unposed\", Up-OSRT) sees rays \
                     relative to its first input camera, the volumetric decoder's box \
                     (model.decoder.kind = \"volumetric\") is in world coordinates: use one or \
                     the other"
                        .into(),
                );
            }
        }
    }
    Ok(())
}
