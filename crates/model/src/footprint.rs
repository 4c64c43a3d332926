//! How much memory a train step's forward and backward passes hold at their peak, from
//! the model's configuration and the batch's shapes alone, before anything is allocated.
//!
//! The count follows what the step keeps, op by op: every op's output is held by the
//! autograd graph until the step ends (candle keeps the graph whole through the backward
//! pass), and the one-node kernels of `osrt_kernels` keep their own saved buffers (im2col
//! columns, attention weights, an MLP's hidden layers) until their backward pass takes
//! them. On top of what is held, each op briefly needs room of its own: the attention
//! kernel's per-task copies in the forward pass, the gradients of its operands in the
//! backward pass. The ledger below replays the forward pass in order and the backward
//! pass in reverse and reports the largest sum.
//!
//! Three op paths keep different tensors: the f32 fused CPU kernels (`Kernels::Fused`,
//! the default on a CPU), candle's composed ops on the CPU (`Kernels::Composed`: softmax
//! and LayerNorm composed too, and their backward passes' temporaries, counted as
//! measured), and the GPU's graph (`Kernels::Device`, on a GPU or built on the CPU: the
//! product, LayerNorm, softmax, bias-activation, attention, MLP and convolution nodes,
//! products read only by products stored in bf16 with bf16 products). On every path the
//! backward pass runs in segments (`osrt_kernels::cut`), each segment's graph freed
//! before the next. The fused and the GPU graph's counts are checked against the counted
//! peak heap of `osrt bench model` in `tests/memory_estimate.rs` (the GPU's graph built
//! on the CPU); the composed count is from the code (docs/performance.md has how close
//! it comes).

use crate::decoder;
use crate::encoder::{self, RayInput};
use crate::nn::TransformerConfig;
use crate::osrt::Config;

/// The shapes of one worker's train step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepShape {
    /// Scenes per worker step.
    pub batch: usize,
    pub input_views: usize,
    /// Input image height and width in pixels.
    pub height: usize,
    pub width: usize,
    /// Target rays per scene.
    pub rays: usize,
    /// Threads the step's kernels run on (the attention backward works on one batch
    /// element per thread at a time).
    pub threads: usize,
    /// Whether the transformer blocks', the convolutions' and the render MLP's
    /// activations are made again in the backward pass (`train.recompute`).
    pub recompute: bool,
}

/// Which implementation of the ops the step runs: they keep different tensors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpPath {
    /// The one-node f32 CPU kernels of `osrt_kernels`.
    Fused,
    /// candle's composed ops on the CPU.
    Composed,
    /// A CUDA step; `bf16` where the matrix products cast their operands.
    Gpu { bf16: bool },
}

/// What one step's forward and backward passes hold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Footprint {
    /// The peak of the activations and gradients (fused ops: the packed parameters too),
    /// in bytes; the weights and the optimiser's state are not included.
    pub activations: f64,
    /// The parameters the ops reach: the model's parameter count.
    pub parameters: usize,
}

/// The footprint of one step of `cfg` on `shape`; `None` for a decoder without a count
/// (volumetric).
pub fn step(cfg: &Config, shape: &StepShape, path: OpPath) -> Option<Footprint> {
    let mut l = Ledger::new(path, shape.threads, shape.recompute);
    encode(&mut l, cfg, shape);
    decode(&mut l, cfg, shape)?;
    Some(Footprint {
        activations: l.peak(),
        parameters: l.ops.iter().map(|o| o.params).sum(),
    })
}

/// Bytes of `n` f32 values.
fn f32s(n: usize) -> f64 {
    4.0 * n as f64
}

/// One op of the forward pass, as the ledger books it.
#[derive(Debug, Clone, Copy, Default)]
struct Op {
    /// The output (and any operand copies) the graph holds until the step ends.
    held: f64,
    /// What the op keeps for its backward pass and frees there.
    saved: f64,
    /// Room the forward pass needs above `held + saved` while the op runs.
    forward_extra: f64,
    /// Room the backward pass needs while the op's gradient is computed.
    backward_extra: f64,
    /// Parameters the op's gradient reaches: their gradients stay from there on.
    params: usize,
}

