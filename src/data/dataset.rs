//! Datasets of grasps and finite-element ground truth, in chunks readable from Rust and Python.
//!
//! A dataset directory holds `dataset.json` (mesh, regime, seed, sizes, split rule) and chunks
//! `chunk-NNNNN.safetensors` + `chunk-NNNNN.json`. A chunk's safetensors holds `displacement` f32
//! [B, N, 3] (the full field, metres); its JSON lists each sample: global index, subset (`single` or
//! `multi`), split (`train`, `val`, `test`), and its grasps (region, nodes, displacement). A chunk's
//! JSON is written last, by rename, so a chunk with a JSON is complete: generation resumes by skipping
//! those. `mesh.safetensors` carries the mesh as nak loaded it (node order, lumped nodal volumes,
//! surface nodes and normals, hash, prior), so training code reads the same geometry nak serves. Sample i is drawn from (seed, i), so a dataset is the same however often it was resumed,
//! and the linear and nonlinear sets of one seed hold the same grasps.

use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};

use super::shard::Shard;
use super::{GraspSampler, SamplingError};
use crate::engine::{Grasp, Regime};
use crate::fem::nonlinear::{Elimination, NewtonOptions, SolveStats};
use crate::mesh::{TetMesh, VolumetricLaw};

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Format { path: String, message: String },
    #[error(transparent)]
    Sampling(#[from] SamplingError),
    #[error("{0}")]
    Solver(String),
}

pub(crate) fn io(path: &Path) -> impl Fn(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.display().to_string(),
        source,
    }
}

