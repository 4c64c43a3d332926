//! A peer checkpoint as an osrt model and optimiser state ([`import`]), and osrt's
//! weights as the peer's state dict ([`export`]).

use super::{
    AdamSettings, Entry, PEER_HEADS, PEER_OCTAVES, PeerCheckpoint, PeerConfig, Shapes, Tensors,
    entries, peer_shape, ray_permutation, to_osrt, to_peer,
};
use crate::error::{InteropError, Result};
use crate::npz::NamedArray;
use candle_core::Device;
use osrt_model::decoder::Config as DecoderConfig;
use osrt_model::encoder::{Poses, RayInput};
use osrt_model::{Osrt, Params, slot_attention::SlotInit};
use std::collections::BTreeMap;

/// osrt's parameter shapes of the model `cfg`, by name.
pub fn osrt_shapes(cfg: &osrt_model::Config) -> Result<Shapes> {
    let params = Params::new(0);
    Osrt::new(cfg, params.var_builder(&Device::Cpu)).map_err(|e| InteropError::Candle {
        path: "the imported model".into(),
        source: e,
    })?;
    Ok(params
        .vars()
        .into_iter()
        .map(|(n, v)| (n, v.dims().to_vec()))
        .collect())
}

/// Every missing, unexpected and mis-shaped tensor of `have` against the peer model of
/// `entries`, one line each; `Ok` when there is none.
pub fn check_tensors(entries: &[Entry], osrt: &Shapes, have: &Shapes, path: &str) -> Result<()> {
    let mut lines = Vec::new();
    let mut expected = BTreeMap::new();
    for e in entries {
        let shape = peer_shape(e, osrt).expect("entries name osrt's parameters");
        expected.insert(e.peer.as_str(), shape);
    }
    for (name, shape) in &expected {
        match have.get(*name) {
            None => lines.push(format!("  missing `{name}` {shape:?}")),
            Some(got) if got != shape => lines.push(format!(
                "  mis-shaped `{name}`: {got:?}, expected {shape:?}"
            )),
            Some(_) => {}
        }
    }
    for (name, shape) in have {
        if !expected.contains_key(name.as_str()) {
            lines.push(format!("  unexpected `{name}` {shape:?}"));
        }
    }
    match lines.is_empty() {
        true => Ok(()),
        false => Err(InteropError::Mismatch {
            path: path.to_string(),
            report: lines.join("\n"),
        }),
    }
}

/// Adam's state in osrt's terms.
#[derive(Debug, Clone)]
pub struct ImportedAdam {
    pub settings: AdamSettings,
    /// First and second moments by osrt's parameter name; empty when the peer's
    /// optimiser never stepped.
    pub m: BTreeMap<String, Vec<f32>>,
    pub v: BTreeMap<String, Vec<f32>>,
}

/// A peer checkpoint as osrt's model.
#[derive(Debug, Clone)]
pub struct Imported {
    pub config: osrt_model::Config,
    /// Weights by osrt's parameter name.
    pub params: Tensors,
    pub adam: Option<ImportedAdam>,
    pub peer_it: Option<i64>,
}

/// Maps `ckpt` onto the osrt model its config describes, after checking every tensor's
/// name and shape (and every moment's) against that model.
pub fn import(ckpt: &PeerCheckpoint, cfg: &PeerConfig) -> Result<Imported> {
    let have = ckpt.shapes();
    let config = cfg.model_config(&have, &ckpt.path)?;
    let osrt = osrt_shapes(&config)?;
    let list = entries(&config);
    check_tensors(&list, &osrt, &have, &ckpt.path)?;
    let perm = ray_permutation(&config.ray_encoding);
    let mut params = Tensors::new();
    for e in &list {
        let (shape, values) = &ckpt.tensors[&e.peer];
        params.extend(to_osrt(e, shape, values, &perm));
    }
    debug_assert_eq!(
        params.keys().collect::<Vec<_>>(),
        osrt.keys().collect::<Vec<_>>()
    );
    let adam = match &ckpt.adam {
        None => None,
        Some(a) => {
            let mut out = ImportedAdam {
                settings: a.settings,
                m: BTreeMap::new(),
                v: BTreeMap::new(),
            };
            if !a.moments.is_empty() {
                for (i, e) in list.iter().enumerate() {
                    let bad = |reason: String| InteropError::Tensor {
                        path: ckpt.path.clone(),
                        name: format!("optimizer.state[{i}] (the moments of `{}`)", e.peer),
                        reason,
                    };
                    let mo = a.moments.get(&i).ok_or_else(|| bad("missing".into()))?;
                    let (shape, m, v) = (&mo.shape, &mo.m, &mo.v);
                    let want = &ckpt.tensors[&e.peer].0;
                    if shape != want {
                        return Err(bad(format!("shape {shape:?}, the weight's is {want:?}")));
                    }
                    for (name, (_, x)) in to_osrt(e, shape, m, &perm) {
                        out.m.insert(name, x);
                    }
                    for (name, (_, x)) in to_osrt(e, shape, v, &perm) {
                        out.v.insert(name, x);
                    }
                }
                if let Some(extra) = a.moments.keys().find(|&&i| i >= list.len()) {
                    return Err(InteropError::Tensor {
                        path: ckpt.path.clone(),
                        name: format!("optimizer.state[{extra}]"),
                        reason: format!("the model has {} parameters", list.len()),
                    });
                }
            }
            Some(out)
        }
    };
    Ok(Imported {
        config,
        params,
        adam,
        peer_it: ckpt.it,
    })
}