/// The forward pass replayed in order, the backward pass in reverse.
struct Ledger {
    path: OpPath,
    threads: usize,
    ops: Vec<Op>,
    live: f64,
    forward_peak: f64,
    /// Forward-pass locals freed when their function returns (not held by the graph).
    locals: f64,
    /// Where each segment after the first begins (an index into `ops`): the step's
    /// backward pass runs segment by segment, last first, and frees each segment's
    /// graph before the next (`osrt_kernels::cut`).
    cuts: Vec<usize>,
    /// Whether [`Self::recomputed`] segments keep their activations or make them again.
    recompute: bool,
    /// The ops (`start..end` in `ops`) of each segment made again in the backward pass
    /// (`osrt_kernels::recompute`), in order.
    recomputed: Vec<std::ops::Range<usize>>,
}

impl Ledger {
    fn new(path: OpPath, threads: usize, recompute: bool) -> Self {
        Self {
            path,
            threads: threads.max(1),
            ops: Vec::new(),
            live: 0.0,
            forward_peak: 0.0,
            locals: 0.0,
            cuts: Vec::new(),
            recompute,
            recomputed: Vec::new(),
        }
    }

    fn fused(&self) -> bool {
        self.path == OpPath::Fused
    }

    fn gpu(&self) -> bool {
        matches!(self.path, OpPath::Gpu { .. })
    }

    /// Bytes of `n` values as a product stores them where only products or attention
    /// read them (`osrt_kernels::linear_low`): bf16 on a GPU step with bf16 products.
    fn lows(&self, n: usize) -> f64 {
        match self.path {
            OpPath::Gpu { bf16: true } => 2.0 * n as f64,
            _ => f32s(n),
        }
    }

    /// A segment boundary (`osrt_kernels::cut`).
    fn cut(&mut self) {
        self.cuts.push(self.ops.len());
    }

    /// Books `f`'s ops as a segment that a step with recomputation makes again in its
    /// backward pass (`osrt_kernels::recompute`), `out` values its output: its forward
    /// pass then keeps only the output's copy (beside the segment's inputs, held before).
    fn recomputed(&mut self, out: usize, f: impl FnOnce(&mut Self)) {
        let from = self.ops.len();
        f(self);
        if !self.recompute {
            return;
        }
        self.live -= kept(&self.ops[from..]);
        self.recomputed.push(from..self.ops.len());
        self.node(out);
    }

    /// A boundary's copy of `bytes` where a recomputed segment reads a tensor that is not
    /// a leaf (`osrt_kernels::recompute`); nothing without recomputation.
    fn boundary_copy(&mut self, bytes: f64) {
        if self.recompute {
            self.op(Op {
                held: bytes,
                ..Op::default()
            });
        }
    }

    fn op(&mut self, op: Op) {
        self.live += op.held + op.saved;
        self.forward_peak = self.forward_peak.max(self.live + op.forward_extra);
        self.ops.push(op);
    }

    /// An op output of `n` values held to the end of the step.
    fn node(&mut self, n: usize) {
        self.op(Op {
            held: f32s(n),
            backward_extra: 2.0 * f32s(n),
            ..Op::default()
        });
    }

    /// A forward local of `n` values (no graph holds it), live until [`Self::drop_locals`].
    fn local(&mut self, n: usize) {
        self.live += f32s(n);
        self.locals += f32s(n);
        self.forward_peak = self.forward_peak.max(self.live);
    }

    /// Books `f`'s ops as a repeat of ops already booked: the same parameters, whose
    /// gradients are already counted.
    fn repeat(&mut self, f: impl FnOnce(&mut Self)) {
        let from = self.ops.len();
        f(self);
        self.ops[from..].iter_mut().for_each(|op| op.params = 0);
    }

    fn drop_locals(&mut self) {
        self.live -= self.locals;
        self.locals = 0.0;
    }

