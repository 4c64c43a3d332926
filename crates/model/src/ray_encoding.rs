//! Ray encoding (paper §2, appendix): a 6-D ray (origin, unit direction) mapped to sines
//! and cosines at octave frequencies `2^o · π`. Origins use octaves starting below zero
//! (2^-5 in the paper) so that cameras far from the origin do not alias.
//!
//! Layout of the output: `[sin(origin·f) for each octave and axis, sin(direction·f)…,
//! cos(origin·f)…, cos(direction·f)…]`, i.e. a sine block then a cosine block.

use candle_core::{D, DType, Device, Result, Tensor};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub origin_octaves: usize,
    pub origin_start_octave: i32,
    pub direction_octaves: usize,
    pub direction_start_octave: i32,
}

impl Config {
    /// Paper: 15 octaves each, origins from 2^-5, directions from 2^0 → 180 dims.
    pub fn paper() -> Self {
        Self {
            origin_octaves: 15,
            origin_start_octave: -5,
            direction_octaves: 15,
            direction_start_octave: 0,
        }
    }

    pub fn dim(&self) -> usize {
        6 * (self.origin_octaves + self.direction_octaves)
    }
}

/// Parameter-free encoder; holds its frequency vectors.
#[derive(Debug, Clone)]
pub struct RayEncoding {
    cfg: Config,
    /// `[3·origin_octaves]`: frequency per (octave, axis), octave-major.
    origin_freqs: Tensor,
    /// `[3·direction_octaves]`
    direction_freqs: Tensor,
}

fn freqs(octaves: usize, start: i32, dtype: DType, dev: &Device) -> Result<Tensor> {
    let v: Vec<f32> = (0..octaves)
        .flat_map(|o| {
            let f = 2f64.powi(start + o as i32) * std::f64::consts::PI;
            [f as f32; 3]
        })
        .collect();
    Tensor::from_vec(v, 3 * octaves, dev)?.to_dtype(dtype)
}

impl RayEncoding {
    pub fn new(cfg: Config, dtype: DType, dev: &Device) -> Result<Self> {
        Ok(Self {
            origin_freqs: freqs(cfg.origin_octaves, cfg.origin_start_octave, dtype, dev)?,
            direction_freqs: freqs(
                cfg.direction_octaves,
                cfg.direction_start_octave,
                dtype,
                dev,
            )?,
            cfg,
        })
    }

    pub fn dim(&self) -> usize {
        self.cfg.dim()
    }

    pub fn device(&self) -> &Device {
        self.origin_freqs.device()
    }

    /// # Shapes
    /// `origins: [.., 3]`, `directions: [.., 3]` → `[.., dim]`
    pub fn forward(&self, origins: &Tensor, directions: &Tensor) -> Result<Tensor> {
        // Repeat xyz once per octave: [.., 3] → [.., 3·octaves], then scale.
        let scaled = |x: &Tensor, f: &Tensor, octaves: usize| -> Result<Tensor> {
            let rep = Tensor::cat(&vec![x; octaves], D::Minus1)?;
            rep.broadcast_mul(f)
        };
        let o = scaled(origins, &self.origin_freqs, self.cfg.origin_octaves)?;
        let d = scaled(
            directions,
            &self.direction_freqs,
            self.cfg.direction_octaves,
        )?;
        let angles = Tensor::cat(&[&o, &d], D::Minus1)?;
        Tensor::cat(&[&angles.sin()?, &angles.cos()?], D::Minus1)
    }
}
