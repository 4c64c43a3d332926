//! The choice of the whole-MLP op: the fused CPU node where it applies, on the device
//! graph the MLP node built from tensor ops, else layer by layer ([`mlp_layer_by_layer`]);
//! the same for the MLP of two inputs side by side ([`mlp_cat`]).

use super::linear::{linear, linear_act};
use super::{usable, usable_with_cuda};
use crate::cpu::mlp::MlpLayer;
use crate::cpu::{self, MlpAct, usable_with_cuda_any};
use crate::graph::matmul::stores_low;
use crate::graph::mlp_node::{mlp_cat_node, mlp_node};
use crate::{Precision, device_graph, enabled, precision, profile};
use candle_core::{D, Result, Tensor};

/// `x: [.., in]` through `layers` (`(weight [out, in], bias [out])` each) with `act`
/// between them → `[.., out]`, as one graph node where the fused ops apply (see
/// `cpu::mlp`), else layer by layer.
pub fn mlp(x: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let (all, biased) = operands(&[x], layers);
    profile::op("mlp", &all, move |t| {
        mlp_here(&t[0], &layers_of(&t[1..], &biased), act)
    })
}

/// An MLP's operands as one list (`lead` first, then each layer's weight and bias) for
/// the profile's record, and which layers have a bias.
pub(crate) fn operands<'a>(
    lead: &[&'a Tensor],
    layers: &[MlpLayer<'a>],
) -> (Vec<&'a Tensor>, Vec<bool>) {
    let mut all = lead.to_vec();
    for (w, b) in layers {
        all.push(w);
        all.extend(*b);
    }
    (all, layers.iter().map(|(_, b)| b.is_some()).collect())
}

/// The layers back from [`operands`]' list (without its lead operands).
pub(crate) fn layers_of<'a>(t: &'a [Tensor], biased: &[bool]) -> Vec<MlpLayer<'a>> {
    let mut i = 0;
    biased
        .iter()
        .map(|&b| {
            let w = &t[i];
            i += 1 + b as usize;
            (w, b.then(|| &t[i - 1]))
        })
        .collect()
}

fn mlp_here(x: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let bias = layers.first().is_some_and(|(_, b)| b.is_some());
    let mut all = vec![x];
    for (w, b) in layers {
        all.push(w);
        all.extend(*b);
    }
    let fits = !layers.is_empty()
        && layers
            .iter()
            .all(|(w, b)| w.rank() == 2 && b.is_some() == bias);
    if !(fits && usable(&all)) {
        // On a GPU, the whole MLP as one node of tensor ops (`graph::mlp_node`).
        if enabled() && usable_with_cuda_any(&all) && device_graph(x) {
            let bf16 = precision() == Precision::Bf16;
            if let Some(y) = mlp_node(x, layers, act, bf16)? {
                return Ok(y);
            }
        }
        return mlp_layer_by_layer(x, layers, act);
    }
    cpu::mlp::mlp(x, layers, act, bias)
}

/// The MLP of `[a, b]` concatenated on the last dim — `a: [.., in_a]`, `b: [.., in_b]`,
/// `layers[0]` of width `in_a + in_b` — as one graph node without the concatenation:
/// the first layer multiplies each input by its columns of the weight and adds the two
/// products. Why: the Slot Mixer's render MLP reads (mixed slot ⊕ ray query), and the
/// concatenated `[8192, 224]` was a copy forward, two copies backward and one more
/// gradient accumulation. The first layer's sums are split in two, so the bits differ
/// from the MLP of the concatenation by rounding (tested to float tolerance).
pub fn mlp_cat(a: &Tensor, b: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let (all, biased) = operands(&[a, b], layers);
    profile::op("mlp", &all, move |t| {
        mlp_cat_here(&t[0], &t[1], &layers_of(&t[2..], &biased), act)
    })
}

fn mlp_cat_here(a: &Tensor, b: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    // (A part stored in bf16, `crate::matmul_low`, joins the other in f32.)
    let f32 = |t: &Tensor| match t.dtype() {
        candle_core::DType::BF16 => t.to_dtype(candle_core::DType::F32),
        _ => Ok(t.clone()),
    };
    let cat = || mlp(&Tensor::cat(&[f32(a)?, f32(b)?], D::Minus1)?, layers, act);
    let bias = layers.first().is_some_and(|(_, b)| b.is_some());
    let mut all = vec![a, b];
    for (w, b) in layers {
        all.push(w);
        all.extend(*b);
    }
    let lead_fits = a.rank() == b.rank() && a.dims()[..a.rank() - 1] == b.dims()[..b.rank() - 1];
    let fits = !layers.is_empty()
        && layers
            .iter()
            .all(|(w, b)| w.rank() == 2 && b.is_some() == bias);
    if !(fits && lead_fits && usable(&all)) {
        // On a GPU, the whole MLP as one node of tensor ops that concatenates inside (its
        // inputs may be stored in bf16: `crate::matmul_low`).
        let takes = usable_with_cuda_any(&all) || stores_low(&all);
        if enabled() && takes && device_graph(a) {
            let bf16 = precision() == Precision::Bf16;
            if let Some(y) = mlp_cat_node(a, b, layers, act, bf16)? {
                return Ok(y);
            }
        }
        return cat();
    }
    cpu::mlp::mlp_cat(a, b, layers, act, bias)
}

/// The same MLP as separate nodes: [`linear`] and the activation op per layer (on
/// a GPU: candle's product, then the bias and the activation as one node).
pub fn mlp_layer_by_layer(x: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let (all, biased) = operands(&[x], layers);
    profile::op("mlp", &all, move |t| {
        mlp_layer_by_layer_here(&t[0], &layers_of(&t[1..], &biased), act)
    })
}

fn mlp_layer_by_layer_here(x: &Tensor, layers: &[MlpLayer], act: MlpAct) -> Result<Tensor> {
    let mut h = x.clone();
    for (i, (w, b)) in layers.iter().enumerate() {
        let hidden = i + 1 < layers.len();
        if usable_with_cuda(&[&h, w]) && device_graph(&h) {
            h = linear_act(&h, w, *b, hidden.then_some(act))?;
            continue;
        }
        h = linear(&h, w, *b)?;
        if hidden {
            h = act.apply(&h)?;
        }
    }
    Ok(h)
}

#[cfg(test)]
mod tests;