pub(crate) fn format(path: &Path, message: impl std::fmt::Display) -> DatasetError {
    DatasetError::Format {
        path: path.display().to_string(),
        message: message.to_string(),
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetInfo {
    pub mesh_name: String,
    pub mesh_hash: String,
    pub node_count: usize,
    pub regime: String,
    pub seed: u64,
    pub single: usize,
    pub multi: usize,
    pub chunk_size: usize,
    /// How samples are assigned to splits (see [`split_of`]).
    pub split_rule: String,
    pub made_by: String,
    /// Limits the nonlinear solver ran with (absent in linear datasets).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub solver: Option<SolverLimits>,
    /// The hyperelastic law's volumetric term the fields were solved under (nonlinear datasets;
    /// [`read_info`] fills in the law of nonlinear datasets made before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volumetric_law: Option<VolumetricLaw>,
    /// Which shard of the dataset this directory holds (absent in a whole or joined dataset).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<Shard>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SolverLimits {
    pub max_newton_iterations: usize,
    pub max_step_cuts: usize,
    /// Absent in datasets made before it could be set: they used 1e-3.
    #[serde(default = "default_intermediate_tolerance")]
    pub intermediate_tolerance: f64,
    /// How the graspers' neighbourhood was eliminated; `null`, or absent in datasets made before
    /// it existed, when it was not.
    #[serde(default)]
    pub elimination: Option<Elimination>,
    /// The longest load step, as a fraction of the grasp; absent in datasets made before it could
    /// be set: they let steps grow to the whole grasp.
    #[serde(default = "default_max_load_step")]
    pub max_load_step: f64,
}

fn default_max_load_step() -> f64 {
    NewtonOptions::default().max_load_step
}

fn default_intermediate_tolerance() -> f64 {
    NewtonOptions::default().intermediate_tolerance
}

/// The fields in which two datasets' descriptions differ (`a` first), for refusals.
pub fn differences(a: &DatasetInfo, b: &DatasetInfo) -> String {
    let (a, b) = (
        serde_json::to_value(a).unwrap_or_default(),
        serde_json::to_value(b).unwrap_or_default(),
    );
    let (Some(a), Some(b)) = (a.as_object(), b.as_object()) else {
        return String::new();
    };
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    let show = |v: Option<&serde_json::Value>| v.map_or("absent".to_owned(), ToString::to_string);
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| format!("{k} {} against {}", show(a.get(k)), show(b.get(k))))
        .collect::<Vec<_>>()
        .join("; ")
}

impl DatasetInfo {
    pub fn total(&self) -> usize {
        self.single + self.multi
    }

    pub fn chunks(&self) -> usize {
        self.total().div_ceil(self.chunk_size)
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspRecord {
    pub region: String,
    pub nodes: Vec<u32>,
    pub displacement: [f64; 3],
    /// The force (N) the grasper exerts on the tissue, from the finite elements (linear: K·u at the
    /// held nodes; nonlinear: internal minus body force there). Absent in datasets made before nak
    /// stored forces, and where the solve failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force: Option<[f64; 3]>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SampleRecord {
    pub index: u64,
    pub subset: String,
    pub split: String,
    pub grasps: Vec<GraspRecord>,
    /// How the nonlinear solver fared (absent in linear datasets).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub solver: Option<SolveRecord>,
}

/// The nonlinear solve of one sample. A failed sample keeps its place in the dataset with a NaN
/// field and the reason here, so nothing is silently dropped or replaced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SolveRecord {
    #[serde(flatten)]
    pub stats: SolveStats,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
}

impl SampleRecord {
    pub fn failed(&self) -> bool {
        self.solver.as_ref().is_some_and(|s| s.failure.is_some())
    }

    /// Every grasped node with its displacement.
    pub fn prescribed(&self) -> Vec<(u32, [f64; 3])> {
        self.grasps
            .iter()
            .flat_map(|g| g.nodes.iter().map(move |&n| (n, g.displacement)))
            .collect()
    }

    /// Sets each grasp's force from the force at each held node; a node held by two grasps counts
    /// for the first, as the server counts it.
    pub fn set_forces(&mut self, force_at: impl Fn(u32) -> [f64; 3]) {
        let mut counted = std::collections::HashSet::new();
        for grasp in &mut self.grasps {
            let mut total = [0.0; 3];
            for &n in grasp.nodes.iter().filter(|&&n| counted.insert(n)) {
                let f = force_at(n);
                for k in 0..3 {
                    total[k] += f[k];
                }
            }
            grasp.force = Some(total);
        }
    }

    /// Each grasp's stored force, if every grasp has one.
    pub fn forces(&self) -> Option<Vec<[f64; 3]>> {
        self.grasps.iter().map(|g| g.force).collect()
    }

    pub fn grasps(&self) -> Vec<Grasp> {
        self.grasps
            .iter()
            .map(|g| Grasp {
                nodes: g.nodes.clone(),
                displacement: g.displacement,
                ..Grasp::default()
            })
            .collect()
    }
}

/// 13 in 16 samples train, 2 validate, 1 tests (81.25 / 12.5 / 6.25 %), by a fixed hash of the
/// sample index (so a split does not depend on the dataset's size).
pub fn split_of(index: u64) -> &'static str {
    match index.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 60 {
        0..=12 => "train",
        13..=14 => "val",
        _ => "test",
    }
}

pub const SPLIT_RULE: &str = "(index * 0x9E3779B97F4A7C15) >> 60: 0-12 train, 13-14 val, 15 test";

/// The grasps of sample `index`: single-grasper samples first, then multi-grasper ones.
pub fn draw(sampler: &GraspSampler, info: &DatasetInfo, index: u64) -> Result<SampleRecord, DatasetError> {
    let multi = index as usize >= info.single;
    let grasps = sampler
        .sample(info.seed, index, if multi { 2 } else { 1 })?
        .into_iter()
        .map(|(region, g)| GraspRecord {
            region: sampler.regions()[region].name.clone(),
            nodes: g.nodes,
            displacement: g.displacement,
            force: None,
        })
        .collect();
    Ok(SampleRecord {
        index,
        subset: if multi { "multi" } else { "single" }.to_owned(),
        split: split_of(index).to_owned(),
        grasps,
        solver: None,
    })
}

pub fn chunk_paths(dir: &Path, chunk: usize) -> (PathBuf, PathBuf) {
    (
        dir.join(format!("chunk-{chunk:05}.safetensors")),
        dir.join(format!("chunk-{chunk:05}.json")),
    )
}

/// A converged state on the way to a sample's whole grasp: its grasps moved by `load` times their
/// displacements, and the organ's field then (f32, [N × 3]).
#[derive(Debug, Clone, PartialEq)]
pub struct PathField {
    pub sample: u64,
    pub load: f64,
    pub field: Vec<f32>,
}

/// Where a chunk's path states live, beside the chunk (`nak datagen`'s nonlinear solves write them).
pub fn path_states_path(dir: &Path, chunk: usize) -> PathBuf {
    dir.join(format!("chunk-{chunk:05}.path.safetensors"))
}

/// Writes a chunk's path states: `displacement` f32 [P, N, 3], `sample` i64 [P] (the sample each
/// state is on the way to), `load` f64 [P]. Written before the chunk's JSON, which marks it complete.
pub fn write_path_states(
    dir: &Path,
    chunk: usize,
    node_count: usize,
    states: &[PathField],
) -> Result<(), DatasetError> {
    let path = path_states_path(dir, chunk);
    let flat: Vec<f32> = states.iter().flat_map(|s| s.field.iter().copied()).collect();
    let samples: Vec<i64> = states.iter().map(|s| s.sample as i64).collect();
    let loads: Vec<f64> = states.iter().map(|s| s.load).collect();
    let view = |dtype, shape, bytes| TensorView::new(dtype, shape, bytes).map_err(|e| format(&path, e));
    let tensors = [
        (
            "displacement",
            view(
                Dtype::F32,
                vec![states.len(), node_count, 3],
                bytemuck::cast_slice(&flat),
            )?,
        ),
        (
            "sample",
            view(Dtype::I64, vec![states.len()], bytemuck::cast_slice(&samples))?,
        ),
        (
            "load",
            view(Dtype::F64, vec![states.len()], bytemuck::cast_slice(&loads))?,
        ),
    ];
    let bytes = safetensors::serialize(tensors, None).map_err(|e| format(&path, e))?;
    std::fs::write(&path, bytes).map_err(io(&path))
}

/// Writes one chunk; the JSON goes last, by rename, marking the chunk complete.
pub fn write_chunk(
    dir: &Path,
    chunk: usize,
    node_count: usize,
    samples: &[SampleRecord],
    fields: &[Vec<f32>],
) -> Result<(), DatasetError> {
    let (tensors, json) = chunk_paths(dir, chunk);
    let flat: Vec<f32> = fields.iter().flatten().copied().collect();
    let view = TensorView::new(
        Dtype::F32,
        vec![samples.len(), node_count, 3],
        bytemuck::cast_slice(&flat),
    )
    .map_err(|e| format(&tensors, e))?;
    let bytes = safetensors::serialize([("displacement", view)], None).map_err(|e| format(&tensors, e))?;
    std::fs::write(&tensors, bytes).map_err(io(&tensors))?;
    let tmp = json.with_extension("json.partial");
    let text = serde_json::to_string(samples).map_err(|e| format(&json, e))?;
    std::fs::write(&tmp, text).map_err(io(&tmp))?;
    std::fs::rename(&tmp, &json).map_err(io(&json))
}

pub fn read_info(dir: &Path) -> Result<DatasetInfo, DatasetError> {
    let path = dir.join("dataset.json");
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    let mut info: DatasetInfo = serde_json::from_str(&text).map_err(|e| format(&path, e))?;
    // Nonlinear data from before the law was recorded was solved under (κ/2)(J − 1)².
    if info.regime == Regime::Nonlinear.name() && info.volumetric_law.is_none() {
        info.volumetric_law = Some(VolumetricLaw::JMinusOneSquared);
    }
    Ok(info)
}

pub fn write_info(dir: &Path, info: &DatasetInfo) -> Result<(), DatasetError> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let path = dir.join("dataset.json");
    let text = serde_json::to_string_pretty(info).map_err(|e| format(&path, e))?;
    std::fs::write(&path, text + "\n").map_err(io(&path))
}

