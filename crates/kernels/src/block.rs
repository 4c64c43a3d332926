//! A whole pre-LayerNorm transformer block — `x + Attn(LN(x), ctx)`, then `x + MLP(LN(x))`
//! — as one graph node with a hand-written backward pass.
//!
//! Why: as separate fused ops a block is ten graph nodes (two LayerNorms, the q, k, v and
//! output projections, the attention core, the MLP, two residual adds), and candle's
//! backward gives each one that carries a gradient a zero tensor and an add of its input
//! gradient, on the calling thread. In the Slot Mixer's allocation transformer six of
//! those tensors are `[8192, 96–128]` (all of a step's target rays), and such
//! accumulations were the largest serial share of a 2-thread step (docs/performance.md,
//! profile of 2026-11-25). As one node only the block's own input and output are
//! accumulated, and the residual adds run inside the op's parallel passes.
//!
//! The parameters enter packed (`Tensor::cat` of the flattened tensors, as in `mlp.rs`),
//! so the variables, their names and checkpoints stay as they are. The arithmetic is the
//! separate ops', kernel for kernel: the same LayerNorm, projection, attention and MLP
//! kernels on the same operands, and the forward pass gives the same bits (tested); in
//! the backward pass only the order in which a tensor's gradient terms are summed may
//! differ.

use super::attention::{self, AttentionBwd, Dims};
use super::gemm::{self, MatRef, Threads};
use super::mlp::{self, MlpAct, MlpBwd, MlpLayer, Plan};
use super::{
    ColumnSum, Kept, LayerNormBwd, LayerNormOp, add_bias_rows, cpu_storage as cpu, f32_slice,
    matmul_xwt, rows_layout, usable, weight_grad,
};
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// The tensors of one block (those of `nn::Block`).
pub struct BlockParams<'a> {
    /// LayerNorm before attention: weight, bias `[d]`.
    pub norm_attn: (&'a Tensor, &'a Tensor),
    /// Bias-free projections: q `[h·dh, d]`, k and v `[h·dh, d_ctx]`.
    pub q: &'a Tensor,
    pub k: &'a Tensor,
    pub v: &'a Tensor,
    /// Output projection: weight `[d, h·dh]`, bias `[d]`.
    pub out: (&'a Tensor, &'a Tensor),
    /// LayerNorm before the MLP.
    pub norm_mlp: (&'a Tensor, &'a Tensor),
    /// The MLP `d → … → d`, every layer with a bias.
    pub mlp: Vec<MlpLayer<'a>>,
    pub act: MlpAct,
    pub heads: usize,
    /// The LayerNorms' ε.
    pub eps: f64,
}

/// Sizes of one block call and where each parameter sits in the packed buffer.
#[derive(Debug, Clone)]
struct Geometry {
    /// Batch, query rows per element, context rows per element (`n` for self-attention).
    b: usize,
    n: usize,
    m: usize,
    /// Query and context widths, attention width, heads.
    d: usize,
    dc: usize,
    inner: usize,
    heads: usize,
    eps: f32,
    scale: f32,
    mlp: Plan,
    act: MlpAct,
    /// Self-attention: the context is the block's own normalised input.
    self_attn: bool,
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

    fn rows(&self) -> usize {
        self.b * self.n
    }

    fn ctx_rows(&self) -> usize {
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
        }
    }
}

/// What the forward pass keeps for the backward pass.
struct Saved {
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

struct Block<'a> {
    g: &'a Geometry,
    o: Offsets,
    p: &'a CpuStorage,
    p_l: &'a Layout,
}

