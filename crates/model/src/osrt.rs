//! The whole model: encoder → slot attention → decoder (paper Fig. 2), its configuration
//! and presets, and scene editing on the slot set.

use crate::decoder::{self, Decoder, DecoderOutput};
use crate::encoder::{self, Encoder};
use crate::nn::TransformerConfig;
use crate::ray_encoding::{self, RayEncoding};
use crate::slot_attention::{self, SlotAttention, SlotInit, SlotOutput};
use candle_core::{Device, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub ray_encoding: ray_encoding::Config,
    pub encoder: encoder::Config,
    pub slot_attention: slot_attention::Config,
    pub decoder: decoder::Config,
}

impl Config {
    /// The paper's appendix sizes (CLEVR-3D: 6 slots, Slot Mixer), ≈ 81 M parameters.
    pub fn paper() -> Self {
        Self {
            ray_encoding: ray_encoding::Config::paper(),
            encoder: encoder::Config::paper(),
            slot_attention: slot_attention::Config::paper(),
            decoder: decoder::Config::SlotMixer(decoder::slot_mixer::Config::paper()),
        }
    }

    /// A ≈ 1 M-parameter model for 2-core CPUs: 8-octave ray encoding, stride-4 CNN over
    /// RGB with the rays added as a patch embedding (`RayInput::Add`, beyond the paper:
    /// with the paper's concatenation this model never leaves the background plateau on
    /// clevr-lite, docs/time-to-quality.md), two 128-wide encoder layers, 7 slots of 128
    /// with 3 iterations, a one-layer allocation transformer and a 2 × 128 render MLP.
    pub fn cpu() -> Self {
        let small = TransformerConfig {
            layers: 2,
            heads: 4,
            head_dim: 32,
            mlp_hidden: 256,
        };
        Self {
            ray_encoding: ray_encoding::Config {
                origin_octaves: 8,
                origin_start_octave: -3,
                direction_octaves: 8,
                direction_start_octave: 0,
            },
            encoder: encoder::Config {
                conv_channels: vec![32, 64],
                dim: 128,
                transformer: small,
                ray_input: encoder::RayInput::Add,
                poses: encoder::Poses::Absolute,
                max_grid: 64,
                project_bias: false,
            },
            slot_attention: slot_attention::Config {
                num_slots: 7,
                slot_dim: 128,
                mlp_hidden: 256,
                iterations: 3,
                init: SlotInit::Learned,
                eps: 1e-8,
                gradient: Default::default(),
            },
            decoder: decoder::Config::SlotMixer(decoder::slot_mixer::Config {
                query_hidden: 192,
                allocation: TransformerConfig {
                    layers: 1,
                    heads: 4,
                    head_dim: 32,
                    mlp_hidden: 192,
                },
                render_hidden: vec![128, 128],
            }),
        }
    }

    /// A very small model for tests (fast finite-difference checks).
    pub fn tiny() -> Self {
        let t = TransformerConfig {
            layers: 1,
            heads: 2,
            head_dim: 4,
            mlp_hidden: 12,
        };
        Self {
            ray_encoding: ray_encoding::Config {
                origin_octaves: 2,
                origin_start_octave: -2,
                direction_octaves: 2,
                direction_start_octave: 0,
            },
            encoder: encoder::Config {
                conv_channels: vec![4],
                dim: 8,
                transformer: t.clone(),
                ray_input: encoder::RayInput::Concat,
                poses: encoder::Poses::Absolute,
                max_grid: 16,
                project_bias: false,
            },
            slot_attention: slot_attention::Config {
                num_slots: 3,
                slot_dim: 8,
                mlp_hidden: 12,
                iterations: 2,
                init: SlotInit::Learned,
                eps: 1e-8,
                gradient: Default::default(),
            },
            decoder: decoder::Config::SlotMixer(decoder::slot_mixer::Config {
                query_hidden: 12,
                allocation: t,
                render_hidden: vec![12, 12],
            }),
        }
    }

