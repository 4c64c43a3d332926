//! The transformer block's forward and backward passes over CPU buffers: where each
//! parameter sits in the packed buffer, what the forward pass keeps, and the passes
//! themselves from the LayerNorm, projection, attention and MLP kernels of `cpu`.

use crate::cpu::attention::{self, AttentionBwd, Dims};
use crate::cpu::gemm;
use crate::cpu::layer_norm::{LayerNormBwd, LayerNormOp};
use crate::cpu::linear::{ColumnSum, add_bias_rows, matmul_xwt, weight_grad};
use crate::cpu::matrix::{MatRef, Threads};
use crate::cpu::mlp::{self, MlpBwd, Plan};
use crate::cpu::{MlpAct, f32_slice};
use crate::kept::Kept;
use candle_core::{CpuStorage, CustomOp1, CustomOp3, Layout, Result};
use rayon::prelude::*;

/// Sizes of one block call and where each parameter sits in the packed buffer.
#[derive(Debug, Clone)]
pub(super) struct Geometry {
    /// Batch, query rows per element, context rows per element (`n` for self-attention).
    pub(super) b: usize,
    pub(super) n: usize,
    pub(super) m: usize,
    /// Query and context widths, attention width, heads.
    pub(super) d: usize,
    pub(super) dc: usize,
    pub(super) inner: usize,
    pub(super) heads: usize,
    pub(super) eps: f32,
    pub(super) scale: f32,
    pub(super) mlp: Plan,
    pub(super) act: MlpAct,
    /// Self-attention: the context is the block's own normalised input.
    pub(super) self_attn: bool,
}

/// Offsets into the packed parameters: `[γ₁, β₁, W_q, W_k, W_v, W_o, b_o, γ₂, β₂, MLP]`.
struct Offsets {
    g1: usize,
    b1: usize,
    wq: usize,
    wk: usize,
    wv: usize,
    wo: usize,
    bo: usize,
    g2: usize,
    b2: usize,
    mlp: usize,
    total: usize,
}

impl Geometry {
    fn offsets(&self) -> Offsets {
        let (d, dc, inner) = (self.d, self.dc, self.inner);
        let g1 = 0;
        let b1 = g1 + d;
        let wq = b1 + d;
        let wk = wq + inner * d;
        let wv = wk + inner * dc;
        let wo = wv + inner * dc;
        let bo = wo + d * inner;
        let g2 = bo + d;
        let b2 = g2 + d;
        let mlp = b2 + d;
        Offsets {
            g1,
            b1,
            wq,
            wk,
            wv,
            wo,
            bo,
            g2,
            b2,
            mlp,
            total: mlp + self.mlp.params(),
        }
    }

    pub(super) fn rows(&self) -> usize {
        self.b * self.n
    }

    pub(super) fn ctx_rows(&self) -> usize {
        self.b * self.m
    }

    fn attention(&self) -> Dims {
        Dims {
            b: self.b,
            n: self.n,
            m: self.m,
            h: self.heads,
            dh: self.inner / self.heads,
            scale: self.scale,
            precision: self.mlp.precision,
        }
    }
}

/// What the forward pass keeps for the backward pass.
pub(super) struct Saved {
    /// `LN₁(x)`, `[R, d]`.
    h1: CpuStorage,
    /// Queries `[R, h·dh]`, keys and values `[R_ctx, h·dh]`.
    q: CpuStorage,
    k: CpuStorage,
    v: CpuStorage,
    /// The attention weights, per batch element.
    weights: attention::Saved,
    /// The attention output before its projection, `[R, h·dh]`.
    att: CpuStorage,
    /// After the attention residual, `[R, d]`, and `LN₂` of it.
    x2: CpuStorage,
    h2: CpuStorage,
    mlp: mlp::Saved,
}

fn f32_vec(s: CpuStorage, what: &str) -> Result<Vec<f32>> {
    match s {
        CpuStorage::F32(v) => Ok(v),
        _ => candle_core::bail!("{what}: fused ops take f32"),
    }
}

fn f32s<'a>(s: &'a CpuStorage, what: &str) -> Result<&'a [f32]> {
    match s {
        CpuStorage::F32(v) => Ok(v),
        _ => candle_core::bail!("{what}: fused ops take f32"),
    }
}

/// `acc[i] += other[i]` in parallel (a residual add, or a second gradient term; float
/// addition commutes, so the bits are those of candle's `other + acc`).
fn add_into(acc: &mut [f32], other: &[f32]) {
    const PER_TASK: usize = 8192;
    acc.par_chunks_mut(PER_TASK)
        .zip(other.par_chunks(PER_TASK))
        .for_each(|(a, o)| a.iter_mut().zip(o).for_each(|(a, o)| *a += *o));
}

/// `dx`, `d ctx` (cross-attention only) and the packed parameters' gradient.
type Grads = (Vec<f32>, Option<Vec<f32>>, Vec<f32>);

