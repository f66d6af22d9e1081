//! Exact real-time linear models through Green's functions (docs/design.md §4; James & Pai's capacitance
//! matrix): `green-linear`, small-strain elasticity at the reference configuration, and
//! `green-tangent`, the hyperelastic model linearized about its gravity-preloaded equilibrium (the
//! exact answer of the nonlinear regime for small grasps).
//!
//! With G = K⁻¹ on the DOFs that are not fixed, the Dirichlet solution for grasped nodes S moved by
//! u_S is `u = G[:,S] (G[S,S])⁻¹ u_S`: the forces at S that produce u_S, applied through G. Columns of
//! G for every candidate grasp node are computed once (one sparse Cholesky, one solve per column),
//! cached on disk keyed by the mesh and the stiffness's own hash, and memory-mapped; a request is then
//! a 3K×3K solve and a dense 3N×3K product.

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use faer::Mat;
use memmap2::Mmap;
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use super::nonlinear::NewtonOptions;
use super::preload::{Preloaded, hyperelastic_hash};
use super::{FemError, LinearSystem};
use crate::mesh::TetMesh;

const MAGIC: &[u8; 8] = b"NAKGRN01";
/// Header bytes before the candidate list: magic, node count, candidate count, two 64-byte hashes.
const HEADER: usize = 8 + 8 + 8 + 64 + 64;
/// Surface nodes this close to a grasp region get columns too: grasps hold a region node and its
/// nearest neighbours, which may lie just outside the region.
const REACH_M: f64 = 0.015;
/// Right-hand sides solved together.
const BATCH: usize = 48;

/// Why Green's functions cannot answer a grasp.
#[derive(Debug, thiserror::Error)]
pub enum GreenError {
    #[error(
        "{model} has no Green's function for node {node}: it serves grasps within {reach_mm:.0} mm of the grasp \
         regions ({candidates} nodes)"
    )]
    NoColumn {
        model: &'static str,
        node: u32,
        reach_mm: f64,
        candidates: usize,
    },
    #[error("G[S,S] is not positive definite")]
    NotPositiveDefinite,
}

/// The stiffness K whose inverse the Green's functions are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stiffness {
    /// Small-strain linear elasticity at the reference configuration (model.toml's μ, ν).
    Linear,
    /// The Mooney–Rivlin tangent at the gravity-preloaded equilibrium: material and initial-stress
    /// stiffness in the sagged geometry, which is where nonlinear grasps start from.
    PreloadTangent,
}

impl Stiffness {
    /// The served model these Green's functions are.
    pub const fn model_name(self) -> &'static str {
        match self {
            Stiffness::Linear => "green-linear",
            Stiffness::PreloadTangent => "green-tangent",
        }
    }

    /// The hash of what K depends on besides the geometry.
    fn key(self, mesh: &TetMesh) -> String {
        match self {
            Stiffness::Linear => material_hash(mesh),
            Stiffness::PreloadTangent => hyperelastic_hash(mesh),
        }
    }

    /// Whether these Green's functions of `mesh` are in `cache_dir` already: loading them is then a
    /// mapping of the file, not a solve per column.
    pub fn cached(self, mesh: &TetMesh, cache_dir: &Path) -> bool {
        self.cache_file(mesh, &self.key(mesh), cache_dir).exists()
    }

    /// The cache file of these Green's functions, named by the mesh and `key` (see [`Stiffness::key`]).
    fn cache_file(self, mesh: &TetMesh, key: &str, cache_dir: &Path) -> PathBuf {
        let prefix = match self {
            Stiffness::Linear => "green",
            Stiffness::PreloadTangent => "green-tangent",
        };
        cache_dir.join(format!("{prefix}-{}-{}.bin", &mesh.content_hash[..16], &key[..16]))
    }

    /// K with the fixed nodes eliminated, factorized. The tangent needs the preloaded state, which is
    /// solved (and cached in `cache_dir`) if no earlier run did.
    fn system(self, mesh: &TetMesh, cache_dir: &Path) -> Result<LinearSystem, FemError> {
        match self {
            Stiffness::Linear => LinearSystem::new(mesh),
            Stiffness::PreloadTangent => {
                let preloaded = Preloaded::load_or_compute(mesh, cache_dir, NewtonOptions::default())?;
                let (tangent, _) = preloaded
                    .solver
                    .linearize(&preloaded.rest)
                    .ok_or_else(|| FemError::Assembly("the preloaded state has an inverted element".into()))?;
                LinearSystem::from_stiffness(preloaded.solver.dofs().clone(), &tangent)
            }
        }
    }
}

/// Columns of G for the candidate nodes, memory-mapped from the cache.
pub struct GreenFunctions {
    stiffness: Stiffness,
    nodes: usize,
    candidates: Vec<u32>,
    column_of: HashMap<u32, usize>,
    map: Mmap,
    data_offset: usize,
    pub path: PathBuf,
}

