pub mod bench;
pub mod mesh_info;
pub mod predict;
pub mod replay;