pub(super) struct Block<'a> {
    g: &'a Geometry,
    o: Offsets,
    p: &'a CpuStorage,
    p_l: &'a Layout,
}

impl<'a> Block<'a> {
    pub(super) fn new(g: &'a Geometry, p: &'a CpuStorage, p_l: &'a Layout) -> Result<Self> {
        let o = g.offsets();
        if p_l.shape().elem_count() != o.total {
            candle_core::bail!(
                "block: {} packed parameters, expected {}",
                p_l.shape().elem_count(),
                o.total
            );
        }
        f32_slice(p, p_l, "block parameters")?;
        Ok(Self { g, o, p, p_l })
    }

    /// `len` parameters at `off`.
    fn vec(&self, off: usize, len: usize) -> Layout {
        Layout::contiguous_with_offset(len, self.p_l.start_offset() + off)
    }

    /// A `[rows, cols]` parameter matrix at `off`.
    fn mat(&self, off: usize, rows: usize, cols: usize) -> Layout {
        Layout::contiguous_with_offset((rows, cols), self.p_l.start_offset() + off)
    }

    fn params(&self, off: usize, len: usize) -> Result<&[f32]> {
        Ok(&f32_slice(self.p, self.p_l, "block parameters")?[off..off + len])
    }

    fn layer_norm(&self, x: &CpuStorage, x_l: &Layout, g: usize, b: usize) -> Result<CpuStorage> {
        let d = self.g.d;
        let op = LayerNormOp { eps: self.g.eps };
        Ok(op
            .cpu_fwd(x, x_l, self.p, &self.vec(g, d), self.p, &self.vec(b, d))?
            .0)
    }

    /// LayerNorm's backward for its input `x: [R, d]` (laid out as `x_l`), weight at `g`
    /// and upstream `dh`: the input gradient and `[dγ | dβ]`.
    fn layer_norm_backward(
        &self,
        (x, x_l): (&CpuStorage, &Layout),
        g: usize,
        dh: Vec<f32>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let (rows, d) = (self.g.rows(), self.g.d);
        let rl = Layout::contiguous((rows, d));
        let ln = LayerNormBwd { eps: self.g.eps };
        let gl = self.vec(g, d);
        let dh = CpuStorage::F32(dh);
        let mut dx = f32_vec(ln.cpu_fwd(x, x_l, self.p, &gl, &dh, &rl)?.0, "block")?;
        let dgb = dx.split_off(rows * d);
        Ok((dx, dgb))
    }

    /// The forward pass: the output `[R, d]` and what the backward pass needs.
    pub(super) fn forward(
        &self,
        x: &CpuStorage,
        x_l: &Layout,
        ctx: Option<(&CpuStorage, &Layout)>,
    ) -> Result<(Vec<f32>, Saved)> {
        let (g, o) = (self.g, &self.o);
        let pr = g.mlp.precision;
        let (rows, d, inner) = (g.rows(), g.d, g.inner);
        let rl = Layout::contiguous((rows, d));
        let h1 = self.layer_norm(x, x_l, o.g1, o.b1)?;
        let q = CpuStorage::F32(matmul_xwt(&h1, &rl, self.p, &self.mat(o.wq, inner, d), pr)?);
        let (c, c_l) = match ctx {
            Some(c) => c,
            None => (&h1, &rl),
        };
        let proj = |off: usize| -> Result<CpuStorage> {
            let w = self.mat(off, inner, g.dc);
            Ok(CpuStorage::F32(matmul_xwt(c, c_l, self.p, &w, pr)?))
        };
        let (k, v) = (proj(o.wk)?, proj(o.wv)?);
        let dims = g.attention();
        let q_l = Layout::contiguous((g.b, g.n, inner));
        let (att, weights) = attention::forward(&dims, (&q, &q_l), (&k, 0, inner), (&v, 0, inner))?;
        let att = CpuStorage::F32(att);
        // x₂ = x + (att·W_oᵀ + b_o)
        let al = Layout::contiguous((rows, inner));
        let mut x2 = matmul_xwt(&att, &al, self.p, &self.mat(o.wo, d, inner), pr)?;
        add_bias_rows(&mut x2, self.params(o.bo, d)?);
        add_into(&mut x2, f32_slice(x, x_l, "block input")?);
        let x2 = CpuStorage::F32(x2);
        let h2 = self.layer_norm(&x2, &rl, o.g2, o.b2)?;
        let mlp_l = self.vec(o.mlp, g.mlp.params());
        let (mut y, mlp) = mlp::forward(&g.mlp, g.act, mlp::Input::One(&h2, &rl), self.p, &mlp_l)?;
        add_into(&mut y, f32s(&x2, "block")?);
        let saved = Saved {
            h1,
            q,
            k,
            v,
            weights,
            att,
            x2,
            h2,
            mlp,
        };
        Ok((y, saved))
    }

