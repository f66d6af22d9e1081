//! Triangular solves with a supernodal Cholesky factor in f32, the preconditioner every
//! conjugate-gradient iteration of a Newton solve applies.
//!
//! faer's own solve dispatches a general matrix product and a triangular solve for each supernode
//! (the phantom's factor has 4,047, 3,316 of them one node wide) and takes 6.4 ms on the phantom's
//! 44 MB factor, where two plain passes over it take 2.0 ms (2-vCPU AMD EPYC; `cargo bench --bench
//! fem`). Here each sweep is one loop over the supernodes, compiled once per instruction set: a
//! supernode's part of the vector is copied beside the rows below it, so that each group of
//! [`SWEEP`] columns is one stream down the factor, and the solve takes 5.0 ms.

use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};
use multiversion::multiversion;

/// Columns swept together in the off-diagonal products: four streams over the factor at once,
/// sharing each pass over the short vector they update or read.
const SWEEP: usize = 4;

/// The layout of a supernodal factor's values: each supernode is a column-major block of
/// (width + pattern) rows by width columns, its top square holding the diagonal block.
#[derive(Debug, Clone)]
pub struct SupernodalLayout {
    /// First column of each supernode, and one past the last.
    begin: Vec<usize>,
    /// Where each supernode's values start, and one past the last.
    value_start: Vec<usize>,
    /// Where each supernode's off-diagonal row indices start in `rows`.
    row_start: Vec<usize>,
    /// Row indices below each supernode's diagonal block.
    rows: Vec<u32>,
    /// The most rows of any supernode: the scratch a sweep needs.
    tallest: usize,
}

impl SupernodalLayout {
    /// The layout of `symbolic`, or `None` for a simplicial factor (faer chooses one only for very
    /// sparse matrices, which the tangents of a tetrahedral mesh are not).
    pub fn new(symbolic: &SymbolicCholesky<usize>) -> Option<Self> {
        let SymbolicCholeskyRaw::Supernodal(s) = symbolic.raw() else {
            return None;
        };
        let count = s.n_supernodes();
        let mut begin: Vec<usize> = s.supernode_begin().to_vec();
        begin.push(s.supernode_end()[count - 1]);
        let value_start = s.col_ptr_for_val()[..=count].to_vec();
        let row_start = s.col_ptr_for_row_idx()[..=count].to_vec();
        let rows: Vec<u32> = s.row_idx().iter().map(|&r| r as u32).collect();
        let tallest = (0..count)
            .map(|k| begin[k + 1] - begin[k] + row_start[k + 1] - row_start[k])
            .max()
            .unwrap_or(0);
        Some(Self {
            begin,
            value_start,
            row_start,
            rows,
            tallest,
        })
    }

    /// x ← (L Lᵀ)⁻¹ x for the factor `values` of this layout; `scratch` is reused between calls.
    pub fn solve_in_place(&self, values: &[f32], x: &mut [f32], scratch: &mut Vec<f32>) {
        scratch.resize(self.tallest, 0.0);
        forward(self, values, x, scratch);
        backward(self, values, x, scratch);
    }

    fn supernode(&self, k: usize) -> (usize, usize, &[u32], usize) {
        let pattern = &self.rows[self.row_start[k]..self.row_start[k + 1]];
        (
            self.begin[k],
            self.begin[k + 1] - self.begin[k],
            pattern,
            self.value_start[k],
        )
    }
}

/// L y = b, supernode by supernode: its columns' part of x copied beside the rows below them, each
/// group of [`SWEEP`] columns solved in its small triangle and then subtracted from every row
/// beneath it in one pass, the rows below scattered back.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn forward(layout: &SupernodalLayout, values: &[f32], x: &mut [f32], work: &mut [f32]) {
    for k in 0..layout.begin.len() - 1 {
        let (first, width, pattern, start) = layout.supernode(k);
        let height = width + pattern.len();
        let block = &values[start..start + height * width];
        let work = &mut work[..height];
        work[..width].copy_from_slice(&x[first..first + width]);
        work[width..].fill(0.0);
        let mut j = 0;
        while j < width {
            let group = SWEEP.min(width - j);
            let column = |q: usize| &block[(j + q) * height..(j + q + 1) * height];
            for q in 0..group {
                let c = column(q);
                let v = work[j + q] / c[j + q];
                work[j + q] = v;
                for r in q + 1..group {
                    work[j + r] -= c[j + r] * v;
                }
            }
            let below = j + group;
            if group == SWEEP {
                let v: [f32; SWEEP] = std::array::from_fn(|q| -work[j + q]);
                let c: [&[f32]; SWEEP] = std::array::from_fn(|q| &column(q)[below..]);
                axpy4(&mut work[below..], c, v);
            } else {
                for q in 0..group {
                    let v = -work[j + q];
                    for (w, l) in work[below..].iter_mut().zip(&column(q)[below..]) {
                        *w += l * v;
                    }
                }
            }
            j += group;
        }
        x[first..first + width].copy_from_slice(&work[..width]);
        for (&row, w) in pattern.iter().zip(&work[width..]) {
            x[row as usize] += w;
        }
    }
}

