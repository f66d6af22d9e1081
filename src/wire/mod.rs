//! Between messages and values, for every part of nak that talks gRPC (the server, the recorder, the
//! client, the load tester): the packed-rows codec, the conversions between engine values and
//! `nak.v1` messages, and the PEM and token files that both ends of a connection read.

pub mod convert;
mod files;

pub use convert::{f32_bytes, grasp_message, response_rows, vec3_rows};
pub use files::{FileError, read_pem, read_token};
