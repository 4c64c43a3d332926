//! The time of each op kind in a train step, forward and backward, on any device.
//!
//! candle's backward pass is one loop inside candle, with no hook per op, so the ops are
//! not timed where they run. Instead every op of this crate's public interface (and any
//! region the model names with [`op`]) is recorded when a [`Recorder`] is active: its
//! kind, its operands (detached: the recording keeps their storage, not their graph),
//! which operands carried a gradient, and a closure that runs it again. [`time_calls`]
//! then runs each distinct call (kind and operand shapes) alone, synchronising the device
//! around it: the forward pass, and the backward pass of the sum of its outputs less that
//! of the sum alone. Calls inside a recorded call (a linear layer inside an MLP that falls
//! back to layer-by-layer) belong to the outer one. What no recorded op covers (reshapes
//! and residual adds between ops, candle's gradient accumulation) is the step's time less
//! the table's sum, which the benchmark prints beside it.

use candle_core::{DType, Device, Result, Tensor, Var};
use std::cell::{Cell, RefCell};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Runs a recorded op on its operands again (the same order as recorded).
pub type Rerun = Arc<dyn Fn(&[Tensor]) -> Result<Vec<Tensor>> + Send + Sync>;

/// One recorded op call.
pub struct Call {
    pub kind: &'static str,
    inputs: Vec<Tensor>,
    /// Whether each operand carried a gradient (a weight, or an activation downstream of one).
    tracked: Vec<bool>,
    rerun: Rerun,
}

impl Call {
    /// `kind [shape dtype, …]`, with `*` on the operands that carried a gradient: calls
    /// with the same signature cost the same and are timed once.
    pub fn signature(&self) -> String {
        let ops: Vec<String> = self
            .inputs
            .iter()
            .zip(&self.tracked)
            .map(|(t, &g)| format!("{:?} {:?}{}", t.dims(), t.dtype(), if g { "*" } else { "" }))
            .collect();
        format!("{} [{}]", self.kind, ops.join(", "))
    }
}

/// Where the op calls of a step go while recording; shared with the device pool's
/// threads ([`crate::on_device_pool`] carries it along).
#[derive(Clone, Default)]
pub struct Recorder(Arc<Mutex<Vec<Call>>>);

impl Recorder {
    /// The calls recorded so far, in call order.
    pub fn take(&self) -> Vec<Call> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

thread_local! {
    static RECORDER: RefCell<Option<Recorder>> = const { RefCell::new(None) };
    /// Recorded ops entered and not yet left on this thread (only the outermost records).
    static DEPTH: Cell<u32> = const { Cell::new(0) };
}

/// This thread's recorder, if any.
pub(crate) fn current() -> Option<Recorder> {
    RECORDER.with(|r| r.borrow().clone())
}

/// Runs `f` with op calls on this thread going to `rec` (or to none).
pub fn recording<T>(rec: Option<Recorder>, f: impl FnOnce() -> T) -> T {
    let prev = RECORDER.with(|r| r.replace(rec));
    let out = f();
    RECORDER.with(|r| *r.borrow_mut() = prev);
    out
}

/// Runs the op `rerun` on `inputs`, recording the call when a recorder is active and no
/// recorded op encloses this one.
pub fn op(
    kind: &'static str,
    inputs: &[&Tensor],
    rerun: impl Fn(&[Tensor]) -> Result<Tensor> + Send + Sync + 'static,
) -> Result<Tensor> {
    let owned: Vec<Tensor> = inputs.iter().map(|t| (*t).clone()).collect();
    let Some(rec) = current() else {
        return crate::ledger::within(kind, || rerun(&owned));
    };
    let y = crate::ledger::within(kind, || nested(|| rerun(&owned)))?;
    record(&rec, kind, inputs, Arc::new(move |t| Ok(vec![rerun(t)?])));
    Ok(y)
}

/// Runs `f` as the inside of a recorded op: the calls it makes are not recorded apart.
pub(crate) fn nested<T>(f: impl FnOnce() -> T) -> T {
    DEPTH.with(|d| d.set(d.get() + 1));
    let out = f();
    DEPTH.with(|d| d.set(d.get() - 1));
    out
}

/// Records one call if no recorded op encloses it (ops whose result is not one tensor
/// run under [`nested`] and record themselves here).
pub(crate) fn record(rec: &Recorder, kind: &'static str, inputs: &[&Tensor], rerun: Rerun) {
    if DEPTH.with(|d| d.get()) > 0 {
        return;
    }
    let call = Call {
        kind,
        inputs: inputs.iter().map(|t| t.detach()).collect(),
        tracked: inputs.iter().map(|t| t.track_op()).collect(),
        rerun,
    };
    rec.0.lock().unwrap_or_else(|e| e.into_inner()).push(call);
}

/// The time of one distinct call, and how often the step made it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct CallTime {
    pub kind: String,
    pub signature: String,
    pub calls: usize,
    /// Median seconds of one forward pass.
    pub forward_s: f64,
    /// Median seconds of one backward pass (0 where no operand carried a gradient).
    pub backward_s: f64,
    /// Bytes one call holds from its forward pass until its backward pass: its outputs
    /// and what its graph keeps for the backward pass (the step holds this for every
    /// call at once, so the sum over calls is the activations' share of its peak).
    pub kept_bytes: Option<u64>,
    /// The most bytes one call's forward and backward passes held at once above what
    /// was held before it (kept bytes, the gradients and the passes' temporaries).
    pub peak_bytes: Option<u64>,
}