/// Writes `mesh.safetensors`: `positions` f64 [N, 3], `nodal_volumes` f64 [N], `surface_nodes` u32 [S],
/// `normals` f64 [N, 3], `tets` u32 [T, 4] (graph networks read the mesh's edges from them); metadata: name, content hash, the prior (ν, ε, λ) and the grasp neighbour range.
pub fn write_mesh(dir: &Path, mesh: &TetMesh) -> Result<(), DatasetError> {
    let path = dir.join("mesh.safetensors");
    let positions: Vec<f64> = mesh.positions.as_flattened().to_vec();
    let normals: Vec<f64> = mesh.normals.as_flattened().to_vec();
    let n = mesh.node_count();
    let views = [
        (
            "positions",
            Dtype::F64,
            vec![n, 3],
            bytemuck::cast_slice::<f64, u8>(&positions),
        ),
        (
            "nodal_volumes",
            Dtype::F64,
            vec![n],
            bytemuck::cast_slice(&mesh.nodal_volumes),
        ),
        (
            "surface_nodes",
            Dtype::U32,
            vec![mesh.surface_nodes.len()],
            bytemuck::cast_slice(&mesh.surface_nodes),
        ),
        ("normals", Dtype::F64, vec![n, 3], bytemuck::cast_slice(&normals)),
        (
            "tets",
            Dtype::U32,
            vec![mesh.tets.len(), 4],
            bytemuck::cast_slice(&mesh.tets),
        ),
    ]
    .into_iter()
    .map(|(name, dtype, shape, data)| Ok((name, TensorView::new(dtype, shape, data).map_err(|e| format(&path, e))?)))
    .collect::<Result<Vec<_>, DatasetError>>()?;
    let prior = mesh.config.prior;
    let (fewest, most) = mesh.config.sampling.neighbours;
    let metadata = [
        ("name", mesh.config.name.clone()),
        ("content_hash", mesh.content_hash.clone()),
        ("poisson_ratio", prior.poisson_ratio.to_string()),
        ("epsilon_m", prior.epsilon.to_string()),
        ("lambda", prior.lambda.to_string()),
        ("neighbours_min", fewest.to_string()),
        ("neighbours_max", most.to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect();
    let bytes = safetensors::serialize(views, Some(metadata)).map_err(|e| format(&path, e))?;
    std::fs::write(&path, bytes).map_err(io(&path))
}

/// Whether two `mesh.safetensors` hold the same tensors and metadata. Their bytes may differ: the
/// metadata is a hash map whose order changes from process to process.
pub fn same_mesh_file(a: &[u8], b: &[u8]) -> bool {
    let contents = |bytes| {
        let (_, metadata) = SafeTensors::read_metadata(bytes).ok()?;
        let tensors = SafeTensors::deserialize(bytes).ok()?;
        let mut views: Vec<_> = tensors
            .tensors()
            .into_iter()
            .map(|(name, view)| (name, view.dtype(), view.shape().to_vec(), view.data().to_vec()))
            .collect();
        views.sort_by(|x, y| x.0.cmp(&y.0));
        Some((metadata.metadata().clone(), views))
    };
    matches!((contents(a), contents(b)), (Some(x), Some(y)) if x == y)
}

/// The samples of one complete chunk and their fields ([N, 3] each).
pub fn read_chunk(dir: &Path, chunk: usize, node_count: usize) -> Result<Vec<(SampleRecord, Vec<f32>)>, DatasetError> {
    let (tensors, json) = chunk_paths(dir, chunk);
    let samples: Vec<SampleRecord> =
        serde_json::from_str(&std::fs::read_to_string(&json).map_err(io(&json))?).map_err(|e| format(&json, e))?;
    let bytes = std::fs::read(&tensors).map_err(io(&tensors))?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| format(&tensors, e))?;
    let view = st.tensor("displacement").map_err(|e| format(&tensors, e))?;
    if view.dtype() != Dtype::F32 || view.shape() != [samples.len(), node_count, 3] {
        return Err(format(
            &tensors,
            format!("displacement is {:?} {:?}", view.dtype(), view.shape()),
        ));
    }
    // safetensors data is little-endian, as is every host nak builds for (see wire::convert).
    let values: Vec<f32> = bytemuck::pod_collect_to_vec(view.data());
    Ok(samples
        .into_iter()
        .zip(values.chunks_exact(3 * node_count).map(<[f32]>::to_vec))
        .collect())
}

/// Chunks already complete in `dir`.
pub fn complete_chunks(dir: &Path, chunks: usize) -> Vec<bool> {
    (0..chunks).map(|c| chunk_paths(dir, c).1.is_file()).collect()
}
