//! A whole MLP as one graph node built from tensor ops and the bias-with-activation
//! kernels, for devices without the fused CPU MLP (a GPU: the products are cuBLAS's).
//!
//! Why: layer by layer, every product and every bias-with-activation is a node of
//! candle's graph, which holds every node's output until the end of the backward pass
//! and gives each node's gradient a zero tensor and an add; in bf16 each product also
//! casts its f32 input again. This node runs the same ops on detached tensors and keeps
//! for the backward pass one tensor per hidden layer: its product's output (the
//! pre-activation before the bias) in the products' precision. A layer's input is not
//! kept: the first is the node's own input, and each later one is made again in the
//! backward pass from the layer before's kept output by the same bias-with-activation op
//! (and, in bf16, the same rounding), so it has the forward pass's bits. That is one
//! tensor per hidden layer where PyTorch keeps one (ReLU: its output) or two (GELU: its
//! input and output), in f32 or, in bf16, half the bytes, as autocast keeps them; the
//! price is one elementwise pass per hidden layer in the backward pass. The backward pass
//! takes them layer by layer, so each is freed once used.

use super::handover::Handover;
use super::links::{ParamGrads, link};
use super::node::{Node, TensorNode};
use crate::cpu::MlpAct;
use crate::cpu::bias_act::{
    BiasActOp, bias_act_bwd_in_place, bias_act_bwd_low, bias_act_in_place, bias_act_low,
};
use crate::cpu::linear::ColumnSum;
use crate::cpu::mlp::MlpLayer;
use crate::kept::Kept;
use crate::ledger;
use candle_core::{DType, Result, Tensor};

/// `x: [.., in]` through biased `layers` with `act` between them → `[.., out]` (f32), the
/// products in bf16 where `bf16` is set. `None` where a layer has no bias or an operand
/// is not f32 (the caller goes layer by layer).
pub(crate) fn mlp_node(
    x: &Tensor,
    layers: &[MlpLayer],
    act: MlpAct,
    bf16: bool,
) -> Result<Option<Tensor>> {
    mlp_node_of(&[x], layers, act, bf16)
}

/// [`mlp_node`] of the concatenation `a ⊕ b` (`[.., in_a]`, `[.., in_b]`, the same leading
/// dims): the node concatenates detached copies, in the forward pass and again in the
/// backward pass, so the graph keeps `a` and `b` (which it holds anyway when another op
/// reads them) and no concatenated copy (the Slot Mixer's render MLP at 8,192 rays and
/// batch 2: 112 MB). The values and gradients are those of the MLP of `Tensor::cat`.
/// With `bf16`, a part may be stored in bf16 (`crate::matmul_low`): the node reads its
/// exact f32 values and returns its gradient in bf16.
pub(crate) fn mlp_cat_node(
    a: &Tensor,
    b: &Tensor,
    layers: &[MlpLayer],
    act: MlpAct,
    bf16: bool,
) -> Result<Option<Tensor>> {
    let r = a.rank();
    if r == 0 || b.rank() != r || a.dims()[..r - 1] != b.dims()[..r - 1] {
        return Ok(None);
    }
    mlp_node_of(&[a, b], layers, act, bf16)
}