/// What the device's tensors hold: the heap on the CPU, the memory pool on a GPU.
pub trait MemoryMeter {
    /// Bytes held now (after the device's queued work).
    fn live(&self) -> Option<u64>;
    /// Starts a new peak from what is held now.
    fn reset_peak(&self);
    /// The most bytes held at once since [`MemoryMeter::reset_peak`].
    fn peak(&self) -> Option<u64>;
}

/// No memory figures.
pub struct NoMeter;

impl MemoryMeter for NoMeter {
    fn live(&self) -> Option<u64> {
        None
    }
    fn reset_peak(&self) {}
    fn peak(&self) -> Option<u64> {
        None
    }
}

/// Times each distinct call of `calls` alone on `device`: medians of `repeats` runs after
/// one warm-up, forward and backward. Runs in the caller's kernel and precision settings
/// (call it inside the same `with_kernels` / `with_precision` / `on_device_pool` as the
/// step). Sorted by total time (calls × (forward + backward)), largest first. The calls'
/// operands are let go as soon as they are no longer needed (the repeated calls' before
/// any timing, each timed call's after it), so the replay holds less than the step did.
pub fn time_calls(
    calls: Vec<Call>,
    device: &Device,
    repeats: usize,
    meter: &dyn MemoryMeter,
) -> Result<Vec<CallTime>> {
    let mut groups: BTreeMap<String, (usize, Call)> = BTreeMap::new();
    for c in calls {
        match groups.get_mut(&c.signature()) {
            Some(g) => g.0 += 1,
            None => {
                groups.insert(c.signature(), (1, c));
            }
        }
    }
    let mut out = Vec::with_capacity(groups.len());
    while let Some((signature, (count, c))) = groups.pop_first() {
        let (kept_bytes, peak_bytes) = measure_memory(&c, meter)?;
        let (forward_s, backward_s) = time_call(&c, device, repeats.max(1))?;
        out.push(CallTime {
            kind: c.kind.to_string(),
            signature,
            calls: count,
            forward_s,
            backward_s,
            kept_bytes,
            peak_bytes,
        });
    }
    let total = |t: &CallTime| t.calls as f64 * (t.forward_s + t.backward_s);
    out.sort_by(|a, b| total(b).total_cmp(&total(a)));
    Ok(out)
}

/// The call's operands: fresh leaves for those that carried a gradient, so that the
/// backward pass computes what the step's did for this op (and no more).
fn operands(c: &Call) -> Result<Vec<Tensor>> {
    c.inputs
        .iter()
        .zip(&c.tracked)
        .map(|(t, &g)| {
            if g {
                Var::from_tensor(t).map(Var::into_inner)
            } else {
                Ok(t.clone())
            }
        })
        .collect()
}

/// The bytes one call keeps from its forward pass to its backward pass, and the most it
/// holds at once through both (see [`CallTime`]), once the kernels are loaded.
fn measure_memory(c: &Call, meter: &dyn MemoryMeter) -> Result<(Option<u64>, Option<u64>)> {
    let inputs = operands(c)?;
    drop((c.rerun)(&inputs)?);
    let Some(before) = meter.live() else {
        return Ok((None, None));
    };
    meter.reset_peak();
    let outs = (c.rerun)(&inputs)?;
    let kept = meter.live().map(|b| b.saturating_sub(before));
    if c.tracked.iter().any(|&g| g) {
        let loss = sum_of(&outs)?;
        drop(outs);
        drop(loss.backward()?);
    }
    let peak = meter.peak().map(|b| b.saturating_sub(before));
    Ok((kept, peak))
}

