//! The ledger of a train step: every matrix product (its m, n, k and batch count, its
//! operands' and output's types, which operand the product reads transposed and which
//! had to be copied first), every cast and copy (its bytes), and the bytes the other ops
//! of this crate's nodes read and write, each under the op kind of the profile
//! ([`crate::profile`]) it belongs to and the pass that made it (forward, backward, or a
//! segment's forward made again). What runs where is decided by the code, not by the
//! device, so a step's ledger taken on the CPU is the GPU's too (the same kernels and
//! precision); [`Rates`] turns it into the time an accelerator would need at its rates.
//!
//! Recorded where this crate makes the op (a [`Ledger`] is active on the thread:
//! [`recording`]; [`crate::on_device_pool`] carries it to the pool's thread). Not seen:
//! candle's own ops between this crate's ops (reshapes, residual adds, the loss) and
//! candle's backward passes of them; the backward pass of a composed product (candle's
//! `Op::Matmul`: two products) and of a pointwise op is entered when its forward pass is
//! made, from its shapes.

use candle_core::{DType, Layout, Tensor};
use std::cell::{Cell, RefCell};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Which pass made an entry.
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    #[default]
    Forward,
    Backward,
    /// A segment's forward pass made again in the backward pass (`train.recompute`).
    Recompute,
}

/// One matrix product `[batch, m, k] · [batch, k, n] → [batch, m, n]`.
#[derive(
    Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
pub struct Product {
    pub kind: String,
    pub phase: Phase,
    pub batch: usize,
    pub m: usize,
    pub n: usize,
    pub k: usize,
    /// The operands' and the output's types as the product reads and writes them.
    pub a: String,
    pub b: String,
    pub out: String,
    /// Whether the product reads the operand transposed (by strides, no copy).
    pub transposed: [bool; 2],
    /// Whether the operand was copied (cast, or made contiguous) for this product.
    pub copied: [bool; 2],
}

impl Product {
    pub fn flops(&self) -> f64 {
        2.0 * (self.batch * self.m * self.n) as f64 * self.k as f64
    }

    /// The bytes of both operands and the output.
    pub fn bytes(&self) -> f64 {
        let mn = (self.batch * self.m) as f64;
        let kb = (self.batch * self.k) as f64;
        mn * self.k as f64 * bytes_of(&self.a)
            + kb * self.n as f64 * bytes_of(&self.b)
            + mn * self.n as f64 * bytes_of(&self.out)
    }

    /// The operands' type: `bf16`, `f32`, or `mixed`.
    pub fn precision(&self) -> &str {
        match self.a == self.b {
            true => &self.a,
            false => "mixed",
        }
    }
}

/// What a movement of bytes is.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Moved {
    /// A change of type.
    Cast,
    /// A copy in the same type (a view made contiguous, heads split or merged, a node's
    /// output handed to the graph, a concatenation).
    Copy,
    /// Another op's reads and writes (a bias with activation, a softmax, a column sum).
    Op,
}

/// One cast, copy or other op.
#[derive(
    Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
pub struct Movement {
    pub kind: String,
    pub phase: Phase,
    pub moved: Moved,
    /// What it is (`cast f32→bf16`, `softmax`, …).
    pub what: String,
    pub read: u64,
    pub written: u64,
}

/// Entries with how often the step made each.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Entries {
    pub products: Vec<(Product, usize)>,
    pub movements: Vec<(Movement, usize)>,
}

/// Where a step's entries go while recording; shared with the device pool's threads.
#[derive(Clone, Default)]
pub struct Ledger(Arc<Mutex<Recorded>>);

#[derive(Default)]
struct Recorded {
    products: BTreeMap<Product, usize>,
    movements: BTreeMap<Movement, usize>,
}

impl Ledger {
    /// The entries recorded so far, each once with its count (in a fixed order).
    pub fn take(&self) -> Entries {
        let r = std::mem::take(&mut *self.0.lock().unwrap_or_else(|e| e.into_inner()));
        Entries {
            products: r.products.into_iter().collect(),
            movements: r.movements.into_iter().collect(),
        }
    }
}

