//! Slot Attention (paper eq. 2; Locatello et al. 2020): slots compete for the SLSR tokens.
//! The softmax is taken over **slots** (each token is explained by the slots together),
//! then each slot takes a weighted mean of the values, with ε added before renormalising
//! so that a slot that wins no token divides by ε, not by zero. Slots are updated by a
//! GRU cell followed by a pre-LayerNorm residual MLP. Keys and values are computed once.

use crate::nn::{Activation, LayerNorm, Linear, Mlp, linear};
use candle_core::{D, Module, Result, Tensor};
use candle_nn::{Init, VarBuilder};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SlotInit {
    /// One learned vector per slot (paper; fixed slot count).
    Learned,
    /// Slots drawn from a learned Gaussian `μ + σ·z` (any slot count at test time).
    Random,
    /// Not in the paper (an explicit option, reported as an ablation): learned vectors
    /// plus a learned projection of the SLSR tokens at evenly spaced positions, so the
    /// initial slots already carry scene content. With learned or random init the slots
    /// of two scenes differ by ~0.3 % at initialisation and a small model never learns
    /// to tell scenes apart (docs/time-to-quality.md).
    Tokens,
}

impl std::str::FromStr for SlotInit {
    type Err = String;

    /// The names the configs use: `learned`, `random`, `tokens`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "learned" => Ok(Self::Learned),
            "random" => Ok(Self::Random),
            "tokens" => Ok(Self::Tokens),
            other => Err(format!(
                "unknown slot init `{other}`: expected learned, random or tokens"
            )),
        }
    }
}

/// How the training gradient flows through the slot iterations (the values are the same
/// in all three).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SlotGradient {
    /// Through every iteration (the paper's).
    #[default]
    Full,
    /// Through the last iteration only: the slots are detached before it, treating the
    /// earlier iterations as finding a fixed point (Chang et al. 2022, "Object
    /// Representations as Fixed Points"). The initial slots get no gradient.
    Implicit,
    /// As `implicit`, with the last iteration's gradient passed straight through to the
    /// initial slots (`slots.detach() + init − init.detach()`), so that learned initial
    /// slots still learn (BO-QSA: Jia et al. 2023, "Improving Object-centric Learning
    /// with Query Optimization"). With one iteration, the same as `full`.
    Bilevel,
}

impl SlotGradient {
    pub fn is_full(&self) -> bool {
        *self == SlotGradient::Full
    }
}

impl std::str::FromStr for SlotGradient {
    type Err = String;
    /// The names the configs use: `full`, `implicit`, `bilevel`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "full" => Ok(Self::Full),
            "implicit" => Ok(Self::Implicit),
            "bilevel" => Ok(Self::Bilevel),
            other => Err(format!(
                "unknown slot gradient `{other}`: expected full, implicit or bilevel"
            )),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub num_slots: usize,
    pub slot_dim: usize,
    pub mlp_hidden: usize,
    pub iterations: usize,
    pub init: SlotInit,
    pub eps: f64,
    /// How the gradient flows through the iterations ([`SlotGradient`]); serialised only
    /// when not `full`, so configs written before it keep their hashes.
    #[serde(default, skip_serializing_if = "SlotGradient::is_full")]
    pub gradient: SlotGradient,
}

impl Config {
    /// Paper (CLEVR-3D): 6 slots of 1536, MLP 3072, one iteration, learned init, ε = 1e-8.
    pub fn paper() -> Self {
        Self {
            num_slots: 6,
            slot_dim: 1536,
            mlp_hidden: 3072,
            iterations: 1,
            init: SlotInit::Learned,
            eps: 1e-8,
            gradient: SlotGradient::Full,
        }
    }
}

/// GRU cell: `r = σ(W_ir x + W_hr h)`, `z = σ(W_iz x + W_hz h)`,
/// `n = tanh(W_in x + r ⊙ (W_hn h))`, `h' = (1 − z) ⊙ n + z ⊙ h` (with biases).
#[derive(Debug, Clone)]
pub struct GruCell {
    input: Linear,
    hidden: Linear,
    dim: usize,
}