    /// The largest sum: the forward pass's, or the backward pass's, which starts from
    /// everything held, frees each op's saved buffers as it passes the op and each
    /// segment's graph once past the segment.
    fn peak(&self) -> f64 {
        let mut live = self.live;
        let mut peak = self.forward_peak;
        let mut segment = 0.0;
        let mut cuts = self.cuts.clone();
        let mut recomputed = self.recomputed.clone();
        // What the recomputed segment being passed holds, freed at its start.
        let mut remade = 0.0;
        for (i, op) in self.ops.iter().enumerate().rev() {
            let inside = recomputed.last().filter(|r| r.contains(&i)).cloned();
            if let Some(r) = inside.as_ref().filter(|r| r.end == i + 1) {
                // The segment's forward pass again: its activations, at its forward peak.
                let ops = &self.ops[r.clone()];
                live += kept(ops);
                peak = peak.max(live + ops.iter().map(|o| o.forward_extra).fold(0.0, f64::max));
            }
            live += f32s(op.params);
            peak = peak.max(live + op.backward_extra);
            live -= op.saved;
            match inside {
                Some(r) => {
                    remade += op.held;
                    if r.start == i {
                        live -= remade;
                        remade = 0.0;
                        recomputed.pop();
                    }
                }
                None => segment += op.held,
            }
            if cuts.last() == Some(&i) {
                cuts.pop();
                live -= segment;
                segment = 0.0;
            }
        }
        peak
    }
}

/// What `ops` hold from the forward pass until their backward pass: outputs and saved
/// buffers.
fn kept(ops: &[Op]) -> f64 {
    ops.iter().map(|o| o.held + o.saved).sum()
}