thread_local! {
    static LEDGER: RefCell<Option<Ledger>> = const { RefCell::new(None) };
    /// The op kind entries go under (the outermost recorded op's, see [`within`]).
    static KIND: Cell<&'static str> = const { Cell::new("") };
    static PHASE: Cell<Phase> = const { Cell::new(Phase::Forward) };
}

/// This thread's ledger, if any.
pub(crate) fn current() -> Option<Ledger> {
    LEDGER.with(|l| l.borrow().clone())
}

/// Whether entries are being recorded on this thread.
pub(crate) fn on() -> bool {
    LEDGER.with(|l| l.borrow().is_some())
}

/// Runs `f` with entries on this thread going to `ledger` (or to none).
pub fn recording<T>(ledger: Option<Ledger>, f: impl FnOnce() -> T) -> T {
    let prev = LEDGER.with(|l| l.replace(ledger));
    let out = f();
    LEDGER.with(|l| *l.borrow_mut() = prev);
    out
}

/// The current op kind and pass (to carry to another thread, or into a node's backward
/// pass).
pub(crate) fn context() -> (&'static str, Phase) {
    (KIND.with(|k| k.get()), PHASE.with(|p| p.get()))
}

/// Runs `f` with entries under `kind` and `phase`.
pub(crate) fn in_context<T>((kind, phase): (&'static str, Phase), f: impl FnOnce() -> T) -> T {
    let prev = (
        KIND.with(|k| k.replace(kind)),
        PHASE.with(|p| p.replace(phase)),
    );
    let out = f();
    KIND.with(|k| k.set(prev.0));
    PHASE.with(|p| p.set(prev.1));
    out
}

/// Runs `f` with its entries under op kind `kind`, unless an enclosing op named one (the
/// products of a linear layer inside an MLP are the MLP's).
pub(crate) fn within<T>(kind: &'static str, f: impl FnOnce() -> T) -> T {
    match KIND.with(|k| k.get()) {
        "" => in_context((kind, PHASE.with(|p| p.get())), f),
        _ => f(),
    }
}

/// Runs `f` as the backward pass of an op of `kind` (made at a forward pass's context,
/// `made`: its kind where one was set, else `kind`).
pub(crate) fn backward<T>(made: &'static str, kind: &'static str, f: impl FnOnce() -> T) -> T {
    let k = if made.is_empty() { kind } else { made };
    in_context((k, Phase::Backward), f)
}

/// Runs `f` with its entries in `phase` (the trainer's segments made again).
pub fn in_phase<T>(phase: Phase, f: impl FnOnce() -> T) -> T {
    in_context((KIND.with(|k| k.get()), phase), f)
}

fn name(d: DType) -> String {
    format!("{d:?}").to_lowercase()
}

fn bytes_of(dtype: &str) -> f64 {
    match dtype {
        "f64" | "i64" | "u64" => 8.0,
        "bf16" | "f16" => 2.0,
        "u8" => 1.0,
        _ => 4.0,
    }
}

fn kind_now() -> String {
    match KIND.with(|k| k.get()) {
        "" => "other".to_string(),
        k => k.to_string(),
    }
}

/// Enters a product of `(batch, m, n, k)` on operands of `a` and `b` giving `out`.
pub(crate) fn product(
    (batch, m, n, k): (usize, usize, usize, usize),
    (a, b, out): (DType, DType, DType),
    transposed: [bool; 2],
    copied: [bool; 2],
) {
    let Some(l) = current() else { return };
    let p = Product {
        kind: kind_now(),
        phase: PHASE.with(|p| p.get()),
        batch,
        m,
        n,
        k,
        a: name(a),
        b: name(b),
        out: name(out),
        transposed,
        copied,
    };
    *l.0.lock()
        .unwrap_or_else(|e| e.into_inner())
        .products
        .entry(p)
        .or_default() += 1;
}

/// Enters a movement of `read` and `written` bytes.
pub(crate) fn moved(moved: Moved, what: &str, read: u64, written: u64) {
    let Some(l) = current() else { return };
    let e = Movement {
        kind: kind_now(),
        phase: PHASE.with(|p| p.get()),
        moved,
        what: what.to_string(),
        read,
        written,
    };
    *l.0.lock()
        .unwrap_or_else(|e| e.into_inner())
        .movements
        .entry(e)
        .or_default() += 1;
}

/// The bytes of `t`'s values.
pub(crate) fn size(t: &Tensor) -> u64 {
    (t.elem_count() * t.dtype().size_in_bytes()) as u64
}

/// Enters a cast of `elems` values from `from` to `to` (same types: a copy).
pub(crate) fn cast_of(elems: usize, from: DType, to: DType) {
    let (read, written) = (elems * from.size_in_bytes(), elems * to.size_in_bytes());
    let (m, what) = match from == to {
        true => (Moved::Copy, format!("copy {}", name(from))),
        false => (Moved::Cast, format!("cast {}→{}", name(from), name(to))),
    };
    moved(m, &what, read as u64, written as u64);
}

/// `t` in `dtype`, the cast entered (none where `t` is in `dtype` already: candle's
/// `to_dtype` returns it as it is then).
pub(crate) fn cast(t: &Tensor, dtype: DType) -> candle_core::Result<Tensor> {
    if t.dtype() != dtype {
        cast_of(t.elem_count(), t.dtype(), dtype);
    }
    t.to_dtype(dtype)
}

/// `t` contiguous, the copy entered where one is made.
pub(crate) fn contiguous(t: &Tensor) -> candle_core::Result<Tensor> {
    if !t.is_contiguous() {
        cast_of(t.elem_count(), t.dtype(), t.dtype());
    }
    t.contiguous()
}

/// Enters an op that reads `reads` and writes `writes` (whole tensors).
pub(crate) fn op(what: &str, reads: &[&Tensor], writes: &[&Tensor]) {
    if !on() {
        return;
    }
    let sum = |ts: &[&Tensor]| ts.iter().map(|t| size(t)).sum::<u64>();
    moved(Moved::Op, what, sum(reads), sum(writes));
}

/// How a product reads a `[.., rows, cols]` operand: `Some(false)` row-major, `Some(true)`
/// transposed, `None` neither (it needs a copy first).
pub(crate) fn reads_as(l: &Layout) -> Option<bool> {
    let (d, s) = (l.dims(), l.stride());
    let r = d.len();
    if r < 2 {
        return Some(false);
    }
    let (rows, cols) = (d[r - 2], d[r - 1]);
    if (s[r - 1] == 1 || cols == 1) && (s[r - 2] == cols || rows == 1) {
        return Some(false);
    }
    if (s[r - 2] == 1 || rows == 1) && (s[r - 1] == rows || cols == 1) {
        return Some(true);
    }
    None
}

/// `(batch, m, n, k)` of `a · b` (`[.., m, k]`, `[.., k, n]`).
pub(crate) fn bmnk(a: &[usize], b: &[usize]) -> (usize, usize, usize, usize) {
    let r = a.len();
    let batch = a[..r.saturating_sub(2)].iter().product();
    (batch, a[r - 2], b[b.len() - 1], a[r - 1])
}

/// `a · b` (candle's product), entered: the operands' layouts say which it reads
/// transposed.
pub(crate) fn mm(a: &Tensor, b: &Tensor) -> candle_core::Result<Tensor> {
    let y = a.matmul(b)?;
    if on() {
        let t = |x: &Tensor| reads_as(x.layout()).unwrap_or(false);
        product(
            bmnk(a.dims(), b.dims()),
            (a.dtype(), b.dtype(), y.dtype()),
            [t(a), t(b)],
            [false, false],
        );
    }
    Ok(y)
}

/// An accelerator's rates, for the time a ledger's entries would take on it: each product
/// at its type's product rate or its bytes at the memory bandwidth, whichever takes
/// longer, and each movement at the bandwidth.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Rates {
    pub name: std::borrow::Cow<'static, str>,
    /// Dense bf16 products (f32 accumulation), FLOP/s.
    pub bf16_flops: f64,
    /// f32 products without TF32 (candle turns TF32 off), FLOP/s.
    pub f32_flops: f64,
    /// Memory bandwidth, bytes/s.
    pub bandwidth: f64,
}