impl<'a> Block<'a> {
    fn new(g: &'a Geometry, p: &'a CpuStorage, p_l: &'a Layout) -> Result<Self> {
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
    fn forward(
        &self,
        x: &CpuStorage,
        x_l: &Layout,
        ctx: Option<(&CpuStorage, &Layout)>,
    ) -> Result<(Vec<f32>, Saved)> {
        let (g, o) = (self.g, &self.o);
        let (rows, d, inner) = (g.rows(), g.d, g.inner);
        let rl = Layout::contiguous((rows, d));
        let h1 = self.layer_norm(x, x_l, o.g1, o.b1)?;
        let q = CpuStorage::F32(matmul_xwt(&h1, &rl, self.p, &self.mat(o.wq, inner, d))?);
        let (c, c_l) = match ctx {
            Some(c) => c,
            None => (&h1, &rl),
        };
        let proj = |off: usize| -> Result<CpuStorage> {
            let w = self.mat(off, inner, g.dc);
            Ok(CpuStorage::F32(matmul_xwt(c, c_l, self.p, &w)?))
        };
        let (k, v) = (proj(o.wk)?, proj(o.wv)?);
        let dims = g.attention();
        let q_l = Layout::contiguous((g.b, g.n, inner));
        let (att, weights) = attention::forward(&dims, (&q, &q_l), (&k, 0, inner), (&v, 0, inner))?;
        let att = CpuStorage::F32(att);
        // x₂ = x + (att·W_oᵀ + b_o)
        let al = Layout::contiguous((rows, inner));
        let mut x2 = matmul_xwt(&att, &al, self.p, &self.mat(o.wo, d, inner))?;
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
    fn backward(
        &self,
        x: (&CpuStorage, &Layout),
        ctx: Option<(&CpuStorage, &Layout)>,
        dy: (&CpuStorage, &Layout),
        saved: Saved,
    ) -> Result<Grads> {
        let (g, o) = (self.g, &self.o);
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
        put(o.wo, &weight_grad(&dx2, &rl, &saved.att, &al)?);
        let wo = MatRef::of(self.p, &self.mat(o.wo, d, inner))?;
        let datt = gemm::matmul(MatRef::of(&dx2, &rl)?, wo, Threads::Pool)?;
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
        put(o.wq, &weight_grad(&grads, &dq_l, &saved.h1, &rl)?);
        let (c, c_l) = match ctx {
            Some(c) => c,
            None => (&saved.h1, &rl),
        };
        put(o.wk, &weight_grad(&grads, &dk_l, c, c_l)?);
        put(o.wv, &weight_grad(&grads, &dv_l, c, c_l)?);
        let w = |off: usize| MatRef::of(self.p, &self.mat(off, inner, dc));
        let mut dc_ = gemm::matmul(MatRef::of(&grads, &dk_l)?, w(o.wk)?, Threads::Pool)?;
        let dcv = gemm::matmul(MatRef::of(&grads, &dv_l)?, w(o.wv)?, Threads::Pool)?;
        add_into(&mut dc_, &dcv);
        let wq = MatRef::of(self.p, &self.mat(o.wq, inner, d))?;
        let mut dh1 = gemm::matmul(MatRef::of(&grads, &dq_l)?, wq, Threads::Pool)?;
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

struct BlockOp {
    g: Geometry,
    /// Whether a backward pass can follow: only then is the forward pass's state kept.
    keep: bool,
    saved: Kept<Saved>,
}

impl BlockOp {
    fn fwd(
        &self,
        x: &CpuStorage,
        x_l: &Layout,
        ctx: Option<(&CpuStorage, &Layout)>,
        p: &CpuStorage,
        p_l: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let rows = rows_layout(x_l)?;
        if rows.dims() != [self.g.rows(), self.g.d] {
            candle_core::bail!("block: input {:?} for {:?}", x_l.dims(), self.g);
        }
        let ctx = match ctx {
            Some((c, c_l)) => {
                let c_rows = rows_layout(c_l)?;
                if c_rows.dims() != [self.g.ctx_rows(), self.g.dc] {
                    candle_core::bail!("block: context {:?} for {:?}", c_l.dims(), self.g);
                }
                f32_slice(c, c_l, "block context")?;
                Some((c, c_rows))
            }
            None => None,
        };
        let ctx = ctx.as_ref().map(|(c, l)| (*c, l));
        let (y, saved) = Block::new(&self.g, p, p_l)?.forward(x, &rows, ctx)?;
        if self.keep {
            self.saved.put(saved);
        }
        Ok((CpuStorage::F32(y), x_l.shape().clone()))
    }

    /// The gradients of input, context (cross-attention) and packed parameters.
    fn grads(
        &self,
        x: &Tensor,
        ctx: Option<&Tensor>,
        p: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Tensor)> {
        let grad = grad.contiguous()?;
        let (xs, x_l) = x.storage_and_layout();
        let (ps, p_l) = p.storage_and_layout();
        let (gs, g_l) = grad.storage_and_layout();
        let cs = ctx.map(|c| c.storage_and_layout());
        let (xs, ps, gs) = (cpu(&xs)?, cpu(&ps)?, cpu(&gs)?);
        let ctx_cpu = match &cs {
            Some((s, l)) => Some((cpu(s)?, rows_layout(l)?)),
            None => None,
        };
        let block = Block::new(&self.g, ps, p_l)?;
        let x_rows = rows_layout(x_l)?;
        let ctx_ref = ctx_cpu.as_ref().map(|(s, l)| (*s, l));
        // Taken, not cloned: a second backward through the same graph recomputes it.
        let saved = match self.saved.take() {
            Some(s) => s,
            None => block.forward(xs, &x_rows, ctx_ref)?.1,
        };
        let g_rows = rows_layout(g_l)?;
        let (dx, dctx, dp) = block.backward((xs, &x_rows), ctx_ref, (gs, &g_rows), saved)?;
        let dev = x.device();
        let dx = match x.track_op() {
            true => Some(Tensor::from_vec(dx, x.shape(), dev)?),
            false => None,
        };
        let dctx = match (ctx, dctx) {
            (Some(c), Some(v)) if c.track_op() => Some(Tensor::from_vec(v, c.shape(), dev)?),
            _ => None,
        };
        Ok((dx, dctx, Tensor::from_vec(dp, p.shape(), dev)?))
    }
}

impl CustomOp2 for BlockOp {
    fn name(&self) -> &'static str {
        "osrt-block-self"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.fwd(s1, l1, None, s2, l2)
    }

    fn bwd(
        &self,
        x: &Tensor,
        p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (dx, _, dp) = self.grads(x, None, p, grad)?;
        Ok((dx, Some(dp)))
    }
}

impl CustomOp3 for BlockOp {
    fn name(&self) -> &'static str {
        "osrt-block-cross"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.fwd(s1, l1, Some((s2, l2)), s3, l3)
    }

    fn bwd(
        &self,
        x: &Tensor,
        ctx: &Tensor,
        p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (dx, dctx, dp) = self.grads(x, Some(ctx), p, grad)?;
        Ok((dx, dctx, Some(dp)))
    }
}

/// A pre-LayerNorm transformer block, `x + Attn(LN₁(x), ctx)` then `x + MLP(LN₂(x))`, as
/// one graph node, or `None` where the fused block does not apply (then the caller
/// composes it from the separate ops). With `ctx = None` it is self-attention.
///
/// # Shapes
/// `x: [b, n, d]`, `ctx: [b, m, d_ctx]` → `[b, n, d]`
pub fn block(x: &Tensor, ctx: Option<&Tensor>, p: &BlockParams) -> Result<Option<Tensor>> {
    let Some(rec) = crate::profile::current() else {
        return block_here(x, ctx, p);
    };
    let y = crate::profile::nested(|| block_here(x, ctx, p))?;
    if y.is_some() {
        // The operands in one list: x, the eight attention-half tensors, the context if
        // any, then the MLP's layers.
        let mut lead = vec![
            x,
            p.norm_attn.0,
            p.norm_attn.1,
            p.q,
            p.k,
            p.v,
            p.out.0,
            p.out.1,
        ];
        lead.extend([p.norm_mlp.0, p.norm_mlp.1]);
        lead.extend(ctx);
        let (all, biased) = crate::mlp::operands(&lead, &p.mlp);
        let (act, heads, eps, n) = (p.act, p.heads, p.eps, lead.len());
        let rerun = move |t: &[Tensor]| -> Result<Vec<Tensor>> {
            let params = BlockParams {
                norm_attn: (&t[1], &t[2]),
                q: &t[3],
                k: &t[4],
                v: &t[5],
                out: (&t[6], &t[7]),
                norm_mlp: (&t[8], &t[9]),
                mlp: crate::mlp::layers_of(&t[n..], &biased),
                act,
                heads,
                eps,
            };
            match block_here(&t[0], t[10..n].first(), &params)? {
                Some(y) => Ok(vec![y]),
                None => candle_core::bail!("profile: the recorded block no longer fits"),
            }
        };
        crate::profile::record(&rec, "block", &all, std::sync::Arc::new(rerun));
    }
    Ok(y)
}

fn block_here(x: &Tensor, ctx: Option<&Tensor>, p: &BlockParams) -> Result<Option<Tensor>> {
    let mut all = vec![
        x,
        p.norm_attn.0,
        p.norm_attn.1,
        p.q,
        p.k,
        p.v,
        p.out.0,
        p.out.1,
    ];
    all.extend([p.norm_mlp.0, p.norm_mlp.1]);
    all.extend(ctx);
    for (w, b) in &p.mlp {
        all.push(w);
        all.extend(*b);
    }
    if !(usable(&all) && x.rank() == 3 && ctx.is_none_or(|c| c.rank() == 3)) {
        return Ok(None);
    }
    let (b, n, d) = x.dims3()?;
    let (m, dc) = match ctx {
        Some(c) => {
            let (bc, m, dc) = c.dims3()?;
            if bc != b {
                candle_core::bail!("block: input {:?}, context {:?}", x.dims(), c.dims());
            }
            (m, dc)
        }
        None => (n, d),
    };
    let (inner, heads) = (p.q.dim(0)?, p.heads);
    let mut mlp_dims = vec![d];
    for (w, bias) in &p.mlp {
        let (out, k) = w.dims2()?;
        if bias.is_none() || k != *mlp_dims.last().unwrap_or(&0) {
            return Ok(None);
        }
        mlp_dims.push(out);
    }
    let shapes_fit = p.q.dims() == [inner, d]
        && p.k.dims() == [inner, dc]
        && p.v.dims() == [inner, dc]
        && p.out.0.dims() == [d, inner]
        && heads > 0
        && inner % heads == 0
        && mlp_dims.len() >= 2
        && mlp_dims.last() == Some(&d)
        && n > 0
        && m > 0;
    if !shapes_fit {
        return Ok(None);
    }
    let g = Geometry {
        b,
        n,
        m,
        d,
        dc,
        inner,
        heads,
        eps: p.eps as f32,
        scale: 1.0 / ((inner / heads) as f32).sqrt(),
        mlp: Plan {
            dims: mlp_dims,
            bias: true,
        },
        act: p.act,
        self_attn: ctx.is_none(),
    };
    let mut flat = vec![
        p.norm_attn.0.flatten_all()?,
        p.norm_attn.1.flatten_all()?,
        p.q.flatten_all()?,
        p.k.flatten_all()?,
        p.v.flatten_all()?,
        p.out.0.flatten_all()?,
        p.out.1.flatten_all()?,
        p.norm_mlp.0.flatten_all()?,
        p.norm_mlp.1.flatten_all()?,
    ];
    for (w, b) in &p.mlp {
        flat.push(w.flatten_all()?);
        flat.extend(b.map(|b| b.flatten_all()).transpose()?);
    }
    let packed = Tensor::cat(&flat, 0)?;
    let op = BlockOp {
        keep: x.track_op() || packed.track_op() || ctx.is_some_and(|c| c.track_op()),
        g,
        saved: Kept::new(None),
    };
    let x = x.contiguous()?;
    Ok(Some(match ctx {
        Some(c) => x.apply_op3(&c.contiguous()?, &packed, op)?,
        None => x.apply_op2(&packed, op)?,
    }))
}

#[cfg(test)]
mod tests;
