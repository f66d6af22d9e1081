pub mod bench;
pub mod mesh_info;
pub mod predict;
