//! The worker: train step, ring all-reduce over gRPC, checkpoints, evaluation, rendering.
//!
//! Not yet written: this crate is a placeholder in the workspace layout. It exports nothing.