/// The hash of what G depends on besides the geometry: materials and the fixed set.
pub fn material_hash(mesh: &TetMesh) -> String {
    let mut h = blake3::Hasher::new();
    h.update(b"nak-linear-materials-v1");
    for (name, m) in &mesh.config.materials {
        h.update(name.as_bytes());
        for v in [m.shear_modulus, m.poisson_ratio] {
            h.update(&v.to_le_bytes());
        }
    }
    for n in mesh.node_sets.get("fixed").into_iter().flatten() {
        h.update(&n.to_le_bytes());
    }
    h.finalize().to_hex().to_string()
}

/// Grasp-region nodes and the surface nodes within [`REACH_M`] of them, sorted.
pub fn candidate_nodes(mesh: &TetMesh) -> Vec<u32> {
    let region_nodes: Vec<u32> = mesh
        .config
        .sampling
        .grasp_regions
        .iter()
        .filter_map(|r| mesh.node_sets.get(&r.node_set))
        .flatten()
        .copied()
        .collect();
    let near = |n: u32| {
        let p = mesh.positions[n as usize];
        region_nodes.iter().any(|&r| {
            let q = mesh.positions[r as usize];
            (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>() <= REACH_M * REACH_M
        })
    };
    mesh.surface_nodes.iter().copied().filter(|&n| near(n)).collect()
}

impl GreenFunctions {
    /// Loads the cached columns of `stiffness`'s inverse for `mesh` from `cache_dir`, computing and
    /// caching them first if needed; `progress(done, total)` reports the columns solved.
    pub fn load_or_compute(
        mesh: &TetMesh,
        stiffness: Stiffness,
        cache_dir: &Path,
        progress: impl Fn(usize, usize) + Sync,
    ) -> Result<Self, FemError> {
        let key = stiffness.key(mesh);
        let path = stiffness.cache_file(mesh, &key, cache_dir);
        if !path.exists() {
            let candidates = candidate_nodes(mesh);
            let started = Instant::now();
            let system = stiffness.system(mesh, cache_dir)?;
            compute(mesh, &system, &candidates, &key, &path, progress)?;
            tracing::info!(
                model = stiffness.model_name(),
                file = %path.display(),
                columns = 3 * candidates.len(),
                seconds = started.elapsed().as_secs_f64(),
                "Green's functions computed"
            );
        }
        Self::open(&path, mesh, stiffness, &key)
    }

    fn open(path: &Path, mesh: &TetMesh, stiffness: Stiffness, key: &str) -> Result<Self, FemError> {
        let origin = path.display().to_string();
        let corrupt = |message: &str| FemError::Cache {
            path: origin.clone(),
            message: format!("{message}; delete it to recompute"),
        };
        let file = std::fs::File::open(path).map_err(|source| FemError::Io {
            path: origin.clone(),
            source,
        })?;
        // SAFETY: the cache file is written once (atomically renamed into place) and never modified.
        let map = unsafe { Mmap::map(&file) }.map_err(|source| FemError::Io {
            path: origin.clone(),
            source,
        })?;
        if map.len() < HEADER || &map[..8] != MAGIC {
            return Err(corrupt("not a nak Green's function cache"));
        }
        let u64_at = |o: usize| u64::from_le_bytes(map[o..o + 8].try_into().unwrap_or_default()) as usize;
        let (nodes, count) = (u64_at(8), u64_at(16));
        if nodes != mesh.node_count() || &map[24..88] != mesh.content_hash.as_bytes() || &map[88..152] != key.as_bytes()
        {
            return Err(corrupt("made for another mesh or materials"));
        }
        let list_end = HEADER + 4 * count;
        let data_offset = list_end.div_ceil(64) * 64;
        if map.len() != data_offset + 4 * 3 * count * 3 * nodes {
            return Err(corrupt("truncated"));
        }
        let candidates: Vec<u32> = map[HEADER..list_end]
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let column_of = candidates.iter().enumerate().map(|(i, &n)| (n, i)).collect();
        Ok(Self {
            stiffness,
            nodes,
            candidates,
            column_of,
            map,
            data_offset,
            path: path.to_owned(),
        })
    }

    pub fn candidates(&self) -> &[u32] {
        &self.candidates
    }

    pub fn stiffness(&self) -> Stiffness {
        self.stiffness
    }

    /// Column of G for a unit force on (candidate index, component): 3N values.
    fn column(&self, candidate: usize, component: usize) -> &[f32] {
        let len = 3 * self.nodes;
        let start = self.data_offset + 4 * (3 * candidate + component) * len;
        bytemuck::cast_slice(&self.map[start..start + 4 * len])
    }

    /// For held nodes `held` moved by `moved` (metres), writes the displacement of the nodes `nodes`
    /// (all nodes when `None`) into `out`, and the force on each held node, `(G[S,S])⁻¹ u_S` (N),
    /// into `forces`.
    pub fn solve(
        &self,
        held: &[u32],
        moved: &[[f64; 3]],
        nodes: Option<&[u32]>,
        out: &mut [f32],
        forces: &mut Vec<[f64; 3]>,
    ) -> Result<(), GreenError> {
        let k = held.len();
        let mut columns = Vec::with_capacity(k);
        for &node in held {
            let c = self.column_of.get(&node).ok_or_else(|| GreenError::NoColumn {
                model: self.stiffness.model_name(),
                node,
                reach_mm: REACH_M * 1e3,
                candidates: self.candidates.len(),
            })?;
            columns.push(*c);
        }
        // G[S,S] (3K×3K, symmetric positive definite), then the forces f that produce u_S.
        let gss = DMatrix::<f64>::from_fn(3 * k, 3 * k, |r, c| {
            self.column(columns[c / 3], c % 3)[3 * held[r / 3] as usize + r % 3] as f64
        });
        let u = DVector::from_iterator(3 * k, moved.iter().flatten().copied());
        let forces_at_s = gss.cholesky().ok_or(GreenError::NotPositiveDefinite)?.solve(&u);
        forces.extend(forces_at_s.as_slice().chunks_exact(3).map(|f| [f[0], f[1], f[2]]));
        let weights: Vec<(usize, usize, f32)> = (0..3 * k)
            .map(|i| (columns[i / 3], i % 3, forces_at_s[i] as f32))
            .collect();
        match nodes {
            None => {
                // Rows split over cores; each adds the 3K weighted columns.
                out.par_chunks_mut(3 * 1024).enumerate().for_each(|(chunk, rows)| {
                    rows.fill(0.0);
                    let start = chunk * 3 * 1024;
                    for &(c, j, w) in &weights {
                        let col = &self.column(c, j)[start..start + rows.len()];
                        for (o, g) in rows.iter_mut().zip(col) {
                            *o += w * g;
                        }
                    }
                });
            }
            Some(nodes) => {
                for (row, &n) in out.chunks_exact_mut(3).zip(nodes) {
                    for (a, o) in row.iter_mut().enumerate() {
                        *o = weights
                            .iter()
                            .map(|&(c, j, w)| w * self.column(c, j)[3 * n as usize + a])
                            .sum();
                    }
                }
            }
        }
        Ok(())
    }
}

/// Solves for the columns in batches across cores and writes the cache file atomically.
fn compute(
    mesh: &TetMesh,
    system: &LinearSystem,
    candidates: &[u32],
    key: &str,
    path: &Path,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<(), FemError> {
    let n = mesh.node_count();
    let total = 3 * candidates.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let batches: Vec<Vec<f32>> = (0..total)
        .collect::<Vec<_>>()
        .par_chunks(BATCH)
        .map(|batch| {
            let mut rhs = Mat::<f64>::zeros(system.dofs.len(), batch.len());
            for (col, &c) in batch.iter().enumerate() {
                if let Some(dof) = system.dofs.get(candidates[c / 3], c % 3) {
                    rhs[(dof, col)] = 1.0;
                }
            }
            system.solve_in_place(&mut rhs);
            let mut out = vec![0.0f32; batch.len() * 3 * n];
            for col in 0..batch.len() {
                let dst = &mut out[col * 3 * n..(col + 1) * 3 * n];
                for node in 0..n as u32 {
                    for a in 0..3 {
                        if let Some(dof) = system.dofs.get(node, a) {
                            dst[3 * node as usize + a] = rhs[(dof, col)] as f32;
                        }
                    }
                }
            }
            let finished = done.fetch_add(batch.len(), std::sync::atomic::Ordering::Relaxed) + batch.len();
            progress(finished, total);
            out
        })
        .collect();

    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|source| FemError::Io {
        path: dir.display().to_string(),
        source,
    })?;
    let tmp = super::cache_temporary(path);
    let io = |source| FemError::Io {
        path: tmp.display().to_string(),
        source,
    };
    let mut file = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
    let mut header = Vec::with_capacity(HEADER + 4 * candidates.len() + 64);
    header.extend_from_slice(MAGIC);
    header.extend_from_slice(&(n as u64).to_le_bytes());
    header.extend_from_slice(&(candidates.len() as u64).to_le_bytes());
    header.extend_from_slice(mesh.content_hash.as_bytes());
    header.extend_from_slice(key.as_bytes());
    for c in candidates {
        header.extend_from_slice(&c.to_le_bytes());
    }
    header.resize(header.len().div_ceil(64) * 64, 0);
    file.write_all(&header).map_err(io)?;
    for batch in &batches {
        file.write_all(bytemuck::cast_slice(batch)).map_err(io)?;
    }
    file.flush().map_err(io)?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(|source| FemError::Io {
        path: path.display().to_string(),
        source,
    })
}
