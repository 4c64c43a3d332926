//! Integration tests of the dataset crate, in one binary to keep link time down.

mod bad_input;
mod generator;
mod io;

use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{Scene, generator::generate_scene};

/// A small, fast clevr-lite configuration for tests.
pub fn tiny_config(size: u32) -> GeneratorConfig {
    GeneratorConfig {
        image_size: size,
        antialias: 1,
        ..GeneratorConfig::clevr_lite()
    }
}

pub fn tiny_scenes(n: u64, size: u32) -> Vec<Scene> {
    let cfg = tiny_config(size);
    (0..n)
        .map(|i| generate_scene(&cfg, 7, "test", i).unwrap())
        .collect()
}