/// Why the peer's code cannot build a model of `cfg`, as (setting, reason); `any_widths`
/// accepts widths its classes hard-code differently (the file then loads into a model
/// built at those widths, not into `OSRT(cfg)`).
pub fn peer_cannot_build(cfg: &osrt_model::Config, any_widths: bool) -> Option<(String, String)> {
    let no = |setting: &str, reason: String| Some((setting.to_string(), reason));
    let r = &cfg.ray_encoding;
    if (
        r.origin_octaves,
        r.direction_octaves,
        r.direction_start_octave,
    ) != (PEER_OCTAVES, PEER_OCTAVES, 0)
    {
        return no(
            "model.ray_encoding",
            format!("the peer encodes rays with {PEER_OCTAVES} octaves each, directions from 2^0"),
        );
    }
    let e = &cfg.encoder;
    if e.ray_input != RayInput::Concat || e.poses != Poses::Absolute {
        return no(
            "model.encoder.ray_input / poses",
            "the peer's encoder concatenates rays to posed inputs only".into(),
        );
    }
    let sa = &cfg.slot_attention;
    if sa.init != SlotInit::Learned || sa.eps != 1e-8 {
        return no(
            "model.slot_attention.init / eps",
            "the peer learns one initial vector per slot, with ε = 1e-8".into(),
        );
    }
    let DecoderConfig::SlotMixer(d) = &cfg.decoder else {
        return no(
            "model.decoder.kind",
            format!(
                "`{}`: only the Slot Mixer decoder is exported",
                cfg.decoder.name()
            ),
        );
    };
    let heads = [&e.transformer, &d.allocation]
        .iter()
        .all(|t| t.heads == PEER_HEADS);
    if !heads {
        return no(
            "heads",
            format!("the peer's transformers have {PEER_HEADS} heads"),
        );
    }
    let paper = osrt_model::Config::paper();
    let DecoderConfig::SlotMixer(pd) = &paper.decoder else {
        unreachable!("the paper's decoder is a Slot Mixer")
    };
    let widths = e.conv_channels == paper.encoder.conv_channels
        && e.dim == paper.encoder.dim
        && e.transformer == paper.encoder.transformer
        && (sa.slot_dim, sa.mlp_hidden) == (1536, 3072)
        && (
            d.query_hidden,
            &d.allocation.heads,
            d.allocation.head_dim,
            d.allocation.mlp_hidden,
        ) == (
            pd.query_hidden,
            &pd.allocation.heads,
            pd.allocation.head_dim,
            pd.allocation.mlp_hidden,
        )
        && d.render_hidden == pd.render_hidden;
    if !widths && !any_widths {
        return no(
            "model widths",
            "the peer's classes build the paper's widths only (conv 96/192/384, tokens 768, \
             slots 1536, render MLP 4 × 1536); pass --any-widths to write its key names at \
             these widths anyway"
                .into(),
        );
    }
    None
}

/// osrt's weights as the peer's state dict of `OSRT(cfg)` (full names, `encoder.…` and
/// `decoder.…`, in its parameter order); a model without the per-patch bias gets zeros.
pub fn export(
    cfg: &osrt_model::Config,
    params: &Tensors,
    any_widths: bool,
) -> Result<Vec<NamedArray>> {
    if let Some((setting, reason)) = peer_cannot_build(cfg, any_widths) {
        return Err(InteropError::Unsupported {
            path: "the run's model".into(),
            setting,
            reason,
        });
    }
    let mut params = params.clone();
    if !cfg.encoder.project_bias {
        params.insert(
            "encoder.project.bias".into(),
            (vec![cfg.encoder.dim], vec![0.0; cfg.encoder.dim]),
        );
    }
    let perm = ray_permutation(&cfg.ray_encoding);
    entries(cfg)
        .iter()
        .map(|e| {
            let (shape, values) =
                to_peer(e, &params, &perm).ok_or_else(|| InteropError::Tensor {
                    path: "the run's checkpoint".into(),
                    name: e.osrt_names().join(", "),
                    reason: "missing".into(),
                })?;
            Ok(NamedArray::new(e.peer.clone(), shape, values))
        })
        .collect()
}

/// The `model:` section of a peer config.yaml that builds `cfg`'s model.
pub fn peer_model_yaml(cfg: &osrt_model::Config) -> String {
    let layers = match &cfg.decoder {
        DecoderConfig::SlotMixer(d) => d.allocation.layers,
        _ => 2,
    };
    format!(
        "model:\n  encoder: osrt\n  encoder_kwargs:\n    pos_start_octave: {o}\n    \
         num_slots: {k}\n    slot_iters: {it}\n  decoder: slot_mixer\n  decoder_kwargs:\n    \
         pos_start_octave: {o}\n    num_att_blocks: {layers}\n",
        o = cfg.ray_encoding.origin_start_octave,
        k = cfg.slot_attention.num_slots,
        it = cfg.slot_attention.iterations,
    )
}