impl GruCell {
    pub fn new(in_dim: usize, dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            input: linear(in_dim, 3 * dim, true, vb.pp("input"))?,
            hidden: linear(dim, 3 * dim, true, vb.pp("hidden"))?,
            dim,
        })
    }

    /// # Shapes
    /// `x: [.., in]`, `h: [.., dim]` → `[.., dim]`
    pub fn forward(&self, x: &Tensor, h: &Tensor) -> Result<Tensor> {
        let gi = self.input.forward(x)?;
        let gh = self.hidden.forward(h)?;
        let d = self.dim;
        let part = |t: &Tensor, i: usize| t.narrow(D::Minus1, i * d, d);
        let r = candle_nn::ops::sigmoid(&(part(&gi, 0)? + part(&gh, 0)?)?)?;
        let z = candle_nn::ops::sigmoid(&(part(&gi, 1)? + part(&gh, 1)?)?)?;
        let n = (part(&gi, 2)? + (r * part(&gh, 2)?)?)?.tanh()?;
        // (1 − z)·n + z·h = n + z·(h − n)
        &n + (z * (h - &n)?)?
    }
}

#[derive(Debug, Clone)]
pub struct SlotAttention {
    cfg: Config,
    norm_inputs: LayerNorm,
    norm_slots: LayerNorm,
    norm_mlp: LayerNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    gru: GruCell,
    mlp: Mlp,
    /// Learned: `[num_slots, slot_dim]`; random: `μ` `[1, slot_dim]`.
    init_mu: Tensor,
    /// Random init only: `log σ` `[1, slot_dim]`.
    init_log_sigma: Option<Tensor>,
    /// Tokens init only: normalised token → slot projection.
    init_from_tokens: Option<Linear>,
}

/// What slot attention returns.
pub struct SlotOutput {
    /// `[b, k, slot_dim]`
    pub slots: Tensor,
    /// Attention of the last iteration, normalised over slots: `[b, k, n]`.
    pub attention: Tensor,
}

impl SlotAttention {
    pub fn new(cfg: &Config, input_dim: usize, vb: VarBuilder) -> Result<Self> {
        let ds = cfg.slot_dim;
        let (init_mu, init_log_sigma) = match cfg.init {
            SlotInit::Learned | SlotInit::Tokens => (
                vb.get_with_hints(
                    (cfg.num_slots, ds),
                    "init_slots",
                    Init::Randn {
                        mean: 0.0,
                        stdev: 1.0,
                    },
                )?,
                None,
            ),
            SlotInit::Random => {
                let bound = (6.0 / (1 + ds) as f64).sqrt();
                (
                    vb.get_with_hints(
                        (1, ds),
                        "init_mu",
                        Init::Uniform {
                            lo: -bound,
                            up: bound,
                        },
                    )?,
                    Some(vb.get_with_hints(
                        (1, ds),
                        "init_log_sigma",
                        Init::Uniform {
                            lo: -bound,
                            up: bound,
                        },
                    )?),
                )
            }
        };
        Ok(Self {
            norm_inputs: LayerNorm::new(input_dim, vb.pp("norm_inputs"))?,
            norm_slots: LayerNorm::new(ds, vb.pp("norm_slots"))?,
            norm_mlp: LayerNorm::new(ds, vb.pp("norm_mlp"))?,
            to_q: linear(ds, ds, false, vb.pp("to_q"))?,
            to_k: linear(input_dim, ds, false, vb.pp("to_k"))?,
            to_v: linear(input_dim, ds, false, vb.pp("to_v"))?,
            gru: GruCell::new(ds, ds, vb.pp("gru"))?,
            mlp: Mlp::new(
                &[ds, cfg.mlp_hidden, ds],
                Activation::Relu,
                true,
                vb.pp("mlp"),
            )?,
            init_mu,
            init_log_sigma,
            init_from_tokens: (cfg.init == SlotInit::Tokens)
                .then(|| linear(input_dim, ds, false, vb.pp("init_from_tokens")))
                .transpose()?,
            cfg: cfg.clone(),
        })
    }

