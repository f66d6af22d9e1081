//! Where a mesh comes from: the embedded phantom, a model directory, or a mesh file (`.msh`, `.vtu`,
//! legacy `.vtk`) with its `model.toml` beside it.

use std::path::{Path, PathBuf};

use super::{MeshConfig, MeshError, TetMesh, vtk};

/// Name under which the embedded phantom liver is known.
pub const EMBEDDED_NAME: &str = "phantom-liver";

const EMBEDDED_MSH: &[u8] = include_bytes!("../../models/phantom-liver/liver.msh");
const EMBEDDED_CONFIG: &str = include_str!("../../models/phantom-liver/model.toml");

/// What `--mesh` names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MeshSource {
    /// The phantom liver compiled into the binary.
    Embedded,
    /// A model directory: `model.toml` names its default mesh.
    Directory(PathBuf),
    /// One `.msh` file; the configuration is the `model.toml` in the same directory.
    File(PathBuf),
}

impl MeshSource {
    /// Interprets a `--mesh` argument; `None` means the embedded phantom.
    pub fn from_arg(arg: Option<&Path>) -> Self {
        match arg {
            None => MeshSource::Embedded,
            Some(p) if p.is_dir() => MeshSource::Directory(p.to_owned()),
            Some(p) => MeshSource::File(p.to_owned()),
        }
    }
}

impl std::fmt::Display for MeshSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MeshSource::Embedded => write!(f, "embedded:{EMBEDDED_NAME}"),
            MeshSource::Directory(p) | MeshSource::File(p) => write!(f, "{}", p.display()),
        }
    }
}

fn read(path: &Path) -> Result<Vec<u8>, MeshError> {
    std::fs::read(path).map_err(|source| MeshError::Io {
        path: path.display().to_string(),
        source,
    })
}

fn read_config(dir: &Path) -> Result<MeshConfig, MeshError> {
    let path = dir.join("model.toml");
    let bytes = read(&path).map_err(|e| match e {
        MeshError::Io { path, source } if source.kind() == std::io::ErrorKind::NotFound => MeshError::Config {
            path,
            message: "not found: every mesh needs a model.toml beside it (materials, prior, node sets); \
                      start from models/phantom-liver/model.toml"
                .to_owned(),
        },
        other => other,
    })?;
    let text = String::from_utf8(bytes).map_err(|_| MeshError::Config {
        path: path.display().to_string(),
        message: "not UTF-8 text".to_owned(),
    })?;
    MeshConfig::parse(&text, &path.display().to_string())
}

/// A mesh file, MSH or VTK by its extension, with its configuration. The file is read first: a
/// missing mesh is the error to report, not the configuration beside it.
fn load_file(path: &Path, config: impl FnOnce() -> Result<MeshConfig, MeshError>) -> Result<TetMesh, MeshError> {
    let bytes = read(path)?;
    let origin = path.display().to_string();
    match vtk::format(path) {
        Some(format) => TetMesh::from_vtk(&bytes, &origin, format, config()?),
        None => TetMesh::from_msh(&bytes, &origin, config()?),
    }
}

/// The text of the `model.toml` a source's mesh is configured by.
pub fn config_text(source: &MeshSource) -> Result<String, MeshError> {
    let dir = match source {
        MeshSource::Embedded => return Ok(EMBEDDED_CONFIG.to_owned()),
        MeshSource::Directory(dir) => dir.as_path(),
        MeshSource::File(path) => path
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new(".")),
    };
    let path = dir.join("model.toml");
    String::from_utf8(read(&path)?).map_err(|_| MeshError::Config {
        path: path.display().to_string(),
        message: "not UTF-8 text".to_owned(),
    })
}

/// Loads and validates the mesh a source names.
pub fn load(source: &MeshSource) -> Result<TetMesh, MeshError> {
    match source {
        MeshSource::Embedded => {
            let origin = source.to_string();
            let config = MeshConfig::parse(EMBEDDED_CONFIG, &origin)?;
            TetMesh::from_msh(EMBEDDED_MSH, &origin, config)
        }
        MeshSource::Directory(dir) => {
            let config = read_config(dir)?;
            load_file(&dir.join(&config.default_mesh), || Ok(config))
        }
        MeshSource::File(path) => {
            let dir = path
                .parent()
                .filter(|d| !d.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            load_file(path, || read_config(dir))
        }
    }
}
