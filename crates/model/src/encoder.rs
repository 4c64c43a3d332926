//! The SRT encoder (paper eq. 1): a CNN over each input view's RGB ⊕ per-pixel ray
//! encoding, the feature maps of all views flattened into one token set, then a pre-norm
//! self-attention transformer. Its output is the Set-Latent Scene Representation (SLSR).
//!
//! Up-OSRT (paper §4.3, appendix "Poses"): with `poses = "unposed"` the CNN reads RGB
//! only, and each token gets a learned camera-ID embedding (the reference camera — the
//! first input view, whose frame the target rays are expressed in — or any other) and
//! learned row and column embeddings of its place in the feature grid, as in UpSRT.
//!
//! Paper sizes: 3 blocks of [conv3×3 s1 → ReLU → conv3×3 s2 → ReLU] without biases,
//! 183 → 96 → 192 → 384 → 768 channels, total stride 8, a 1×1 conv to the token width,
//! and 5 transformer layers of width 768 (12 heads × 64, MLP 1536).

use crate::nn::{Transformer, TransformerConfig};
use crate::ray_encoding::RayEncoding;
use candle_core::{D, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use osrt_kernels::{conv2d_nhwc, conv2d_relu_nhwc};
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

/// Whether the encoder sees the input views' poses.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Poses {
    /// OSRT: every input pixel's ray, in the world frame, enters the CNN (`ray_input`).
    #[default]
    Absolute,
    /// Up-OSRT: no input rays (`ray_input` is unused); camera-ID and 2D position
    /// embeddings instead, and target rays relative to the first input camera (the batch
    /// builder's `RayFrame::FirstInput`).
    Unposed,
}

impl std::str::FromStr for Poses {
    type Err = String;

    /// The names the configs use: `absolute`, `unposed`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "absolute" => Ok(Self::Absolute),
            "unposed" => Ok(Self::Unposed),
            other => Err(format!(
                "unknown poses `{other}`: expected absolute or unposed"
            )),
        }
    }
}

/// Rows and columns of the largest token grid the unposed position embeddings cover.
fn default_max_grid() -> usize {
    128
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
    /// Posed (OSRT) or unposed (Up-OSRT) inputs (absent in older configs: posed).
    #[serde(default)]
    pub poses: Poses,
    /// Unposed only: the position embeddings' rows and columns (feature-grid sides up to
    /// this; 128 covers 512 × 512 inputs at stride 4).
    #[serde(default = "default_max_grid")]
    pub max_grid: usize,
    /// A bias on the 1×1 projection to the token width. Not in the paper's model (its
    /// CNN has no biases); the PyTorch implementation stelzner/osrt has one, so a model
    /// imported from it (`osrt_interop`) turns this on. Off in every preset.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub project_bias: bool,
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
            poses: Poses::Absolute,
            max_grid: default_max_grid(),
            project_bias: false,
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
    /// `project_bias` only: `[dim]`, added to every token.
    project_bias: Option<Tensor>,
    /// `RayInput::Add` only: ray-encoding patch embedding, kernel = stride = CNN stride.
    ray_embed: Option<Conv2d>,
    /// `Poses::Unposed` only: camera-ID `[2, dim]` (reference, other), row and column
    /// position embeddings `[max_grid, dim]`.
    unposed: Option<UnposedEmbeddings>,
    transformer: Transformer,
    cfg: Config,
}

#[derive(Debug, Clone)]
struct UnposedEmbeddings {
    camera: Tensor,
    row: Tensor,
    col: Tensor,
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
        let mut c_in = match (cfg.poses, cfg.ray_input) {
            (Poses::Unposed, _) | (Poses::Absolute, RayInput::Add) => 3,
            (Poses::Absolute, RayInput::Concat) => 3 + ray_dim,
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
        let project_bias = cfg
            .project_bias
            .then(|| {
                vb.pp("project")
                    .get_with_hints(cfg.dim, "bias", candle_nn::Init::Const(0.0))
            })
            .transpose()?;
        let ray_embed = match (cfg.poses, cfg.ray_input) {
            (Poses::Unposed, _) | (Poses::Absolute, RayInput::Concat) => None,
            (Poses::Absolute, RayInput::Add) => Some(candle_nn::conv2d_no_bias(
                ray_dim,
                cfg.dim,
                cfg.stride(),
                Default::default(),
                vb.pp("ray_embed"),
            )?),
        };
        let unposed = match cfg.poses {
            Poses::Absolute => None,
            Poses::Unposed => {
                // Small random values, as a ViT's learned position embedding starts.
                let init = candle_nn::Init::Randn {
                    mean: 0.0,
                    stdev: 0.02,
                };
                let vb = vb.pp("unposed");
                Some(UnposedEmbeddings {
                    camera: vb.get_with_hints((2, cfg.dim), "camera", init)?,
                    row: vb.get_with_hints((cfg.max_grid, cfg.dim), "row", init)?,
                    col: vb.get_with_hints((cfg.max_grid, cfg.dim), "col", init)?,
                })
            }
        };
        let transformer =
            Transformer::new(cfg.dim, cfg.dim, &cfg.transformer, vb.pp("transformer"))?;
        Ok(Self {
            convs,
            project,
            project_bias,
            ray_embed,
            unposed,
            transformer,
            cfg: cfg.clone(),
        })
    }