/// NVIDIA H200 SXM, the datasheet's peak figures (nvidia.com/en-us/data-center/h200,
/// read 2026-11-29): BF16 tensor core 1,979 TFLOPS with sparsity (989 dense), FP32 67
/// TFLOPS, HBM3e 4.8 TB/s.
pub const H200: Rates = Rates {
    name: std::borrow::Cow::Borrowed("H200 SXM (datasheet peaks)"),
    bf16_flops: 989e12,
    f32_flops: 67e12,
    bandwidth: 4.8e12,
};

impl Rates {
    /// Seconds of one product.
    pub fn product_s(&self, p: &Product) -> f64 {
        let rate = match p.precision() {
            "bf16" | "f16" => self.bf16_flops,
            _ => self.f32_flops,
        };
        (p.flops() / rate).max(p.bytes() / self.bandwidth)
    }

    /// Seconds of one movement.
    pub fn movement_s(&self, m: &Movement) -> f64 {
        (m.read + m.written) as f64 / self.bandwidth
    }
}

/// One op kind's share of a step (or the whole step's: kind `step`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Totals {
    pub kind: String,
    pub products: usize,
    /// Product FLOPs by the operands' type (`bf16`, `f32`, `mixed`).
    pub flops: BTreeMap<String, f64>,
    /// Products' FLOPs made again in the backward pass (`Phase::Recompute`), included above.
    pub recompute_flops: f64,
    /// Bytes read and written by casts, copies and other ops.
    pub bytes: BTreeMap<Moved, u64>,
    /// Seconds at [`Rates`]: the products, the movements.
    pub product_s: f64,
    pub movement_s: f64,
}

