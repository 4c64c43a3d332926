//! The PyTorch OSRT of stelzner/osrt (MIT licence; github.com/stelzner/osrt, read at
//! [`PEER_COMMIT`]), "the peer" below: its checkpoints and run configs in osrt's terms.
//!
//! A peer checkpoint (`model.pt`, `osrt/checkpoint.py`) is `torch.save` of a dict: the
//! `encoder` and `decoder` state dicts, the Adam `optimizer` state dict, `it`,
//! `epoch_it`, `t`, `loss_val_best`. Its model is osrt's `paper` model layer for layer
//! but for three things, bridged here:
//! - **names and fusions**: `to_qkv` and `to_kv` hold q, k, v in one matrix (split by
//!   rows), `GRUCell`'s `weight_ih`/`weight_hh` are osrt's `gru.input`/`gru.hidden` (same
//!   gate order r, z, n), `nn.Sequential` indices become layer numbers;
//! - **the ray encoding's feature order**: the peer lays out sines and cosines per axis,
//!   then octave, origins' block before directions'; osrt octave-major, sines of both
//!   before cosines. The encoding only enters two linear maps (the first convolution,
//!   after the 3 colour channels, and the decoder's first query layer), so their input
//!   columns are permuted ([`ray_permutation`]): the same function, no option needed;
//! - **a bias on the 1×1 per-patch convolution**: `encoder.project_bias` in osrt's config.
//!
//! Adam's moments are mapped exactly as the weights they belong to; the peer's optimiser
//! indexes them by the parameter's position in `model.parameters()`, the module
//! registration order that [`entries`] reproduces.

mod run_config;
mod state_dict;

pub use run_config::{PEER_HEADS, PEER_OCTAVES, PeerConfig};
pub use state_dict::{
    Imported, ImportedAdam, check_tensors, export, import, osrt_shapes, peer_cannot_build,
    peer_model_yaml,
};

use crate::error::{InteropError, Result};
use crate::torch_file::{Key, TorchFile, Value};
use osrt_model::ray_encoding;
use std::collections::BTreeMap;
use std::path::Path;

/// The peer's commit whose code these mappings were read from.
pub const PEER_COMMIT: &str = "a4764e8";

/// Tensor shapes by name.
pub type Shapes = BTreeMap<String, Vec<usize>>;

/// Tensors by name: shape and values (C order).
pub type Tensors = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

pub(crate) fn missing(path: &str, key: &str) -> InteropError {
    InteropError::Mismatch {
        path: path.to_string(),
        report: format!("  missing `{key}`"),
    }
}

/// How one peer tensor becomes osrt's.
#[derive(Debug, Clone, PartialEq)]
pub enum Map {
    /// The same values under another name.
    Same(String),
    /// A weight whose dim 1 reads the ray encoding from `offset` on: those input
    /// channels permuted ([`ray_permutation`]).
    RayInputs { osrt: String, offset: usize },
    /// Rows split into equal parts, in order (fused q/k/v projections).
    Rows(Vec<String>),
}

/// One peer tensor (full name: `encoder.…` or `decoder.…`) and its osrt counterpart.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    pub peer: String,
    pub map: Map,
}

impl Entry {
    /// osrt's tensor names this entry fills.
    pub fn osrt_names(&self) -> Vec<&str> {
        match &self.map {
            Map::Same(n) | Map::RayInputs { osrt: n, .. } => vec![n.as_str()],
            Map::Rows(parts) => parts.iter().map(String::as_str).collect(),
        }
    }
}

/// Builds the entries in the peer's parameter order.
#[derive(Default)]
struct Order(Vec<Entry>);

impl Order {
    fn same(&mut self, peer: String, osrt: String) {
        self.0.push(Entry {
            peer,
            map: Map::Same(osrt),
        });
    }

    fn linear(&mut self, peer: &str, osrt: &str, bias: bool) {
        self.same(format!("{peer}.weight"), format!("{osrt}.weight"));
        if bias {
            self.same(format!("{peer}.bias"), format!("{osrt}.bias"));
        }
    }

    fn norm(&mut self, peer: &str, osrt: &str) {
        self.linear(peer, osrt, true);
    }