    /// Named presets: `paper`, `cpu`, `tiny`.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "paper" => Some(Self::paper()),
            "cpu" => Some(Self::cpu()),
            "tiny" => Some(Self::tiny()),
            _ => None,
        }
    }

    /// The same model with another decoder kind (`slot_mixer`, `spatial_broadcast`,
    /// `transformer`, `volumetric`), widths taken from the current decoder's.
    pub fn with_decoder(mut self, kind: &str) -> Option<Self> {
        let (query_hidden, alloc, render) = match &self.decoder {
            decoder::Config::SlotMixer(c) => (
                c.query_hidden,
                c.allocation.clone(),
                c.render_hidden.clone(),
            ),
            decoder::Config::Transformer(c) => (
                c.query_hidden,
                c.transformer.clone(),
                c.render_hidden.clone(),
            ),
            decoder::Config::Volumetric(c) => (
                c.query_hidden,
                c.allocation.clone(),
                c.render_hidden.clone(),
            ),
            decoder::Config::SpatialBroadcast(c) => {
                let t = TransformerConfig {
                    layers: 1,
                    heads: 4,
                    head_dim: 32,
                    mlp_hidden: c.hidden[0],
                };
                (c.hidden[0], t, c.hidden.clone())
            }
        };
        self.decoder = match kind {
            "slot_mixer" => decoder::Config::SlotMixer(decoder::slot_mixer::Config {
                query_hidden,
                allocation: alloc,
                render_hidden: render,
            }),
            "spatial_broadcast" => {
                decoder::Config::SpatialBroadcast(decoder::spatial_broadcast::Config {
                    hidden: render,
                })
            }
            "transformer" => decoder::Config::Transformer(decoder::transformer::Config {
                query_hidden,
                transformer: alloc,
                render_hidden: render,
            }),
            // 16 points per ray: the light field's one decoder pass becomes 16 (the
            // paper's 64 are `volumetric::Config::paper`); the box comes from the data.
            "volumetric" => decoder::Config::Volumetric(decoder::volumetric::Config {
                samples: 16,
                query_hidden,
                allocation: alloc,
                render_hidden: render,
                bounds: None,
                cull: true,
            }),
            _ => return None,
        };
        Some(self)
    }
}

/// OSRT: images with their rays in, slots and per-ray colours (and slot weights) out.
#[derive(Debug, Clone)]
pub struct Osrt {
    pub cfg: Config,
    pub rays: RayEncoding,
    pub encoder: Encoder,
    pub slot_attention: SlotAttention,
    pub decoder: Decoder,
}

