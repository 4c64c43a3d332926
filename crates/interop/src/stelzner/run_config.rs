//! The peer's run config (`runs/*/osrt/config.yaml`) and the osrt model it describes.
//!
//! What the peer's YAML does not say is fixed in its code (read at
//! [`super::PEER_COMMIT`]): 15 origin octaves from `pos_start_octave` and 15 direction
//! octaves from 2^0 (`RayEncoder(pos_octaves=15, ray_octaves=15)`), 12 heads in every
//! transformer, 3×3 convolutions without biases, a biased 1×1 per-patch convolution,
//! erf GELU, learned initial slots, slot attention's ε = 1e-8, LayerNorm's ε = 1e-5.
//! Widths come from the tensors' shapes.

use super::{Shapes, missing};
use crate::error::{InteropError, Result};
use osrt_model::decoder::{self, slot_mixer};
use osrt_model::nn::TransformerConfig;
use osrt_model::{encoder, ray_encoding, slot_attention};
use serde::Deserialize;
use std::path::Path;

/// Heads of every attention layer of the peer's model (`heads=12` in its code).
pub const PEER_HEADS: usize = 12;
/// Octaves of both halves of the peer's ray encoding (`RayEncoder(15, …, 15)`).
pub const PEER_OCTAVES: usize = 15;

/// The parts of the peer's config.yaml that import reads.
#[derive(Debug, Clone, Deserialize)]
pub struct PeerConfig {
    pub model: PeerModel,
    #[serde(default)]
    pub data: Option<PeerData>,
    #[serde(default)]
    pub training: Option<PeerTraining>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct PeerModel {
    pub encoder: String,
    #[serde(default)]
    pub encoder_kwargs: EncoderKwargs,
    pub decoder: String,
    #[serde(default)]
    pub decoder_kwargs: DecoderKwargs,
}

/// `OSRTEncoder`'s keyword arguments with its defaults; any other key is a peer version
/// this reader does not know.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EncoderKwargs {
    pub pos_start_octave: i32,
    pub num_slots: usize,
    pub slot_dim: usize,
    pub slot_iters: usize,
    pub randomize_initial_slots: bool,
}

impl Default for EncoderKwargs {
    fn default() -> Self {
        Self {
            pos_start_octave: 0,
            num_slots: 6,
            slot_dim: 1536,
            slot_iters: 1,
            randomize_initial_slots: false,
        }
    }
}

/// `SlotMixerDecoder`'s keyword arguments with its defaults.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DecoderKwargs {
    pub num_att_blocks: usize,
    pub pos_start_octave: i32,
    pub layer_norm: bool,
}

