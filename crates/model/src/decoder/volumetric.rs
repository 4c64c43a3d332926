//! The volumetric decoder of V-OSRT (paper §4.3, after SRT's VolSRT): points sampled
//! along each target ray are decoded through the Slot Mixer's machinery (query MLP,
//! allocation transformer, slot mixing, render MLP) into a density and a colour, and
//! composited with the standard quadrature
//!
//! `αᵢ = 1 − exp(−σᵢδᵢ)`, `Tᵢ = exp(−Σ_{j<i} σⱼδⱼ)`, `wᵢ = Tᵢαᵢ`,
//! `rgb = Σᵢ wᵢcᵢ + T_N · background`,
//!
//! with a learned background colour for the light that passes the scene's box. The ray's
//! slot weights (its segmentation) are the mixing weights accumulated with the same `wᵢ`,
//! plus `T_N` spread evenly over the slots, so they sum to 1.
//!
//! **What a ray does not need is left out.** Points are sampled only on the segment of
//! the ray inside the scene's axis-aligned box (`bounds`, from the dataset manifest), and
//! rays that miss the box are never decoded: they take the background colour directly.
//! With `cull = false` every ray is decoded over the depth range of the box's bounding
//! sphere (NeRF's near/far), the comparison the render benchmark measures.

use crate::decoder::DecoderOutput;
use crate::decoder::slot_mixer::{self, SlotMixer};
use crate::nn::TransformerConfig;
use crate::ray_encoding::RayEncoding;
use candle_core::{D, DType, Device, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

/// `[min corner, max corner]` of the scene's axis-aligned box, world coordinates.
pub type Bounds = [[f32; 3]; 2];

fn default_cull() -> bool {
    true
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Points per ray (stratified: one per equal-depth bin, jittered in training).
    pub samples: usize,
    /// Hidden width of the query MLP (point encoding → hidden → encoding width).
    pub query_hidden: usize,
    pub allocation: TransformerConfig,
    /// Hidden widths of the render MLP (mixed slot ⊕ query → density, RGB).
    pub render_hidden: Vec<usize>,
    /// The scene's box; `None` until the launcher fills it from the dataset's manifest
    /// (a model cannot be built without it).
    #[serde(default)]
    pub bounds: Option<Bounds>,
    /// Sample only inside the box and skip rays that miss it (`false`: the bounding
    /// sphere's depth range for every ray).
    #[serde(default = "default_cull")]
    pub cull: bool,
}

impl Config {
    /// The paper's Slot Mixer sizes with 64 points per ray.
    pub fn paper() -> Self {
        let sm = super::slot_mixer::Config::paper();
        Self {
            samples: 64,
            query_hidden: sm.query_hidden,
            allocation: sm.allocation,
            render_hidden: sm.render_hidden,
            bounds: None,
            cull: true,
        }
    }
}

/// Where along one ray points are sampled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    pub near: f64,
    pub far: f64,
}

/// The part of the ray `o + t·d`, `t ≥ 0`, inside the box (slab method); `None` when
/// the ray misses it or only touches it (an empty segment renders nothing). Axis-parallel
/// rays are handled without dividing by zero.
pub fn box_segment(o: [f64; 3], d: [f64; 3], b: &Bounds) -> Option<Segment> {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        let (lo, hi) = (b[0][a] as f64, b[1][a] as f64);
        if d[a].abs() < 1e-12 {
            if o[a] < lo || o[a] > hi {
                return None;
            }
            continue;
        }
        let (t0, t1) = ((lo - o[a]) / d[a], (hi - o[a]) / d[a]);
        near = near.max(t0.min(t1));
        far = far.min(t0.max(t1));
    }
    (far > near && near.is_finite() && far.is_finite()).then_some(Segment { near, far })
}

/// The depth range of the box's bounding sphere seen from `o` (clamped at 0).
fn sphere_segment(o: [f64; 3], b: &Bounds) -> Segment {
    let mut dist2 = 0.0;
    let mut radius2 = 0.0;
    for a in 0..3 {
        let (lo, hi) = (b[0][a] as f64, b[1][a] as f64);
        dist2 += (o[a] - 0.5 * (lo + hi)).powi(2);
        radius2 += (0.5 * (hi - lo)).powi(2);
    }
    let (dist, radius) = (dist2.sqrt(), radius2.sqrt());
    Segment {
        near: (dist - radius).max(0.0),
        far: dist + radius,
    }
}

/// The largest σδ the quadrature takes: e^{−200} underflows to 0 in f32 and bf16, and
/// `n` such terms still sum to a finite value.
pub const SIGMA_DELTA_MAX: f64 = 200.0;

