//! Checkpoints of a trainer: [`Snapshot::take`] copies the weights and optimiser moments
//! (the only part on the training thread); serialising, hashing and uploading happen in
//! [`Snapshot::commit`], which can run in a task; [`load`] puts a verified checkpoint back
//! into a trainer. Layout, commit protocol, verification, listing and retention:
//! `osrt_run::checkpoint`.

use crate::error::{Result, TrainError};
use crate::step::Trainer;
use bytes::Bytes;
use candle_core::{Device, Tensor};
use osrt_run::checkpoint::*;
use osrt_store::Location;

/// A copy of the weights and optimiser state, ready to be written.
pub struct Snapshot {
    names: Vec<(String, Vec<usize>)>,
    params: Vec<f32>,
    m: Vec<f32>,
    v: Vec<f32>,
    pub state: CheckpointState,
}

impl Snapshot {
    /// Copies what a checkpoint needs out of `trainer` (the only part that must happen on
    /// the training thread).
    pub fn take(trainer: &Trainer, state: CheckpointState) -> Result<Self> {
        let names = trainer
            .params
            .vars()
            .into_iter()
            .map(|(n, v)| (n, v.dims().to_vec()))
            .collect();
        let (m, v) = trainer.opt.moments()?;
        Ok(Self {
            names,
            params: trainer.params.flatten()?,
            m,
            v,
            state,
        })
    }

    fn serialise(&self) -> Result<Vec<(&'static str, Bytes)>> {
        let dev = Device::Cpu;
        let mut off = 0;
        let mut model = Vec::with_capacity(self.names.len());
        for (name, dims) in &self.names {
            let n: usize = dims.iter().product();
            model.push((
                name.as_str(),
                Tensor::from_slice(&self.params[off..off + n], dims.as_slice(), &dev)?,
            ));
            off += n;
        }
        let ser = |tensors: Vec<(&str, Tensor)>| {
            safetensors::serialize(tensors.iter().map(|(k, v)| (*k, v)), None).map_err(|e| {
                TrainError::Checkpoint {
                    path: "checkpoint".into(),
                    reason: format!("serialising: {e}"),
                }
            })
        };
        let opt = vec![
            ("m", Tensor::from_slice(&self.m, self.m.len(), &dev)?),
            ("v", Tensor::from_slice(&self.v, self.v.len(), &dev)?),
        ];
        Ok(vec![
            (MODEL, Bytes::from(ser(model)?)),
            (OPTIMIZER, Bytes::from(ser(opt)?)),
            (
                STATE,
                Bytes::from(serde_json::to_vec_pretty(&self.state).expect("serialises")),
            ),
        ])
    }

    /// Serialises the snapshot and commits it (`osrt_run::checkpoint::commit`), fenced
    /// by the writer's generation where it has one.
    pub async fn commit(self, run: &Location, fence: Option<u64>) -> Result<u64> {
        let files = self.serialise()?;
        Ok(osrt_run::checkpoint::commit(run, &self.state, files, fence).await?)
    }
}

/// Loads checkpoint `step` (verified) into `trainer`; returns its state.
pub async fn load(run: &Location, step: u64, trainer: &mut Trainer) -> Result<CheckpointState> {
    let files = verify_retrying(run, step).await?;
    let dir = step_dir(step);
    let bad = |name: &str, reason: String| {
        TrainError::from(store_err(run, &format!("{dir}/{name}"), reason))
    };
    let state: CheckpointState = serde_json::from_slice(&files[STATE])
        .map_err(|e| bad(STATE, format!("unreadable state: {e}")))?;
    let dev = trainer.device().clone();
    let model = candle_core::safetensors::load_buffer(&files[MODEL], &dev)
        .map_err(|e| bad(MODEL, e.to_string()))?;
    trainer
        .params
        .load_tensors(&model)
        .map_err(|e| bad(MODEL, e.to_string()))?;
    // The moments pass through the host as flat buffers either way.
    let opt = candle_core::safetensors::load_buffer(&files[OPTIMIZER], &Device::Cpu)
        .map_err(|e| bad(OPTIMIZER, e.to_string()))?;
    let n = trainer.num_parameters();
    let moment = |k: &str| -> Result<Vec<f32>> {
        let t = opt
            .get(k)
            .ok_or_else(|| bad(OPTIMIZER, format!("no tensor `{k}`")))?;
        let v = t.to_vec1::<f32>()?;
        if v.len() != n {
            return Err(bad(
                OPTIMIZER,
                format!("`{k}` has {} values, the model has {n}", v.len()),
            ));
        }
        Ok(v)
    };
    trainer
        .opt
        .restore(moment("m")?, moment("v")?, state.adam_t)?;
    trainer.step = state.step;
    trainer.skipped_total = state.skipped_total;
    trainer.skipped_in_a_row = 0;
    Ok(state)
}
