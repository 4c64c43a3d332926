//! Building blocks shared by the paper components: a LayerNorm whose backward exists,
//! linear layers with PyTorch's default initialisation, MLPs, multi-head attention and
//! pre-norm transformer blocks (self- and cross-attention).
//!
//! candle's fused `layer_norm` and `softmax_last_dim` have no backward pass and fail
//! silently (their parameters never train), so everything here uses ops that have one:
//! our own fused LayerNorm, softmax, GELU and bias add (`osrt_kernels`, hand-written
//! backward passes), falling back to candle's composed ops where those do not apply.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Init, VarBuilder};
use serde::{Deserialize, Serialize};

/// Linear layer with PyTorch's default init: weight and bias ~ U(−1/√in, 1/√in).
pub fn linear(in_dim: usize, out_dim: usize, bias: bool, vb: VarBuilder) -> Result<Linear> {
    let bound = 1.0 / (in_dim as f64).sqrt();
    let init = Init::Uniform {
        lo: -bound,
        up: bound,
    };
    let w = vb.get_with_hints((out_dim, in_dim), "weight", init)?;
    let b = if bias {
        Some(vb.get_with_hints(out_dim, "bias", init)?)
    } else {
        None
    };
    Ok(Linear { weight: w, bias: b })
}

/// `x Wᵀ + b`, as `candle_nn::Linear` computes it, with the bias added by the fused op
/// (its gradient is one column sum instead of candle's broadcast reduction).
#[derive(Debug, Clone)]
pub struct Linear {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// [`Module::forward`], the output stored in bf16 where the products run in bf16 on
    /// the device graph and the layer has no bias (`osrt_kernels::linear_low`: for an
    /// output whose one reader is another product or attention).
    pub fn forward_low(&self, x: &Tensor) -> Result<Tensor> {
        match &self.bias {
            None => osrt_kernels::linear_low(x, &self.weight),
            Some(_) => self.forward(x),
        }
    }
}

impl Module for Linear {
    /// `[.., in] → [.., out]`
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        // Bias included, over all leading dims at once, without reshape nodes around it.
        osrt_kernels::linear(x, &self.weight, self.bias.as_ref())
    }
}

/// LayerNorm over the last dimension, composed from differentiable ops. Safe on constant
/// input: the centred values are exactly 0, and ε keeps the divisor positive.
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn new(dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(dim, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(dim, "bias", Init::Const(0.0))?,
            eps: 1e-5,
        })
    }
}

impl Module for LayerNorm {
    /// `[.., d] → [.., d]`
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        osrt_kernels::layer_norm(x, &self.weight, &self.bias, self.eps)
    }
}

/// Negative slope of the leaky ReLU (the paper's render MLP: LeakyReLU(0.01)).
const LEAKY_RELU_SLOPE: f32 = 0.01;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    Relu,
    Gelu,
    LeakyRelu,
}

impl Activation {
    /// The fused ops' activation.
    fn fused(self) -> osrt_kernels::MlpAct {
        match self {
            Activation::Relu => osrt_kernels::MlpAct::Relu,
            // erf-based GELU, as in the reference transformer.
            Activation::Gelu => osrt_kernels::MlpAct::Gelu,
            Activation::LeakyRelu => osrt_kernels::MlpAct::LeakyRelu(LEAKY_RELU_SLOPE),
        }
    }
}

/// `Linear → act → … → Linear` (no activation after the last layer).
#[derive(Debug, Clone)]
pub struct Mlp {
    layers: Vec<Linear>,
    act: Activation,
}

impl Mlp {
    /// `dims = [in, hidden…, out]`.
    pub fn new(dims: &[usize], act: Activation, bias: bool, vb: VarBuilder) -> Result<Self> {
        let layers = dims
            .windows(2)
            .enumerate()
            .map(|(i, w)| linear(w[0], w[1], bias, vb.pp(i.to_string())))
            .collect::<Result<_>>()?;
        Ok(Self { layers, act })
    }
}

impl Mlp {
    /// The MLP of `[a, b]` concatenated on the last dim, without building the
    /// concatenation where the fused ops apply (`osrt_kernels::mlp_cat`).
    ///
    /// # Shapes
    /// `a: [.., in_a]`, `b: [.., in_b]` with `in_a + in_b = in` → `[.., out]`
    pub fn forward_cat(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let layers: Vec<_> = self
            .layers
            .iter()
            .map(|l| (&l.weight, l.bias.as_ref()))
            .collect();
        osrt_kernels::mlp_cat(a, b, &layers, self.act.fused())
    }
}

impl Module for Mlp {
    /// `[.., in] → [.., out]`
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        // One node for the whole MLP over all leading dims (`osrt_kernels::mlp`; layer by layer
        // where the fused ops do not apply).
        let layers: Vec<_> = self
            .layers
            .iter()
            .map(|l| (&l.weight, l.bias.as_ref()))
            .collect();
        osrt_kernels::mlp(x, &layers, self.act.fused())
    }
}

/// Multi-head scaled dot-product attention: bias-free q/k/v projections and an output
/// projection with bias (as in SRT). Queries and keys/values may have different widths.
#[derive(Debug, Clone)]
pub struct Attention {
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    heads: usize,
    head_dim: usize,
}

impl Attention {
    pub fn new(
        q_dim: usize,
        kv_dim: usize,
        heads: usize,
        head_dim: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let inner = heads * head_dim;
        Ok(Self {
            q: linear(q_dim, inner, false, vb.pp("q"))?,
            k: linear(kv_dim, inner, false, vb.pp("k"))?,
            v: linear(kv_dim, inner, false, vb.pp("v"))?,
            out: linear(inner, q_dim, true, vb.pp("out"))?,
            heads,
            head_dim,
        })
    }