/// A linear layer `[rows, i] → [rows, o]` (fused: one node; on a GPU a layer with a bias
/// is the one-layer MLP node; composed: the product, and the bias add as a second node).
fn linear(l: &mut Ledger, rows: usize, i: usize, o: usize, bias: bool) {
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
fn layer_norm(l: &mut Ledger, rows: usize, d: usize) {
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
fn mlp(l: &mut Ledger, rows: usize, dims: &[usize]) {
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

fn transformer(
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
fn conv(
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

/// The SRT encoder and slot attention (`Osrt::encode`).
fn encode(l: &mut Ledger, cfg: &Config, s: &StepShape) {
    let e = cfg.ray_encoding.dim();
    let enc = &cfg.encoder;
    let images = s.batch * s.input_views;
    let (mut h, mut w) = (s.height, s.width);
    // The input views' ray encoding, a constant: concatenated to the images, it lives
    // while the encoder runs; added as a patch embedding, the graph holds it.
    let mut c_in = match (enc.poses, enc.ray_input) {
        (encoder::Poses::Absolute, RayInput::Concat) => {
            l.local(images * h * w * e);
            l.node(images * h * w * (3 + e));
            3 + e
        }
        (encoder::Poses::Absolute, RayInput::Add) => {
            l.node(images * h * w * e);
            3
        }
        (encoder::Poses::Unposed, _) => 3,
    };
    for &c in &enc.conv_channels {
        let (h2, w2) = (h.div_ceil(2), w.div_ceil(2));
        l.recomputed(images * h2 * w2 * 2 * c, |l| {
            conv(l, images, (h, w, c_in), 3, c, true);
            conv(l, images, (h2, w2, c), 3, 2 * c, true);
        });
        (h, w, c_in) = (h2, w2, 2 * c);
    }
    conv(l, images, (h, w, c_in), 1, enc.dim, false);
    let tokens = s.input_views * h * w;
    if enc.poses == encoder::Poses::Absolute && enc.ray_input == RayInput::Add {
        let stride = enc.stride();
        conv(l, images, (h, w, e), stride, enc.dim, false);
        l.node(s.batch * tokens * enc.dim);
    }
    // The backward pass's segments (`Osrt::encode`'s cuts): the CNN, the transformer, the
    // slot attention, then the decoder.
    l.cut();
    transformer(l, &enc.transformer, (s.batch, tokens, enc.dim), None);
    l.drop_locals();
    l.cut();
    slot_attention(l, cfg, s.batch, tokens);
    l.cut();
}

/// Slot attention over `tokens` set-latent tokens per scene.
fn slot_attention(l: &mut Ledger, cfg: &Config, b: usize, tokens: usize) {
    let sa = &cfg.slot_attention;
    let (d, ds, k) = (cfg.encoder.dim, sa.slot_dim, sa.num_slots);
    let rows = b * tokens;
    layer_norm(l, rows, d);
    linear(l, rows, d, ds, false);
    linear(l, rows, d, ds, false);
    l.node(rows * ds); // keys transposed
    let logits = b * k * tokens;
    // The initial slots.
    l.op(Op {
        held: f32s(b * k * ds),
        params: k * ds,
        ..Op::default()
    });
    let iteration = |l: &mut Ledger| {
        layer_norm(l, b * k, ds);
        linear(l, b * k, ds, ds, false);
        // Logits, scaled, softmax over slots, plus ε, renormalised over the inputs.
        l.node(5 * logits);
        l.node(b * k * ds);
        // The GRU cell on `[b·k, ds]`: its gates and their products, small beside the rest.
        l.op(Op {
            held: f32s(12 * b * k * ds),
            params: 6 * ds * ds + 6 * ds,
            ..Op::default()
        });
        layer_norm(l, b * k, ds);
        mlp(l, b * k, &[ds, sa.mlp_hidden, ds]);
        l.node(b * k * ds);
    };
    iteration(l);
    for _ in 1..sa.iterations {
        l.repeat(iteration);
    }
}

/// The decoder on `rays` target rays per scene, and the loss.
fn decode(l: &mut Ledger, cfg: &Config, s: &StepShape) -> Option<()> {
    let e = cfg.ray_encoding.dim();
    let (b, r) = (s.batch, s.rays);
    let rows = b * r;
    let (ds, k) = (cfg.slot_attention.slot_dim, cfg.slot_attention.num_slots);
    match &cfg.decoder {
        decoder::Config::SlotMixer(c) => {
            l.node(rows * e); // the rays' encoding
            mlp(l, rows, &[e, c.query_hidden, e]);
            transformer(l, &c.allocation, (b, r, e), Some((k, ds)));
            let mut dims = vec![ds + e];
            dims.extend(&c.render_hidden);
            dims.push(3);
            // The mixing block and the render MLP, a recomputed segment reading a copy of
            // the query.
            l.boundary_copy(f32s(rows * e));
            l.recomputed(rows * 3, |l| {
                // Slot mixing: the queries' projection, the weights over slots, the mix (on
                // a GPU the projection and the mix stored as their products return them).
                let (q, mixed) = (l.lows(rows * ds), l.lows(rows * ds));
                l.op(Op {
                    held: q + f32s(rows * k) + if l.gpu() { mixed } else { 0.0 },
                    saved: if l.gpu() {
                        0.0
                    } else {
                        f32s(rows * ds + rows * k)
                    },
                    backward_extra: f32s(3 * rows * ds + 2 * rows * e),
                    params: e * ds + ds * ds,
                    ..Op::default()
                });
                // Composed, the concatenation is a node; the fused and GPU MLPs join inside.
                if l.path == OpPath::Composed {
                    l.node(rows * (ds + e));
                }
                mlp(l, rows, &dims);
            });
        }
        decoder::Config::Transformer(c) => {
            l.node(rows * e);
            mlp(l, rows, &[e, c.query_hidden, e]);
            transformer(l, &c.transformer, (b, r, e), Some((k, ds)));
            let mut dims = vec![e];
            dims.extend(&c.render_hidden);
            dims.push(3);
            l.recomputed(rows * 3, |l| mlp(l, rows, &dims));
        }
        decoder::Config::SpatialBroadcast(c) => {
            l.node(rows * e);
            let pairs = rows * k;
            let mut dims = vec![e + ds];
            dims.extend(&c.hidden);
            dims.push(4);
            l.recomputed(pairs * 4, |l| {
                l.node(pairs * (e + ds));
                mlp(l, pairs, &dims);
            });
            // Colours, weights, their product.
            l.node(pairs * 7);
        }
        decoder::Config::Volumetric(_) => return None,
    }
    // Sigmoid, the difference to the target, its square.
    l.node(3 * rows * 3);
    Some(())
}
