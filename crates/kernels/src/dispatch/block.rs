//! The choice of the transformer block: one fused CPU node where it applies, else `None`
//! (the caller composes the block from the separate ops).

use super::mlp::{layers_of, operands};
use super::usable;
use crate::graph::block::{BlockParams, block_node};
use crate::profile;
use candle_core::{Result, Tensor};

/// A pre-LayerNorm transformer block, `x + Attn(LN₁(x), ctx)` then `x + MLP(LN₂(x))`, as
/// one graph node, or `None` where the fused block does not apply (then the caller
/// composes it from the separate ops). With `ctx = None` it is self-attention.
///
/// # Shapes
/// `x: [b, n, d]`, `ctx: [b, m, d_ctx]` → `[b, n, d]`
pub fn block(x: &Tensor, ctx: Option<&Tensor>, p: &BlockParams) -> Result<Option<Tensor>> {
    let here = || crate::ledger::within("block", || block_here(x, ctx, p));
    let Some(rec) = profile::current() else {
        return here();
    };
    let y = profile::nested(here)?;
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
        let (all, biased) = operands(&lead, &p.mlp);
        let (act, heads, eps, n) = (p.act, p.heads, p.eps, lead.len());
        let rerun = move |t: &[Tensor]| -> Result<Vec<Tensor>> {
            let params = BlockParams {
                norm_attn: (&t[1], &t[2]),
                q: &t[3],
                k: &t[4],
                v: &t[5],
                out: (&t[6], &t[7]),
                norm_mlp: (&t[8], &t[9]),
                mlp: layers_of(&t[n..], &biased),
                act,
                heads,
                eps,
            };
            match block_here(&t[0], t[10..n].first(), &params)? {
                Some(y) => Ok(vec![y]),
                None => candle_core::bail!("profile: the recorded block no longer fits"),
            }
        };
        profile::record(&rec, "block", &all, std::sync::Arc::new(rerun));
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
    if !usable(&all) {
        return Ok(None);
    }
    block_node(x, ctx, p)
}

#[cfg(test)]
mod tests;
