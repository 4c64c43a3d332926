//! What each kind of layer books in the ledger, on each op path: a linear layer, a
//! LayerNorm, an MLP, a transformer block and a convolution. Its own file because these
//! are the per-op counts (what a kernel keeps, what its backward pass needs), apart from
//! the walk over the model that calls them (`super::encode`, `super::decode`).

use super::{Ledger, Op, OpPath, f32s};
use crate::nn::TransformerConfig;

/// A linear layer `[rows, i] → [rows, o]` (fused: one node; on a GPU a layer with a bias
/// is the one-layer MLP node; composed: the product, and the bias add as a second node).
pub(super) fn linear(l: &mut Ledger, rows: usize, i: usize, o: usize, bias: bool) {
    linear_then(l, rows, (i, o), bias, bias && l.path == OpPath::Composed);
}

/// A bias-free projection read only by products or attention: stored as the product
/// returns it (`osrt_kernels::linear_low`; bf16 on a GPU step with bf16 products).
fn linear_low(l: &mut Ledger, rows: usize, i: usize, o: usize) {
    let held = l.lows(rows * o);
    l.op(Op {
        held,
        backward_extra: f32s(2 * rows * o + rows * i),
        params: i * o,
        ..Op::default()
    });
}

/// [`linear`], with the bias add as a node of its own or not (`bias_node`: on a GPU an
/// MLP's bias add is one node with the activation).
fn linear_then(l: &mut Ledger, rows: usize, (i, o): (usize, usize), bias: bool, bias_node: bool) {
    l.op(Op {
        held: f32s(rows * o),
        backward_extra: f32s(2 * rows * o + rows * i),
        params: i * o + if bias { o } else { 0 },
        ..Op::default()
    });
    if bias_node {
        l.node(rows * o);
    }
}

/// A LayerNorm over `[rows, d]`: one node for the fused CPU kernel and on a GPU; composed,
/// the centred input, its square, the normalised and the scaled input besides.
pub(super) fn layer_norm(l: &mut Ledger, rows: usize, d: usize) {
    if l.path == OpPath::Composed {
        l.node(4 * rows * d);
    }
    l.op(Op {
        held: f32s(rows * d),
        saved: f32s(2 * rows),
        backward_extra: 3.0 * f32s(rows * d),
        params: 2 * d,
        ..Op::default()
    });
}

/// An MLP `dims[0] → … → dims[last]` over `rows` rows: fused, one node keeping each
/// hidden layer's pre-activation and activation; composed, a linear layer and an
/// activation node per layer.
pub(super) fn mlp(l: &mut Ledger, rows: usize, dims: &[usize]) {
    let hidden: usize = dims[1..dims.len() - 1].iter().sum();
    let out = dims[dims.len() - 1];
    if l.fused() {
        // The parameters enter packed into one tensor, which the graph holds, and leave
        // the backward pass as one gradient that is then split.
        let params: usize = dims.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
        let widest = dims.iter().copied().max().unwrap_or(0);
        l.op(Op {
            held: f32s(rows * out + params),
            saved: 2.0 * f32s(rows * hidden),
            forward_extra: f32s(rows * widest),
            backward_extra: f32s(3 * rows * widest + params),
            params,
        });
        return;
    }
    if l.gpu() {
        // One node (`osrt_kernels::mlp_node`) keeping each hidden layer's product in the
        // products' precision; it joins its input (one part or two) when it needs it.
        // Forward: a layer's input and output beside the kept products; backward: a
        // hidden layer's f32 gradient (in f32 written over its kept product), the
        // incoming gradient and the layer's input made again in the products' precision.
        let params: usize = dims.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
        let widest = dims.iter().copied().max().unwrap_or(0);
        l.op(Op {
            held: f32s(rows * out),
            saved: l.lows(rows * hidden),
            forward_extra: l.lows(rows * dims[0]) + l.lows(2 * rows * widest),
            backward_extra: f32s(rows * widest) + 2.0 * l.lows(rows * widest) + f32s(params),
            params,
        });
        return;
    }
    for w in dims.windows(2) {
        linear_then(l, rows, (w[0], w[1]), true, true);
    }
    l.node(rows * hidden);
}

