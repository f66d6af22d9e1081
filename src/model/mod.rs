//! ONNX-exported networks under the model contract (docs/design.md §7): manifests, discovery and serving.

pub mod basis;
pub mod green;
pub mod manifest;
pub mod onnx;
pub mod prior;
pub mod runtime;
pub mod shipped;
pub mod signature;

use std::path::{Path, PathBuf};
use std::sync::Arc;

pub use basis::Basis;
pub use green::GreenModel;
pub use manifest::{Channel, Manifest, Method, Mode, PriorModel};
pub use onnx::{ModelFiles, OnnxModel};
pub use prior::ModelPrior;

use crate::fem::{GreenFunctions, Stiffness};
use crate::mesh::TetMesh;

/// Gives the Green's functions of a stiffness (green-linear's or green-tangent's) to the networks
/// trained on that prior. Called only when such a network is loaded: computing them costs seconds
/// and a cache file (4 s and 232 MB on the phantom), which a server whose networks do not need them
/// should not pay.
pub type GreenSource<'a> = &'a dyn Fn(Stiffness) -> Result<Arc<GreenFunctions>, String>;

/// What loading a network may need from outside its directory.
#[derive(Clone, Copy, Default)]
pub struct LoadContext<'a> {
    /// ONNX Runtime's shared library (`None`: $ORT_DYLIB_PATH).
    pub ort_dylib: Option<&'a Path>,
    /// `None`: networks on a Green's-function prior are refused, saying how to serve them.
    pub green: Option<GreenSource<'a>>,
}

impl<'a> From<Option<&'a Path>> for LoadContext<'a> {
    fn from(ort_dylib: Option<&'a Path>) -> Self {
        Self { ort_dylib, green: None }
    }
}

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
pub fn load_each<'a>(
    root: &Path,
    mesh: &TetMesh,
    context: impl Into<LoadContext<'a>>,
) -> Result<Vec<Result<OnnxModel, ModelLoadError>>, ModelLoadError> {
    let context = context.into();
    let dirs = model_dirs(root)?;
    if !dirs.is_empty() {
        runtime::locate(context.ort_dylib)?;
    }
    Ok(dirs.iter().map(|dir| OnnxModel::load(dir, mesh, context)).collect())
}

/// Loads every model under `root` for `mesh`; the first refusal stops the load with its reason.
pub fn load_all<'a>(
    root: &Path,
    mesh: &TetMesh,
    context: impl Into<LoadContext<'a>>,
) -> Result<Vec<OnnxModel>, ModelLoadError> {
    load_each(root, mesh, context)?.into_iter().collect()
}
