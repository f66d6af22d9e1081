//! A reduced basis Φ beside a graph whose output is `coefficients` g (docs/design.md §7, `interaction`
//! form): the network's field is Φ g, multiplied here rather than in ONNX Runtime.
//!
//! `basis.safetensors` holds one tensor `basis`, f32 or f16, shaped [N, 3, M] (node-major), and the
//! metadata key `mesh_hash`, the content hash of the mesh it was made on. In memory the values are
//! rearranged into tiles (see [`TILE`]). The product streams the whole basis per request at the
//! speed the caches deliver it, so f16, half the bytes, is the faster where the CPU widens it in
//! hardware (F16C: 44 µs against 67 µs for f32 at M = 64 on the phantom; docs/training.md).
//! Accumulation is f32 either way.

use multiversion::multiversion;
use rayon::prelude::*;
use safetensors::SafeTensors;
use safetensors::tensor::Dtype;

use super::ModelLoadError;
use crate::mesh::TetMesh;

pub const FILE: &str = "basis.safetensors";
pub const TENSOR: &str = "basis";
pub const MESH_HASH_KEY: &str = "mesh_hash";

/// Most modes a basis may have.
pub const MAX_MODES: usize = 1024;
/// Nodes per tile. In memory Φ is stored in tiles of TILE nodes, mode-major within a tile
/// ([N/TILE, M, 3·TILE]): a tile's product is M multiply-adds of 48 contiguous values into 48
/// accumulators that stay in registers — no horizontal sums — and a tile of 64 f16 modes is 6 KB.
const TILE: usize = 16;
const TILE_ROWS: usize = 3 * TILE;
/// Below this many nodes one core is faster than waking another.
const PARALLEL_MIN_NODES: usize = 2048;
/// A node list at least 1/this of the mesh is answered from the whole-mesh product.
const DENSE_LIST_FRACTION: usize = 8;
/// Modes of an f16 tile widened at a time into an f32 scratch (48 × 8 values: 1.5 KB).
const WIDEN_MODES: usize = 8;

/// Basis values as stored: f32, or f16 as its bits (widened exactly in the product).
#[derive(Debug, Clone, PartialEq)]
enum Values {
    F32(Vec<f32>),
    F16(Vec<u16>),
}

/// Φ, [N, 3, M], held in tiles (see [`TILE`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Basis {
    nodes: usize,
    modes: usize,
    values: Values,
}

/// Index of node `n`'s component `c`, mode `m`, in the tiled layout.
fn tiled(n: usize, c: usize, m: usize, modes: usize) -> usize {
    (n / TILE) * modes * TILE_ROWS + m * TILE_ROWS + 3 * (n % TILE) + c
}

/// Rearranges node-major [N, 3, M] values into tiles, padding the last tile with zeros.
fn tile<T: Copy + Default>(values: &[T], nodes: usize, modes: usize) -> Vec<T> {
    let mut out = vec![T::default(); nodes.div_ceil(TILE) * TILE * 3 * modes];
    for n in 0..nodes {
        for c in 0..3 {
            for m in 0..modes {
                out[tiled(n, c, m, modes)] = values[(3 * n + c) * modes + m];
            }
        }
    }
    out
}