    /// The backward pass for upstream `dy: [R, d]`: `dx [R, d]`, `d ctx [R_ctx, d_ctx]`
    /// (cross-attention only) and the packed parameters' gradient.
    pub(super) fn backward(
        &self,
        x: (&CpuStorage, &Layout),
        ctx: Option<(&CpuStorage, &Layout)>,
        dy: (&CpuStorage, &Layout),
        saved: Saved,
    ) -> Result<Grads> {
        let (g, o) = (self.g, &self.o);
        let pr = g.mlp.precision;
        let (rows, crows, d, dc, inner) = (g.rows(), g.ctx_rows(), g.d, g.dc, g.inner);
        let rl = Layout::contiguous((rows, d));
        let al = Layout::contiguous((rows, inner));
        let mut dp = vec![0f32; o.total];
        let mut put = |off: usize, v: &[f32]| dp[off..off + v.len()].copy_from_slice(v);

        // MLP: dh₂ and its parameters.
        let mlp_bwd = MlpBwd {
            plan: g.mlp.clone(),
            act: g.act,
            saved: Kept::new(Some(saved.mlp)),
            input_grad: true,
        };
        let mlp_l = self.vec(o.mlp, g.mlp.params());
        let mut dh2 = f32_vec(
            mlp_bwd
                .cpu_fwd(&saved.h2, &rl, self.p, &mlp_l, dy.0, dy.1)?
                .0,
            "block",
        )?;
        put(o.mlp, &dh2.split_off(rows * d));
        // LN₂, then dx₂ = dy + LN₂'s input gradient.
        let (mut dx2, dgb2) = self.layer_norm_backward((&saved.x2, &rl), o.g2, dh2)?;
        put(o.g2, &dgb2[..d]);
        put(o.b2, &dgb2[d..]);
        add_into(&mut dx2, f32_slice(dy.0, dy.1, "block gradient")?);
        let dx2 = CpuStorage::F32(dx2);
        // Output projection.
        let dbo = ColumnSum { d }.cpu_fwd(&dx2, &rl)?.0;
        put(o.bo, f32s(&dbo, "block")?);
        put(o.wo, &weight_grad(&dx2, &rl, &saved.att, &al, pr)?);
        let wo = MatRef::of(self.p, &self.mat(o.wo, d, inner))?;
        let datt = gemm::matmul(MatRef::of(&dx2, &rl)?, wo, Threads::Pool, pr)?;
        // Attention: [dq | dk | dv].
        let att_bwd = AttentionBwd {
            dims: g.attention(),
            saved: Kept::new(Some(saved.weights)),
        };
        let q_l = Layout::contiguous((g.b, g.n, inner));
        let grads = CpuStorage::F32(att_bwd.backward(
            (&saved.q, &q_l),
            (&saved.k, 0, inner),
            (&saved.v, 0, inner),
            (&CpuStorage::F32(datt), &q_l),
        )?);
        let dq_l = Layout::contiguous((rows, inner));
        let dk_l = Layout::contiguous_with_offset((crows, inner), rows * inner);
        let dv_l = Layout::contiguous_with_offset((crows, inner), (rows + crows) * inner);
        // Projections: W_q from LN₁(x), W_k and W_v from the context.
        put(o.wq, &weight_grad(&grads, &dq_l, &saved.h1, &rl, pr)?);
        let (c, c_l) = match ctx {
            Some(c) => c,
            None => (&saved.h1, &rl),
        };
        put(o.wk, &weight_grad(&grads, &dk_l, c, c_l, pr)?);
        put(o.wv, &weight_grad(&grads, &dv_l, c, c_l, pr)?);
        let w = |off: usize| MatRef::of(self.p, &self.mat(off, inner, dc));
        let mut dc_ = gemm::matmul(MatRef::of(&grads, &dk_l)?, w(o.wk)?, Threads::Pool, pr)?;
        let dcv = gemm::matmul(MatRef::of(&grads, &dv_l)?, w(o.wv)?, Threads::Pool, pr)?;
        add_into(&mut dc_, &dcv);
        let wq = MatRef::of(self.p, &self.mat(o.wq, inner, d))?;
        let mut dh1 = gemm::matmul(MatRef::of(&grads, &dq_l)?, wq, Threads::Pool, pr)?;
        let dctx = match g.self_attn {
            true => {
                add_into(&mut dh1, &dc_);
                None
            }
            false => Some(dc_),
        };
        // LN₁, then dx = dx₂ + LN₁'s input gradient.
        let (mut dx, dgb1) = self.layer_norm_backward(x, o.g1, dh1)?;
        put(o.g1, &dgb1[..d]);
        put(o.b1, &dgb1[d..]);
        add_into(&mut dx, f32s(&dx2, "block")?);
        Ok((dx, dctx, dp))
    }
}
