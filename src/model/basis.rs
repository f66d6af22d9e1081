//! A reduced basis Φ beside a graph whose output is `coefficients` g (DESIGN.md §7, `interaction`
//! form): the network's field is Φ g, multiplied here rather than in ONNX Runtime.
//!
//! `basis.safetensors` holds one tensor `basis`, f32 or f16, shaped [N, 3, M] — node-major, so a
//! node's three rows are 3·M contiguous values and any subset of nodes (a surface or a listed
//! selection) costs only its own rows — and the metadata key `mesh_hash`, the content hash of the
//! mesh it was made on. The product is memory-bound (9,701 × 3 × 64 values: 7.4 MB in f32, 3.7 MB in
//! f16), so f16 storage halves its time; accumulation is f32 either way.

use half::f16;
use half::slice::HalfFloatSliceExt;
use multiversion::multiversion;
use rayon::prelude::*;
use safetensors::SafeTensors;
use safetensors::tensor::Dtype;

use super::ModelLoadError;
use crate::mesh::TetMesh;

pub const FILE: &str = "basis.safetensors";
pub const TENSOR: &str = "basis";
pub const MESH_HASH_KEY: &str = "mesh_hash";

/// Nodes per unit of work: 16 nodes of 3 × 64 f16 values (6 KB) convert to f32 within L1.
const NODES_PER_BLOCK: usize = 16;
/// Below this many nodes one core is faster than waking another.
const PARALLEL_MIN_NODES: usize = 2048;
/// Most modes a basis may have: the f16 conversion buffer holds at least 16 rows of this many.
pub const MAX_MODES: usize = 768;
/// Independent accumulators per dot product: wide enough for one AVX-512 register, and what lets
/// the compiler vectorize an f32 sum without reassociating it.
const LANES: usize = 16;

#[derive(Debug, Clone, PartialEq)]
enum Values {
    F32(Vec<f32>),
    F16(Vec<f16>),
}

/// Φ, [N, 3, M] node-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Basis {
    nodes: usize,
    modes: usize,
    values: Values,
}