    /// A pre-norm transformer block: `{peer}0` is attention, `{peer}1` the feed-forward.
    fn block(&mut self, peer: &str, osrt: &str, self_attention: bool) {
        self.norm(&format!("{peer}0.norm"), &format!("{osrt}norm_attn"));
        let attn = |p: &str| format!("{osrt}attn.{p}.weight");
        if self_attention {
            self.0.push(Entry {
                peer: format!("{peer}0.fn.to_qkv.weight"),
                map: Map::Rows(vec![attn("q"), attn("k"), attn("v")]),
            });
        } else {
            self.same(format!("{peer}0.fn.to_q.weight"), attn("q"));
            self.0.push(Entry {
                peer: format!("{peer}0.fn.to_kv.weight"),
                map: Map::Rows(vec![attn("k"), attn("v")]),
            });
        }
        self.linear(
            &format!("{peer}0.fn.to_out.0"),
            &format!("{osrt}attn.out"),
            true,
        );
        self.norm(&format!("{peer}1.norm"), &format!("{osrt}norm_mlp"));
        self.linear(&format!("{peer}1.fn.net.0"), &format!("{osrt}mlp.0"), true);
        self.linear(&format!("{peer}1.fn.net.3"), &format!("{osrt}mlp.1"), true);
    }
}

/// Every tensor of the peer's model for osrt's `cfg` (a Slot Mixer model), in the order
/// of the peer's `model.parameters()`: the encoder's state dict, then the decoder's.
pub fn entries(cfg: &osrt_model::Config) -> Vec<Entry> {
    let mut o = Order::default();
    let enc = "encoder.srt_encoder";
    for i in 0..cfg.encoder.conv_channels.len() {
        let peer = format!("{enc}.conv_blocks.{i}.layers.0.weight");
        let osrt = format!("encoder.conv{i}.a.weight");
        match i {
            // The first convolution reads RGB (3 channels), then the ray encoding.
            0 => o.0.push(Entry {
                peer,
                map: Map::RayInputs { osrt, offset: 3 },
            }),
            _ => o.same(peer, osrt),
        }
        o.same(
            format!("{enc}.conv_blocks.{i}.layers.2.weight"),
            format!("encoder.conv{i}.b.weight"),
        );
    }
    o.linear(&format!("{enc}.per_patch_linear"), "encoder.project", true);
    for l in 0..cfg.encoder.transformer.layers {
        o.block(
            &format!("{enc}.transformer.layers.{l}."),
            &format!("encoder.transformer.{l}."),
            true,
        );
    }
    let (p, s) = ("encoder.slot_attention", "slot_attention");
    o.same(format!("{p}.initial_slots"), format!("{s}.init_slots"));
    for w in ["to_q", "to_k", "to_v"] {
        o.linear(&format!("{p}.{w}"), &format!("{s}.{w}"), false);
    }
    o.same(
        format!("{p}.gru.weight_ih"),
        format!("{s}.gru.input.weight"),
    );
    o.same(
        format!("{p}.gru.weight_hh"),
        format!("{s}.gru.hidden.weight"),
    );
    o.same(format!("{p}.gru.bias_ih"), format!("{s}.gru.input.bias"));
    o.same(format!("{p}.gru.bias_hh"), format!("{s}.gru.hidden.bias"));
    o.linear(&format!("{p}.mlp.0"), &format!("{s}.mlp.0"), true);
    o.linear(&format!("{p}.mlp.2"), &format!("{s}.mlp.1"), true);
    o.norm(&format!("{p}.norm_input"), &format!("{s}.norm_inputs"));
    o.norm(&format!("{p}.norm_slots"), &format!("{s}.norm_slots"));
    o.norm(&format!("{p}.norm_pre_mlp"), &format!("{s}.norm_mlp"));
    let osrt_model::decoder::Config::SlotMixer(d) = &cfg.decoder else {
        unreachable!("entries are asked for Slot Mixer models only (check_peer_model)");
    };
    let a = "decoder.allocation_transformer";
    o.0.push(Entry {
        peer: format!("{a}.input_mlp.0.weight"),
        map: Map::RayInputs {
            osrt: "decoder.query_mlp.0.weight".into(),
            offset: 0,
        },
    });
    o.same(
        format!("{a}.input_mlp.0.bias"),
        "decoder.query_mlp.0.bias".into(),
    );
    o.linear(&format!("{a}.input_mlp.2"), "decoder.query_mlp.1", true);
    for l in 0..d.allocation.layers {
        o.block(
            &format!("{a}.transformer.layers.{l}."),
            &format!("decoder.allocation.{l}."),
            false,
        );
    }
    o.linear("decoder.mixing_block.to_q", "decoder.mix_q", false);
    o.linear("decoder.mixing_block.to_k", "decoder.mix_k", false);
    for j in 0..=d.render_hidden.len() {
        o.linear(
            &format!("decoder.render_mlp.net.{}", 2 * j),
            &format!("decoder.render.{j}"),
            true,
        );
    }
    o.0
}

