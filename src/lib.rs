//! nak: real-time soft-tissue deformation (Neural-Augmented Kelvinlet).
//!
//! The library behind the `nak` binary: meshes ([`mesh`]), the Kelvinlet prior ([`prior`]), the
//! prediction engine ([`engine`]) and the gRPC service ([`serve`]).

pub mod bench;
pub mod client;
pub mod cpu_idle;
pub mod data;
pub mod engine;
pub mod fem;
pub mod mesh;
pub mod model;
pub mod prior;
pub mod proto;
pub mod record;
pub mod serve;