impl Basis {
    /// Reads a basis file's bytes; `origin` names the file in errors. Refuses another mesh's basis,
    /// a shape other than [N, 3, M] for the served mesh, and values that are not finite.
    pub fn parse(bytes: &[u8], mesh: &TetMesh, origin: &str) -> Result<Self, ModelLoadError> {
        let refuse = |message: String| ModelLoadError::new(origin, message);
        let (_, metadata) =
            SafeTensors::read_metadata(bytes).map_err(|e| refuse(format!("not a safetensors file ({e})")))?;
        let hash = metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get(MESH_HASH_KEY))
            .ok_or_else(|| {
                refuse(format!(
                    "metadata has no {MESH_HASH_KEY:?}: which mesh is this basis for?"
                ))
            })?;
        if *hash != mesh.content_hash {
            return Err(refuse(format!(
                "made for mesh {hash}; the served mesh {:?} is {}",
                mesh.config.name, mesh.content_hash
            )));
        }
        let tensors = SafeTensors::deserialize(bytes).map_err(|e| refuse(format!("unreadable ({e})")))?;
        let view = tensors
            .tensor(TENSOR)
            .map_err(|_| refuse(format!("no tensor {TENSOR:?}")))?;
        let n = mesh.node_count();
        let modes = match view.shape() {
            [nodes, 3, modes] if *nodes == n && (1..=MAX_MODES).contains(modes) => *modes,
            shape => {
                return Err(refuse(format!(
                    "{TENSOR} is {shape:?}; expected [{n}, 3, M] for the served mesh's {n} nodes, \
                     1 <= M <= {MAX_MODES}"
                )));
            }
        };
        let data = view.data();
        let values = match view.dtype() {
            Dtype::F32 => Values::F32(
                data.chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
            ),
            Dtype::F16 => Values::F16(data.chunks_exact(2).map(|b| f16::from_le_bytes([b[0], b[1]])).collect()),
            other => return Err(refuse(format!("{TENSOR} is {other:?}; expected F32 or F16"))),
        };
        let finite = match &values {
            Values::F32(v) => v.iter().all(|x| x.is_finite()),
            Values::F16(v) => v.iter().all(|x| x.is_finite()),
        };
        if !finite {
            return Err(refuse(format!("{TENSOR} holds values that are not finite")));
        }
        Ok(Basis {
            nodes: n,
            modes,
            values,
        })
    }

    /// M, the number of coefficients the graph must give.
    pub fn modes(&self) -> usize {
        self.modes
    }

    /// "f32" or "f16".
    pub fn precision(&self) -> &'static str {
        match self.values {
            Values::F32(_) => "f32",
            Values::F16(_) => "f16",
        }
    }

    /// Bytes of basis a whole-mesh product reads.
    pub fn size_bytes(&self) -> usize {
        match &self.values {
            Values::F32(v) => 4 * v.len(),
            Values::F16(v) => 2 * v.len(),
        }
    }

    /// Adds Φ g at `nodes` (every node in order if `None`) to `out`, row-major (n, 3).
    pub fn add_product(&self, g: &[f32], nodes: Option<&[u32]>, out: &mut [f32]) {
        debug_assert_eq!(g.len(), self.modes, "coefficients do not match the basis");
        let row = 3 * self.modes;
        match (nodes, &self.values) {
            (None, values) => {
                debug_assert_eq!(out.len(), 3 * self.nodes);
                let block = |(b, chunk): (usize, &mut [f32])| {
                    let first = b * NODES_PER_BLOCK;
                    let count = chunk.len() / 3;
                    match values {
                        Values::F32(v) => add_rows_f32(&v[first * row..(first + count) * row], g, chunk),
                        Values::F16(v) => add_rows_f16(&v[first * row..(first + count) * row], g, chunk),
                    }
                };
                if self.nodes >= PARALLEL_MIN_NODES {
                    out.par_chunks_mut(3 * NODES_PER_BLOCK)
                        .enumerate()
                        .with_min_len(8)
                        .for_each(block);
                } else {
                    out.chunks_mut(3 * NODES_PER_BLOCK).enumerate().for_each(block);
                }
            }
            // Listed nodes are few and scattered: one node's rows at a time, on this core.
            (Some(nodes), Values::F32(v)) => {
                for (&n, dst) in nodes.iter().zip(out.chunks_exact_mut(3)) {
                    let n = n as usize;
                    add_rows_f32(&v[n * row..(n + 1) * row], g, dst);
                }
            }
            (Some(nodes), Values::F16(v)) => {
                for (&n, dst) in nodes.iter().zip(out.chunks_exact_mut(3)) {
                    let n = n as usize;
                    add_rows_f16(&v[n * row..(n + 1) * row], g, dst);
                }
            }
        }
    }

    /// Φ's rows [n, 3, M] in f32 for `nodes` (every node in order if `None`), e.g. to upload them to
    /// a GPU.
    pub fn rows_f32(&self, nodes: Option<&[u32]>) -> Vec<f32> {
        let row = 3 * self.modes;
        let all: Vec<u32>;
        let nodes = match nodes {
            Some(nodes) => nodes,
            None => {
                all = (0..self.nodes as u32).collect();
                &all
            }
        };
        let mut out = Vec::with_capacity(nodes.len() * row);
        for &n in nodes {
            let range = n as usize * row..(n as usize + 1) * row;
            match &self.values {
                Values::F32(v) => out.extend_from_slice(&v[range]),
                Values::F16(v) => out.extend(v[range].iter().map(|x| x.to_f32())),
            }
        }
        out
    }
}

/// `out[r] += rows[r, :] · g` for consecutive rows of M values (`rows.len() == out.len() * M`).
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn add_rows_f32(rows: &[f32], g: &[f32], out: &mut [f32]) {
    for (row, o) in rows.chunks_exact(g.len()).zip(out.iter_mut()) {
        *o += dot(row, g);
    }
}

/// [`add_rows_f32`] over f16 rows: converted a block at a time (F16C where the CPU has it).
fn add_rows_f16(rows: &[f16], g: &[f32], out: &mut [f32]) {
    let mut converted = [0.0f32; 16 * MAX_MODES];
    let per_chunk = converted.len() / g.len();
    for (chunk, o) in rows.chunks(per_chunk * g.len()).zip(out.chunks_mut(per_chunk)) {
        let buffer = &mut converted[..chunk.len()];
        chunk.convert_to_f32_slice(buffer);
        add_rows_f32(buffer, g, o);
    }
}

#[inline(always)]
fn dot(row: &[f32], g: &[f32]) -> f32 {
    let mut acc = [0.0f32; LANES];
    let whole = row.len() / LANES * LANES;
    for (r, w) in row[..whole].chunks_exact(LANES).zip(g[..whole].chunks_exact(LANES)) {
        for l in 0..LANES {
            acc[l] += r[l] * w[l];
        }
    }
    let tail: f32 = row[whole..].iter().zip(&g[whole..]).map(|(r, w)| r * w).sum();
    acc.iter().sum::<f32>() + tail
}
