//! Loading ONNX Runtime itself: the shared library from the PyPI wheel (DESIGN.md §9), located by
//! `--ort-dylib` or `ORT_DYLIB_PATH`, loaded once per process.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::environment::Environment;

use super::ModelLoadError;

/// The ONNX Runtime version nak is built against (`ort` 2.0.0-rc.15, API 31).
pub const ORT_VERSION: &str = "1.31.1";

static ENVIRONMENT: OnceLock<Result<Environment, String>> = OnceLock::new();

/// Where the library is: the explicit path if given, else `ORT_DYLIB_PATH`.
pub fn locate(explicit: Option<&Path>) -> Result<PathBuf, ModelLoadError> {
    let path = explicit
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("ORT_DYLIB_PATH").map(PathBuf::from))
        .ok_or_else(|| {
            ModelLoadError::runtime(format!(
                "ONNX Runtime {ORT_VERSION} is needed to serve ONNX models but was not configured: set \
                 ORT_DYLIB_PATH or pass --ort-dylib to libonnxruntime.so.{ORT_VERSION} (from `pip install \
                 onnxruntime=={ORT_VERSION}`; scripts/onnxruntime-path prints it)"
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