/// The node over the concatenation of one or two `parts` (see [`mlp_cat_node`]).
fn mlp_node_of(
    parts: &[&Tensor],
    layers: &[MlpLayer],
    act: MlpAct,
    bf16: bool,
) -> Result<Option<Tensor>> {
    // A part may be stored in bf16 (`crate::matmul_low`) where the products are bf16.
    let part_fits = |x: &&Tensor| {
        x.rank() > 0 && (x.dtype() == DType::F32 || (bf16 && x.dtype() == DType::BF16))
    };
    let f32s = parts.iter().all(part_fits)
        && layers.iter().all(|(w, b)| {
            w.dtype() == DType::F32 && w.rank() == 2 && b.is_some_and(|b| b.dtype() == DType::F32)
        });
    if !f32s || layers.is_empty() {
        return Ok(None);
    }
    let params: Vec<(Tensor, Tensor)> = layers
        .iter()
        .filter_map(|(w, b)| Some((w.detach(), (*b)?.detach())))
        .collect();
    let lead = parts[0].dims().split_last().expect("rank ≥ 1").1.to_vec();
    // Each part as rows `[rows, width]`.
    let rows: Vec<Tensor> = parts
        .iter()
        .map(|x| x.reshape(((), x.dim(candle_core::D::Minus1)?)))
        .collect::<Result<_>>()?;
    let widths: Vec<usize> = rows.iter().map(|x| x.dim(1)).collect::<Result<_>>()?;
    let plan = Plan { act, bf16, params };
    let keep = parts.iter().any(|x| x.track_op())
        || layers
            .iter()
            .any(|(w, b)| w.track_op() || b.is_some_and(|b| b.track_op()));
    let (y, saved) = plan.forward(plan.joined(&rows)?, keep)?;
    let pairs: Vec<&Tensor> = layers
        .iter()
        .flat_map(|(w, b)| [*w, b.expect("checked")])
        .collect();
    let (chain, grads) = link(&pairs)?;
    let node = MlpNode {
        out: Handover::new(y)?,
        saved: Kept::new(saved),
        plan,
        grads,
        widths,
    };
    let mut out = lead;
    out.push(layers.last().expect("not empty").0.dim(0)?);
    let y = match &rows[..] {
        [x] => x.apply_op2(&chain, Node::new(node))?,
        [a, b] => a.apply_op3(b, &chain, Node::new(node))?,
        _ => candle_core::bail!("mlp node: one or two inputs"),
    };
    Ok(Some(y.reshape(out)?))
}

/// What the backward pass needs: each hidden layer's product output (the pre-activation
/// before its bias), in the products' precision.
type Saved = Vec<Tensor>;

struct Plan {
    act: MlpAct,
    bf16: bool,
    /// Each layer's weight `[out, in]` and bias `[out]`, detached.
    params: Vec<(Tensor, Tensor)>,
}

impl Plan {
    /// The node's input as the first product reads it: the part's rows, or the parts' rows
    /// side by side, detached, in the products' precision. In bf16 each part is rounded
    /// before the concatenation (the values of rounding after it), so that no f32 copy
    /// of the whole input is made.
    fn joined(&self, rows: &[Tensor]) -> Result<Tensor> {
        let dtype = match self.bf16 {
            true => DType::BF16,
            false => DType::F32,
        };
        match rows {
            [x] => ledger::cast(&x.detach(), dtype),
            _ => {
                let parts = rows
                    .iter()
                    .map(|t| ledger::cast(&t.detach(), dtype))
                    .collect::<Result<Vec<_>>>()?;
                let joined = Tensor::cat(&parts, 1)?;
                ledger::cast_of(joined.elem_count(), dtype, dtype);
                Ok(joined)
            }
        }
    }

    /// An operand in the products' precision.
    fn low(&self, t: &Tensor) -> Result<Tensor> {
        match self.bf16 {
            true => ledger::cast(t, DType::BF16),
            false => Ok(t.clone()),
        }
    }

    /// A product's result back in f32.
    fn high(&self, t: Tensor) -> Result<Tensor> {
        match self.bf16 {
            true => ledger::cast(&t, DType::F32),
            false => Ok(t),
        }
    }

    /// Layer `i`'s product output `z: [rows, out]` (products' precision) with its bias and,
    /// on a hidden layer, the activation: `[rows, out]` in f32. In bf16 the widened copy of
    /// `z` is this node's own and is overwritten (one f32 buffer where there were two).
    fn finish(&self, i: usize, z: &Tensor) -> Result<Tensor> {
        let hidden = i + 1 < self.params.len();
        let act = hidden.then_some(self.act);
        let b = &self.params[i].1;
        match self.bf16 {
            true => {
                let h = ledger::contiguous(&ledger::cast(z, DType::F32)?)?;
                bias_act_in_place(&h, b, act)?;
                ledger::op("bias_act", &[&h, b], &[&h]);
                Ok(h)
            }
            false => {
                let h = ledger::contiguous(z)?.apply_op2_no_bwd(b, &BiasActOp { act })?;
                ledger::op("bias_act", &[z, b], &[&h]);
                Ok(h)
            }
        }
    }

