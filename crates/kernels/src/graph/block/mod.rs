//! A whole pre-LayerNorm transformer block — `x + Attn(LN(x), ctx)`, then `x + MLP(LN(x))`
//! — as one graph node with a hand-written backward pass.
//!
//! Why: as separate fused ops a block is ten graph nodes (two LayerNorms, the q, k, v and
//! output projections, the attention core, the MLP, two residual adds), and candle's
//! backward gives each one that carries a gradient a zero tensor and an add of its input
//! gradient, on the calling thread. In the Slot Mixer's allocation transformer six of
//! those tensors are `[8192, 96–128]` (all of a step's target rays), and such
//! accumulations are the largest serial share of a 2-thread step of separate ops
//! (docs/performance.md). As one node only the block's own input and output are
//! accumulated, and the residual adds run inside the op's parallel passes.
//!
//! The parameters enter packed (`Tensor::cat` of the flattened tensors, as in `cpu::mlp`),
//! so the variables, their names and checkpoints stay as they are. The arithmetic is the
//! separate ops', kernel for kernel: the same LayerNorm, projection, attention and MLP
//! kernels on the same operands, and the forward pass gives the same bits (tested); in
//! the backward pass only the order in which a tensor's gradient terms are summed may
//! differ.

mod pass;

use crate::cpu::mlp::{MlpLayer, Plan};
use crate::cpu::{MlpAct, cpu_storage as cpu, f32_slice, rows_layout};
use crate::kept::Kept;
use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use pass::{Block, Geometry, Saved};

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
        crate::ledger::backward("", "block", || {
            let (dx, _, dp) = self.grads(x, None, p, grad)?;
            Ok((dx, Some(dp)))
        })
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
        crate::ledger::backward("", "block", || {
            let (dx, dctx, dp) = self.grads(x, Some(ctx), p, grad)?;
            Ok((dx, dctx, Some(dp)))
        })
    }
}

/// The block as one node (f32 on the CPU; see [`crate::block`]), or `None` where the
/// shapes do not fit it (then the caller composes the block from the separate ops).
pub(crate) fn block_node(
    x: &Tensor,
    ctx: Option<&Tensor>,
    p: &BlockParams,
) -> Result<Option<Tensor>> {
    if !(x.rank() == 3 && ctx.is_none_or(|c| c.rank() == 3)) {
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
            precision: crate::precision(),
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