/// The quadrature (module docs) over `n` points of each ray.
///
/// # Shapes
/// `sigma_delta: [m, n]` (density × interval, ≥ 0), `rgb: [m, n, 3]`, `weights: [m, n, k]`,
/// `background: [3]` → rgb `[m, 3]`, slot weights `[m, k]`
pub fn composite(
    sigma_delta: &Tensor,
    rgb: &Tensor,
    weights: &Tensor,
    background: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let n = sigma_delta.dim(1)?;
    let k = weights.dim(2)?;
    // An infinite σδ (an overflowed density) would make the prefix-sum matmul's ∞·0 a NaN
    // along the whole ray; past this bound e^{−σδ} is 0 in f32 anyway, so the point is
    // opaque either way.
    let sigma_delta = &sigma_delta.minimum(SIGMA_DELTA_MAX)?;
    // Exclusive prefix sums as one matmul with a strictly upper-triangular ones matrix.
    let upper: Vec<f64> = (0..n * n)
        .map(|i| if i / n < i % n { 1.0 } else { 0.0 })
        .collect();
    let upper =
        Tensor::from_vec(upper, (n, n), sigma_delta.device())?.to_dtype(sigma_delta.dtype())?;
    let before = sigma_delta.matmul(&upper)?; // [m, n]
    let transmittance = before.neg()?.exp()?;
    let alpha = (1.0 - sigma_delta.neg()?.exp()?)?;
    let w = (transmittance * alpha)?.unsqueeze(2)?; // [m, n, 1]
    let left = sigma_delta.sum_keepdim(1)?.neg()?.exp()?; // [m, 1]: T_N
    let colour = w
        .broadcast_mul(rgb)?
        .sum(1)?
        .broadcast_add(&left.broadcast_mul(&background.unsqueeze(0)?)?)?;
    let slots = (w.broadcast_mul(weights)?.sum(1)?
        + left.broadcast_mul(
            &Tensor::ones((1, k), weights.dtype(), weights.device())?
                .affine(1.0 / k as f64, 0.0)?,
        )?)?;
    Ok((colour, slots))
}

/// `softplus(x) = log(1 + eˣ)` without overflow: `relu(x) + log(1 + e^{−|x|})`.
fn softplus(x: &Tensor) -> Result<Tensor> {
    x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?
}

#[derive(Debug, Clone)]
pub struct Volumetric {
    /// The Slot Mixer over points, its render MLP giving (raw density, raw RGB).
    points: SlotMixer,
    /// Raw background colour `[3]` (sigmoid → RGB).
    background: Tensor,
    cfg: Config,
}

/// The points of a batch's rays that hit the box, padded per scene to the same count.
struct Plan {
    /// Rays decoded per scene (the most any scene has).
    per_scene: usize,
    points: Vec<f64>,
    dirs: Vec<f64>,
    /// `[b · per_scene, n]` interval lengths.
    deltas: Vec<f64>,
    /// For every input ray, its row in `[decoded rays …, background]`.
    rows: Vec<u32>,
}

impl Volumetric {
    pub fn new(cfg: &Config, ray_dim: usize, slot_dim: usize, vb: VarBuilder) -> Result<Self> {
        let Some(bounds) = cfg.bounds else {
            candle_core::bail!(
                "the volumetric decoder needs the scene's box (model.decoder.bounds): \
                 training fills it from the dataset manifest's scene_bounds"
            );
        };
        if !bounds[0]
            .iter()
            .zip(&bounds[1])
            .all(|(lo, hi)| lo.is_finite() && hi.is_finite() && lo < hi)
        {
            candle_core::bail!(
                "volumetric decoder: bounds {bounds:?} are not a box (min < max, finite)"
            );
        }
        if cfg.samples == 0 {
            candle_core::bail!("volumetric decoder: samples must be positive");
        }
        let sm = slot_mixer::Config {
            query_hidden: cfg.query_hidden,
            allocation: cfg.allocation.clone(),
            render_hidden: cfg.render_hidden.clone(),
        };
        Ok(Self {
            points: SlotMixer::with_outputs(&sm, ray_dim, slot_dim, 4, vb.clone())?,
            background: vb.get_with_hints(3, "background", candle_nn::Init::Const(0.0))?,
            cfg: cfg.clone(),
        })
    }