/// An f16's exact value as f32, branch-free so that the product's loop vectorizes: the magnitude's
/// bits shifted into f32 position and rescaled by 2¹¹² (which also handles subnormals and zero), then
/// the sign. Infinities and NaN are refused when the basis is read.
#[inline(always)]
fn widen(bits: u16) -> f32 {
    let magnitude = f32::from_bits(u32::from(bits & 0x7fff) << 13) * f32::from_bits(0x7780_0000);
    f32::from_bits(magnitude.to_bits() | (u32::from(bits & 0x8000) << 16))
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
        let (values, finite) = match view.dtype() {
            Dtype::F32 => {
                let v: Vec<f32> = data
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                let finite = v.iter().all(|x| x.is_finite());
                (Values::F32(tile(&v, n, modes)), finite)
            }
            Dtype::F16 => {
                let v: Vec<u16> = data.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
                // An all-ones exponent is an infinity or NaN.
                let finite = v.iter().all(|x| x & 0x7c00 != 0x7c00);
                (Values::F16(tile(&v, n, modes)), finite)
            }
            other => return Err(refuse(format!("{TENSOR} is {other:?}; expected F32 or F16"))),
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

    /// Adds Φ g at `nodes` (every node in order if `None`) to `out`, row-major (n, 3).
    pub fn add_product(&self, g: &[f32], nodes: Option<&[u32]>, out: &mut [f32]) {
        debug_assert_eq!(g.len(), self.modes, "coefficients do not match the basis");
        let tile_len = self.modes * TILE_ROWS;
        match nodes {
            None => {
                debug_assert_eq!(out.len(), 3 * self.nodes);
                let run = |(t, chunk): (usize, &mut [f32])| match &self.values {
                    Values::F32(v) => add_tile_f32(&v[t * tile_len..(t + 1) * tile_len], g, chunk),
                    Values::F16(v) => add_tile_f16(&v[t * tile_len..(t + 1) * tile_len], g, chunk),
                };
                if self.nodes >= PARALLEL_MIN_NODES {
                    out.par_chunks_mut(TILE_ROWS).enumerate().with_min_len(16).for_each(run);
                } else {
                    out.chunks_mut(TILE_ROWS).enumerate().for_each(run);
                }
            }
            // Many listed nodes (a surface) touch most tiles: the whole product, then their rows.
            Some(nodes) if nodes.len() * DENSE_LIST_FRACTION >= self.nodes => {
                let mut field = vec![0.0f32; 3 * self.nodes];
                self.add_product(g, None, &mut field);
                for (&n, dst) in nodes.iter().zip(out.chunks_exact_mut(3)) {
                    for (d, v) in dst.iter_mut().zip(&field[3 * n as usize..3 * n as usize + 3]) {
                        *d += v;
                    }
                }
            }
            // A few scattered nodes: each reads its three values per mode from its tile.
            Some(nodes) => match &self.values {
                Values::F32(v) => self.add_listed(nodes, g, out, |i| v[i]),
                Values::F16(v) => self.add_listed(nodes, g, out, |i| widen(v[i])),
            },
        }
    }

    fn add_listed(&self, nodes: &[u32], g: &[f32], out: &mut [f32], value: impl Fn(usize) -> f32) {
        for (&n, dst) in nodes.iter().zip(out.chunks_exact_mut(3)) {
            let first = tiled(n as usize, 0, 0, self.modes);
            for (m, &gm) in g.iter().enumerate() {
                let at = first + m * TILE_ROWS;
                for (c, d) in dst.iter_mut().enumerate() {
                    *d += gm * value(at + c);
                }
            }
        }
    }

    fn value(&self, index: usize) -> f32 {
        match &self.values {
            Values::F32(v) => v[index],
            Values::F16(v) => widen(v[index]),
        }
    }

    /// Φ's rows [n, 3, M] in f32 for `nodes` (every node in order if `None`), e.g. to upload them to
    /// a GPU.
    pub fn rows_f32(&self, nodes: Option<&[u32]>) -> Vec<f32> {
        let node_ids: Box<dyn Iterator<Item = usize>> = match nodes {
            Some(nodes) => Box::new(nodes.iter().map(|&n| n as usize)),
            None => Box::new(0..self.nodes),
        };
        node_ids
            .flat_map(|n| {
                (0..3).flat_map(move |c| (0..self.modes).map(move |m| self.value(tiled(n, c, m, self.modes))))
            })
            .collect()
    }
}

/// `out[r] += Σ_m g[m] · tile[m, r]` over one tile's rows (`out` is shorter in the last tile).
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn add_tile_f32(tile: &[f32], g: &[f32], out: &mut [f32]) {
    let mut acc = [0.0f32; TILE_ROWS];
    accumulate(tile, g, &mut acc);
    add_rows(&acc, out);
}

/// [`add_tile_f32`] over f16 bits. x86 CPUs with F16C widen eight values in one instruction, so the
/// product reads half the bytes at the f32 product's pace; elsewhere the bits are widened in software.
fn add_tile_f16(tile: &[u16], g: &[f32], out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if *HAS_F16C {
        // SAFETY: HAS_F16C says the CPU has every feature the function is compiled for.
        return unsafe { add_tile_f16c(tile, g, out) };
    }
    add_tile_f16_widened(tile, g, out)
}

/// Whether this CPU runs [`add_tile_f16c`], detected once rather than per tile.
#[cfg(target_arch = "x86_64")]
static HAS_F16C: std::sync::LazyLock<bool> = std::sync::LazyLock::new(|| {
    std::arch::is_x86_feature_detected!("f16c")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
});

/// [`add_tile_f32`] over f16 bits with F16C: per mode, six loads of eight halves, each widened and
/// multiply-added into one of six 8-lane accumulators (the tile's 48 rows).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn add_tile_f16c(tile: &[u16], g: &[f32], out: &mut [f32]) {
    use std::arch::x86_64::{__m128i, _mm_loadu_si128, _mm256_cvtph_ps, _mm256_fmadd_ps, _mm256_set1_ps};
    use std::arch::x86_64::{_mm256_setzero_ps, _mm256_storeu_ps};

    let mut acc = [_mm256_setzero_ps(); TILE_ROWS / 8];
    let (columns, _) = tile.as_chunks::<TILE_ROWS>();
    for (column, &gm) in columns.iter().zip(g) {
        let gm = _mm256_set1_ps(gm);
        let (eights, _) = column.as_chunks::<8>();
        for (a, eight) in acc.iter_mut().zip(eights) {
            // SAFETY: `eight` is 16 readable bytes; the load needs no alignment.
            let halves = unsafe { _mm_loadu_si128(eight.as_ptr().cast::<__m128i>()) };
            *a = _mm256_fmadd_ps(gm, _mm256_cvtph_ps(halves), *a);
        }
    }
    let mut sums = [0.0f32; TILE_ROWS];
    let (lanes, _) = sums.as_chunks_mut::<8>();
    for (lane, a) in lanes.iter_mut().zip(acc) {
        // SAFETY: `lane` is 32 writable bytes; the store needs no alignment.
        unsafe { _mm256_storeu_ps(lane.as_mut_ptr(), a) };
    }
    add_rows(&sums, out);
}

