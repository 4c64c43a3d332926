//! Parameters: deterministic initialisation and a fixed order.
//!
//! candle's CPU RNG cannot be seeded and `VarMap` iterates a `HashMap`, so neither gives
//! reproducible weights. [`Params`] is a `VarBuilder` backend that draws every tensor from
//! a ChaCha RNG seeded by `(seed, parameter name)` — the value of a parameter depends only
//! on the seed and its name, not on construction order — and keeps the variables in a
//! `BTreeMap`, so the flat parameter order (sorted names) is the same in every process.

use candle_core::{DType, Device, Result, Shape, Tensor, Var};
use candle_nn::VarBuilder;
use candle_nn::init::{Init, NormalOrUniform};
use candle_nn::var_builder::SimpleBackend;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// The named variables of a model, in sorted-name order.
#[derive(Clone, Default)]
pub struct Params {
    seed: u64,
    vars: Arc<Mutex<BTreeMap<String, Var>>>,
    /// Counts the loads below, so that a holder of facts about the values (the
    /// optimiser's maxima) can tell they were replaced; see [`Params::version`].
    version: Arc<AtomicU64>,
}

fn name_seed(seed: u64, name: &str) -> u64 {
    // FNV-1a over the name, then mixed with the seed.
    let h = name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    });
    h ^ seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// Standard normal samples by Box–Muller (stable across `rand` versions, unlike
/// distribution crates' algorithms).
pub fn normal_samples(rng: &mut impl Rng, n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n + 1);
    while out.len() < n {
        let u1: f64 = rng.random::<f64>().max(1e-300);
        let u2: f64 = rng.random::<f64>();
        let r = (-2.0 * u1.ln()).sqrt();
        let t = 2.0 * std::f64::consts::PI * u2;
        out.push((r * t.cos()) as f32);
        out.push((r * t.sin()) as f32);
    }
    out.truncate(n);
    out
}

fn init_values(init: Init, shape: &Shape, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let n = shape.elem_count();
    let uniform = |rng: &mut ChaCha8Rng, lo: f64, up: f64| -> Vec<f32> {
        (0..n)
            .map(|_| (lo + (up - lo) * rng.random::<f64>()) as f32)
            .collect()
    };
    match init {
        Init::Const(c) => vec![c as f32; n],
        Init::Uniform { lo, up } => uniform(rng, lo, up),
        Init::Randn { mean, stdev } => normal_samples(rng, n)
            .into_iter()
            .map(|z| (mean + stdev * z as f64) as f32)
            .collect(),
        Init::Kaiming {
            dist,
            fan,
            non_linearity,
        } => {
            let std = non_linearity.gain() / (fan.for_shape(shape) as f64).sqrt();
            match dist {
                NormalOrUniform::Uniform => {
                    let b = 3f64.sqrt() * std;
                    uniform(rng, -b, b)
                }
                NormalOrUniform::Normal => normal_samples(rng, n)
                    .into_iter()
                    .map(|z| (std * z as f64) as f32)
                    .collect(),
            }
        }
    }
}

impl Params {
    pub fn new(seed: u64) -> Self {
        Self {
            seed,
            ..Self::default()
        }
    }

