//! The SRT encoder (paper eq. 1): a CNN over each input view's RGB ⊕ per-pixel ray
//! encoding, the feature maps of all views flattened into one token set, then a pre-norm
//! self-attention transformer. Its output is the Set-Latent Scene Representation (SLSR).
//!
//! Paper sizes: 3 blocks of [conv3×3 s1 → ReLU → conv3×3 s2 → ReLU] without biases,
//! 183 → 96 → 192 → 384 → 768 channels, total stride 8, a 1×1 conv to the token width,
//! and 5 transformer layers of width 768 (12 heads × 64, MLP 1536).

use crate::nn::{Transformer, TransformerConfig};
use crate::ray_encoding::RayEncoding;
use candle_core::{D, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use osrt_kernels::{conv2d_nhwc, relu};
use serde::{Deserialize, Serialize};

/// How the ray encoding enters the encoder.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RayInput {
    /// Paper: the CNN reads RGB ⊕ ray encoding per pixel.
    #[default]
    Concat,
    /// Not in the paper (an explicit option, reported as an ablation): the CNN reads RGB
    /// only, and a linear embedding of each token's patch of ray encodings (a conv with
    /// kernel = stride = the CNN's stride) is added to its tokens, as Slot Attention adds
    /// its position embedding. Why: concatenated, the 3 colour channels are ~2 % of the
    /// first conv's input energy beside the ray encoding, so at initialisation the
    /// tokens of two scenes seen from one camera differ by ~2.5 % (docs/time-to-quality.md).
    Add,
}

impl std::str::FromStr for RayInput {
    type Err = String;

    /// The names the configs use: `concat`, `add`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "concat" => Ok(Self::Concat),
            "add" => Ok(Self::Add),
            other => Err(format!(
                "unknown ray input `{other}`: expected concat or add"
            )),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Width of the first conv of each block; the block's stride-2 conv doubles it.
    pub conv_channels: Vec<usize>,
    /// Token width (the 1×1 conv's output and the transformer's width).
    pub dim: usize,
    pub transformer: TransformerConfig,
    /// How the ray encoding enters (absent in older configs: the paper's `concat`).
    #[serde(default)]
    pub ray_input: RayInput,
}

impl Config {
    pub fn paper() -> Self {
        Self {
            conv_channels: vec![96, 192, 384],
            dim: 768,
            transformer: TransformerConfig {
                layers: 5,
                heads: 12,
                head_dim: 64,
                mlp_hidden: 1536,
            },
            ray_input: RayInput::Concat,
        }
    }

    /// Total downsampling of the CNN.
    pub fn stride(&self) -> usize {
        1 << self.conv_channels.len()
    }
}

#[derive(Debug, Clone)]
pub struct Encoder {
    convs: Vec<(Conv2d, Conv2d)>,
    project: Conv2d,
    /// `RayInput::Add` only: ray-encoding patch embedding, kernel = stride = CNN stride.
    ray_embed: Option<Conv2d>,
    transformer: Transformer,
    cfg: Config,
}

impl Encoder {
    pub fn new(cfg: &Config, ray_dim: usize, vb: VarBuilder) -> Result<Self> {
        let s1 = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        let s2 = Conv2dConfig {
            padding: 1,
            stride: 2,
            ..Default::default()
        };
        let mut c_in = match cfg.ray_input {
            RayInput::Concat => 3 + ray_dim,
            RayInput::Add => 3,
        };
        let mut convs = Vec::new();
        for (i, &c) in cfg.conv_channels.iter().enumerate() {
            let vbi = vb.pp(format!("conv{i}"));
            let a = candle_nn::conv2d_no_bias(c_in, c, 3, s1, vbi.pp("a"))?;
            let b = candle_nn::conv2d_no_bias(c, 2 * c, 3, s2, vbi.pp("b"))?;
            convs.push((a, b));
            c_in = 2 * c;
        }
        let project =
            candle_nn::conv2d_no_bias(c_in, cfg.dim, 1, Default::default(), vb.pp("project"))?;
        let ray_embed = match cfg.ray_input {
            RayInput::Concat => None,
            RayInput::Add => Some(candle_nn::conv2d_no_bias(
                ray_dim,
                cfg.dim,
                cfg.stride(),
                Default::default(),
                vb.pp("ray_embed"),
            )?),
        };
        let transformer =
            Transformer::new(cfg.dim, cfg.dim, &cfg.transformer, vb.pp("transformer"))?;
        Ok(Self {
            convs,
            project,
            ray_embed,
            transformer,
            cfg: cfg.clone(),
        })
    }

    /// # Shapes
    /// `images: [b, v, h, w, 3]` in `[0, 1]`, `origins`/`directions: [b, v, h, w, 3]`
    /// → SLSR `[b, v·(h/s)·(w/s), dim]` with `s` = [`Config::stride`].
    pub fn forward(
        &self,
        rays: &RayEncoding,
        images: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
    ) -> Result<Tensor> {
        let (b, v, h, w, _) = images.dims5()?;
        let enc = rays.forward(origins, directions)?; // [b, v, h, w, r]
        let r = rays.dim();
        let s = self.cfg.stride();
        if self.ray_embed.is_some() && (h % s != 0 || w % s != 0) {
            // Checked before the CNN runs: the patch embedding's grid must match the CNN's.
            candle_core::bail!(
                "encoder: ray_input = \"add\" needs image sides divisible by the CNN stride {s}, got {h}×{w}"
            );
        }
        // Channels-last throughout: the convolutions are im2col + matmul on NHWC
        // (`osrt_kernels::conv2d_nhwc`), and the tokens come out in (view, row, column) order.
        let mut x = match &self.ray_embed {
            None => Tensor::cat(&[images, &enc], D::Minus1)? // [b, v, h, w, 3 + r]
                .reshape((b * v, h, w, 3 + r))?, // [b·v, h, w, c]
            Some(_) => images.reshape((b * v, h, w, 3))?,
        };
        for (a, s2) in &self.convs {
            x = relu(&conv2d_nhwc(&x, a.weight(), 1, 1)?)?;
            x = relu(&conv2d_nhwc(&x, s2.weight(), 2, 1)?)?;
        }
        let mut x = conv2d_nhwc(&x, self.project.weight(), 1, 0)?; // [b·v, h', w', d]
        if let Some(embed) = &self.ray_embed {
            let enc = enc.reshape((b * v, h, w, r))?;
            x = (x + conv2d_nhwc(&enc, embed.weight(), s, 0)?)?; // [b·v, h/s, w/s, d]
        }
        let (_, h2, w2, d) = x.dims4()?;
        let tokens = x.reshape((b, v * h2 * w2, d))?;
        self.transformer.forward(&tokens, None)
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }
}