/// `perm[j]`: the peer's index of osrt's ray-encoding feature `j`. osrt: `[sin | cos]`,
/// each `[origin | direction]`, each octave-major (`3·octave + axis`); the peer:
/// `[origin: sin | cos][direction: sin | cos]`, each axis-major (`octaves·axis + octave`).
pub fn ray_permutation(r: &ray_encoding::Config) -> Vec<usize> {
    let (no, nd) = (r.origin_octaves, r.direction_octaves);
    let half = 3 * (no + nd);
    (0..2 * half)
        .map(|j| {
            let (cos, j) = (j >= half, j % half);
            match (j < 3 * no, cos) {
                (true, false) => (j % 3) * no + j / 3,
                (true, true) => 3 * no + (j % 3) * no + j / 3,
                (false, cos) => {
                    let j = j - 3 * no;
                    6 * no + usize::from(cos) * 3 * nd + (j % 3) * nd + j / 3
                }
            }
        })
        .collect()
}

/// Permutes the channels `offset..offset + perm.len()` of dim 1 of `values` (shape
/// `shape`): forward, channel `offset + j` takes the input's `offset + perm[j]` (peer →
/// osrt); inverse, the input's `offset + j` goes to `offset + perm[j]` (osrt → peer).
fn permute_inputs(
    shape: &[usize],
    values: &[f32],
    offset: usize,
    perm: &[usize],
    inverse: bool,
) -> Vec<f32> {
    let (rows, cols) = (shape[0], shape[1]);
    let inner: usize = shape[2..].iter().product();
    let mut out = values.to_vec();
    for r in 0..rows {
        let row = r * cols * inner;
        for (j, &p) in perm.iter().enumerate() {
            let (dst, src) = match inverse {
                false => (offset + j, offset + p),
                true => (offset + p, offset + j),
            };
            out[row + dst * inner..row + (dst + 1) * inner]
                .copy_from_slice(&values[row + src * inner..row + (src + 1) * inner]);
        }
    }
    out
}

/// The peer's shape of `entry` given osrt's shapes.
pub fn peer_shape(entry: &Entry, osrt: &Shapes) -> Option<Vec<usize>> {
    match &entry.map {
        Map::Same(n) | Map::RayInputs { osrt: n, .. } => osrt.get(n).cloned(),
        Map::Rows(parts) => {
            let mut shape = osrt.get(&parts[0])?.clone();
            shape[0] *= parts.len();
            Some(shape)
        }
    }
}

/// One peer tensor (a weight or one of its moments) as osrt's tensors.
pub fn to_osrt(entry: &Entry, shape: &[usize], values: &[f32], perm: &[usize]) -> Tensors {
    match &entry.map {
        Map::Same(n) => BTreeMap::from([(n.clone(), (shape.to_vec(), values.to_vec()))]),
        Map::RayInputs { osrt, offset } => BTreeMap::from([(
            osrt.clone(),
            (
                shape.to_vec(),
                permute_inputs(shape, values, *offset, perm, false),
            ),
        )]),
        Map::Rows(parts) => {
            let mut part_shape = shape.to_vec();
            part_shape[0] /= parts.len();
            let len = values.len() / parts.len();
            parts
                .iter()
                .enumerate()
                .map(|(k, n)| {
                    let v = values[k * len..(k + 1) * len].to_vec();
                    (n.clone(), (part_shape.clone(), v))
                })
                .collect()
        }
    }
}

/// osrt's tensors of `entry` as the peer's one tensor; `None` if one is not in `osrt`.
pub fn to_peer(entry: &Entry, osrt: &Tensors, perm: &[usize]) -> Option<(Vec<usize>, Vec<f32>)> {
    match &entry.map {
        Map::Same(n) => osrt.get(n).cloned(),
        Map::RayInputs { osrt: n, offset } => {
            let (shape, values) = osrt.get(n)?;
            Some((
                shape.clone(),
                permute_inputs(shape, values, *offset, perm, true),
            ))
        }
        Map::Rows(parts) => {
            let mut shape = osrt.get(&parts[0])?.0.clone();
            shape[0] *= parts.len();
            let mut values = Vec::new();
            for n in parts {
                values.extend_from_slice(&osrt.get(n)?.1);
            }
            Some((shape, values))
        }
    }
}

