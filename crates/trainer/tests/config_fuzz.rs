//! The job config against hostile TOML: presets' documents with fields of every table
//! (`[model]`, `[train]`, `[cluster]`) set to values of any TOML type (huge, negative and
//! non-finite floats, extreme integers, strings, arrays, tables). Parsing and validation
//! give a config or an error naming the file or the field, never a panic; a config that
//! validates turns into the durations the coordinator and the workers build from it
//! (`Duration::from_secs_f64(1e30)` panicked in the coordinator) and serialises back to
//! itself. `cargo test` runs `PROPTEST_CASES` cases (256 by default); a longer run by
//! hand is `PROPTEST_CASES=100000 cargo test -p osrt-trainer --test config_fuzz`.

use osrt_run::cluster_config::ClusterConfig;
use osrt_trainer::JobConfig;
use proptest::prelude::*;
use std::time::{Duration, Instant};
use toml::Value;

/// One step of a path into a TOML document.
#[derive(Debug, Clone)]
enum Seg {
    Key(String),
    Index(usize),
}

/// The documents mutated: the presets' configs, with the optional fields present.
fn bases() -> Vec<Value> {
    let mut jobs = Vec::new();
    for name in ["tiny", "clevr-lite-cpu", "paper"] {
        let mut j = JobConfig::preset(name).unwrap();
        j.train.clip_norm = Some(1.0);
        jobs.push(j);
    }
    let mut v = JobConfig::preset("tiny").unwrap();
    v.model = v.model.with_decoder("volumetric").unwrap();
    if let osrt_model::decoder::Config::Volumetric(c) = &mut v.model.decoder {
        c.bounds = Some([[-1.0; 3], [1.0; 3]]);
    }
    jobs.push(v);
    for j in &jobs {
        j.validate().unwrap();
    }
    jobs.iter()
        .map(|j| toml::from_str(&j.to_toml()).unwrap())
        .collect()
}

/// Every non-table value of `v` (arrays and their elements both), by path.
fn leaves(v: &Value, path: &mut Vec<Seg>, out: &mut Vec<Vec<Seg>>) {
    match v {
        Value::Table(t) => {
            for (k, x) in t {
                path.push(Seg::Key(k.clone()));
                leaves(x, path, out);
                path.pop();
            }
            return;
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                path.push(Seg::Index(i));
                leaves(x, path, out);
                path.pop();
            }
        }
        _ => {}
    }
    out.push(path.clone());
}

fn set(v: &mut Value, path: &[Seg], new: Value) {
    let Some((first, rest)) = path.split_first() else {
        *v = new;
        return;
    };
    let next = match (first, v) {
        (Seg::Key(k), Value::Table(t)) => t.get_mut(k),
        (Seg::Index(i), Value::Array(a)) => a.get_mut(*i),
        _ => None,
    };
    if let Some(next) = next {
        set(next, rest, new);
    }
}

/// `model.encoder.conv_channels[0]` → `model.encoder.conv_channels`: how errors name it.
fn field(path: &[Seg]) -> String {
    let keys: Vec<&str> = path
        .iter()
        .filter_map(|s| match s {
            Seg::Key(k) => Some(k.as_str()),
            Seg::Index(_) => None,
        })
        .collect();
    keys.join(".")
}

fn value() -> impl Strategy<Value = Value> {
    let float = prop_oneof![
        prop_oneof![
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(1e30),
            Just(-1e30),
            Just(f64::MAX),
            Just(f64::MIN_POSITIVE),
            Just(0.0),
            Just(-0.0),
            Just(-1.0),
            Just(0.5),
            Just(31_536_001.0),
        ],
        any::<f64>(),
    ];
    let int = prop_oneof![
        prop_oneof![
            Just(i64::MAX),
            Just(i64::MIN),
            Just(-1),
            Just(0),
            Just(1),
            Just(1 << 16),
            Just(1 << 40),
        ],
        any::<i64>(),
        0i64..5000,
    ];
    let string = prop_oneof![
        prop_oneof![
            Just("cuda"),
            Just("bf16"),
            Just("device"),
            Just("unposed"),
            Just("volumetric"),
            Just("tokens"),
            Just("nan"),
            Just(""),
        ]
        .prop_map(str::to_string),
        "\\PC{0,12}",
    ];
    let leaf = prop_oneof![
        float.prop_map(Value::Float),
        int.prop_map(Value::Integer),
        string.prop_map(Value::String),
        any::<bool>().prop_map(Value::Boolean),
    ];
    leaf.prop_recursive(2, 12, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,8}", inner, 0..3)
                .prop_map(|m| Value::Table(m.into_iter().collect())),
        ]
    })
}

