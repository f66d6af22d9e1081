//! Loading ONNX Runtime itself: the shared library from the PyPI wheel (docs/design.md §9), located by
//! `--ort-dylib`, `ORT_DYLIB_PATH`, or in the `.venv` of the working directory (where
//! scripts/setup-python puts the wheel when run from a checkout), and loaded once per process.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::environment::Environment;

use super::ModelLoadError;

/// The ONNX Runtime version nak is built against (`ort` 2.0.0-rc.15, API 31).
pub const ORT_VERSION: &str = "1.31.1";

static ENVIRONMENT: OnceLock<Result<Environment, String>> = OnceLock::new();

/// Where the library is: the explicit path if given, else `ORT_DYLIB_PATH`, else the wheel in
/// `./.venv`.
pub fn locate(explicit: Option<&Path>) -> Result<PathBuf, ModelLoadError> {
    let path = explicit
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("ORT_DYLIB_PATH").map(PathBuf::from))
        .or_else(in_project_venv)
        .ok_or_else(|| {
            ModelLoadError::runtime(format!(
                "ONNX Runtime {ORT_VERSION} is needed to serve ONNX models but was not found: run \
                 scripts/setup-python (it installs it into .venv), or set ORT_DYLIB_PATH or pass --ort-dylib \
                 to libonnxruntime.so.{ORT_VERSION} (from `pip install onnxruntime=={ORT_VERSION}`)"
            ))
        })?;
    if !path.is_file() {
        return Err(ModelLoadError::runtime(format!(
            "ONNX Runtime library {} does not exist (ORT_DYLIB_PATH / --ort-dylib)",
            path.display()
        )));
    }
    Ok(path)
}

fn in_project_venv() -> Option<PathBuf> {
    let mut pythons: Vec<PathBuf> = std::fs::read_dir(".venv/lib")
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    pythons.sort();
    pythons
        .into_iter()
        .map(|p| {
            p.join(format!(
                "site-packages/onnxruntime/capi/libonnxruntime.so.{ORT_VERSION}"
            ))
        })
        .find(|p| p.is_file())
        .and_then(|p| std::path::absolute(p).ok())
}

/// The process-wide ONNX Runtime environment, loading the library on first use.
pub fn environment(explicit: Option<&Path>) -> Result<&'static Environment, ModelLoadError> {
    let loaded = ENVIRONMENT.get_or_init(|| {
        let path = locate(explicit).map_err(|e| e.to_string())?;
        let builder =
            ort::init_from(&path).map_err(|e| format!("cannot load ONNX Runtime from {}: {e}", path.display()))?;
        builder
            .with_name("nak")
            .with_telemetry(false)
            .build()
            .map_err(|e| format!("cannot start ONNX Runtime from {}: {e}", path.display()))
    });
    loaded.as_ref().map_err(|e| ModelLoadError::runtime(e.clone()))
}
