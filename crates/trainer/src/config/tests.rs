use super::*;

#[test]
fn presets_validate() {
    for name in [
        "clevr-lite-cpu",
        "clevr-lite-gpu",
        "paper",
        "clevr3d",
        "msn-hard",
        "tiny",
    ] {
        JobConfig::preset(name).unwrap().validate().unwrap();
    }
}

/// Settings that would divide by zero, never log, never checkpoint, or let retention
/// delete the newest checkpoint are refused by name, before any worker starts.
#[test]
fn settings_that_cannot_run_are_refused_by_name() {
    type Edit = fn(&mut JobConfig);
    let cases: [(&str, Edit); 22] = [
        ("train.log_every", |j| j.train.log_every = 0),
        ("train.decay_steps", |j| j.train.decay_steps = 0.0),
        ("train.decay_steps", |j| j.train.decay_steps = f64::NAN),
        ("train.eval_every_s", |j| j.train.eval_every_s = -1.0),
        ("train.eval_scenes", |j| j.train.eval_scenes = 0),
        ("train.beta2", |j| j.train.beta2 = 1.0),
        ("train.weight_decay", |j| j.train.weight_decay = -0.1),
        ("train.clip_norm", |j| j.train.clip_norm = Some(0.0)),
        ("train.salient_fraction", |j| j.train.salient_fraction = 1.5),
        ("cluster.checkpoint_every", |j| {
            j.cluster.checkpoint_every = 0
        }),
        ("cluster.keep_last", |j| j.cluster.keep_last = 0),
        ("cluster.join_grace_s", |j| j.cluster.join_grace_s = -1.0),
        ("cluster.wait_timeout_s", |j| j.cluster.wait_timeout_s = 0.0),
        ("cluster.rpc_timeout_s", |j| {
            j.cluster.rpc_timeout_s = f64::INFINITY
        }),
        // `Duration::from_secs_f64` panics on these.
        ("cluster.heartbeat_timeout_s", |j| {
            j.cluster.heartbeat_timeout_s = 1e30
        }),
        ("train.eval_every_s", |j| j.train.eval_every_s = 1e30),
        // One ring hop per float.
        ("cluster.bucket_floats", |j| j.cluster.bucket_floats = 1),
        // Sizes whose products overflow or exhaust memory.
        ("train.batch_size", |j| j.train.batch_size = usize::MAX),
        ("model.encoder.dim", |j| j.model.encoder.dim = 1 << 40),
        ("model.slot_attention.num_slots", |j| {
            j.model.slot_attention.num_slots = 0
        }),
        ("model.ray_encoding.origin_start_octave", |j| {
            j.model.ray_encoding.origin_start_octave = i32::MAX
        }),
        ("model.decoder.render_hidden[1]", |j| {
            if let DecoderConfig::SlotMixer(c) = &mut j.model.decoder {
                c.render_hidden[1] = 0;
            }
        }),
    ];
    for (name, edit) in cases {
        let mut j = JobConfig::preset("tiny").unwrap();
        edit(&mut j);
        let e = j.validate().unwrap_err().to_string();
        assert!(e.contains(name), "{name}: {e}");
    }
}