/// Adam's update count and hyperparameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamSettings {
    /// Updates taken (the bias corrections' `t`).
    pub step: u64,
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
}

/// Adam's state in a peer checkpoint.
#[derive(Debug, Clone)]
pub struct PeerAdam {
    pub settings: AdamSettings,
    /// `exp_avg` and `exp_avg_sq` by the parameter's index in the peer's order; empty
    /// when the optimiser never stepped.
    pub moments: BTreeMap<usize, Moments>,
}

/// One parameter's Adam moments (`exp_avg`, `exp_avg_sq`) and their shape.
#[derive(Debug, Clone)]
pub struct Moments {
    pub shape: Vec<usize>,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
}

/// A peer checkpoint read into memory.
#[derive(Debug, Clone)]
pub struct PeerCheckpoint {
    pub path: String,
    /// The `encoder` and `decoder` state dicts' tensors by full name (`encoder.…`).
    pub tensors: Tensors,
    pub adam: Option<PeerAdam>,
    /// The peer's iteration counter `it`, when present.
    pub it: Option<i64>,
}

impl PeerCheckpoint {
    /// Reads a peer `model.pt` (`torch.save`), or weights alone as a safetensors file
    /// with the peer's full names (what `osrt export-checkpoint` writes).
    pub fn read(path: &Path) -> Result<Self> {
        let shown = path.display().to_string();
        let mut head = [0u8; 2];
        let is_zip = std::fs::File::open(path)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
            .map(|_| &head == b"PK")
            .unwrap_or(true);
        if !is_zip {
            return read_safetensors(path);
        }
        let mut file = TorchFile::open(path)?;
        let root = file.root().clone();
        let not_peer = |what: String| InteropError::File {
            path: shown.clone(),
            reason: format!(
                "not a stelzner/osrt checkpoint: {what}; expected the dict its \
                 Checkpoint.save writes, with `encoder` and `decoder` state dicts"
            ),
        };
        let Value::Dict(_) = &root else {
            return Err(not_peer(format!("the pickled object is {}", root.kind())));
        };
        let mut tensors = Tensors::new();
        for part in ["encoder", "decoder"] {
            let Some(Value::Dict(sd)) = root.get(part) else {
                return Err(not_peer(format!(
                    "`{part}` is {}",
                    root.get(part).map_or("absent".into(), Value::kind)
                )));
            };
            for (k, v) in sd {
                let name = match k {
                    Key::Str(s) => format!("{part}.{s}"),
                    Key::Int(i) => format!("{part}.{i}"),
                };
                match v {
                    Value::Tensor(t) => {
                        let values = file.tensor(t, &name)?;
                        tensors.insert(name, (t.shape.clone(), values));
                    }
                    // PyTorch stores module versions beside the tensors.
                    _ if matches!(k, Key::Str(s) if s == "_metadata") => {}
                    other => {
                        return Err(InteropError::Tensor {
                            path: shown.clone(),
                            name,
                            reason: format!("{} where a tensor belongs", other.kind()),
                        });
                    }
                }
            }
        }
        let adam = match root.get("optimizer") {
            None | Some(Value::None) => None,
            Some(opt) => Some(read_adam(&mut file, opt)?),
        };
        let it = root.get("it").and_then(|v| match v {
            Value::Int(i) => Some(*i),
            _ => None,
        });
        Ok(Self {
            path: shown,
            tensors,
            adam,
            it,
        })
    }

    pub fn shapes(&self) -> Shapes {
        self.tensors
            .iter()
            .map(|(k, (s, _))| (k.clone(), s.clone()))
            .collect()
    }
}

