//! The benchmarks and the device's checks, in one place: what `osrt bench` and `osrt
//! check-device` run, and what the CLI prints from.
//!
//! - [`model`]: the train step, the renders and the per-op profile of a preset
//!   (`osrt bench model`).
//! - [`device_step`]: a device's train step against the CPU's, its memory and its
//!   out-of-memory handling (`osrt check-device`; the ops themselves are compared in
//!   `osrt_kernels::device_check`).
//! - [`data_path`]: the data path's throughput (`osrt bench data`).
//! - [`allreduce`]: the ring all-reduce against bare TCP (`osrt bench allreduce`).

pub mod allreduce;
pub mod data_path;
pub mod device_step;
pub mod model;

/// Median of timings (upper median for even counts); shared by every benchmark.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
