//! ONNX-exported networks under the model contract (DESIGN.md §7): manifests, discovery and serving.

pub mod basis;
pub mod manifest;
pub mod onnx;
pub mod runtime;
pub mod shipped;
pub mod signature;

use std::path::{Path, PathBuf};

pub use basis::Basis;
pub use manifest::{Channel, Manifest, Method, Mode};
pub use onnx::{ModelFiles, OnnxModel};

use crate::mesh::TetMesh;

/// Why a model (or ONNX Runtime) could not be loaded; the message names the file and the problem.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{origin}: {message}")]
pub struct ModelLoadError {
    pub origin: String,
    pub message: String,
}

impl ModelLoadError {
    pub fn new(origin: &str, message: impl Into<String>) -> Self {
        Self {
            origin: origin.to_owned(),
            message: message.into(),
        }
    }

    fn runtime(message: impl Into<String>) -> Self {
        Self::new("onnxruntime", message)
    }
}

/// Model directories under `root`: every subdirectory holding a `manifest.toml`, sorted by name.
pub fn model_dirs(root: &Path) -> Result<Vec<PathBuf>, ModelLoadError> {
    let entries =
        std::fs::read_dir(root).map_err(|e| ModelLoadError::new(&root.display().to_string(), e.to_string()))?;
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.join("manifest.toml").is_file())
        .collect();
    dirs.sort();
    Ok(dirs)
}

/// Loads every model under `root` for `mesh`, each on its own: a model that cannot be loaded is its
/// error, so that a server can refuse it and serve the others. Fails as a whole when `root` is
/// unreadable or when it holds models and ONNX Runtime is missing: that is the machine's fault, not
/// one model's, and none of them could be served.
pub fn load_each(
    root: &Path,
    mesh: &TetMesh,
    ort_dylib: Option<&Path>,
) -> Result<Vec<Result<OnnxModel, ModelLoadError>>, ModelLoadError> {
    let dirs = model_dirs(root)?;
    if !dirs.is_empty() {
        runtime::locate(ort_dylib)?;
    }
    Ok(dirs.iter().map(|dir| OnnxModel::load(dir, mesh, ort_dylib)).collect())
}

/// Loads every model under `root` for `mesh`; the first refusal stops the load with its reason.
pub fn load_all(root: &Path, mesh: &TetMesh, ort_dylib: Option<&Path>) -> Result<Vec<OnnxModel>, ModelLoadError> {
    load_each(root, mesh, ort_dylib)?.into_iter().collect()
}