/// Forward and backward medians of one call.
fn time_call(c: &Call, device: &Device, repeats: usize) -> Result<(f64, f64)> {
    let inputs = operands(c)?;
    let timed = |f: &mut dyn FnMut() -> Result<()>| -> Result<f64> {
        device.synchronize()?;
        let t0 = Instant::now();
        f()?;
        device.synchronize()?;
        Ok(t0.elapsed().as_secs_f64())
    };
    let mut fwd = Vec::with_capacity(repeats);
    for i in 0..=repeats {
        let s = timed(&mut || (c.rerun)(&inputs).map(drop))?;
        if i > 0 {
            fwd.push(s);
        }
    }
    if !c.tracked.iter().any(|&g| g) {
        return Ok((median(fwd), 0.0));
    }
    let mut bwd = Vec::with_capacity(repeats);
    for i in 0..=repeats {
        let outs = (c.rerun)(&inputs)?;
        let op_s = {
            let loss = sum_of(&outs)?;
            timed(&mut || loss.backward().map(drop))?
        };
        // The backward pass of the sum alone, over leaves shaped like the outputs.
        let leaves = outs
            .iter()
            .map(|o| Var::from_tensor(&o.detach()).map(Var::into_inner))
            .collect::<Result<Vec<_>>>()?;
        drop(outs);
        let sum_s = {
            let loss = sum_of(&leaves)?;
            timed(&mut || loss.backward().map(drop))?
        };
        if i > 0 {
            bwd.push((op_s - sum_s).max(0.0));
        }
    }
    Ok((median(fwd), median(bwd)))
}

