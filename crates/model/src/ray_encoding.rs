//! Ray encoding (paper §2, appendix): a 6-D ray (origin, unit direction) mapped to sines
//! and cosines at octave frequencies `2^o · π`. Origins use octaves starting below zero
//! (2^-5 in the paper) so that cameras far from the origin do not alias.
//!
//! Layout of the output: `[sin(origin·f) for each octave and axis, sin(direction·f)…,
//! cos(origin·f)…, cos(direction·f)…]`, i.e. a sine block then a cosine block.

use candle_core::{CpuStorage, CustomOp2, D, DType, Device, Layout, Result, Shape, Tensor};
use osrt_kernels::fastmath;
use rayon::prelude::*;
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

/// `2^o · π` for each octave, in f32.
fn octave_freqs(octaves: usize, start: i32) -> Vec<f32> {
    (0..octaves)
        .map(|o| (2f64.powi(start + o as i32) * std::f64::consts::PI) as f32)
        .collect()
}

fn freqs(octaves: usize, start: i32, dtype: DType, dev: &Device) -> Result<Tensor> {
    let v: Vec<f32> = octave_freqs(octaves, start)
        .into_iter()
        .flat_map(|f| [f; 3])
        .collect();
    Tensor::from_vec(v, 3 * octaves, dev)?.to_dtype(dtype)
}

/// The encoding of f32 rays on the CPU in one pass, forward only (no gradient flows into
/// rays). Same layout and same f32 angles (`x · f`) as the composed version.
struct EncodeKernel {
    origin: Vec<f32>,
    direction: Vec<f32>,
}

impl CustomOp2 for EncodeKernel {
    fn name(&self) -> &'static str {
        "osrt-ray-encoding"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let o = osrt_kernels::f32_slice(s1, l1, "ray encoding origins")?;
        let d = osrt_kernels::f32_slice(s2, l2, "ray encoding directions")?;
        let (no, nd) = (3 * self.origin.len(), 3 * self.direction.len());
        let half = no + nd;
        let dim = 2 * half;
        let rays = o.len() / 3;
        let mut out = vec![0f32; rays * dim];
        out.par_chunks_mut(dim * 256)
            .zip(o.par_chunks(3 * 256).zip(d.par_chunks(3 * 256)))
            .for_each(|(out, (o, d))| {
                let mut angles = vec![0f32; half];
                for ((row, o), d) in out.chunks_mut(dim).zip(o.chunks(3)).zip(d.chunks(3)) {
                    for (a, &f) in angles[..no].chunks_mut(3).zip(&self.origin) {
                        a.iter_mut().zip(o).for_each(|(a, &x)| *a = x * f);
                    }
                    for (a, &f) in angles[no..].chunks_mut(3).zip(&self.direction) {
                        a.iter_mut().zip(d).for_each(|(a, &x)| *a = x * f);
                    }
                    let (sin, cos) = row.split_at_mut(half);
                    fastmath::sin_cos_slice(sin, cos, &angles);
                }
            });
        let mut dims = l1.dims().to_vec();
        *dims.last_mut().expect("rank ≥ 1") = dim;
        Ok((CpuStorage::F32(out), Shape::from(dims)))
    }
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

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    pub fn device(&self) -> &Device {
        self.origin_freqs.device()
    }

    /// # Shapes
    /// `origins: [.., 3]`, `directions: [.., 3]` → `[.., dim]`
    pub fn forward(&self, origins: &Tensor, directions: &Tensor) -> Result<Tensor> {
        // Rays are data: without gradients to carry, one pass writes every sine and
        // cosine (the composed version below makes seven tensors and calls libm per value).
        if osrt_kernels::enabled()
            && !origins.track_op()
            && !directions.track_op()
            && origins.dtype() == DType::F32
            && directions.dtype() == DType::F32
            && origins.device().is_cpu()
            && origins.dims() == directions.dims()
            && origins.dims().last() == Some(&3)
        {
            let kernel = EncodeKernel {
                origin: octave_freqs(self.cfg.origin_octaves, self.cfg.origin_start_octave),
                direction: octave_freqs(
                    self.cfg.direction_octaves,
                    self.cfg.direction_start_octave,
                ),
            };
            return origins
                .contiguous()?
                .apply_op2_no_bwd(&directions.contiguous()?, &kernel);
        }
        self.forward_composed(origins, directions)
    }

    /// The same encoding from differentiable tensor ops (any dtype and device).
    pub fn forward_composed(&self, origins: &Tensor, directions: &Tensor) -> Result<Tensor> {
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
