//! Models and arrays in other tools' formats.
//!
//! - [`torch_file`]: files written by `torch.save`, read without Python and without
//!   running any of the pickle's code;
//! - [`stelzner`]: the PyTorch OSRT of stelzner/osrt — its checkpoints and run configs
//!   mapped onto osrt's model, and osrt's weights back under its names;
//! - [`npz`]: NumPy `.npz` archives of float32 arrays (`osrt predict`).
//!
//! Nothing here writes a run folder: the trainer turns an [`stelzner::Imported`] model into
//! one (`osrt_trainer::interop`).

mod error;
pub mod npz;
pub mod stelzner;
pub mod torch_file;

pub use error::{InteropError, Result};