/// A pre-LayerNorm transformer block over `b` elements of `n` query rows of width `d`,
/// attending to `m` context rows of width `dc` (`None`: self-attention).
fn block(
    l: &mut Ledger,
    t: &TransformerConfig,
    (b, n, d): (usize, usize, usize),
    ctx: Option<(usize, usize)>,
) {
    let (m, dc) = ctx.unwrap_or((n, d));
    let (rows, ctx_rows) = (b * n, b * m);
    let inner = t.heads * t.head_dim;
    let weights = b * t.heads * n * m;
    // The weights one backward task holds at a time, two of them (dP, dS) per thread.
    let per_thread = 2 * t.heads * n * m * b.min(l.threads);
    if l.fused() {
        // The attention's forward tasks each hold their output and, with fewer than eight
        // elements (row-block tasks), their weights until copied into place.
        let copies = if b < 8 && n > 128 { weights } else { 0 };
        let params = 4 * d + 2 * inner * (d + dc) + d + 2 * d * t.mlp_hidden + t.mlp_hidden + d;
        l.op(Op {
            held: f32s(rows * d + params),
            params,
            saved: f32s(
                2 * rows * d
                    + 2 * rows * inner
                    + 2 * ctx_rows * inner
                    + weights
                    + rows * d
                    + 2 * rows * t.mlp_hidden,
            ),
            forward_extra: f32s(rows * inner + copies),
            backward_extra: f32s(
                per_thread
                    + 3 * rows * inner
                    + 2 * ctx_rows * inner
                    + 3 * rows * d
                    + ctx_rows * dc
                    + params,
            ),
        });
        return;
    }
    layer_norm(l, rows, d);
    let source = if ctx.is_some() { ctx_rows } else { rows };
    if l.gpu() {
        // q, k, v stored as their products return them; one node that splits and merges
        // the heads inside (in the products' precision), keeps the weights, and in its
        // backward pass holds the weights' gradient (the logits' written over it) and one
        // operand's copies and its gradient at a time.
        linear_low(l, rows, d, inner);
        linear_low(l, source, dc, inner);
        linear_low(l, source, dc, inner);
        let held = l.lows(rows * inner);
        l.op(Op {
            held,
            saved: f32s(weights),
            forward_extra: l.lows(2 * rows * inner + 2 * ctx_rows * inner),
            backward_extra: f32s(weights) + l.lows(3 * rows * inner + 2 * ctx_rows * inner),
            ..Op::default()
        });
        linear(l, rows, inner, d, true);
        l.node(rows * d);
        layer_norm(l, rows, d);
        mlp(l, rows, &[d, t.mlp_hidden, d]);
        l.node(rows * d);
        return;
    }
    linear(l, rows, d, inner, false);
    linear(l, source, dc, inner, false);
    linear(l, source, dc, inner, false);
    // The heads split (three copies), the attention core, the heads merged.
    l.node(rows * inner + 2 * ctx_rows * inner);
    // Logits, scaled logits and the composed softmax's shifted logits, exponentials and
    // quotient; its backward pass's temporaries, as measured: eleven more.
    l.op(Op {
        held: f32s(5 * weights + rows * inner),
        backward_extra: f32s(11 * weights),
        ..Op::default()
    });
    l.node(rows * inner);
    linear(l, rows, inner, d, true);
    l.node(rows * d);
    layer_norm(l, rows, d);
    mlp(l, rows, &[d, t.mlp_hidden, d]);
    l.node(rows * d);
}

pub(super) fn transformer(
    l: &mut Ledger,
    t: &TransformerConfig,
    rows: (usize, usize, usize),
    ctx: Option<(usize, usize)>,
) {
    let (b, n, d) = rows;
    for _ in 0..t.layers {
        l.recomputed(b * n * d, |l| block(l, t, rows, ctx));
    }
}

/// A 3×3 or 1×1 convolution (NHWC) of `images` inputs of `h × w × c_in` to `c_out`
/// channels, with a ReLU after it where `relu`: the im2col columns (kept for the weight
/// gradient), the product, the ReLU's output.
pub(super) fn conv(
    l: &mut Ledger,
    images: usize,
    (h, w, c_in): (usize, usize, usize),
    kernel: usize,
    c_out: usize,
    relu: bool,
) {
    let cols = images * h * w * kernel * kernel * c_in;
    let out = images * h * w * c_out;
    let params = kernel * kernel * c_in * c_out;
    if l.gpu() {
        // The convolution node (`osrt_kernels::conv_node`): its input is held by the op
        // before; it unfolds at most 2²⁵ values at a time and, with the ReLU, keeps a
        // one-byte mask where it would keep its output.
        let unfolded = l.lows(cols.min(1 << 25));
        l.op(Op {
            held: f32s(out),
            saved: if relu { out as f64 } else { 0.0 },
            forward_extra: unfolded,
            backward_extra: unfolded + f32s(2 * out),
            params,
        });
        return;
    }
    if l.fused() {
        l.op(Op {
            held: f32s(out),
            saved: f32s(cols),
            backward_extra: f32s(cols + 2 * out),
            params,
            ..Op::default()
        });
    } else {
        l.node(cols);
        l.op(Op {
            held: f32s(out),
            backward_extra: f32s(cols + 2 * out),
            params,
            ..Op::default()
        });
    }
    if relu {
        l.node(out);
    }
}
