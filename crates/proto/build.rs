//! Compiles `proto/pathfarm/v1/*.proto` (the workspace's `proto/` directory) with protox,
//! in pure Rust: no system `protoc`. Generates the prost messages and the tonic client and
//! server stubs into OUT_DIR, and writes the encoded descriptor set (with imports and
//! comments) to OUT_DIR/pathfarm_v1_descriptor.bin for `FILE_DESCRIPTOR_SET`.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let manifest_dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?);
    let include = manifest_dir.join("../../proto");
    let package_dir = include.join("pathfarm/v1");

    // Every .proto of the package, in a fixed order, so a new file is picked up without
    // editing this script.
    let mut files = Vec::new();
    for entry in std::fs::read_dir(&package_dir)
        .map_err(|e| format!("reading {}: {e}", package_dir.display()))?
    {
        let path = entry?.path();
        if path.extension().is_some_and(|ext| ext == "proto") {
            files.push(path);
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(format!("no .proto files in {}", package_dir.display()).into());
    }

    println!("cargo:rerun-if-changed={}", package_dir.display());
    for file in &files {
        println!("cargo:rerun-if-changed={}", file.display());
    }

    let mut compiler = protox::Compiler::new([&include])?;
    // Source info carries the .proto comments into the generated docs and into reflection.
    compiler.include_imports(true).include_source_info(true);
    compiler.open_files(&files)?;

    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out_dir.join("pathfarm_v1_descriptor.bin"),
        compiler.encode_file_descriptor_set(),
    )?;

    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .emit_rerun_if_changed(false)
        .compile_fds(compiler.file_descriptor_set())?;
    Ok(())
}