impl Osrt {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let rays = RayEncoding::new(cfg.ray_encoding.clone(), vb.dtype(), vb.device())?;
        Ok(Self {
            encoder: Encoder::new(&cfg.encoder, rays.dim(), vb.pp("encoder"))?,
            slot_attention: SlotAttention::new(
                &cfg.slot_attention,
                cfg.encoder.dim,
                vb.pp("slot_attention"),
            )?,
            decoder: Decoder::new(
                &cfg.decoder,
                rays.dim(),
                cfg.slot_attention.slot_dim,
                vb.pp("decoder"),
            )?,
            rays,
            cfg: cfg.clone(),
        })
    }

    /// Standard-normal slot noise `[b, k, slot_dim]` for random slot init, drawn from the
    /// caller's seeded RNG (candle's own RNG cannot be seeded); `None` for other inits.
    pub fn slot_noise(&self, b: usize, rng: &mut impl rand::Rng) -> Result<Option<Tensor>> {
        let sa = &self.cfg.slot_attention;
        if sa.init != SlotInit::Random {
            return Ok(None);
        }
        let n = b * sa.num_slots * sa.slot_dim;
        Ok(Some(Tensor::from_vec(
            crate::params::normal_samples(rng, n),
            (b, sa.num_slots, sa.slot_dim),
            self.device(),
        )?))
    }

    /// [`Osrt::slot_noise`] with one RNG per scene (`rngs[i]` draws scene `i`'s rows).
    ///
    /// # Shapes
    /// → `[rngs.len(), k, slot_dim]`
    pub fn slot_noise_each<R: rand::Rng>(&self, rngs: &mut [R]) -> Result<Option<Tensor>> {
        let sa = &self.cfg.slot_attention;
        if sa.init != SlotInit::Random {
            return Ok(None);
        }
        let n = sa.num_slots * sa.slot_dim;
        let noise: Vec<f32> = rngs
            .iter_mut()
            .flat_map(|rng| crate::params::normal_samples(rng, n))
            .collect();
        Ok(Some(Tensor::from_vec(
            noise,
            (rngs.len(), sa.num_slots, sa.slot_dim),
            self.device(),
        )?))
    }

    /// [`Osrt::ray_offsets`] with one RNG per scene.
    ///
    /// # Shapes
    /// → `[rngs.len(), r, samples]`
    pub fn ray_offsets_each<R: rand::Rng>(
        &self,
        r: usize,
        rngs: &mut [R],
    ) -> Result<Option<Tensor>> {
        let decoder::Config::Volumetric(c) = &self.cfg.decoder else {
            return Ok(None);
        };
        let n = r * c.samples;
        let u: Vec<f32> = rngs
            .iter_mut()
            .flat_map(|rng| (0..n).map(|_| rng.random::<f32>()).collect::<Vec<_>>())
            .collect();
        Ok(Some(Tensor::from_vec(
            u,
            (rngs.len(), r, c.samples),
            self.device(),
        )?))
    }

    /// Every tensor of the model lives on this device.
    pub fn device(&self) -> &Device {
        self.rays.device()
    }

    /// Input views → slots.
    ///
    /// # Shapes
    /// `images`, `origins`, `directions: [b, v, h, w, 3]`, `noise: [b, k, slot_dim]`
    /// (random slot init only) → slots `[b, k, slot_dim]`, attention `[b, k, n_tokens]`
    pub fn encode(
        &self,
        images: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
        noise: Option<&Tensor>,
    ) -> Result<SlotOutput> {
        let slsr = self
            .encoder
            .forward(&self.rays, images, origins, directions)?;
        // Encoder, slot attention and decoder are segments of the backward pass
        // (`osrt_kernels::cut`), freed one after the other as it goes.
        let out = self
            .slot_attention
            .forward(&osrt_kernels::cut(&slsr)?, noise)?;
        Ok(SlotOutput {
            slots: osrt_kernels::cut(&out.slots)?,
            ..out
        })
    }

    /// Slots and target rays → colours (and slot weights); a volumetric decoder samples
    /// the centres of its depth bins (deterministic: evaluation and rendering).
    ///
    /// # Shapes
    /// `slots: [b, k, slot_dim]`, `origins`, `directions: [b, r, 3]` → rgb `[b, r, 3]`,
    /// weights `[b, r, k]`
    pub fn decode(
        &self,
        slots: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
    ) -> Result<DecoderOutput> {
        self.decode_with(slots, origins, directions, None)
    }

    /// [`Self::decode`] with a volumetric decoder's stratification offsets (training).
    ///
    /// # Shapes
    /// as [`Self::decode`], `offsets: [b, r, samples]` in `[0, 1)`
    pub fn decode_with(
        &self,
        slots: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
        offsets: Option<&Tensor>,
    ) -> Result<DecoderOutput> {
        self.decoder
            .forward(&self.rays, slots, origins, directions, offsets)
    }

    /// Uniform stratification offsets `[b, r, samples]` for a volumetric decoder, drawn
    /// from the caller's seeded RNG; `None` (and nothing drawn) for the other decoders.
    pub fn ray_offsets(
        &self,
        b: usize,
        r: usize,
        rng: &mut impl rand::Rng,
    ) -> Result<Option<Tensor>> {
        let decoder::Config::Volumetric(c) = &self.cfg.decoder else {
            return Ok(None);
        };
        let n = b * r * c.samples;
        let u: Vec<f32> = (0..n).map(|_| rng.random::<f32>()).collect();
        Ok(Some(Tensor::from_vec(u, (b, r, c.samples), self.device())?))
    }
}

/// Scene editing: the slot set without slot `k`.
///
/// # Shapes
/// `slots: [b, k, d]` → `[b, k − 1, d]`
pub fn drop_slot(slots: &Tensor, k: usize) -> Result<Tensor> {
    let n = slots.dim(1)?;
    if k >= n {
        candle_core::bail!("slot {k} does not exist: the scene has {n} slots");
    }
    let parts: Vec<Tensor> = [(0, k), (k + 1, n - k - 1)]
        .into_iter()
        .filter(|&(_, len)| len > 0)
        .map(|(s, len)| slots.narrow(1, s, len))
        .collect::<Result<_>>()?;
    if parts.is_empty() {
        candle_core::bail!("cannot drop the only slot");
    }
    Tensor::cat(&parts, 1)
}

/// Scene editing: the slot set with slot `j` of `other` (another scene's slots) appended.
///
/// # Shapes
/// `slots: [b, k, d]`, `other: [b, k', d]` → `[b, k + 1, d]`
pub fn add_slot(slots: &Tensor, other: &Tensor, j: usize) -> Result<Tensor> {
    let n = other.dim(1)?;
    if j >= n {
        candle_core::bail!("slot {j} does not exist: the other scene has {n} slots");
    }
    Tensor::cat(&[slots, &other.narrow(1, j, 1)?], 1)
}