/// [`add_tile_f32`] over f16 bits widened in software: a few modes at a time into an f32 scratch
/// (a plain map that vectorizes), then multiplied as f32.
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn add_tile_f16_widened(tile: &[u16], g: &[f32], out: &mut [f32]) {
    let mut acc = [0.0f32; TILE_ROWS];
    let mut wide = [0.0f32; TILE_ROWS * WIDEN_MODES];
    for (chunk, gs) in tile.chunks(TILE_ROWS * WIDEN_MODES).zip(g.chunks(WIDEN_MODES)) {
        for (w, &bits) in wide.iter_mut().zip(chunk) {
            *w = widen(bits);
        }
        accumulate(&wide, gs, &mut acc);
    }
    add_rows(&acc, out);
}

/// `acc[r] += Σ_m g[m] · columns[m, r]` over columns of TILE_ROWS values (inlined into the
/// multiversioned callers, so it is compiled for their CPU features).
#[inline(always)]
fn accumulate(columns: &[f32], g: &[f32], acc: &mut [f32; TILE_ROWS]) {
    for (column, &gm) in columns.chunks_exact(TILE_ROWS).zip(g) {
        for r in 0..TILE_ROWS {
            acc[r] += gm * column[r];
        }
    }
}

#[inline(always)]
fn add_rows(acc: &[f32; TILE_ROWS], out: &mut [f32]) {
    for (o, a) in out.iter_mut().zip(acc) {
        *o += a;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every finite f16 widens to exactly the value the `half` crate gives.
    #[test]
    fn widening_is_exact_for_every_finite_f16() {
        for bits in 0..=u16::MAX {
            let reference = half::f16::from_bits(bits);
            if reference.is_finite() {
                assert_eq!(widen(bits).to_bits(), reference.to_f32().to_bits(), "bits {bits:#06x}");
            }
        }
    }

    /// The tiled product equals a plain sum over node-major rows, for every node and for a list, with
    /// a node count that leaves the last tile partial.
    #[test]
    fn the_tiled_product_equals_the_plain_sum() {
        let (nodes, modes) = (37, 5);
        let rows: Vec<f32> = (0..nodes * 3 * modes)
            .map(|i| ((i * 7919) % 101) as f32 / 50.0 - 1.0)
            .collect();
        let basis = Basis {
            nodes,
            modes,
            values: Values::F32(tile(&rows, nodes, modes)),
        };
        let g = [0.5f32, -1.25, 2.0, 0.125, -0.75];
        let expected: Vec<f32> = (0..3 * nodes)
            .map(|r| (0..modes).map(|m| rows[r * modes + m] * g[m]).sum())
            .collect();
        let mut all = vec![1.0f32; 3 * nodes];
        basis.add_product(&g, None, &mut all);
        let listed_nodes = [36u32, 0, 17, 17];
        let mut listed = vec![0.0f32; 3 * listed_nodes.len()];
        basis.add_product(&g, Some(&listed_nodes), &mut listed);
        for r in 0..3 * nodes {
            assert!((all[r] - 1.0 - expected[r]).abs() < 1e-5, "row {r}");
        }
        for (i, &n) in listed_nodes.iter().enumerate() {
            for c in 0..3 {
                assert!((listed[3 * i + c] - expected[3 * n as usize + c]).abs() < 1e-5);
            }
        }
        assert_eq!(basis.rows_f32(None), rows);
    }

    /// An f16 basis gives the plain sum over its widened values, on either kernel, whatever the CPU.
    #[test]
    fn both_f16_kernels_equal_the_plain_sum() {
        let (nodes, modes) = (TILE, 11);
        let bits: Vec<u16> = (0..nodes * 3 * modes)
            .map(|i| half::f16::from_f32(((i * 7919) % 101) as f32 / 50.0 - 1.0).to_bits())
            .collect();
        let tiled = tile(&bits, nodes, modes);
        let g: Vec<f32> = (0..modes).map(|m| (m as f32 * 0.37).cos()).collect();
        let expected: Vec<f32> = (0..3 * nodes)
            .map(|r| (0..modes).map(|m| widen(bits[r * modes + m]) * g[m]).sum())
            .collect();
        let mut kernels: Vec<(&str, Vec<f32>)> = Vec::new();
        let mut widened = vec![0.0f32; 3 * nodes];
        add_tile_f16_widened(&tiled, &g, &mut widened);
        kernels.push(("software", widened));
        #[cfg(target_arch = "x86_64")]
        if *HAS_F16C {
            let mut f16c = vec![0.0f32; 3 * nodes];
            // SAFETY: HAS_F16C says the CPU has the features.
            unsafe { add_tile_f16c(&tiled, &g, &mut f16c) };
            kernels.push(("f16c", f16c));
        }
        for (name, out) in kernels {
            for r in 0..3 * nodes {
                assert!(
                    (out[r] - expected[r]).abs() < 1e-5,
                    "{name} row {r}: {} vs {}",
                    out[r],
                    expected[r]
                );
            }
        }
    }
}
