//! A whole MLP, `Linear → act → … → Linear`, as one graph node with a hand-written
//! backward pass.
//!
//! Why: candle's backward costs every graph node a zero tensor and an add of the node's
//! input gradient (`GradStore::or_insert`), on one thread while gemm runs on all of them.
//! A three-layer render MLP over the decoder's 8,192 rays is five nodes, four of them
//! with `[8192, hidden]` inputs; as one node only the MLP's own input is accumulated.
//! The parameters enter packed (`Tensor::cat` of the flattened weights and biases, a
//! parameter-sized copy whose backward hands each parameter its slice), so one
//! `CustomOp2` takes them all and the variables, names and checkpoints stay as they are.
//!
//! The arithmetic is the per-layer fused path's, op for op: the same matmuls (candle's CPU
//! gemm, same operand layouts), the same in-place bias add, the same activation kernels
//! and column sums. The results are the same bits (tested): it changes speed, not
//! training.

use super::activation::MlpAct;
use super::gemm;
use super::linear::{ColumnSum, add_bias_rows, matmul_xwt, weight_grad};
use super::matrix::{MatRef, Threads};
use super::{cpu_storage as cpu, f32_slice, rows_layout, with_last_dim};
use crate::Precision;
use crate::kept::Kept;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, D, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// One layer's weight `[out, in]` and bias `[out]`, if it has one.
pub type MlpLayer<'a> = (&'a Tensor, Option<&'a Tensor>);

/// Widths `[in, hidden…, out]` and whether layers have biases: where each layer's weight
/// (`[out, in]`, row-major) and bias sit in the packed parameters.
#[derive(Debug, Clone)]
pub(crate) struct Plan {
    pub(crate) dims: Vec<usize>,
    pub(crate) bias: bool,
    /// The products' precision, forward and backward (the node's when it was made).
    pub(crate) precision: Precision,
}

impl Plan {
    fn layers(&self) -> usize {
        self.dims.len() - 1
    }

    /// `(in, out, weight offset, bias offset)` of layer `l`.
    fn layer(&self, l: usize) -> (usize, usize, usize, Option<usize>) {
        let mut off = 0;
        for i in 0..l {
            off += self.dims[i] * self.dims[i + 1] + if self.bias { self.dims[i + 1] } else { 0 };
        }
        let (k, o) = (self.dims[l], self.dims[l + 1]);
        (k, o, off, self.bias.then_some(off + o * k))
    }

    pub(crate) fn params(&self) -> usize {
        let (k, o, w, _) = self.layer(self.layers() - 1);
        w + o * k + if self.bias { o } else { 0 }
    }
}

/// Layer weight `W: [o, k]` at `w_off` of the packed parameters, as a layout.
fn weight_layout(p_l: &Layout, (k, o, w_off): (usize, usize, usize)) -> Layout {
    Layout::contiguous_with_offset((o, k), p_l.start_offset() + w_off)
}

/// What the forward pass keeps for the backward pass: per hidden layer its
/// pre-activation `z` and activation `a = act(z)`, both `[n, width]`.
pub(crate) type Saved = Vec<(Vec<f32>, CpuStorage)>;

/// An MLP's input `[n, in]`: one matrix, or two `[n, in_a]`, `[n, in_b]` that the first
/// layer reads side by side — the MLP of their concatenation, without building it.
#[derive(Clone, Copy)]
pub(crate) enum Input<'a> {
    One(&'a CpuStorage, &'a Layout),
    Two([(&'a CpuStorage, &'a Layout); 2]),
}

impl Input<'_> {
    /// The parts and, for each, the first column of the first layer's weight it meets.
    fn parts(&self) -> Vec<((&CpuStorage, &Layout), usize)> {
        match *self {
            Input::One(x, l) => vec![((x, l), 0)],
            Input::Two([a, b]) => vec![(a, 0), (b, a.1.dims()[1])],
        }
    }
}

/// Columns `c0 .. c0 + len` of the `[o, k]` weight at `w_off`, as a `[o, len]` view.
fn weight_cols<'a>(
    p: &'a CpuStorage,
    p_l: &Layout,
    (k, o, w_off): (usize, usize, usize),
    (c0, len): (usize, usize),
) -> Result<MatRef<'a>> {
    MatRef::of(p, &weight_layout(p_l, (k, o, w_off)))?.cols(c0, len)
}