    /// Token positions the tokens init reads: `k` evenly spaced centres of `n` tokens.
    pub fn init_token_positions(&self, n: usize) -> Vec<u32> {
        let k = self.cfg.num_slots;
        (0..k).map(|i| ((2 * i + 1) * n / (2 * k)) as u32).collect()
    }

    /// Initial slots. Learned init ignores `noise`; random init needs standard-normal
    /// `noise: [b, k, slot_dim]` drawn by the caller's seeded RNG (candle's is
    /// unseedable); tokens init reads `normed: [b, n, input_dim]`, the LayerNorm'ed
    /// inputs.
    ///
    /// # Shapes
    /// → `[b, k, slot_dim]`
    fn initial_slots_from(
        &self,
        b: usize,
        noise: Option<&Tensor>,
        normed: Option<&Tensor>,
    ) -> Result<Tensor> {
        if let Some(proj) = &self.init_from_tokens {
            let x = normed.expect("tokens init is given the inputs");
            let n = x.dim(1)?;
            let idx = Tensor::new(self.init_token_positions(n), x.device())?;
            let picked = x.index_select(&idx, 1)?; // [b, k, input_dim]
            return proj.forward(&picked)?.broadcast_add(&self.init_mu);
        }
        match (&self.init_log_sigma, noise) {
            (None, _) => self.init_mu.unsqueeze(0)?.repeat((b, 1, 1)),
            (Some(log_sigma), Some(z)) => z
                .broadcast_mul(&log_sigma.exp()?)?
                .broadcast_add(&self.init_mu),
            (Some(_), None) => {
                candle_core::bail!("random slot init needs a noise tensor [b, k, slot_dim]")
            }
        }
    }

    /// # Shapes
    /// `inputs: [b, n, input_dim]`, `noise: [b, k, slot_dim]` (random init) →
    /// slots `[b, k, slot_dim]`, attention `[b, k, n]`
    pub fn forward(&self, inputs: &Tensor, noise: Option<&Tensor>) -> Result<SlotOutput> {
        let b = inputs.dim(0)?;
        let x = self.norm_inputs.forward(inputs)?;
        let k = self.to_k.forward(&x)?; // [b, n, ds]
        let v = self.to_v.forward(&x)?; // [b, n, ds]
        let kt = k.t()?.contiguous()?; // [b, ds, n]
        let scale = 1.0 / (self.cfg.slot_dim as f64).sqrt();
        let init = self.initial_slots_from(b, noise, Some(&x))?;
        let mut slots = init.clone();
        let mut attention = None;
        let iterations = self.cfg.iterations.max(1);
        for i in 0..iterations {
            if i + 1 == iterations {
                slots = match self.cfg.gradient {
                    SlotGradient::Full => slots,
                    SlotGradient::Implicit => slots.detach(),
                    // init − init.detach() is exactly 0: the values are unchanged.
                    SlotGradient::Bilevel => (slots.detach() + (&init - init.detach())?)?,
                };
            }
            let prev = slots.clone();
            let q = self.to_q.forward(&self.norm_slots.forward(&slots)?)?; // [b, k, ds]
            // Products in the thread's precision (bf16 operands where the step asks for
            // them, as autocast runs them), f32 otherwise to candle's bits.
            let logits = (osrt_kernels::matmul(&q, &kt)? * scale)?; // [b, k, n]
            let attn = osrt_kernels::softmax(&logits, 1)?; // over slots
            let weights = (&attn + self.cfg.eps)?;
            let weights = weights.broadcast_div(&weights.sum_keepdim(D::Minus1)?)?; // mean over inputs
            let updates = osrt_kernels::matmul(&weights, &v)?; // [b, k, ds]
            slots = self.gru.forward(&updates, &prev)?;
            slots = (&slots + self.mlp.forward(&self.norm_mlp.forward(&slots)?)?)?;
            attention = Some(attn);
        }
        Ok(SlotOutput {
            slots,
            attention: attention.expect("at least one iteration"),
        })
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }
}
