use super::*;
use candle_core::{Device, Tensor};
use osrt_model::ray_encoding::RayEncoding;

fn paper_with_bias() -> osrt_model::Config {
    let mut cfg = osrt_model::Config::paper();
    cfg.encoder.project_bias = true;
    cfg
}

#[test]
fn the_paper_model_maps_onto_every_peer_tensor_once() {
    let cfg = paper_with_bias();
    let osrt = osrt_shapes(&cfg).unwrap();
    let list = entries(&cfg);
    let mut filled: Vec<&str> = list.iter().flat_map(Entry::osrt_names).collect();
    filled.sort();
    let before = filled.len();
    filled.dedup();
    assert_eq!(before, filled.len(), "an osrt tensor is filled twice");
    assert_eq!(filled, osrt.keys().map(String::as_str).collect::<Vec<_>>());
    // The peer's CLEVR-3D model has 83,110,767 parameters (`train.py --print-model`
    // counts of its classes): osrt's paper model (83,109,999) and the per-patch bias.
    let peer: usize = list
        .iter()
        .map(|e| peer_shape(e, &osrt).unwrap().iter().product::<usize>())
        .sum();
    assert_eq!(peer, 83_110_767);
    let mut names: Vec<&str> = list.iter().map(|e| e.peer.as_str()).collect();
    names.dedup();
    assert_eq!(names.len(), list.len());
}

/// The peer's encoding of one ray, computed from its definition: per half (origin,
/// direction) the sines then the cosines of `x_axis · 2^o · π`, axis-major.
fn peer_encoding(r: &ray_encoding::Config, origin: [f32; 3], dir: [f32; 3]) -> Vec<f32> {
    let mut out = Vec::new();
    for (x, octaves, start) in [
        (origin, r.origin_octaves, r.origin_start_octave),
        (dir, r.direction_octaves, r.direction_start_octave),
    ] {
        let angles: Vec<f32> = (0..3)
            .flat_map(|d| {
                (0..octaves).map(move |o| {
                    x[d] * (2f64.powi(start + o as i32) * std::f64::consts::PI) as f32
                })
            })
            .collect();
        out.extend(angles.iter().map(|a| a.sin()));
        out.extend(angles.iter().map(|a| a.cos()));
    }
    out
}

#[test]
fn the_ray_permutation_matches_the_two_encodings() {
    for cfg in [
        ray_encoding::Config::paper(),
        osrt_model::Config::cpu().ray_encoding,
    ] {
        let perm = ray_permutation(&cfg);
        let mut sorted = perm.clone();
        sorted.sort();
        assert_eq!(sorted, (0..cfg.dim()).collect::<Vec<_>>());
        let (o, d) = ([0.3f32, -1.7, 2.2], [0.6f32, -0.48, 0.64]);
        let enc = RayEncoding::new(cfg.clone(), candle_core::DType::F32, &Device::Cpu).unwrap();
        let ours = enc
            .forward_composed(
                &Tensor::new(&[o], &Device::Cpu).unwrap(),
                &Tensor::new(&[d], &Device::Cpu).unwrap(),
            )
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let peer = peer_encoding(&cfg, o, d);
        for (j, &p) in perm.iter().enumerate() {
            assert!(
                (ours[j] - peer[p]).abs() < 1e-5,
                "feature {j}: osrt {} against the peer's {p}: {}",
                ours[j],
                peer[p]
            );
        }
    }
}

