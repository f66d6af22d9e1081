//! Generated gRPC types and service stubs for `nak.v1` (see proto/nak/v1/deformation.proto).

#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod v1 {
    tonic::include_proto!("nak.v1");

    /// Encoded `FileDescriptorSet` of the API, for server reflection and recording schemas.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("nak_v1_descriptor");
}

/// Foxglove's well-known point cloud schema, for MCAP recordings Foxglove can render.
#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod foxglove {
    tonic::include_proto!("foxglove");

    /// Encoded `FileDescriptorSet` of `foxglove.PointCloud` and everything it imports.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("foxglove_descriptor");
}