    /// Stratified depths on every ray that needs decoding (host work: the rays are data).
    fn plan(
        &self,
        origins: &Tensor,
        directions: &Tensor,
        offsets: Option<&Tensor>,
    ) -> Result<Plan> {
        let (b, r, _) = origins.dims3()?;
        let n = self.cfg.samples;
        let host = |t: &Tensor| t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>();
        let (o, d) = (host(origins)?, host(directions)?);
        let u = offsets.map(host).transpose()?;
        if let Some(u) = &u
            && u.len() != b * r * n
        {
            candle_core::bail!(
                "volumetric decoder: {} offsets for {b}×{r} rays of {n} points",
                u.len()
            );
        }
        let bounds = self.cfg.bounds.expect("checked at construction");
        let segments: Vec<Option<Segment>> = (0..b * r)
            .map(|i| {
                let oi = [o[3 * i], o[3 * i + 1], o[3 * i + 2]];
                let di = [d[3 * i], d[3 * i + 1], d[3 * i + 2]];
                match self.cfg.cull {
                    true => box_segment(oi, di, &bounds),
                    false => Some(sphere_segment(oi, &bounds)),
                }
            })
            .collect();
        let hits: Vec<Vec<usize>> = (0..b)
            .map(|s| (0..r).filter(|&i| segments[s * r + i].is_some()).collect())
            .collect();
        let per_scene = hits.iter().map(Vec::len).max().unwrap_or(0);
        let mut plan = Plan {
            per_scene,
            points: Vec::with_capacity(b * per_scene * n * 3),
            dirs: Vec::with_capacity(b * per_scene * n * 3),
            deltas: Vec::with_capacity(b * per_scene * n),
            rows: vec![(b * per_scene) as u32; b * r],
        };
        for (s, hit) in hits.iter().enumerate() {
            for slot in 0..per_scene {
                // Scenes with fewer hits repeat their first hit (or any ray): computed, never read.
                let i = s * r + hit.get(slot).or(hit.first()).copied().unwrap_or(0);
                if slot < hit.len() {
                    plan.rows[i] = (s * per_scene + slot) as u32;
                }
                let seg = segments[i].unwrap_or(Segment {
                    near: 0.0,
                    far: 0.0,
                });
                let step = (seg.far - seg.near) / n as f64;
                for j in 0..n {
                    let jitter = u.as_ref().map_or(0.5, |u| u[i * n + j]);
                    let t = seg.near + (j as f64 + jitter) * step;
                    for a in 0..3 {
                        plan.points.push(o[3 * i + a] + t * d[3 * i + a]);
                        plan.dirs.push(d[3 * i + a]);
                    }
                    plan.deltas.push(step);
                }
            }
        }
        Ok(plan)
    }

    /// # Shapes
    /// `slots: [b, k, ds]`, `origins`, `directions: [b, r, 3]`, `offsets: [b, r, samples]`
    /// in `[0, 1)` (training's stratification; `None`: bin centres) → rgb `[b, r, 3]`,
    /// weights `[b, r, k]`
    pub fn forward(
        &self,
        rays: &RayEncoding,
        slots: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
        offsets: Option<&Tensor>,
    ) -> Result<DecoderOutput> {
        let (b, r, _) = origins.dims3()?;
        let k = slots.dim(1)?;
        let (n, dtype, dev) = (self.cfg.samples, slots.dtype(), slots.device());
        let plan = self.plan(origins, directions, offsets)?;
        let background = candle_nn::ops::sigmoid(&self.background.to_dtype(dtype)?)?;
        let uniform = Tensor::ones((1, k), dtype, dev)?.affine(1.0 / k as f64, 0.0)?;
        let m = b * plan.per_scene; // decoded rays
        let tensor = |v: Vec<f64>, shape: &[usize], dev: &Device| {
            Tensor::from_vec(v, shape, &Device::Cpu)?
                .to_dtype(dtype)?
                .to_device(dev)
        };
        let (rgb_rows, weight_rows) = if m == 0 {
            (background.unsqueeze(0)?, uniform)
        } else {
            let p = plan.per_scene * n;
            let points = tensor(plan.points, &[b, p, 3], dev)?;
            let dirs = tensor(plan.dirs, &[b, p, 3], dev)?;
            let enc = rays.forward(&points, &dirs)?; // [b, p, ray_dim]
            let (out, w) = self.points.forward_raw(slots, &enc)?; // [b, p, 4], [b, p, k]
            let sigma = softplus(&out.narrow(D::Minus1, 0, 1)?.squeeze(D::Minus1)?)?;
            let colour = candle_nn::ops::sigmoid(&out.narrow(D::Minus1, 1, 3)?)?;
            let deltas = tensor(plan.deltas, &[m, n], dev)?;
            let sigma_delta = (sigma.reshape((m, n))? * deltas)?;
            let (rgb, sw) = composite(
                &sigma_delta,
                &colour.reshape((m, n, 3))?,
                &w.reshape((m, n, k))?,
                &background,
            )?;
            (
                Tensor::cat(&[rgb, background.unsqueeze(0)?], 0)?,
                Tensor::cat(&[sw, uniform], 0)?,
            )
        };
        let rows = Tensor::from_vec(plan.rows, b * r, dev)?;
        Ok(DecoderOutput {
            rgb: rgb_rows.index_select(&rows, 0)?.reshape((b, r, 3))?,
            weights: Some(weight_rows.index_select(&rows, 0)?.reshape((b, r, k))?),
        })
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }
}
