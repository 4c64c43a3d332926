//! OSRT in candle: ray encoding, SRT encoder, slot attention and the three decoders
//! (Slot Mixer, spatial broadcast, transformer), plus evaluation metrics.
//!
//! Not yet written: this crate is a placeholder in the workspace layout (see issue
//! "OSRT in candle"). It exports nothing.