fn read_safetensors(path: &Path) -> Result<PeerCheckpoint> {
    let shown = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| InteropError::Io {
        path: shown.clone(),
        source: e,
    })?;
    let loaded =
        candle_core::safetensors::load_buffer(&bytes, &candle_core::Device::Cpu).map_err(|e| {
            InteropError::File {
                path: shown.clone(),
                reason: format!("neither a PyTorch checkpoint (zip) nor safetensors: {e}"),
            }
        })?;
    let mut tensors = Tensors::new();
    for (name, t) in loaded {
        let values = t
            .to_dtype(candle_core::DType::F32)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| InteropError::Tensor {
                path: shown.clone(),
                name: name.clone(),
                reason: e.to_string(),
            })?;
        tensors.insert(name, (t.dims().to_vec(), values));
    }
    Ok(PeerCheckpoint {
        path: shown,
        tensors,
        adam: None,
        it: None,
    })
}

/// A parameter's Adam step count: a 0-d tensor since PyTorch 1.12, a number before.
fn adam_step(file: &mut TorchFile, state: &Value, i: i64) -> Result<Option<f64>> {
    Ok(match state.get("step") {
        Some(Value::Tensor(t)) => file
            .tensor(t, &format!("optimizer.state[{i}].step"))?
            .first()
            .map(|&x| x as f64),
        Some(v) => v.as_f64(),
        None => None,
    })
}

/// `torch.optim.Adam`'s state dict: one parameter group, moments per parameter index.
fn read_adam(file: &mut TorchFile, opt: &Value) -> Result<PeerAdam> {
    let shown = file.path().display().to_string();
    let bad = |what: &str, reason: String| InteropError::Unsupported {
        path: shown.clone(),
        setting: format!("optimizer{what}"),
        reason,
    };
    let Some(Value::List(groups)) = opt.get("param_groups") else {
        return Err(bad(
            "",
            format!("{}: not an optimiser state dict", opt.kind()),
        ));
    };
    let [group] = groups.as_slice() else {
        return Err(bad(
            ".param_groups",
            format!("{} groups; the peer's Adam has one", groups.len()),
        ));
    };
    let num = |k: &str| -> Result<f64> {
        group.get(k).and_then(Value::as_f64).ok_or_else(|| {
            bad(
                &format!(".param_groups[0].{k}"),
                "missing or not a number".into(),
            )
        })
    };
    let betas = match group.get("betas") {
        Some(Value::List(b)) if b.len() == 2 => (b[0].as_f64(), b[1].as_f64()),
        _ => (None, None),
    };
    let (Some(beta1), Some(beta2)) = betas else {
        return Err(bad(
            ".param_groups[0].betas",
            "missing or not two numbers".into(),
        ));
    };
    for flag in ["amsgrad", "maximize"] {
        if group.get(flag) == Some(&Value::Bool(true)) {
            return Err(bad(
                &format!(".param_groups[0].{flag}"),
                "osrt's Adam has no such variant".into(),
            ));
        }
    }
    let mut adam = PeerAdam {
        settings: AdamSettings {
            step: 0,
            lr: num("lr")?,
            beta1,
            beta2,
            eps: num("eps")?,
            weight_decay: num("weight_decay")?,
        },
        moments: BTreeMap::new(),
    };
    let Some(Value::Dict(state)) = opt.get("state") else {
        return Err(bad(".state", "missing".into()));
    };
    let mut steps = std::collections::BTreeSet::new();
    for (k, s) in state {
        let Key::Int(i) = k else {
            return Err(bad(".state", format!("key {k} is not a parameter index")));
        };
        let tensor = |name: &str, file: &mut TorchFile| -> Result<(Vec<usize>, Vec<f32>)> {
            match s.get(name) {
                Some(Value::Tensor(t)) => Ok((
                    t.shape.clone(),
                    file.tensor(t, &format!("optimizer.state[{i}].{name}"))?,
                )),
                other => Err(bad(
                    &format!(".state[{i}].{name}"),
                    other.map_or("missing".into(), Value::kind),
                )),
            }
        };
        let step = adam_step(file, s, *i)?
            .ok_or_else(|| bad(&format!(".state[{i}].step"), "missing".into()))?;
        steps.insert(step as u64);
        let (shape, m) = tensor("exp_avg", file)?;
        let (_, v) = tensor("exp_avg_sq", file)?;
        adam.moments.insert(*i as usize, Moments { shape, m, v });
    }
    match steps.len() {
        0 => {}
        1 => adam.settings.step = *steps.first().expect("one"),
        _ => {
            return Err(bad(
                ".state",
                format!("parameters at different step counts {steps:?}; osrt's Adam has one"),
            ));
        }
    }
    Ok(adam)
}

#[cfg(test)]
mod tests;
