//! The coordinator: job spec and state, membership, shard plans, generations.
//!
//! Not yet written: this crate is a placeholder in the workspace layout. It exports nothing.
