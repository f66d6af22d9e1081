//! nak: real-time soft-tissue deformation (Neural-Augmented Kelvinlet).
//!
//! The library behind the `nak` binary, in layers; a module imports only from layers below its own
//! (docs/architecture.md has the whole table, the reasons and the path of one `Predict` call):
//!
//! 1. [`mesh`]: tetrahedral meshes, their readers, validation and configuration; [`proto`] (the
//!    generated wire types) and [`cpu_idle`] stand apart at the bottom too.
//! 2. Numerics, side by side: [`prior`] (the Kelvinlet solve and field, CPU or GPU) and [`fem`]
//!    (finite elements, the gravity preload, Green's functions). They know no requests and no gRPC.
//! 3. [`engine`]: a request's path (limits, grasps, selections) and the model trait, with the built-in
//!    `kelvinlet` model.
//! 4. Above the engine: [`model`] (ONNX networks and the exact linear models) and [`data`] (the
//!    distribution p, datasets, ground truth, DCM).
//! 5. [`wire`]: the codec between messages and values, and the PEM and token files, shared by
//!    everything that speaks gRPC.
//! 6. [`record`] (MCAP) and [`client`] (nak's gRPC client).
//! 7. [`serve`] (the gRPC service) and [`bench`] (the load tester).
//! 8. The command line (`src/cli`, `src/main.rs`), over all of them.

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
pub mod wire;