/// Lᵀ x = y, supernodes in reverse: the rows below gathered beside the supernode's columns, then
/// from the last group of [`SWEEP`] columns to the first, their products with every row beneath them
/// in one pass, and their small triangle.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn backward(layout: &SupernodalLayout, values: &[f32], x: &mut [f32], work: &mut [f32]) {
    for k in (0..layout.begin.len() - 1).rev() {
        let (first, width, pattern, start) = layout.supernode(k);
        let height = width + pattern.len();
        let block = &values[start..start + height * width];
        let work = &mut work[..height];
        work[..width].copy_from_slice(&x[first..first + width]);
        for (w, &row) in work[width..].iter_mut().zip(pattern) {
            *w = x[row as usize];
        }
        let mut end = width;
        while end > 0 {
            let group = SWEEP.min(end);
            let j = end - group;
            let column = |q: usize| &block[(j + q) * height..(j + q + 1) * height];
            let (head, tail) = work.split_at_mut(end);
            if group == SWEEP {
                let c: [&[f32]; SWEEP] = std::array::from_fn(|q| &column(q)[end..]);
                let sums = dots(c, tail);
                for q in 0..SWEEP {
                    head[j + q] -= sums[q];
                }
            } else {
                for q in 0..group {
                    head[j + q] -= dot(&column(q)[end..], tail);
                }
            }
            for q in (0..group).rev() {
                let c = column(q);
                let mut v = head[j + q];
                for r in q + 1..group {
                    v -= c[j + r] * head[j + r];
                }
                head[j + q] = v / c[j + q];
            }
            end = j;
        }
        x[first..first + width].copy_from_slice(&work[..width]);
    }
}

/// Lanes summed separately, so that the compiler may vectorize a floating-point reduction.
const LANES: usize = 16;

#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; LANES];
    let (a_chunks, a_rest) = a.as_chunks::<LANES>();
    let (b_chunks, b_rest) = b[..a.len()].as_chunks::<LANES>();
    for (x, y) in a_chunks.iter().zip(b_chunks) {
        for l in 0..LANES {
            lanes[l] += x[l] * y[l];
        }
    }
    let tail: f32 = a_rest.iter().zip(b_rest).map(|(x, y)| x * y).sum();
    lanes.iter().sum::<f32>() + tail
}

/// `out += Σ_q columns[q] · v[q]`, the columns as long as `out`.
#[inline(always)]
fn axpy4(out: &mut [f32], columns: [&[f32]; SWEEP], v: [f32; SWEEP]) {
    let n = out.len();
    let (c0, c1, c2, c3) = (&columns[0][..n], &columns[1][..n], &columns[2][..n], &columns[3][..n]);
    for i in 0..n {
        out[i] = c3[i].mul_add(
            v[3],
            c2[i].mul_add(v[2], c1[i].mul_add(v[1], c0[i].mul_add(v[0], out[i]))),
        );
    }
}

/// The dot products of four columns with one vector, reading it once.
#[inline(always)]
fn dots(columns: [&[f32]; SWEEP], b: &[f32]) -> [f32; SWEEP] {
    let n = b.len();
    let (b_chunks, b_rest) = b.as_chunks::<LANES>();
    let [(c0, r0), (c1, r1), (c2, r2), (c3, r3)] = columns.map(|c| c[..n].as_chunks::<LANES>());
    let (mut a0, mut a1, mut a2, mut a3) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
    for ((((y, x0), x1), x2), x3) in b_chunks.iter().zip(c0).zip(c1).zip(c2).zip(c3) {
        for l in 0..LANES {
            a0[l] = x0[l].mul_add(y[l], a0[l]);
            a1[l] = x1[l].mul_add(y[l], a1[l]);
            a2[l] = x2[l].mul_add(y[l], a2[l]);
            a3[l] = x3[l].mul_add(y[l], a3[l]);
        }
    }
    let finish = |lanes: [f32; LANES], rest: &[f32]| {
        lanes.iter().sum::<f32>() + rest.iter().zip(b_rest).map(|(x, y)| x * y).sum::<f32>()
    };
    [finish(a0, r0), finish(a1, r1), finish(a2, r2), finish(a3, r3)]
}