#[test]
fn permuted_and_split_tensors_go_back_to_the_same_bits() {
    let cfg = osrt_model::Config::paper();
    let perm = ray_permutation(&cfg.ray_encoding);
    let conv = Entry {
        peer: "c".into(),
        map: Map::RayInputs {
            osrt: "a".into(),
            offset: 3,
        },
    };
    let shape = vec![2, 183, 3, 3];
    let values: Vec<f32> = (0..2 * 183 * 9).map(|i| i as f32 * 0.5 - 7.0).collect();
    let osrt = to_osrt(&conv, &shape, &values, &perm);
    let (_, moved) = &osrt["a"];
    assert_ne!(moved, &values);
    // The colour channels stay; channel 3 + j holds the peer's 3 + perm[j].
    assert_eq!(moved[..27], values[..27]);
    assert_eq!(
        moved[9 * 4..9 * 5],
        values[9 * (3 + perm[1])..9 * (4 + perm[1])]
    );
    assert_eq!(to_peer(&conv, &osrt, &perm).unwrap(), (shape, values));
    let qkv = Entry {
        peer: "qkv".into(),
        map: Map::Rows(vec!["q".into(), "k".into(), "v".into()]),
    };
    let values: Vec<f32> = (0..6 * 4).map(|i| i as f32).collect();
    let split = to_osrt(&qkv, &[6, 4], &values, &perm);
    assert_eq!(split["k"], (vec![2, 4], values[8..16].to_vec()));
    assert_eq!(to_peer(&qkv, &split, &perm).unwrap(), (vec![6, 4], values));
}

#[test]
fn peer_configs_osrt_cannot_compute_are_refused_by_name() {
    let base = "model:\n  encoder: osrt\n  encoder_kwargs:\n    pos_start_octave: -5\n    \
                num_slots: 6\n  decoder: slot_mixer\n  decoder_kwargs:\n    pos_start_octave: -5\n";
    let cfg = PeerConfig::parse(base, "config.yaml").unwrap();
    assert_eq!(cfg.model.encoder_kwargs.slot_iters, 1);
    assert_eq!(cfg.input_stride(), 1);
    // The peer's runs/clevr3d: `downsample: 1` halves the input views.
    let clevr = format!("data:\n  dataset: clevr3d\n  kwargs:\n    downsample: 1\n{base}");
    assert_eq!(
        PeerConfig::parse(&clevr, "c.yaml").unwrap().input_stride(),
        2
    );
    let err = PeerConfig::parse(&clevr.replace("downsample: 1", "downsample: 9"), "c.yaml");
    assert!(err.unwrap_err().to_string().contains("downsample"));
    for (change, setting) in [
        (
            ("decoder: slot_mixer", "decoder: spatial_broadcast"),
            "model.decoder",
        ),
        (("encoder: osrt", "encoder: srt"), "model.encoder"),
        (
            (
                "num_slots: 6\n",
                "num_slots: 6\n    randomize_initial_slots: true\n",
            ),
            "randomize_initial_slots",
        ),
        (
            (
                "decoder_kwargs:\n",
                "decoder_kwargs:\n    layer_norm: true\n",
            ),
            "layer_norm",
        ),
        (
            (
                "decoder_kwargs:\n    pos_start_octave: -5",
                "decoder_kwargs:\n    pos_start_octave: 0",
            ),
            "pos_start_octave",
        ),
    ] {
        let text = base.replacen(change.0, change.1, 1);
        let err = PeerConfig::parse(&text, "config.yaml")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("config.yaml") && err.contains(setting),
            "{err}"
        );
    }
    let err = PeerConfig::parse(&base.replace("num_slots: 6", "num_slotz: 6"), "c.yaml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("num_slotz"), "{err}");
}

#[test]
fn the_peer_can_build_the_paper_model_and_not_others() {
    assert_eq!(peer_cannot_build(&paper_with_bias(), false), None);
    assert_eq!(peer_cannot_build(&osrt_model::Config::paper(), false), None);
    let cpu = osrt_model::Config::cpu();
    let (setting, _) = peer_cannot_build(&cpu, true).unwrap();
    assert_eq!(setting, "model.ray_encoding");
    let mut small = paper_with_bias();
    small.encoder.dim = 64;
    assert_eq!(peer_cannot_build(&small, false).unwrap().0, "model widths");
    assert_eq!(peer_cannot_build(&small, true), None);
}