/// What the coordinator and the workers build from a validated `[cluster]` table:
/// any of these panicking is a bug the validation let through.
fn cluster_durations(c: &ClusterConfig) {
    let now = Instant::now();
    // The coordinator's state machine (`core.rs`).
    for d in [c.heartbeat_timeout(), c.join_grace(), c.wait_timeout()] {
        let _ = now + d;
    }
    // The worker's heartbeat period and collective deadline.
    let _ = now + Duration::from_secs_f64((c.heartbeat_timeout_s / 5.0).clamp(0.05, 1.0));
    let _ = now + Duration::from_secs_f64(c.rpc_timeout_s);
    let _ = now + c.rpc_timeout();
}

/// The property for one document whose `fields` were set: `Err` says how it failed
/// (a panic fails the test where it happens).
fn holds(doc: &Value, fields: &[String]) -> Result<(), String> {
    // A document TOML cannot write (none known) is no case.
    let Ok(text) = toml::to_string(doc) else {
        return Ok(());
    };
    let job = match JobConfig::from_toml("job.toml", &text) {
        Ok(job) => job,
        Err(e) => {
            let e = e.to_string();
            return match e.contains("job.toml") {
                true => Ok(()),
                false => Err(format!("a parse error naming no file: {e}")),
            };
        }
    };
    if let Err(e) = job.validate() {
        let e = e.to_string();
        return match fields.iter().any(|f| e.contains(f.as_str())) {
            true => Ok(()),
            false => Err(format!("{e} names none of {fields:?}")),
        };
    }
    let _ = Duration::from_secs_f64(job.train.eval_every_s);
    let _ = (job.train.lr_at(0), job.train.lr_at(u64::MAX));
    // The coordinator reads the saved config's `[cluster]` table alone, also when it
    // restarts: the same table, valid, with durations it can build.
    let saved = job.to_toml();
    let cluster = ClusterConfig::from_job_toml("config.toml", &saved).map_err(|e| e.to_string())?;
    if cluster != job.cluster {
        return Err(format!("[cluster] read alone: {cluster:?}"));
    }
    cluster.validate().map_err(|e| e.to_string())?;
    cluster_durations(&cluster);
    match JobConfig::from_toml("config.toml", &saved) {
        Ok(back) if back == job => Ok(()),
        other => Err(format!("the saved config reads back as {other:?}")),
    }
}

/// Values that broke configs before: beyond `Duration`, non-finite, negative, zero,
/// beyond any size, of the wrong type.
fn hostile() -> Vec<Value> {
    let mut v: Vec<Value> = [1e30, f64::NAN, f64::INFINITY, -1.0, 0.0, 31_536_001.0]
        .into_iter()
        .map(Value::Float)
        .collect();
    v.extend(
        [i64::MAX, -1, 0, 1, 1 << 40]
            .into_iter()
            .map(Value::Integer),
    );
    v.push(Value::String("x".into()));
    v.push(Value::Array(vec![Value::Integer(1)]));
    v.push(Value::Boolean(true));
    v
}

/// Every field of every preset, each hostile value in turn.
#[test]
fn every_field_takes_every_hostile_value() {
    for base in bases() {
        let mut paths = Vec::new();
        leaves(&base, &mut Vec::new(), &mut paths);
        for path in &paths {
            for v in hostile() {
                let mut doc = base.clone();
                set(&mut doc, path, v.clone());
                if let Err(e) = holds(&doc, &[field(path)]) {
                    panic!("{} = {v}: {e}", field(path));
                }
            }
        }
    }
}

fn config() -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config())]

    /// One to three fields of a preset's document set to anything: a config or a clear
    /// error, and a valid config's durations and text hold.
    #[test]
    fn any_field_values_give_a_config_or_a_named_error(
        base in any::<prop::sample::Index>(),
        edits in prop::collection::vec((any::<prop::sample::Index>(), value()), 1..=3),
    ) {
        let bases = bases();
        let mut doc = base.get(&bases).clone();
        let mut paths = Vec::new();
        leaves(&doc, &mut Vec::new(), &mut paths);
        let mut fields = Vec::new();
        for (at, v) in edits {
            let path = at.get(&paths).clone();
            fields.push(field(&path));
            set(&mut doc, &path, v);
        }
        let outcome = holds(&doc, &fields);
        prop_assert!(outcome.is_ok(), "{}", outcome.unwrap_err());
    }
}