    /// A `VarBuilder` whose tensors are created (or found) here.
    pub fn var_builder(&self, device: &Device) -> VarBuilder<'static> {
        self.var_builder_dtype(DType::F32, device)
    }

    /// Same with another dtype (f64 for finite-difference gradient checks).
    pub fn var_builder_dtype(&self, dtype: DType, device: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), dtype, device.clone())
    }

    /// `(name, var)` in sorted-name order: the fixed parameter order.
    pub fn vars(&self) -> Vec<(String, Var)> {
        self.vars
            .lock()
            .expect("params lock")
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }

    /// Changes whenever a `load_*` method below replaces the values (not when an
    /// optimiser updates them in place, nor through a `Var` taken from [`Params::vars`]).
    pub fn version(&self) -> u64 {
        self.version.load(Ordering::SeqCst)
    }

    fn replaced(&self) {
        self.version.fetch_add(1, Ordering::SeqCst);
    }

    pub fn num_elements(&self) -> usize {
        self.vars().iter().map(|(_, v)| v.elem_count()).sum()
    }

    /// All parameters as one flat f32 tensor on their device, in the fixed order.
    pub fn flatten_tensor(&self) -> Result<Tensor> {
        let parts = self
            .vars()
            .iter()
            .map(|(_, v)| v.as_tensor().flatten_all()?.to_dtype(DType::F32))
            .collect::<Result<Vec<_>>>()?;
        Tensor::cat(&parts, 0)
    }

    /// All parameters as one flat f32 buffer, in the fixed order.
    pub fn flatten(&self) -> Result<Vec<f32>> {
        let vars = self.vars();
        if vars.first().is_some_and(|(_, v)| !v.device().is_cpu()) {
            // One copy from the device instead of one per parameter.
            return self.flatten_tensor()?.to_vec1::<f32>();
        }
        let mut out = Vec::with_capacity(self.num_elements());
        for (_, v) in self.vars() {
            out.extend(
                v.as_tensor()
                    .flatten_all()?
                    .to_dtype(DType::F32)?
                    .to_vec1::<f32>()?,
            );
        }
        Ok(out)
    }

    /// Overwrites every parameter from a flat buffer in the fixed order.
    pub fn load_flat(&self, flat: &[f32]) -> Result<()> {
        // First: a load that fails half-way has replaced values too.
        self.replaced();
        let vars = self.vars();
        let total: usize = vars.iter().map(|(_, v)| v.elem_count()).sum();
        if flat.len() != total {
            candle_core::bail!(
                "flat parameter buffer has {} values, the model has {total}",
                flat.len()
            );
        }
        let mut off = 0;
        for (_, v) in vars {
            let n = v.elem_count();
            let t = Tensor::from_slice(&flat[off..off + n], v.shape(), v.device())?
                .to_dtype(v.dtype())?;
            v.set(&t)?;
            off += n;
        }
        Ok(())
    }

    /// Overwrites every parameter from a flat f32 tensor in the fixed order (on the
    /// parameters' device: nothing crosses to the host).
    pub fn load_flat_tensor(&self, flat: &Tensor) -> Result<()> {
        // First: a load that fails half-way has replaced values too.
        self.replaced();
        let vars = self.vars();
        let total: usize = vars.iter().map(|(_, v)| v.elem_count()).sum();
        if flat.dims() != [total] {
            candle_core::bail!(
                "flat parameter tensor has shape {:?}, the model has {total} values",
                flat.dims()
            );
        }
        let mut off = 0;
        for (_, v) in vars {
            let n = v.elem_count();
            let t = flat
                .narrow(0, off, n)?
                .reshape(v.shape())?
                .to_dtype(v.dtype())?;
            v.set(&t)?;
            off += n;
        }
        Ok(())
    }

    /// Loads named tensors; every parameter must be present with its shape.
    pub fn load_tensors(&self, tensors: &std::collections::HashMap<String, Tensor>) -> Result<()> {
        // First: a load that fails half-way has replaced values too.
        self.replaced();
        for (name, v) in self.vars() {
            let t = tensors.get(&name).ok_or_else(|| {
                candle_core::Error::Msg(format!("weights lack parameter `{name}`"))
            })?;
            if t.shape() != v.shape() {
                candle_core::bail!(
                    "parameter `{name}` has shape {:?} in the weights, the model expects {:?}",
                    t.dims(),
                    v.dims()
                );
            }
            v.set(&t.to_dtype(v.dtype())?)?;
        }
        Ok(())
    }
}

impl SimpleBackend for Params {
    fn get(&self, s: Shape, name: &str, h: Init, dtype: DType, dev: &Device) -> Result<Tensor> {
        let mut vars = self.vars.lock().expect("params lock");
        if let Some(v) = vars.get(name) {
            if v.shape() != &s {
                candle_core::bail!(
                    "parameter `{name}` requested with shape {s:?}, exists as {:?}",
                    v.shape()
                );
            }
            return Ok(v.as_tensor().clone());
        }
        let mut rng = ChaCha8Rng::seed_from_u64(name_seed(self.seed, name));
        let values = init_values(h, &s, &mut rng);
        let var = Var::from_tensor(&Tensor::from_vec(values, s, dev)?.to_dtype(dtype)?)?;
        vars.insert(name.to_string(), var.clone());
        Ok(var.as_tensor().clone())
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> Result<Tensor> {
        self.vars
            .lock()
            .expect("params lock")
            .get(name)
            .map(|v| v.as_tensor().clone())
            .ok_or_else(|| candle_core::Error::Msg(format!("no parameter `{name}`")))
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.vars.lock().expect("params lock").contains_key(name)
    }
}
