//! Helpers shared by the integration tests.
#![allow(dead_code)]

pub mod models;
pub mod msh_fixture;
pub mod process;
pub mod server;