/// The first layer's product `x·W₀ᵀ` (no bias), `[n, o]`: with two inputs, the sum of
/// each part times its columns of `W₀`.
fn first_product(
    input: Input,
    p: &CpuStorage,
    p_l: &Layout,
    (k, o, w_off): (usize, usize, usize),
    precision: Precision,
) -> Result<Vec<f32>> {
    let mut z: Option<Vec<f32>> = None;
    for ((x, x_l), c0) in input.parts() {
        let xm = MatRef::of(x, x_l)?;
        let w = weight_cols(p, p_l, (k, o, w_off), (c0, xm.dims().1))?;
        let part = gemm::matmul(xm, w.t(), Threads::Pool, precision)?;
        match &mut z {
            None => z = Some(part),
            Some(z) => add_assign(z, &part),
        }
    }
    z.ok_or_else(|| candle_core::Error::Msg("mlp: no input".into()))
}

/// `acc[i] += v[i]`, in parallel.
fn add_assign(acc: &mut [f32], v: &[f32]) {
    acc.par_chunks_mut(8192)
        .zip(v.par_chunks(8192))
        .for_each(|(a, v)| a.iter_mut().zip(v).for_each(|(a, v)| *a += *v));
}

/// The forward pass: the output `[n, out]` and the hidden layers' `(z, act(z))`.
pub(crate) fn forward(
    plan: &Plan,
    act: MlpAct,
    input: Input,
    p: &CpuStorage,
    p_l: &Layout,
) -> Result<(Vec<f32>, Saved)> {
    let n = input.parts()[0].0.1.dims()[0];
    let params = f32_slice(p, p_l, "mlp parameters")?;
    let mut saved: Saved = Vec::with_capacity(plan.layers() - 1);
    for l in 0..plan.layers() {
        let (k, o, w_off, b_off) = plan.layer(l);
        let mut z = match saved.last() {
            None => first_product(input, p, p_l, (k, o, w_off), plan.precision)?,
            Some((_, a)) => matmul_xwt(
                a,
                &Layout::contiguous((n, k)),
                p,
                &weight_layout(p_l, (k, o, w_off)),
                plan.precision,
            )?,
        };
        if let Some(b) = b_off {
            add_bias_rows(&mut z, &params[b..b + o]);
        }
        if l + 1 == plan.layers() {
            return Ok((z, saved));
        }
        let a = act.forward(&z);
        saved.push((z, CpuStorage::F32(a)));
    }
    unreachable!("an MLP has at least one layer")
}

#[cfg(test)]
thread_local! {
    /// One-node MLP forwards run on this thread (tests check the fused path ran).
    pub(crate) static FORWARDS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

struct MlpOp {
    plan: Plan,
    act: MlpAct,
    /// Whether a backward pass can follow (an input carries a gradient): only then are
    /// the hidden layers kept.
    keep: bool,
    saved: Kept<Saved>,
}

impl MlpOp {
    /// The forward pass over `input` (laid out as `input_l`), keeping what the backward
    /// pass needs when one can follow.
    fn run(
        &self,
        input: Input,
        p: &CpuStorage,
        p_l: &Layout,
        input_l: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (y, saved) = forward(&self.plan, self.act, input, p, p_l)?;
        if self.keep {
            self.saved.put(saved);
        }
        let out = *self.plan.dims.last().unwrap_or(&0);
        Ok((CpuStorage::F32(y), with_last_dim(input_l, out)))
    }
}

impl CustomOp2 for MlpOp {
    fn name(&self) -> &'static str {
        "osrt-mlp"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let rows = rows_layout(l1)?;
        let (n, k) = rows.shape().dims2()?;
        if k != self.plan.dims[0] || l2.shape().elem_count() != self.plan.params() {
            candle_core::bail!(
                "mlp: input [{n}, {k}] and {} packed parameters for widths {:?}",
                l2.shape().elem_count(),
                self.plan.dims
            );
        }
        f32_slice(s1, l1, "mlp input")?;
        #[cfg(test)]
        FORWARDS.with(|c| c.set(c.get() + 1));
        self.run(Input::One(s1, &rows), s2, l2, l1)
    }

    fn bwd(
        &self,
        x: &Tensor,
        p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        crate::ledger::backward("", "mlp", || {
            // Taken, not cloned: a second backward through the same graph recomputes them.
            let saved = self.saved.take();
            let bwd = MlpBwd {
                plan: self.plan.clone(),
                act: self.act,
                saved: Kept::new(saved),
                input_grad: x.track_op(),
            };
            let flat = x.apply_op3_no_bwd(p, &grad.contiguous()?, &bwd)?;
            let n_p = self.plan.params();
            let dp = flat.narrow(0, flat.dim(0)? - n_p, n_p)?;
            let dx = if bwd.input_grad {
                Some(flat.narrow(0, 0, x.elem_count())?.reshape(x.shape())?)
            } else {
                None
            };
            Ok((dx, Some(dp)))
        })
    }
}