    /// A hidden layer `i`'s output as the next product reads it: [`Plan::finish`] in the
    /// products' precision (in bf16 one op from the bf16 product to the bf16 output, the
    /// bits of widening, finishing and rounding, with no f32 tensor of the layer's size).
    fn finish_low(&self, i: usize, z: &Tensor) -> Result<Tensor> {
        match self.bf16 {
            true => {
                let h = bias_act_low(z, &self.params[i].1, Some(self.act))?;
                ledger::op("bias_act", &[z, &self.params[i].1], &[&h]);
                Ok(h)
            }
            false => self.finish(i, z),
        }
    }

    /// `[rows, in] → [rows, out]`, and what the backward pass needs where `keep` is set.
    /// Each layer as `linear_act` composes it: the product with the weight's transpose
    /// (in bf16 a contiguous copy of it), then the bias with the activation in f32.
    /// Each layer's input goes once its product is made (the first one too, where the
    /// caller gave up `x`).
    fn forward(&self, x: Tensor, keep: bool) -> Result<(Tensor, Option<Saved>)> {
        let mut saved = Vec::with_capacity(self.params.len());
        let mut h = x;
        for (i, (w, _)) in self.params.iter().enumerate() {
            let z = ledger::mm(&self.low(&h)?, &self.low(&w.t()?)?)?;
            drop(h);
            h = match i + 1 < self.params.len() {
                true => self.finish_low(i, &z)?,
                false => self.finish(i, &z)?,
            };
            if keep && i + 1 < self.params.len() {
                saved.push(z);
            }
        }
        Ok((h, keep.then_some(saved)))
    }

    /// Layer `i`'s input in the products' precision, as the forward pass made it: the
    /// node's input `x() : [rows, in]`, or the layer before's output made again from its
    /// kept product output.
    fn input(&self, i: usize, x: &dyn Fn() -> Result<Tensor>, saved: &Saved) -> Result<Tensor> {
        match i {
            0 => self.low(&x()?),
            _ => self.finish_low(i - 1, &saved[i - 1]),
        }
    }

    /// The gradients of the input `x() : [rows, in]` (where `want_dx`, in the products'
    /// precision as their product made it) and of the parameters (each weight
    /// `[out, in]` then its bias `[out]`, first layer first), from
    /// the output's `dy`: per layer what candle's backward pass of `linear_act` computes,
    /// in the same products. The input is made when the first layer needs it, and each
    /// tensor goes once used: the step's peak is inside this pass (the Slot Mixer's
    /// render MLP in bf16 at 8,192 rays, batch 2: the joined input, 112 MB, and one
    /// gradient of a hidden layer, 101 MB, were held across every layer).
    fn backward(
        &self,
        mut saved: Saved,
        x: &dyn Fn() -> Result<Tensor>,
        dy: &Tensor,
        want_dx: bool,
    ) -> Result<(Option<Tensor>, Vec<Tensor>)> {
        if saved.len() + 1 != self.params.len() {
            candle_core::bail!(
                "mlp node: {} kept tensors for {} layers",
                saved.len(),
                self.params.len()
            );
        }
        // The gradient of the current layer's output: `dy` (f32), then each product's.
        let mut g = dy.clone();
        let mut parts = Vec::with_capacity(2 * self.params.len());
        let mut dx = None;
        for (i, (w, b)) in self.params.iter().enumerate().rev() {
            // This layer's kept output is used for the last time here (the layer after
            // made its input from it already).
            // `g` is taken, so that it is freed once read.
            let g_out = g;
            let dz = match (i + 1 < self.params.len(), self.bf16) {
                // In bf16 the kept product and `g` (the layer after's bf16 product) are read
                // widened by one op: no f32 copy of either.
                (true, true) => {
                    let z = saved.pop().expect("checked");
                    let dz = bias_act_bwd_low(&z, b, &g_out, self.act)?;
                    ledger::op("bias_act backward", &[&z, b, &g_out], &[&dz]);
                    dz
                }
                // In f32 the kept product is this node's own: its gradient is written over it.
                (true, false) => {
                    let z = ledger::contiguous(&saved.pop().expect("checked"))?;
                    bias_act_bwd_in_place(&z, b, &g_out, self.act)?;
                    ledger::op("bias_act backward", &[&z, b, &g_out], &[&z]);
                    z
                }
                (false, _) => ledger::contiguous(&g_out)?,
            };
            drop(g_out);
            let db = dz.apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?;
            ledger::op("column sum", &[&dz], &[&db]);
            // In bf16 the f32 gradient goes here: the products read the rounded one.
            let dz_low = self.low(&dz)?;
            drop(dz);
            let dz = dz_low;
            let wt = self.low(&w.t()?)?;
            // The product was `input · wt`: wt's gradient is inputᵀ · dz, the input's dz · wtᵀ.
            let input = self.input(i, x, &saved)?;
            let dwt = self.high(ledger::mm(&input.t()?, &dz)?)?;
            drop(input);
            parts.push(db.reshape(b.shape())?);
            parts.push(dwt.t()?);
            if i == 0 && !want_dx {
                break;
            }
            let dinput = ledger::mm(&dz, &wt.t()?)?;
            if i == 0 {
                // In the products' precision: each part takes it in its own (see
                // `MlpNode::backward`), with no f32 copy of the whole input's gradient.
                dx = Some(dinput);
                break;
            }
            // In the products' precision (bf16: what `bias_act_bwd_low` reads).
            g = ledger::contiguous(&dinput)?;
        }
        parts.reverse();
        Ok((dx, parts))
    }
}