    /// # Shapes
    /// `images: [b, v, h, w, 3]` in `[0, 1]`, `origins`/`directions: [b, v, h, w, 3]`
    /// (unused when unposed) → SLSR `[b, v·(h/s)·(w/s), dim]` with `s` =
    /// [`Config::stride`].
    pub fn forward(
        &self,
        rays: &RayEncoding,
        images: &Tensor,
        origins: &Tensor,
        directions: &Tensor,
    ) -> Result<Tensor> {
        // The CNN and the transformer are segments of the backward pass
        // (`osrt_kernels::cut`): the transformer's activations are freed before the CNN's
        // backward pass, which ends the step's and so meets all its gradients.
        if let Some(e) = &self.unposed {
            let tokens = self.unposed_tokens(e, images)?;
            return self.transformer.forward(&osrt_kernels::cut(&tokens)?, None);
        }
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
        let x = match &self.ray_embed {
            None => Tensor::cat(&[images, &enc], D::Minus1)? // [b, v, h, w, 3 + r]
                .reshape((b * v, h, w, 3 + r))?, // [b·v, h, w, c]
            Some(_) => images.reshape((b * v, h, w, 3))?,
        };
        let mut x = self.cnn(x)?; // [b·v, h', w', d]
        if let Some(embed) = &self.ray_embed {
            let enc = enc.reshape((b * v, h, w, r))?;
            x = (x + conv2d_nhwc(&enc, embed.weight(), s, 0)?)?; // [b·v, h/s, w/s, d]
        }
        let (_, h2, w2, d) = x.dims4()?;
        let tokens = x.reshape((b, v * h2 * w2, d))?;
        self.transformer.forward(&osrt_kernels::cut(&tokens)?, None)
    }

    /// The CNN: each pair of 3×3 convolutions (stride 1, then 2, ReLU after each), then
    /// the 1×1 projection. Each pair is a segment whose activations a train step may make
    /// again in its backward pass (`osrt_kernels::recompute`).
    ///
    /// # Shapes
    /// `x: [n, h, w, c]` → `[n, h/s, w/s, dim]` with `s` = [`Config::stride`]
    fn cnn(&self, mut x: Tensor) -> Result<Tensor> {
        for (a, s2) in &self.convs {
            let (a, s2) = (a.weight().clone(), s2.weight().clone());
            x = osrt_kernels::recompute(&[&x], move |t| {
                conv2d_relu_nhwc(&conv2d_relu_nhwc(&t[0], &a, 1, 1)?, &s2, 2, 1)
            })?;
        }
        let x = conv2d_nhwc(&x, self.project.weight(), 1, 0)?;
        match &self.project_bias {
            None => Ok(x),
            Some(b) => x.broadcast_add(b), // channels last: `[dim]` broadcasts
        }
    }

    /// Up-OSRT's tokens: the CNN over RGB, plus camera-ID and row/column embeddings.
    ///
    /// # Shapes
    /// `images: [b, v, h, w, 3]` → `[b, v·h'·w', dim]`
    fn unposed_tokens(&self, e: &UnposedEmbeddings, images: &Tensor) -> Result<Tensor> {
        let (b, v, h, w, _) = images.dims5()?;
        let x = self.cnn(images.reshape((b * v, h, w, 3))?)?; // [b·v, h', w', d]
        let (_, h2, w2, d) = x.dims4()?;
        let g = self.cfg.max_grid;
        if h2 > g || w2 > g {
            candle_core::bail!(
                "encoder: the unposed position embeddings cover {g}×{g} tokens, the \
                 feature grid of {h}×{w} inputs is {h2}×{w2} (raise model.encoder.max_grid)"
            );
        }
        let pos = e
            .row
            .narrow(0, 0, h2)?
            .unsqueeze(1)?
            .broadcast_add(&e.col.narrow(0, 0, w2)?.unsqueeze(0)?)?; // [h', w', d]
        // View 0 is the reference camera; the other views are an unordered set and share
        // one embedding, so permuting them permutes the tokens and nothing else.
        let ids: Vec<u32> = (0..v).map(|i| u32::from(i > 0)).collect();
        let ids = Tensor::from_vec(ids, v, images.device())?;
        let cam = e.camera.index_select(&ids, 0)?.reshape((1, v, 1, d))?; // [1, v, 1, d]
        let x = x
            .reshape((b, v, h2 * w2, d))?
            .broadcast_add(&pos.reshape((1, 1, h2 * w2, d))?)?
            .broadcast_add(&cam)?;
        x.reshape((b, v * h2 * w2, d))
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }
}
