//! The SRT encoder (paper eq. 1): a CNN over each input view's RGB ⊕ per-pixel ray
//! encoding, the feature maps of all views flattened into one token set, then a pre-norm
//! self-attention transformer. Its output is the Set-Latent Scene Representation (SLSR).
//!
//! Paper sizes: 3 blocks of [conv3×3 s1 → ReLU → conv3×3 s2 → ReLU] without biases,
//! 183 → 96 → 192 → 384 → 768 channels, total stride 8, a 1×1 conv to the token width,
//! and 5 transformer layers of width 768 (12 heads × 64, MLP 1536).

use crate::fused::conv2d_nhwc;
use crate::nn::{Transformer, TransformerConfig};
use crate::ray_encoding::RayEncoding;
use candle_core::{D, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Width of the first conv of each block; the block's stride-2 conv doubles it.
    pub conv_channels: Vec<usize>,
    /// Token width (the 1×1 conv's output and the transformer's width).
    pub dim: usize,
    pub transformer: TransformerConfig,
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
        let mut c_in = 3 + ray_dim;
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
        let transformer =
            Transformer::new(cfg.dim, cfg.dim, &cfg.transformer, vb.pp("transformer"))?;
        Ok(Self {
            convs,
            project,
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
        // Channels-last throughout: the convolutions are im2col + matmul on NHWC
        // (`fused::conv2d_nhwc`), and the tokens come out in (view, row, column) order.
        let mut x = Tensor::cat(&[images, &enc], D::Minus1)? // [b, v, h, w, 3 + r]
            .reshape((b * v, h, w, 3 + rays.dim()))?; // [b·v, h, w, c]
        for (a, s2) in &self.convs {
            x = conv2d_nhwc(&x, a.weight(), 1, 1)?.relu()?;
            x = conv2d_nhwc(&x, s2.weight(), 2, 1)?.relu()?;
        }
        let x = conv2d_nhwc(&x, self.project.weight(), 1, 0)?; // [b·v, h', w', d]
        let (_, h2, w2, d) = x.dims4()?;
        let tokens = x.reshape((b, v * h2 * w2, d))?;
        self.transformer.forward(&tokens, None)
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }
}