struct MlpNode {
    out: Handover,
    saved: Kept<Saved>,
    plan: Plan,
    /// Where the parameters' gradients go to their links (`graph::links`).
    grads: ParamGrads,
    /// The widths of the input's parts (one, or two side by side).
    widths: Vec<usize>,
}

impl MlpNode {
    /// The layers backward, last first (see [`Plan::backward`]), from the input's parts
    /// `rows` (`[rows, width]` each): the gradient of each part that carries one. A second
    /// backward pass through the same graph finds the kept tensors gone and runs the
    /// forward pass again.
    fn parts_backward(&self, rows: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let owned: Vec<Tensor> = rows.iter().map(|t| (*t).clone()).collect();
        let saved = match self.saved.take() {
            Some(s) => s,
            None => match self.plan.forward(self.plan.joined(&owned)?, true)?.1 {
                Some(s) => s,
                None => candle_core::bail!("mlp node: nothing kept"),
            },
        };
        let want = rows.iter().any(|t| t.track_op());
        let (dx, dp) = self
            .plan
            .backward(saved, &|| self.plan.joined(&owned), grad, want)?;
        self.grads.put(dp);
        // Each part's gradient in the part's type (a view of `dx` where that is the products'
        // type: candle adds it to a fresh tensor at once).
        let mut start = 0;
        let mut out = Vec::with_capacity(rows.len());
        for (t, &w) in rows.iter().zip(&self.widths) {
            out.push(match (&dx, t.track_op()) {
                (Some(dx), true) if rows.len() == 1 => Some(ledger::cast(dx, t.dtype())?),
                (Some(dx), true) => Some(ledger::cast(&dx.narrow(1, start, w)?, t.dtype())?),
                _ => None,
            });
            start += w;
        }
        Ok(out)
    }
}

/// The chain carries no value (see `links.rs`): a zero gradient sends candle down it.
fn chain_grad(chain: &Tensor) -> Result<Option<Tensor>> {
    chain.track_op().then(|| chain.zeros_like()).transpose()
}

impl TensorNode for MlpNode {
    fn name(&self) -> &'static str {
        match self.widths.len() {
            1 => "osrt-mlp-node",
            _ => "osrt-mlp-cat-node",
        }
    }

    fn what(&self) -> &'static str {
        "mlp node"
    }

    fn out(&self) -> &Handover {
        &self.out
    }

    /// The input parts' gradients ([`MlpNode::parts_backward`]), then the chain's.
    fn backward(&self, operands: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let Some((chain, parts)) = operands.split_last() else {
            candle_core::bail!("mlp node: no operands")
        };
        let mut d = self.parts_backward(parts, grad)?;
        d.push(chain_grad(chain)?);
        Ok(d)
    }
}

#[cfg(test)]
mod tests;
