pub mod bench;
pub mod datagen;
pub mod engine;
pub mod eval;
pub mod mesh_info;
pub mod predict;
pub mod replay;
pub mod serve;
