//! What a one-node op's forward pass keeps for its backward pass ([`Kept`]), shared by
//! the fused CPU nodes (`cpu`) and the nodes built from tensor ops (`graph`).

use std::sync::Mutex;

/// What a one-node op's forward pass keeps for its backward pass: put there only when a
/// gradient can follow, and taken (not cloned) by the backward pass, so a second backward
/// through the same graph finds it empty and recomputes it.
pub(crate) struct Kept<T>(Mutex<Option<T>>);

impl<T> Kept<T> {
    pub(crate) fn new(v: Option<T>) -> Self {
        Self(Mutex::new(v))
    }

    pub(crate) fn put(&self, v: T) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
    }

    pub(crate) fn take(&self) -> Option<T> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}