/// The sum of every element of `ts`, in f32.
fn sum_of(ts: &[Tensor]) -> Result<Tensor> {
    let mut total: Option<Tensor> = None;
    for t in ts {
        let s = t.to_dtype(DType::F32)?.sum_all()?;
        total = Some(match total {
            Some(a) => (a + s)?,
            None => s,
        });
    }
    match total {
        Some(t) => Ok(t),
        None => candle_core::bail!("profile: an op with no outputs"),
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// One op kind's share of a step: its calls' totals.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct KindTime {
    pub kind: String,
    pub calls: usize,
    /// Seconds of all its calls' forward passes, and backward passes.
    pub forward_s: f64,
    pub backward_s: f64,
    /// Bytes all its calls keep from forward to backward (`None` without a meter).
    pub kept_bytes: Option<u64>,
    /// The largest peak of one of its calls.
    pub peak_bytes: Option<u64>,
}

/// Per-kind totals of [`time_calls`]' figures, largest total time first.
pub fn by_kind(times: &[CallTime]) -> Vec<KindTime> {
    let mut kinds: BTreeMap<&str, KindTime> = BTreeMap::new();
    for t in times {
        let k = kinds.entry(&t.kind).or_insert_with(|| KindTime {
            kind: t.kind.clone(),
            ..Default::default()
        });
        let n = t.calls as u64;
        k.calls += t.calls;
        k.forward_s += n as f64 * t.forward_s;
        k.backward_s += n as f64 * t.backward_s;
        k.kept_bytes = t.kept_bytes.map(|b| k.kept_bytes.unwrap_or(0) + n * b);
        k.peak_bytes = t.peak_bytes.map(|b| k.peak_bytes.unwrap_or(0).max(b));
    }
    let mut out: Vec<_> = kinds.into_values().collect();
    let total = |k: &KindTime| k.forward_s + k.backward_s;
    out.sort_by(|a, b| total(b).total_cmp(&total(a)));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;
    use crate::{MlpAct, layer_norm, mlp, on_device_pool, with_fused};

    /// An MLP then a LayerNorm over `x`, recorded; returns the output and the calls.
    fn recorded_step(fused: bool, x: &Tensor, ws: &[Var]) -> (Tensor, Vec<Call>) {
        let rec = Recorder::default();
        let y = with_fused(fused, || {
            recording(Some(rec.clone()), || {
                on_device_pool(&Device::Cpu, || {
                    let layers = [
                        (ws[0].as_tensor(), Some(ws[1].as_tensor())),
                        (ws[2].as_tensor(), Some(ws[3].as_tensor())),
                    ];
                    let h = mlp(x, &layers, MlpAct::Gelu)?;
                    layer_norm(&h, ws[4].as_tensor(), ws[5].as_tensor(), 1e-5)
                })
            })
        })
        .unwrap();
        (y, rec.take())
    }

    fn weights() -> Vec<Var> {
        [
            randn(&[16, 8], 0.3, 2),
            randn(&[16], 0.1, 3),
            randn(&[8, 16], 0.3, 4),
            randn(&[8], 0.1, 5),
            randn(&[8], 1.0, 6),
            randn(&[8], 0.1, 7),
        ]
        .iter()
        .map(|t| Var::from_tensor(t).unwrap())
        .collect()
    }

    /// Only the outermost ops are recorded (the composed MLP's linear layers and
    /// activations belong to it), on the pool's threads too, with their operands'
    /// gradient flags; each recorded call run again computes what the step computed.
    #[test]
    fn the_outermost_calls_are_recorded_and_rerun_to_the_same_values() {
        let x = randn(&[3, 5, 8], 1.0, 1);
        let ws = weights();
        for fused in [true, false] {
            let (y, calls) = recorded_step(fused, &x, &ws);
            let kinds: Vec<_> = calls.iter().map(|c| c.kind).collect();
            assert_eq!(kinds, ["mlp", "layer_norm"], "fused {fused}");
            assert_eq!(calls[0].tracked, [false, true, true, true, true]);
            assert_eq!(calls[1].tracked, [true, true, true]);
            assert!(
                calls[0]
                    .signature()
                    .starts_with("mlp [[3, 5, 8] F32, [16, 8] F32*")
            );
            let h = with_fused(fused, || (calls[0].rerun)(&calls[0].inputs)).unwrap();
            let mut ln_in = calls[1].inputs.clone();
            ln_in[0] = h[0].clone();
            let again = with_fused(fused, || (calls[1].rerun)(&ln_in)).unwrap();
            let d = (&again[0] - &y).unwrap().abs().unwrap().max_all().unwrap();
            assert_eq!(d.to_scalar::<f32>().unwrap(), 0.0, "fused {fused}");
        }
        // No recorder: nothing is kept, and the ops still run.
        let y = mlp(&x, &[(ws[0].as_tensor(), None)], MlpAct::Relu).unwrap();
        assert_eq!(y.dims(), [3, 5, 16]);
        assert!(current().is_none());
        assert_eq!(DEPTH.with(|d| d.get()), 0);
    }

    /// A recording that spans the backward pass too (as the profiled step's does) holds
    /// the step's ops only: the products inside a node's backward pass (the device
    /// graph's attention node) are not calls of their own.
    #[test]
    fn a_nodes_backward_pass_records_nothing() {
        let q = Var::from_tensor(&randn(&[2, 5, 8], 1.0, 1)).unwrap();
        let kv = Var::from_tensor(&randn(&[2, 3, 8], 1.0, 2)).unwrap();
        let rec = Recorder::default();
        crate::with_kernels(crate::Kernels::Device, || {
            recording(Some(rec.clone()), || {
                let (k, v) = (kv.as_tensor(), kv.as_tensor());
                let y = crate::attention(q.as_tensor(), k, v, 2, 0.5).unwrap();
                y.sum_all().unwrap().backward().unwrap();
            })
        });
        let kinds: Vec<_> = rec.take().iter().map(|c| c.kind).collect();
        assert_eq!(kinds, ["attention"]);
    }

    /// Calls of one signature are timed once and counted; an op none of whose operands
    /// carried a gradient has no backward pass; the table comes largest first.
    #[test]
    fn equal_calls_are_timed_once_and_counted() {
        let x = randn(&[64, 32], 1.0, 1);
        let w = Var::from_tensor(&randn(&[32], 1.0, 2)).unwrap();
        let b = Var::from_tensor(&randn(&[32], 0.1, 3)).unwrap();
        let rec = Recorder::default();
        recording(Some(rec.clone()), || {
            for _ in 0..3 {
                layer_norm(&x, w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
            }
            crate::softmax(&x, 1).unwrap();
        });
        let times = time_calls(rec.take(), &Device::Cpu, 2, &NoMeter).unwrap();
        assert_eq!(times.len(), 2);
        let ln = times.iter().find(|t| t.kind == "layer_norm").unwrap();
        let sm = times.iter().find(|t| t.kind == "softmax").unwrap();
        assert_eq!((ln.calls, sm.calls), (3, 1));
        assert!(ln.forward_s > 0.0 && ln.backward_s >= 0.0 && sm.forward_s > 0.0);
        assert_eq!(sm.backward_s, 0.0, "x carried no gradient");
        assert_eq!((ln.kept_bytes, ln.peak_bytes), (None, None), "no meter");
        let total = |t: &CallTime| t.calls as f64 * (t.forward_s + t.backward_s);
        assert!(total(&times[0]) >= total(&times[1]));
        let kinds = by_kind(&times);
        assert_eq!(kinds.iter().map(|k| k.calls).sum::<usize>(), 4);
    }
}