/// The backward pass of [`MlpOp`] as a no-grad op over `(x, packed, grad)`: one flat
/// buffer `[dx (when the input carries a gradient) | d packed]`.
pub(crate) struct MlpBwd {
    pub(crate) plan: Plan,
    pub(crate) act: MlpAct,
    pub(crate) saved: Kept<Saved>,
    pub(crate) input_grad: bool,
}

impl CustomOp3 for MlpBwd {
    fn name(&self) -> &'static str {
        "osrt-mlp-bwd"
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
        let l1 = &rows_layout(l1)?;
        let (dx, dp) = self.backward(Input::One(s1, l1), s2, l2, (s3, l3))?;
        let mut out = dx.into_iter().next().flatten().unwrap_or_default();
        out.extend_from_slice(&dp);
        let len = out.len();
        Ok((CpuStorage::F32(out), Shape::from(len)))
    }
}

/// Per input part, its gradient (`None` where none was asked for).
pub(crate) type InputGrads = Vec<Option<Vec<f32>>>;

impl MlpBwd {
    /// For upstream `dy: [n, out]`: each input part's gradient (when `input_grad`) and
    /// the packed parameters' gradient.
    pub(crate) fn backward(
        &self,
        input: Input,
        p: &CpuStorage,
        p_l: &Layout,
        (dy, dy_l): (&CpuStorage, &Layout),
    ) -> Result<(InputGrads, Vec<f32>)> {
        let plan = &self.plan;
        let parts = input.parts();
        let n = parts[0].0.1.dims()[0];
        let saved = match self.saved.take() {
            Some(s) => s,
            None => forward(plan, self.act, input, p, p_l)?.1,
        };
        let mut dp = vec![0f32; plan.params()];
        let mut dx = vec![None; parts.len()];
        // dz of the current layer, `[n, o]`.
        let mut dz = CpuStorage::F32(f32_slice(dy, dy_l, "mlp gradient")?.to_vec());
        for l in (0..plan.layers()).rev() {
            let (k, o, w_off, b_off) = plan.layer(l);
            let dz_l = Layout::contiguous((n, o));
            if let Some(b) = b_off {
                let db = ColumnSum { d: o }.cpu_fwd(&dz, &dz_l)?.0;
                dp[b..b + o].copy_from_slice(f32_slice(&db, &Layout::contiguous(o), "db")?);
            }
            if l > 0 {
                // dW = dzᵀ · a_{l−1}: `[o, n] · [n, k]`; da = dz · W: `[n, o] · [o, k]`.
                let a_l = Layout::contiguous((n, k));
                let dw = weight_grad(&dz, &dz_l, &saved[l - 1].1, &a_l, plan.precision)?;
                dp[w_off..w_off + o * k].copy_from_slice(&dw);
                let w = MatRef::of(p, &weight_layout(p_l, (k, o, w_off)))?;
                let da = gemm::matmul(MatRef::of(&dz, &dz_l)?, w, Threads::Pool, plan.precision)?;
                dz = CpuStorage::F32(self.act.backward(&saved[l - 1].0, &da));
                continue;
            }
            // The first layer, part by part: its columns of dW and its input gradient.
            for (i, ((x, x_l), c0)) in parts.iter().enumerate() {
                let kx = x_l.dims()[1];
                let dw = weight_grad(&dz, &dz_l, x, x_l, plan.precision)?; // [o, kx]
                for (r, row) in dw.chunks(kx.max(1)).enumerate() {
                    let at = w_off + r * k + c0;
                    dp[at..at + kx].copy_from_slice(row);
                }
                if self.input_grad {
                    let w = weight_cols(p, p_l, (k, o, w_off), (*c0, kx))?;
                    let dz = MatRef::of(&dz, &dz_l)?;
                    dx[i] = Some(gemm::matmul(dz, w, Threads::Pool, plan.precision)?);
                }
            }
        }
        Ok((dx, dp))
    }
}

