//! The three decoders of the paper's central ablation (Table 2) and V-OSRT's volumetric
//! decoder (§4.3), behind one config switch. Each maps slots and target rays to RGB per
//! ray and, where it has them, per-ray slot weights (the segmentation is their argmax).

pub mod slot_mixer;
pub mod spatial_broadcast;
pub mod transformer;
pub mod volumetric;

use crate::ray_encoding::RayEncoding;
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Config {
    SlotMixer(slot_mixer::Config),
    SpatialBroadcast(spatial_broadcast::Config),
    Transformer(transformer::Config),
    Volumetric(volumetric::Config),
}

impl Config {
    pub fn name(&self) -> &'static str {
        match self {
            Config::SlotMixer(_) => "slot_mixer",
            Config::SpatialBroadcast(_) => "spatial_broadcast",
            Config::Transformer(_) => "transformer",
            Config::Volumetric(_) => "volumetric",
        }
    }
}

/// What every decoder returns.
pub struct DecoderOutput {
    /// `[b, r, 3]` in `[0, 1]`
    pub rgb: Tensor,
    /// `[b, r, k]`, summing to 1 over slots; `None` for the transformer decoder, which
    /// has no notion of per-slot contribution.
    pub weights: Option<Tensor>,
}

#[derive(Debug, Clone)]
pub enum Decoder {
    SlotMixer(slot_mixer::SlotMixer),
    SpatialBroadcast(spatial_broadcast::SpatialBroadcast),
    Transformer(transformer::TransformerDecoder),
    Volumetric(volumetric::Volumetric),
}

impl Decoder {
    pub fn new(cfg: &Config, ray_dim: usize, slot_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(match cfg {
            Config::SlotMixer(c) => {
                Decoder::SlotMixer(slot_mixer::SlotMixer::new(c, ray_dim, slot_dim, vb)?)
            }
            Config::SpatialBroadcast(c) => Decoder::SpatialBroadcast(
                spatial_broadcast::SpatialBroadcast::new(c, ray_dim, slot_dim, vb)?,
            ),
            Config::Transformer(c) => Decoder::Transformer(transformer::TransformerDecoder::new(
                c, ray_dim, slot_dim, vb,
            )?),
            Config::Volumetric(c) => {
                Decoder::Volumetric(volumetric::Volumetric::new(c, ray_dim, slot_dim, vb)?)
            }
        })
    }

    /// # Shapes
    /// `slots: [b, k, slot_dim]`, `origins`/`directions: [b, r, 3]`, `offsets: [b, r, n]`
    /// (the volumetric decoder's stratification, ignored by the others) → rgb
    /// `[b, r, 3]`, weights `[b, r, k]`
    pub fn forward(
        &self,
        rays: &RayEncoding,
        slots: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
        offsets: Option<&Tensor>,
    ) -> Result<DecoderOutput> {
        if let Decoder::Volumetric(d) = self {
            // Encodes sample points, not rays.
            return d.forward(rays, slots, origins, directions, offsets);
        }
        let enc = rays.forward(origins, directions)?; // [b, r, ray_dim]
        match self {
            Decoder::SlotMixer(d) => d.forward(slots, &enc),
            Decoder::SpatialBroadcast(d) => d.forward(slots, &enc),
            Decoder::Transformer(d) => d.forward(slots, &enc),
            Decoder::Volumetric(_) => unreachable!("returned above"),
        }
    }
}
