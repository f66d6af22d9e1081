//! The networks shipped with the embedded phantom liver (`models/phantom-liver/<name>/`), compiled
//! into the binary so that `nak serve` answers with them wherever it runs.

use super::{LoadContext, ModelFiles, ModelLoadError, OnnxModel};
use crate::mesh::TetMesh;

/// One shipped model: its directory name and files.
pub struct ShippedModel {
    pub name: &'static str,
    pub files: ModelFiles<'static>,
}

include!(concat!(env!("OUT_DIR"), "/embedded_models.rs"));

/// Loads every shipped model for `mesh` (the embedded phantom).
pub fn load(mesh: &TetMesh, context: LoadContext<'_>) -> Result<Vec<OnnxModel>, ModelLoadError> {
    SHIPPED
        .iter()
        .map(|m| {
            let origin = format!("embedded:{}/{}", crate::mesh::EMBEDDED_NAME, m.name);
            OnnxModel::from_parts(&origin, m.files, mesh, context)
        })
        .collect()
}
