//! The nodes of candle's graph above the single-op kernels, and the graph's plumbing:
//!
//! - the matrix product every node is built from, one node in the thread's precision
//!   (`matmul`);
//! - nodes built from tensor ops for the device graph (a GPU, or `--kernels device`):
//!   attention (`attention_node`; over few keys `few_keys`), convolution (`conv_node`)
//!   and MLP (`mlp_node`), with the
//!   custom-op scaffolding they share (`node`), the hand-over of their result
//!   (`handover`) and the links that bring an MLP node's parameters in (`links`);
//! - whole pieces of the model as one fused CPU node from the `cpu` kernels: a transformer
//!   block (`block`) and the Slot Mixer's mixing block (`mix`);
//! - the backward pass in segments, and segments made again in the backward pass (`cut`).

pub(crate) mod attention_node;
pub(crate) mod block;
pub(crate) mod conv_node;
pub mod cut;
pub(crate) mod few_keys;
mod handover;
mod links;
pub(crate) mod matmul;
pub(crate) mod mix;
pub(crate) mod mlp_node;
mod node;
