//! Generates the gRPC code for proto/ without a system protoc: protox parses the .proto files in
//! Rust, tonic-prost-build generates from its descriptors. The descriptor set is also written for
//! gRPC server reflection and for MCAP schemas.

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
    Ok(())
}
