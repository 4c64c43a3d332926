//! OSRT in candle (Sajjadi et al., NeurIPS 2022): one module per paper component, each
//! with a serde `Config` and `new(cfg, vb)`, plus evaluation metrics.
//!
//! ```text
//! images + rays ─ encoder (SRT, eq. 1) ─▶ SLSR ─ slot_attention (eq. 2) ─▶ slots
//! slots + target rays ─ decoder (slot_mixer eqs. 4–6 | spatial_broadcast eqs. 7–8 |
//!                                 transformer eq. 3) ─▶ RGB (+ per-ray slot weights)
//! ```
//! Parameters are created through [`Params`], which makes initialisation deterministic and
//! the parameter order fixed (sorted names).

pub mod decoder;
pub mod encoder;
pub mod footprint;
pub mod metrics;
pub mod nn;
mod osrt;
mod params;
pub mod ray_encoding;
pub mod slot_attention;
#[cfg(test)]
mod tests;

pub use osrt::{Config, Osrt, add_slot, drop_slot};
pub use params::Params;