/// The widths `[in, hidden…, out]` of `layers` after an input of width `input`, and their
/// parameters packed into one tensor (each weight, then its bias, flattened, layer by
/// layer): a parameter-sized copy whose backward hands each parameter its slice.
fn pack(input: usize, layers: &[MlpLayer]) -> Result<(Vec<usize>, Tensor)> {
    let mut dims = vec![input];
    let mut flat = Vec::with_capacity(layers.len() * 2);
    for (w, b) in layers {
        let (o, k) = w.dims2()?;
        if k != *dims.last().unwrap_or(&0) {
            candle_core::bail!("mlp: a layer of width {k} after width {dims:?}");
        }
        dims.push(o);
        flat.push(w.flatten_all()?);
        if let Some(b) = b {
            flat.push(b.flatten_all()?);
        }
    }
    Ok((dims, Tensor::cat(&flat, 0)?))
}

/// `x: [.., in]` through `layers` (every layer with a bias, or none) with `act` between
/// them as one node (f32 on the CPU; shapes checked by the caller).
pub(crate) fn mlp(x: &Tensor, layers: &[MlpLayer], act: MlpAct, bias: bool) -> Result<Tensor> {
    let (dims, packed) = pack(x.dim(D::Minus1)?, layers)?;
    let op = MlpOp {
        plan: Plan {
            dims,
            bias,
            precision: crate::precision(),
        },
        act,
        keep: x.track_op() || packed.track_op(),
        saved: Kept::new(None),
    };
    x.contiguous()?.apply_op2(&packed, op)
}

/// The MLP of `[a, b]` concatenated on the last dim as one node that reads the two side
/// by side (f32 on the CPU; shapes checked by the caller; see [`crate::mlp_cat`]).
pub(crate) fn mlp_cat(
    a: &Tensor,
    b: &Tensor,
    layers: &[MlpLayer],
    act: MlpAct,
    bias: bool,
) -> Result<Tensor> {
    let (dims, packed) = pack(a.dim(D::Minus1)? + b.dim(D::Minus1)?, layers)?;
    let op = MlpCatOp(MlpOp {
        plan: Plan {
            dims,
            bias,
            precision: crate::precision(),
        },
        act,
        keep: a.track_op() || b.track_op() || packed.track_op(),
        saved: Kept::new(None),
    });
    a.contiguous()?.apply_op3(&b.contiguous()?, &packed, op)
}

/// An MLP over two inputs read side by side (see [`crate::mlp_cat`]).
struct MlpCatOp(MlpOp);

impl CustomOp3 for MlpCatOp {
    fn name(&self) -> &'static str {
        "osrt-mlp-cat"
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
        let (a, b) = (rows_layout(l1)?, rows_layout(l2)?);
        let widths = a.dims()[1] + b.dims()[1];
        let plan = &self.0.plan;
        if a.dims()[0] != b.dims()[0] || widths != plan.dims[0] {
            candle_core::bail!(
                "mlp: inputs {:?} and {:?} side by side for widths {:?}",
                l1.dims(),
                l2.dims(),
                plan.dims
            );
        }
        if l3.shape().elem_count() != plan.params() {
            candle_core::bail!("mlp: {} packed parameters", l3.shape().elem_count());
        }
        f32_slice(s1, l1, "mlp input")?;
        f32_slice(s2, l2, "mlp input")?;
        self.0.run(Input::Two([(s1, &a), (s2, &b)]), s3, l3, l1)
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        crate::ledger::backward("", "mlp", || {
            let grad = grad.contiguous()?;
            let op = &self.0;
            let bwd = MlpBwd {
                plan: op.plan.clone(),
                act: op.act,
                // Taken, not cloned: a second backward through the same graph recomputes it.
                saved: Kept::new(op.saved.take()),
                input_grad: a.track_op() || b.track_op(),
            };
            let (sa, la) = a.storage_and_layout();
            let (sb, lb) = b.storage_and_layout();
            let (sp, lp) = p.storage_and_layout();
            let (sg, lg) = grad.storage_and_layout();
            let (la, lb, lg) = (rows_layout(la)?, rows_layout(lb)?, rows_layout(lg)?);
            let input = Input::Two([(cpu(&sa)?, &la), (cpu(&sb)?, &lb)]);
            let (dx, dp) = bwd.backward(input, cpu(&sp)?, lp, (cpu(&sg)?, &lg))?;
            let dev = a.device();
            let mut dx = dx.into_iter();
            let mut part = |t: &Tensor| -> Result<Option<Tensor>> {
                match (dx.next().flatten(), t.track_op()) {
                    (Some(v), true) => Ok(Some(Tensor::from_vec(v, t.shape(), dev)?)),
                    _ => Ok(None),
                }
            };
            let (da, db) = (part(a)?, part(b)?);
            Ok((da, db, Some(Tensor::from_vec(dp, p.shape(), dev)?)))
        })
    }
}
