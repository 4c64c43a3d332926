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
//!
//! This file holds the ledger and the walk over the model's components; what each kind
//! of layer books is in `layers`.

mod layers;

use crate::decoder;
use crate::encoder::{self, RayInput};
use crate::osrt::Config;
use layers::{conv, layer_norm, linear, mlp, transformer};

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
    /// Whether the pass's parameter gradients leave the store as each backward segment
    /// ends, into a running sum held elsewhere (micro-batches summed on the host): then
    /// no segment's gradients stay past it.
    pub summed: bool,
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
    l.summed = shape.summed;
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
    /// Whether each segment's parameter gradients leave at its end ([`StepShape::summed`]).
    summed: bool,
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
            summed: false,
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
    /// segment's graph once past the segment (and, where [`Self::summed`], the segment's
    /// parameter gradients).
    fn peak(&self) -> f64 {
        let mut live = self.live;
        let mut peak = self.forward_peak;
        let mut segment = 0.0;
        // Parameter gradients made since the last segment's end.
        let mut grads = 0.0;
        let flush = |live: &mut f64, grads: &mut f64| {
            if self.summed {
                *live -= *grads;
                *grads = 0.0;
            }
        };
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
            grads += f32s(op.params);
            peak = peak.max(live + op.backward_extra);
            live -= op.saved;
            match inside {
                Some(r) => {
                    remade += op.held;
                    if r.start == i {
                        live -= remade;
                        remade = 0.0;
                        recomputed.pop();
                        flush(&mut live, &mut grads);
                    }
                }
                None => segment += op.held,
            }
            if cuts.last() == Some(&i) {
                cuts.pop();
                live -= segment;
                segment = 0.0;
                flush(&mut live, &mut grads);
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