impl Default for DecoderKwargs {
    fn default() -> Self {
        Self {
            num_att_blocks: 2,
            pos_start_octave: 0,
            layer_norm: false,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
pub struct PeerData {
    pub dataset: String,
    #[serde(default)]
    pub num_points: Option<usize>,
    #[serde(default)]
    pub kwargs: Option<PeerDataKwargs>,
}

/// The dataset's keyword arguments that change what the model reads.
#[derive(Debug, Clone, Default, Deserialize)]
pub struct PeerDataKwargs {
    /// Input views point-sampled every `2^downsample` pixels from pixel `2^downsample / 2`
    /// (CLEVR-3D, `osrt/data/obsurf.py`); targets keep every pixel.
    #[serde(default)]
    pub downsample: Option<u32>,
}

impl PeerConfig {
    /// The input stride of the peer's data (`2^downsample`; 1 without one).
    pub fn input_stride(&self) -> usize {
        1 << self.input_stride_exponent().min(8)
    }

    fn input_stride_exponent(&self) -> u32 {
        self.data
            .as_ref()
            .and_then(|d| d.kwargs.as_ref())
            .and_then(|k| k.downsample)
            .unwrap_or(0)
    }
}

#[derive(Debug, Clone, Deserialize)]
pub struct PeerTraining {
    #[serde(default)]
    pub batch_size: Option<usize>,
    #[serde(default)]
    pub lr_warmup: Option<u64>,
    #[serde(default)]
    pub decay_it: Option<f64>,
}

impl PeerConfig {
    /// Reads and checks a peer config: only what osrt's model computes exactly is accepted.
    pub fn read(path: &Path) -> Result<Self> {
        let shown = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| InteropError::Io {
            path: shown.clone(),
            source: e,
        })?;
        Self::parse(&text, &shown)
    }

    /// [`Self::read`] of the text of a config; `path` names it in errors.
    pub fn parse(text: &str, path: &str) -> Result<Self> {
        let cfg: PeerConfig = serde_yaml_ng::from_str(text).map_err(|e| InteropError::File {
            path: path.to_string(),
            reason: format!("not a stelzner/osrt run config: {e}"),
        })?;
        let unsupported = |setting: &str, reason: &str| InteropError::Unsupported {
            path: path.to_string(),
            setting: setting.to_string(),
            reason: reason.to_string(),
        };
        let m = &cfg.model;
        if m.encoder != "osrt" {
            return Err(unsupported(
                "model.encoder",
                &format!(
                    "`{}`: only the OSRT encoder (`osrt`: SRT encoder + slot attention) is imported",
                    m.encoder
                ),
            ));
        }
        if m.decoder != "slot_mixer" {
            return Err(unsupported(
                "model.decoder",
                &format!(
                    "`{}`: only the Slot Mixer decoder (`slot_mixer`) is imported",
                    m.decoder
                ),
            ));
        }
        if m.encoder_kwargs.randomize_initial_slots {
            return Err(unsupported(
                "model.encoder_kwargs.randomize_initial_slots",
                "random initial slots are not imported (the peer's own code for them reads an \
                 attribute it never sets)",
            ));
        }
        if m.decoder_kwargs.layer_norm {
            return Err(unsupported(
                "model.decoder_kwargs.layer_norm",
                "osrt's mixing block has no LayerNorms",
            ));
        }
        if m.encoder_kwargs.pos_start_octave != m.decoder_kwargs.pos_start_octave {
            return Err(unsupported(
                "model.encoder_kwargs.pos_start_octave",
                &format!(
                    "{} in the encoder and {} in the decoder: osrt's model has one ray encoding",
                    m.encoder_kwargs.pos_start_octave, m.decoder_kwargs.pos_start_octave
                ),
            ));
        }
        if cfg.input_stride_exponent() > 8 {
            return Err(unsupported(
                "data.kwargs.downsample",
                "at most 8 (input views shrunk 256 times)",
            ));
        }
        if m.encoder_kwargs.slot_iters == 0 {
            return Err(unsupported(
                "model.encoder_kwargs.slot_iters",
                "must be at least 1",
            ));
        }
        Ok(cfg)
    }

    /// The osrt model computing the peer's function, its widths read from `shapes`
    /// (the checkpoint's tensors by full name, `encoder.…` and `decoder.…`).
    pub fn model_config(&self, shapes: &Shapes, path: &str) -> Result<osrt_model::Config> {
        let dim = |key: &str, axis: usize| -> Result<usize> {
            shapes
                .get(key)
                .and_then(|s| s.get(axis).copied())
                .ok_or_else(|| missing(path, key))
        };
        let count = |prefix: &str, suffix: &str| {
            (0..)
                .take_while(|i| shapes.contains_key(&format!("{prefix}{i}{suffix}")))
                .count()
        };
        let heads_dim = |key: &str, parts: usize| -> Result<usize> {
            let rows = dim(key, 0)?;
            if rows % (parts * PEER_HEADS) != 0 {
                return Err(InteropError::Mismatch {
                    path: path.to_string(),
                    report: format!(
                        "  mis-shaped `{key}`: {rows} rows are not {parts} × {PEER_HEADS} heads"
                    ),
                });
            }
            Ok(rows / (parts * PEER_HEADS))
        };
        let enc = "encoder.srt_encoder.";
        let blocks = count(&format!("{enc}conv_blocks."), ".layers.0.weight");
        let conv_channels = (0..blocks)
            .map(|i| dim(&format!("{enc}conv_blocks.{i}.layers.0.weight"), 0))
            .collect::<Result<Vec<_>>>()?;
        let enc_layers = count(&format!("{enc}transformer.layers."), ".0.norm.weight");
        let t0 = format!("{enc}transformer.layers.0.");
        let encoder = encoder::Config {
            conv_channels,
            dim: dim(&format!("{enc}per_patch_linear.weight"), 0)?,
            transformer: TransformerConfig {
                layers: enc_layers,
                heads: PEER_HEADS,
                head_dim: heads_dim(&format!("{t0}0.fn.to_qkv.weight"), 3)?,
                mlp_hidden: dim(&format!("{t0}1.fn.net.0.weight"), 0)?,
            },
            project_bias: true,
            ..encoder::Config::paper()
        };
        let k = &self.model.encoder_kwargs;
        let slot_attention = slot_attention::Config {
            num_slots: dim("encoder.slot_attention.initial_slots", 0)?,
            slot_dim: dim("encoder.slot_attention.initial_slots", 1)?,
            mlp_hidden: dim("encoder.slot_attention.mlp.0.weight", 0)?,
            iterations: k.slot_iters,
            init: slot_attention::SlotInit::Learned,
            eps: 1e-8,
            gradient: Default::default(),
        };
        if slot_attention.num_slots != k.num_slots {
            return Err(InteropError::Mismatch {
                path: path.to_string(),
                report: format!(
                    "  `encoder.slot_attention.initial_slots` holds {} slots, the config's \
                     num_slots is {}",
                    slot_attention.num_slots, k.num_slots
                ),
            });
        }
        let dec = "decoder.allocation_transformer.";
        // The render MLP's linear layers are `net.0`, `net.2`, … (activations between).
        let render_layers = (0..)
            .take_while(|j| {
                shapes.contains_key(&format!("decoder.render_mlp.net.{}.weight", 2 * j))
            })
            .count();
        let render_hidden = (0..render_layers.saturating_sub(1))
            .map(|j| dim(&format!("decoder.render_mlp.net.{}.weight", 2 * j), 0))
            .collect::<Result<Vec<_>>>()?;
        let d0 = format!("{dec}transformer.layers.0.");
        let decoder = decoder::Config::SlotMixer(slot_mixer::Config {
            query_hidden: dim(&format!("{dec}input_mlp.0.weight"), 0)?,
            allocation: TransformerConfig {
                layers: count(&format!("{dec}transformer.layers."), ".0.norm.weight"),
                heads: PEER_HEADS,
                head_dim: heads_dim(&format!("{d0}0.fn.to_q.weight"), 1)?,
                mlp_hidden: dim(&format!("{d0}1.fn.net.0.weight"), 0)?,
            },
            render_hidden,
        });
        Ok(osrt_model::Config {
            ray_encoding: ray_encoding::Config {
                origin_octaves: PEER_OCTAVES,
                origin_start_octave: k.pos_start_octave,
                direction_octaves: PEER_OCTAVES,
                direction_start_octave: 0,
            },
            encoder,
            slot_attention,
            decoder,
        })
    }
}