    /// # Shapes
    /// `x: [b, n, q_dim]`, `ctx: [b, m, kv_dim]` → `[b, n, q_dim]`
    pub fn forward(&self, x: &Tensor, ctx: &Tensor) -> Result<Tensor> {
        let scale = 1.0 / (self.head_dim as f64).sqrt();
        // The projections and the attention's output are read only by the attention and by
        // the output projection's product: in bf16 they are stored in bf16.
        let o = osrt_kernels::attention(
            &self.q.forward_low(x)?,
            &self.k.forward_low(ctx)?,
            &self.v.forward_low(ctx)?,
            self.heads,
            scale,
        )?; // [b, n, h·dh]
        self.out.forward(&o)
    }
}

/// Sizes of a transformer stack.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformerConfig {
    pub layers: usize,
    pub heads: usize,
    pub head_dim: usize,
    pub mlp_hidden: usize,
}

/// Pre-LayerNorm block: `x + Attn(LN(x), ctx)`, then `x + MLP(LN(x))`. With `ctx = None`
/// it is self-attention; otherwise the queries cross-attend into `ctx`, and only the
/// queries are normalised (the context — slots — arrives normalised by its producer).
#[derive(Debug, Clone)]
pub struct Block {
    norm_attn: LayerNorm,
    attn: Attention,
    norm_mlp: LayerNorm,
    mlp: Mlp,
}

impl Block {
    pub fn new(
        dim: usize,
        ctx_dim: usize,
        cfg: &TransformerConfig,
        vb: VarBuilder,
    ) -> Result<Self> {
        Ok(Self {
            norm_attn: LayerNorm::new(dim, vb.pp("norm_attn"))?,
            attn: Attention::new(dim, ctx_dim, cfg.heads, cfg.head_dim, vb.pp("attn"))?,
            norm_mlp: LayerNorm::new(dim, vb.pp("norm_mlp"))?,
            mlp: Mlp::new(
                &[dim, cfg.mlp_hidden, dim],
                Activation::Gelu,
                true,
                vb.pp("mlp"),
            )?,
        })
    }

    /// # Shapes
    /// `x: [b, n, dim]`, `ctx: [b, m, ctx_dim]` (or `None`) → `[b, n, dim]`
    pub fn forward(&self, x: &Tensor, ctx: Option<&Tensor>) -> Result<Tensor> {
        // One graph node for the whole block where the fused ops apply.
        let (a, mlp) = (&self.attn, &self.mlp);
        let params = osrt_kernels::BlockParams {
            norm_attn: (&self.norm_attn.weight, &self.norm_attn.bias),
            q: &a.q.weight,
            k: &a.k.weight,
            v: &a.v.weight,
            out: match &a.out.bias {
                Some(b) => (&a.out.weight, b),
                None => return self.forward_composed(x, ctx),
            },
            norm_mlp: (&self.norm_mlp.weight, &self.norm_mlp.bias),
            mlp: mlp
                .layers
                .iter()
                .map(|l| (&l.weight, l.bias.as_ref()))
                .collect(),
            act: mlp.act.fused(),
            heads: a.heads,
            eps: self.norm_attn.eps,
        };
        let biased = a.q.bias.is_some() || a.k.bias.is_some() || a.v.bias.is_some();
        if self.norm_attn.eps != self.norm_mlp.eps || biased {
            return self.forward_composed(x, ctx);
        }
        match osrt_kernels::block(x, ctx, &params)? {
            Some(y) => Ok(y),
            None => self.forward_composed(x, ctx),
        }
    }

    /// The same block from the separate (fused or composed) ops.
    pub fn forward_composed(&self, x: &Tensor, ctx: Option<&Tensor>) -> Result<Tensor> {
        let h = self.norm_attn.forward(x)?;
        let a = match ctx {
            Some(c) => self.attn.forward(&h, c)?,
            None => self.attn.forward(&h, &h)?,
        };
        let x = (x + a)?;
        let m = self.mlp.forward(&self.norm_mlp.forward(&x)?)?;
        x + m
    }
}

/// A stack of [`Block`]s.
#[derive(Debug, Clone)]
pub struct Transformer {
    blocks: Vec<Block>,
}

impl Transformer {
    pub fn new(
        dim: usize,
        ctx_dim: usize,
        cfg: &TransformerConfig,
        vb: VarBuilder,
    ) -> Result<Self> {
        let blocks = (0..cfg.layers)
            .map(|i| Block::new(dim, ctx_dim, cfg, vb.pp(i.to_string())))
            .collect::<Result<_>>()?;
        Ok(Self { blocks })
    }

    /// # Shapes
    /// `x: [b, n, dim]`, `ctx: [b, m, ctx_dim]` (or `None`) → `[b, n, dim]`
    pub fn forward(&self, x: &Tensor, ctx: Option<&Tensor>) -> Result<Tensor> {
        let mut h = x.clone();
        for b in &self.blocks {
            // Each block a segment whose activations a train step may make again in its
            // backward pass (`osrt_kernels::recompute`).
            let block = b.clone();
            h = match ctx {
                None => osrt_kernels::recompute(&[&h], move |t| block.forward(&t[0], None))?,
                Some(c) => {
                    osrt_kernels::recompute(&[&h, c], move |t| block.forward(&t[0], Some(&t[1])))?
                }
            };
        }
        Ok(h)
    }
}
