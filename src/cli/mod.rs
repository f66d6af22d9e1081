pub mod mesh_info;
