//! Generates the gRPC code from `proto/` with the protoc binary vendored by
//! `protoc-bin-vendored`, so no system protoc is needed.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Read when the script runs, not when it is compiled: a target directory shared by
    // clones at other paths reuses the compiled script.
    let manifest = std::env::var("CARGO_MANIFEST_DIR")?;
    let root = std::path::Path::new(&manifest).join("../../proto");
    let file = root.join("osrt/v1/osrt.proto");
    println!("cargo:rerun-if-changed={}", file.display());
    let mut config = tonic_prost_build::Config::new();
    config.protoc_executable(protoc_bin_vendored::protoc_bin_path()?);
    // Gradient chunks arrive as `Bytes`: no copy between the wire and the reducer.
    config.bytes(["."]);
    tonic_prost_build::configure().compile_with_config(config, &[file], &[root])?;
    Ok(())
}