impl Totals {
    pub fn all_flops(&self) -> f64 {
        self.flops.values().sum()
    }

    fn add_product(&mut self, p: &Product, calls: usize, rates: &Rates) {
        let n = calls as f64;
        self.products += calls;
        *self.flops.entry(p.precision().to_string()).or_default() += n * p.flops();
        if p.phase == Phase::Recompute {
            self.recompute_flops += n * p.flops();
        }
        self.product_s += n * rates.product_s(p);
    }

    fn add_movement(&mut self, m: &Movement, calls: usize, rates: &Rates) {
        *self.bytes.entry(m.moved).or_default() += calls as u64 * (m.read + m.written);
        self.movement_s += calls as f64 * rates.movement_s(m);
    }
}

impl Entries {
    /// Per op kind, largest predicted time first, then the whole step (`step`).
    pub fn totals(&self, rates: &Rates) -> Vec<Totals> {
        let mut kinds: BTreeMap<&str, Totals> = BTreeMap::new();
        let mut step = Totals {
            kind: "step".into(),
            ..Totals::default()
        };
        let blank = |k: &str| Totals {
            kind: k.to_string(),
            ..Totals::default()
        };
        for (p, n) in &self.products {
            let t = kinds.entry(&p.kind).or_insert_with(|| blank(&p.kind));
            t.add_product(p, *n, rates);
            step.add_product(p, *n, rates);
        }
        for (m, n) in &self.movements {
            let t = kinds.entry(&m.kind).or_insert_with(|| blank(&m.kind));
            t.add_movement(m, *n, rates);
            step.add_movement(m, *n, rates);
        }
        let mut out: Vec<Totals> = kinds.into_values().collect();
        let time = |t: &Totals| t.product_s + t.movement_s;
        out.sort_by(|a, b| time(b).total_cmp(&time(a)));
        out.push(step);
        out
    }
}

#[cfg(test)]
mod tests;
