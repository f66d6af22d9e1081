//! The gravity-preloaded equilibrium (docs/design.md §4): solved once per mesh and materials, cached, and
//! the state every nonlinear grasp starts from; grasp displacements are reported relative to it.

use std::path::{Path, PathBuf};

use super::FemError;
use super::nonlinear::{Equilibrium, Hyperelastic, Load, NewtonOptions};
use crate::mesh::TetMesh;

const MAGIC: &[u8; 8] = b"NAKPRE01";
/// Magic, node count, mesh hash, key hash.
const HEADER: usize = 8 + 8 + 64 + 64;

/// What the preloaded state depends on besides the geometry: Mooney–Rivlin constants and volumetric
/// law, body force and the fixed set. A cache made under another law has another key, so it is
/// never read for this one.
pub fn hyperelastic_hash(mesh: &TetMesh) -> String {
    let mut h = blake3::Hasher::new();
    h.update(b"nak-hyperelastic-v2");
    h.update(mesh.config.volumetric_law.name().as_bytes());
    for (name, m) in &mesh.config.materials {
        h.update(name.as_bytes());
        for v in [m.c10, m.c01, m.poisson_ratio] {
            h.update(&v.to_le_bytes());
        }
    }
    let body = &mesh.config.body;
    for v in [body.density, body.gravity[0], body.gravity[1], body.gravity[2]] {
        h.update(&v.to_le_bytes());
    }
    for n in mesh.node_sets.get("fixed").into_iter().flatten() {
        h.update(&n.to_le_bytes());
    }
    h.finalize().to_hex().to_string()
}

/// A hyperelastic mesh hanging in equilibrium under gravity.
pub struct Preloaded {
    pub solver: Hyperelastic,
    /// Displacement of the preloaded state from the reference (stress-free) configuration.
    pub rest: Vec<[f64; 3]>,
    pub path: PathBuf,
    /// How the preload was solved, when it was solved now rather than read from the cache.
    pub solved: Option<Equilibrium>,
}

impl Preloaded {
    pub fn load_or_compute(mesh: &TetMesh, cache_dir: &Path, options: NewtonOptions) -> Result<Self, FemError> {
        let key = hyperelastic_hash(mesh);
        let path = cache_dir.join(format!("preload-{}-{}.bin", &mesh.content_hash[..16], &key[..16]));
        let solver = Hyperelastic::new(mesh, true, options)?;
        if path.exists() {
            let rest = read(&path, mesh, &key)?;
            return Ok(Self {
                solver,
                rest,
                path,
                solved: None,
            });
        }
        let start = vec![[0.0; 3]; mesh.node_count()];
        let equilibrium = solver.solve(Load {
            start: &start,
            prescribed: &[],
            body_from: 0.0,
            body_to: 1.0,
        })?;
        tracing::info!(
            file = %path.display(),
            load_steps = equilibrium.stats.load_steps,
            newton_iterations = equilibrium.stats.newton_iterations,
            seconds = equilibrium.seconds,
            "gravity preload solved"
        );
        write(&path, mesh, &key, &equilibrium.displacement)?;
        Ok(Self {
            solver,
            rest: equilibrium.displacement.clone(),
            path,
            solved: Some(equilibrium),
        })
    }

    /// Moves `grasped` nodes by the given displacements from the preloaded state (gravity stays on)
    /// and returns the equilibrium with displacements (its path's too) relative to the preloaded state.
    pub fn grasp(&self, grasped: &[(u32, [f64; 3])]) -> Result<Equilibrium, FemError> {
        let prescribed: Vec<(u32, [f64; 3])> = grasped
            .iter()
            .map(|&(n, d)| (n, std::array::from_fn(|k| self.rest[n as usize][k] + d[k])))
            .collect();
        let mut result = self.solver.solve(Load {
            start: &self.rest,
            prescribed: &prescribed,
            body_from: 1.0,
            body_to: 1.0,
        })?;
        let states =
            std::iter::once(&mut result.displacement).chain(result.path.iter_mut().map(|s| &mut s.displacement));
        for state in states {
            for (u, r) in state.iter_mut().zip(&self.rest) {
                for k in 0..3 {
                    u[k] -= r[k];
                }
            }
        }
        Ok(result)
    }
}

fn read(path: &Path, mesh: &TetMesh, key: &str) -> Result<Vec<[f64; 3]>, FemError> {
    let corrupt = |message: &str| FemError::Cache {
        path: path.display().to_string(),
        message: format!("{message}; delete it to recompute"),
    };
    let bytes = std::fs::read(path).map_err(|source| FemError::Io {
        path: path.display().to_string(),
        source,
    })?;
    if bytes.len() != HEADER + 24 * mesh.node_count() || &bytes[..8] != MAGIC {
        return Err(corrupt("not a nak preload cache for this mesh, or truncated"));
    }
    if &bytes[16..80] != mesh.content_hash.as_bytes() || &bytes[80..144] != key.as_bytes() {
        return Err(corrupt("made for another mesh or materials"));
    }
    let values: Vec<f64> = bytemuck::pod_collect_to_vec(&bytes[HEADER..]);
    Ok(values.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}

fn write(path: &Path, mesh: &TetMesh, key: &str, rest: &[[f64; 3]]) -> Result<(), FemError> {
    let io = |p: &Path| {
        let p = p.display().to_string();
        move |source| FemError::Io { path: p, source }
    };
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let mut bytes = Vec::with_capacity(HEADER + 24 * rest.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&(mesh.node_count() as u64).to_le_bytes());
    bytes.extend_from_slice(mesh.content_hash.as_bytes());
    bytes.extend_from_slice(key.as_bytes());
    bytes.extend_from_slice(bytemuck::cast_slice(rest));
    // Written aside and renamed, so a reader never sees half a file.
    let tmp = super::cache_temporary(path);
    std::fs::write(&tmp, bytes).map_err(io(&tmp))?;
    std::fs::rename(&tmp, path).map_err(io(path))
}
