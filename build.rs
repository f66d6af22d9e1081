//! Generates the gRPC code for proto/ without a system protoc: protox parses the .proto files in
//! Rust, tonic-prost-build generates from its descriptors. The descriptor set is also written for
//! gRPC server reflection and for MCAP schemas. The networks shipped with the phantom liver
//! (models/phantom-liver/<name>/{manifest.toml, model.onnx}) are embedded beside it.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    let mut compiler = protox::Compiler::new(["proto"])?;
    compiler.include_source_info(true);
    compiler.open_file("nak/v1/deformation.proto")?;
    std::fs::write(
        out_dir.join("nak_v1_descriptor.bin"),
        compiler.encode_file_descriptor_set(),
    )?;
    tonic_prost_build::configure()
        .bytes(".")
        .compile_fds(compiler.file_descriptor_set())?;

    // Foxglove's point cloud, for MCAP recordings: its descriptor set carries every import
    // (google/protobuf/timestamp.proto included) so generic readers can decode it alone.
    let mut foxglove = protox::Compiler::new(["proto"])?;
    foxglove.include_imports(true);
    foxglove.open_file("foxglove/PointCloud.proto")?;
    std::fs::write(
        out_dir.join("foxglove_descriptor.bin"),
        foxglove.encode_file_descriptor_set(),
    )?;
    tonic_prost_build::configure()
        .build_client(false)
        .build_server(false)
        .bytes(".")
        .compile_fds(foxglove.file_descriptor_set())?;
    embed_shipped_models(&out_dir)
}

/// Writes `embedded_models.rs`: one (name, manifest, graph) entry per shipped model directory.
fn embed_shipped_models(out_dir: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?).join("models/phantom-liver");
    println!("cargo:rerun-if-changed={}", root.display());
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&root)?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.join("manifest.toml").is_file() && p.join("model.onnx").is_file())
        .collect();
    dirs.sort();
    let mut code = String::from("pub const SHIPPED: &[ShippedModel] = &[\n");
    for dir in dirs {
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or("model directory name is not UTF-8")?;
        let basis = dir.join("basis.safetensors");
        let basis = if basis.is_file() {
            format!("Some(include_bytes!({basis:?}))")
        } else {
            "None".to_owned()
        };
        code.push_str(&format!(
            "    ShippedModel {{ name: {name:?}, files: ModelFiles {{ manifest: include_str!({:?}), \
             onnx: include_bytes!({:?}), basis: {basis} }} }},\n",
            dir.join("manifest.toml"),
            dir.join("model.onnx")
        ));
    }
    code.push_str("];\n");
    std::fs::write(out_dir.join("embedded_models.rs"), code)?;
    Ok(())
}
