//! Small dense symmetric kernels for the coefficient solve: the Gram matrix of a symmetric matrix,
//! its Cholesky factor, and the two triangular solves, all in f64.
//!
//! Why not faer: at the sizes a request brings (3K = 30…150) its general, recursive kernels spend
//! most of their time choosing paths: the K = 20 solve (60 unknowns, about 144,000 FMAs) took
//! 22.7 µs with faer 0.24 and 12 µs with these (`cargo bench --bench prior` at commit 22d1888
//! and after, 2-vCPU Xeon with AVX-512; the README follows it since). Here the O(n³) loops hold an 8-row × 4-column block of the
//! output in registers while the columns it depends on stream past: each loaded chunk feeds four FMAs, eight
//! independent sums hide the FMA latency, and no horizontal sums or store-to-load chains sit in
//! the inner loop. The functions are compiled for AVX-512 and AVX2 and picked at run time, like the
//! field kernel.
//!
//! Past [`LARGE`] unknowns the whole matrix no longer fits in L1, these kernels stream it from L2,
//! and faer's cache-blocked ones win again (K = 64, 192 unknowns: 245 µs with faer against 320 µs
//! here), so the two public entry points hand large systems to faer.
//!
//! Storage: [`Dense`] matrices are column-major and padded with zero rows and columns to a
//! multiple of [`LANES`], which every kernel keeps zero, so no loop needs a tail. One padding row
//! lies below the last block of [`COLUMNS`] columns: the border row, through which a right-hand
//! side rides along the factorization (see [`cholesky_solve`]); products stop at the chunk holding
//! row `n − 1`, so the border costs them nothing.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::{LltError, LltRegularization, cholesky_in_place, cholesky_in_place_scratch};
use faer::linalg::matmul::triangular::{BlockStructure, matmul};
use faer::{Accum, MatMut, MatRef, Par};
use multiversion::multiversion;

/// Unknowns (3K) above which faer's kernels are faster than these (measured between K = 48 and 56).
const LARGE: usize = 150;

/// Rows per chunk: one AVX2 register of f64 (two chunks fill an AVX-512 one, and the compiler pairs
/// them). Four rather than eight because the first chunk of a block holds its diagonal and the last
/// one row `n − 1`: with eight-row chunks a 60-unknown Gram spent a sixth of its FMAs on rows
/// above the diagonal and on padding. Four-row chunks made the K = 20 solve 18 % faster on a
/// 2-vCPU AMD EPYC (`cargo bench --bench prior -- prior/solve/`), where 256-bit FMAs have the
/// 512-bit ones' throughput per lane.
const LANES: usize = 4;

/// Output columns computed together: each loaded chunk of an input column is used this many times.
const COLUMNS: usize = 4;

/// An `n × n` matrix, column-major, padded with zeros to `stride × stride`.
#[derive(Debug, Default)]
pub struct Dense {
    n: usize,
    stride: usize,
    values: Vec<f64>,
}

impl Dense {
    /// Resizes to `n × n` and zeroes the padding; the other entries keep stale values until written.
    pub fn reset(&mut self, n: usize) {
        self.n = n;
        self.stride = (Self::border_row(n) + 1).next_multiple_of(LANES);
        self.values.resize(self.stride * self.stride, 0.0);
        for (col, column) in self.values.chunks_exact_mut(self.stride).enumerate() {
            let from = if col < n { n } else { 0 };
            column[from..].fill(0.0);
        }
    }

    /// The `n` entries (without padding) of columns `first`, `first + step` and `first + 2 step`.
    pub fn strided_columns_mut(&mut self, first: usize, step: usize) -> [&mut [f64]; 3] {
        let (n, stride) = (self.n, self.stride);
        let (head, rest) = self.values[first * stride..].split_at_mut(step * stride);
        let (middle, last) = rest.split_at_mut(step * stride);
        [&mut head[..n], &mut middle[..n], &mut last[..n]]
    }

    /// The padding row below the last block of columns that the factorization updates like any
    /// row of the matrix.
    fn border_row(n: usize) -> usize {
        n.next_multiple_of(COLUMNS)
    }

    pub fn set(&mut self, row: usize, col: usize, value: f64) {
        self.values[row + col * self.stride] = value;
    }

    pub fn get(&self, row: usize, col: usize) -> f64 {
        self.values[row + col * self.stride]
    }

    fn view(&self) -> MatRef<'_, f64> {
        MatRef::from_column_major_slice_with_stride(&self.values, self.n, self.n, self.stride)
    }

    fn view_mut(&mut self) -> MatMut<'_, f64> {
        MatMut::from_column_major_slice_with_stride_mut(&mut self.values, self.n, self.n, self.stride)
    }

    /// Column `col` with its padding rows.
    fn column(&self, col: usize) -> &[f64] {
        &self.values[col * self.stride..(col + 1) * self.stride]
    }

    fn column_mut(&mut self, col: usize) -> &mut [f64] {
        &mut self.values[col * self.stride..(col + 1) * self.stride]
    }
}

/// Sums for `R` chunks of rows in each of [`COLUMNS`] output columns.
type Block<const R: usize> = [[[f64; LANES]; R]; COLUMNS];

/// Adds `sign · Σ_l a[rows, l] · a[first + c, l]` to column `c` of `acc`, over the `R` chunks of
/// rows from `row` on and the columns `l` in `columns`. The scales sit in the column being loaded:
/// row `first + c` of column `l` is `G[l, first + c]` for a symmetric `G`, and is `L[first + c, l]`
/// for a Cholesky factor.
#[inline(always)]
fn accumulate<const R: usize>(
    a: &Dense,
    row: usize,
    first: usize,
    columns: std::ops::Range<usize>,
    sign: f64,
    acc: &mut Block<R>,
) {
    for l in columns {
        let column = a.column(l);
        let (chunks, _) = column[row..row + R * LANES].as_chunks::<LANES>();
        let scales = &column[first..first + COLUMNS];
        for (sums, scale) in acc.iter_mut().zip(scales) {
            let s = sign * scale;
            for (sum, chunk) in sums.iter_mut().zip(chunks) {
                for lane in 0..LANES {
                    sum[lane] = chunk[lane].mul_add(s, sum[lane]);
                }
            }
        }
    }
}

/// Runs `$body` with `$acc` a zeroed [`Block`] for each group of rows from `$from` (a chunk
/// boundary) to `$to`: two chunks at a time, since two chunks × four columns are the eight sums
/// that keep both FMA units busy. An odd count starts one chunk higher, on rows no caller reads,
/// where it can; otherwise its last group is one chunk. A macro because the two sizes are two types.
macro_rules! for_row_groups {
    ($from:expr, $to:expr, |$row:ident, $acc:ident| $body:block) => {{
        let (from, to) = ($from, $to);
        let mut $row = if (to - from) / LANES % 2 == 1 && from >= LANES { from - LANES } else { from };
        while $row < to {
            if to - $row >= 2 * LANES {
                let mut $acc: Block<2> = Default::default();
                $body
                $row += 2 * LANES;
            } else {
                let mut $acc: Block<1> = Default::default();
                $body
                $row += LANES;
            }
        }
    }};
}

/// The lower triangle of `G G` for a symmetric `g` into `out` (resized to match): column `i` is
/// `Σ_l G[:, l] G[l, i]`, and `G[l, i]` runs down column `i` because `G` is symmetric. Rows above
/// the diagonal in the diagonal's chunk are computed too, and never read.
pub fn gram_lower(g: &Dense, out: &mut Dense) {
    out.reset(g.n);
    if g.n > LARGE {
        let (g, out) = (g.view(), out.view_mut());
        let full = BlockStructure::Rectangular;
        matmul(
            out,
            BlockStructure::TriangularLower,
            Accum::Replace,
            g,
            full,
            g,
            full,
            1.0,
            Par::Seq,
        );
    } else {
        gram_lower_blocked(g, out);
    }
}

/// [`gram_lower`] for small systems, in registers: see the module's description.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn gram_lower_blocked(g: &Dense, out: &mut Dense) {
    let n = g.n;
    for first in (0..n).step_by(COLUMNS) {
        for_row_groups!(first / LANES * LANES, n.next_multiple_of(LANES), |row, acc| {
            accumulate(g, row, first, 0..n, 1.0, &mut acc);
            for (c, sums) in acc.iter().enumerate() {
                out.column_mut(first + c)[row..][..sums.len() * LANES].copy_from_slice(sums.as_flattened());
            }
        });
    }
}
/// `Σ a_i b_i` in eight interleaved partial sums, so that consecutive FMAs do not wait on each other.
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let (a_chunks, a_tail) = a.as_chunks::<LANES>();
    let (b_chunks, b_tail) = b.as_chunks::<LANES>();
    // Even and odd chunks into separate sums: two FMA chains, each half as long.
    let mut even = [0.0f64; LANES];
    let mut odd = [0.0f64; LANES];
    for (x, y) in a_chunks.chunks_exact(2).zip(b_chunks.chunks_exact(2)) {
        for lane in 0..LANES {
            even[lane] = x[0][lane].mul_add(y[0][lane], even[lane]);
            odd[lane] = x[1][lane].mul_add(y[1][lane], odd[lane]);
        }
    }
    if let (Some(x), Some(y)) = (
        a_chunks.chunks_exact(2).remainder().first(),
        b_chunks.chunks_exact(2).remainder().first(),
    ) {
        for lane in 0..LANES {
            even[lane] = x[lane].mul_add(y[lane], even[lane]);
        }
    }
    let tail: f64 = a_tail.iter().zip(b_tail).map(|(x, y)| x * y).sum();
    // A tree, not a chain: two dependent additions instead of three.
    let [s0, s1, s2, s3]: [f64; LANES] = std::array::from_fn(|lane| even[lane] + odd[lane]);
    ((s0 + s2) + (s1 + s3)) + tail
}

/// `G u` into `out` (`n` values), as `Σ_l G[:, l] u_l`: whole columns scaled and added, each row
/// independent of the others, where one dot product per row would end each in a chain of
/// dependent additions.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
pub fn times(g: &Dense, u: &[f64], out: &mut [f64]) {
    let out = &mut out[..g.n];
    out.fill(0.0);
    for (l, &scale) in u[..g.n].iter().enumerate() {
        for (o, v) in out.iter_mut().zip(&g.column(l)[..g.n]) {
            *o = v.mul_add(scale, *o);
        }
    }
}

/// The leading minor that was not positive definite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NotPositiveDefinite {
    pub index: usize,
}

/// Solves `A x = b` in place (`n` values) for the symmetric positive definite `a`, given by its
/// lower triangle, which is overwritten with the Cholesky factor `L` (`L Lᵀ = A`; the entries above
/// the diagonal are left unspecified); `inverse_pivots` receives `1 / L[j, j]`.
///
/// For small systems `b` rides through the factorization in the border row, as the last row of
/// `[A b; bᵀ ·]`: the factor's row there is `L⁻¹ b`, computed by the same vectorized updates as the
/// rows of `L`, where a separate forward substitution would be a chain of dependent steps.
pub fn cholesky_solve(a: &mut Dense, b: &mut [f64], inverse_pivots: &mut Vec<f64>) -> Result<(), NotPositiveDefinite> {
    let n = a.n;
    if n > LARGE {
        cholesky_large(a, inverse_pivots)?;
        forward_substitution(a, inverse_pivots, b);
    } else {
        let border = Dense::border_row(n);
        for (j, &value) in b[..n].iter().enumerate() {
            a.set(border, j, value);
        }
        let factorized = cholesky_lower_blocked(a, inverse_pivots);
        for (j, value) in b[..n].iter_mut().enumerate() {
            *value = a.get(border, j);
            a.set(border, j, 0.0);
        }
        factorized?;
    }
    backward_substitution(a, inverse_pivots, b);
    Ok(())
}

/// The Cholesky factor of a large system, by faer's cache-blocked kernel.
fn cholesky_large(a: &mut Dense, inverse_pivots: &mut Vec<f64>) -> Result<(), NotPositiveDefinite> {
    let n = a.n;
    let mut scratch = MemBuffer::new(cholesky_in_place_scratch::<f64>(n, Par::Seq, Default::default()));
    let regularization = LltRegularization::default();
    match cholesky_in_place(
        a.view_mut(),
        regularization,
        Par::Seq,
        MemStack::new(&mut scratch),
        Default::default(),
    ) {
        Ok(_) => {}
        Err(LltError::NonPositivePivot { index }) => return Err(NotPositiveDefinite { index }),
    }
    inverse_pivots.clear();
    inverse_pivots.extend((0..n).map(|j| a.get(j, j).recip()));
    Ok(())
}

/// The Cholesky factor of a small system, in place with its rows down to the stride (the border
/// row among them): left-looking, four columns at a time. Each block first takes the products of
/// every finished column at once (`S = A[:, j] − Σ_{p<first} L[:, p] L[j, p]`, the O(n³) part) on
/// its 4 × 4 diagonal, which is then factorized; the rows below take the same products and, while
/// those are still in registers, solve `L[r, block] · L_blockᵀ = S[r, block]`, every row
/// independently of the others.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn cholesky_lower_blocked(a: &mut Dense, inverse_pivots: &mut Vec<f64>) -> Result<(), NotPositiveDefinite> {
    // The diagonal of a block of columns is exactly one chunk of rows.
    const { assert!(LANES == COLUMNS) };
    let (n, stride) = (a.n, a.stride);
    inverse_pivots.clear();
    for first in (0..n).step_by(COLUMNS) {
        // The diagonal's chunk and the one below it, updated together: the stride leaves at least
        // one chunk (the border row's) below every diagonal.
        let mut head: Block<2> = Default::default();
        update(a, first, first, &mut head);
        let mut block = [[0.0f64; COLUMNS]; COLUMNS];
        let mut inverse = [1.0f64; COLUMNS];
        for c in 0..COLUMNS {
            let j = first + c;
            if j >= n {
                // A padding column: a unit pivot keeps its zeros zero.
                block[c][c] = 1.0;
                continue;
            }
            for d in 0..c {
                let known: f64 = (0..d).map(|e| block[c][e] * block[d][e]).sum();
                block[c][d] = (head[d][0][c] - known) * inverse[d];
            }
            let pivot = head[c][0][c] - (0..c).map(|e| block[c][e] * block[c][e]).sum::<f64>();
            // NaN fails this test too: a corrupt request is refused here rather than spread.
            if pivot.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return Err(NotPositiveDefinite { index: j });
            }
            block[c][c] = pivot.sqrt();
            // 1/√p as √p · (1/p): the division runs beside the root instead of after it.
            inverse[c] = pivot.recip() * block[c][c];
            inverse_pivots.push(inverse[c]);
        }
        let mut below: Block<1> = std::array::from_fn(|c| [head[c][1]]);
        solve_rows(&block, &inverse, &mut below);
        for (column, [rows]) in head.iter_mut().zip(below) {
            column[1] = rows;
        }
        store(a, first, first, &head);
        // Over the diagonal chunk's S, whose entries above the diagonal are left as they are.
        for (c, row) in block.iter().enumerate().take(n - first) {
            for (d, &value) in row[..=c].iter().enumerate() {
                a.set(first + c, first + d, value);
            }
        }
        let mut row = first + 2 * LANES;
        while row < stride {
            row += if stride - row >= 2 * LANES {
                factor_rows::<2>(a, row, first, &block, &inverse)
            } else {
                factor_rows::<1>(a, row, first, &block, &inverse)
            };
        }
    }
    Ok(())
}

/// The `R` chunks of rows from `row` in columns `first..first + COLUMNS`, less the products of the
/// finished columns `0..first` ([`cholesky_lower_blocked`]'s `S`).
#[inline(always)]
fn update<const R: usize>(a: &Dense, row: usize, first: usize, acc: &mut Block<R>) {
    for (c, sums) in acc.iter_mut().enumerate() {
        let sums = sums.as_flattened_mut();
        sums.copy_from_slice(&a.column(first + c)[row..][..sums.len()]);
    }
    accumulate(a, row, first, 0..first, -1.0, acc);
}

/// The factor's `R` chunks of rows from `row` in columns `first..first + COLUMNS`, below the block's
/// factorized diagonal: updated, solved and stored in one go. Returns the rows done.
#[inline(always)]
fn factor_rows<const R: usize>(
    a: &mut Dense,
    row: usize,
    first: usize,
    block: &[[f64; COLUMNS]; COLUMNS],
    inverse: &[f64; COLUMNS],
) -> usize {
    let mut rows: Block<R> = [[[0.0; LANES]; R]; COLUMNS];
    update(a, row, first, &mut rows);
    solve_rows(block, inverse, &mut rows);
    store(a, row, first, &rows);
    R * LANES
}

/// Writes `acc` back to its rows of columns `first..first + COLUMNS`.
#[inline(always)]
fn store<const R: usize>(a: &mut Dense, row: usize, first: usize, acc: &Block<R>) {
    for (c, sums) in acc.iter().enumerate() {
        a.column_mut(first + c)[row..][..R * LANES].copy_from_slice(sums.as_flattened());
    }
}

/// Solves `X · Lᵀ = S` for the rows of `acc` (`S` in, `X` out), with `L` the block's factorized
/// diagonal and `inverse` its inverse pivots: forward along the four columns, every row at once.
#[inline(always)]
fn solve_rows<const R: usize>(block: &[[f64; COLUMNS]; COLUMNS], inverse: &[f64; COLUMNS], acc: &mut Block<R>) {
    let [c0, c1, c2, c3] = acc.each_mut().map(|column| column.as_flattened_mut());
    for (((x0, x1), x2), x3) in c0.iter_mut().zip(c1).zip(c2).zip(c3) {
        *x0 *= inverse[0];
        *x1 = (-*x0).mul_add(block[1][0], *x1) * inverse[1];
        *x2 = (-*x1).mul_add(block[2][1], (-*x0).mul_add(block[2][0], *x2)) * inverse[2];
        let partial = (-*x1).mul_add(block[3][1], (-*x0).mul_add(block[3][0], *x3));
        *x3 = (-*x2).mul_add(block[3][2], partial) * inverse[3];
    }
}

/// Solves `L y = b` in place (`n` values), by columns: once `y_j` is known, its share is removed
/// from the rows below.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn forward_substitution(l: &Dense, inverse_pivots: &[f64], b: &mut [f64]) {
    let n = l.n;
    for j in 0..n {
        let column = &l.column(j)[..n];
        let (solved, below) = b[..n].split_at_mut(j + 1);
        let y = solved[j] * inverse_pivots[j];
        solved[j] = y;
        for (r, c) in below.iter_mut().zip(&column[j + 1..]) {
            *r = (-y).mul_add(*c, *r);
        }
    }
}

/// Solves `Lᵀ x = y` in place (`n` values), [`COLUMNS`] rows at a time from the bottom:
/// `x_j = (y_j − L[j+1.., j] · x[j+1..]) / L[j, j]`. The products with the rows below the block are
/// independent of each other and run side by side; only the few within the block form a chain.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn backward_substitution(l: &Dense, inverse_pivots: &[f64], b: &mut [f64]) {
    let n = l.n;
    for first in (0..n).step_by(COLUMNS).rev() {
        let end = (first + COLUMNS).min(n);
        let (head, solved) = b[..n].split_at_mut(end);
        let mut rest: [f64; COLUMNS] = [0.0; COLUMNS];
        for (j, r) in (first..end).zip(&mut rest) {
            *r = head[j] - dot(&l.column(j)[end..n], solved);
        }
        for j in (first..end).rev() {
            let column = l.column(j);
            let within: f64 = (j + 1..end).map(|i| column[i] * head[i]).sum();
            head[j] = (rest[j - first] - within) * inverse_pivots[j];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;
    use faer::linalg::solvers::Solve;

    /// A symmetric matrix with a spread of eigenvalues (a smooth kernel plus a small diagonal), the
    /// kind the Kelvinlet system produces.
    fn symmetric(n: usize, seed: u64) -> Dense {
        let point = |i: usize| {
            let t = (i as f64 + 1.0) * (seed as f64 + 0.37);
            [(1.3 * t).sin(), (0.7 * t).cos(), (2.1 * t).sin()]
        };
        let mut g = Dense::default();
        g.reset(n);
        for i in 0..n {
            for j in 0..n {
                let (p, q) = (point(i), point(j));
                let d2: f64 = (0..3).map(|c| (p[c] - q[c]).powi(2)).sum();
                g.set(i, j, 1.0 / (d2 + 0.25).sqrt() + if i == j { 1e-2 } else { 0.0 });
            }
        }
        g
    }

    fn as_faer(a: &Dense) -> Mat<f64> {
        Mat::from_fn(a.n, a.n, |i, j| a.get(i, j))
    }

    /// Sizes straddle the 8-row chunks and the 4-column blocks (tails of every length) and reach
    /// beyond K = 64 points; each runs on a workspace last used for a larger size, as a server's is.
    const SIZES: [usize; 9] = [200, 1, 2, 5, 7, 8, 9, 60, 195];

    #[test]
    fn gram_and_product_match_faer() {
        let mut gram = Dense::default();
        for n in SIZES {
            let g = symmetric(n, 3);
            gram_lower(&g, &mut gram);
            let reference = as_faer(&g) * as_faer(&g);
            let u: Vec<f64> = (0..n).map(|i| (i as f64 * 0.3).cos()).collect();
            let mut gu = vec![0.0; n];
            times(&g, &u, &mut gu);
            let reference_gu = as_faer(&g) * Mat::from_fn(n, 1, |i, _| u[i]);
            for i in 0..n {
                // Entries are sums of n terms of size ≤ 2.01²: a few ulps of 4n each.
                assert!(
                    (gu[i] - reference_gu[(i, 0)]).abs() <= 1e-14 * n as f64,
                    "n {n} row {i}"
                );
                for j in 0..=i {
                    let (got, want) = (gram.get(i, j), reference[(i, j)]);
                    assert!(
                        (got - want).abs() <= 1e-14 * n as f64,
                        "n {n} ({i},{j}): {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn solve_matches_faer_cholesky() {
        let (mut a, mut inverse_pivots) = (Dense::default(), Vec::new());
        for n in SIZES {
            let g = symmetric(n, 5);
            gram_lower(&g, &mut a);
            for d in 0..n {
                a.set(d, d, a.get(d, d) + 1e-3);
            }
            let full = Mat::from_fn(n, n, |i, j| a.get(i.max(j), i.min(j)));
            let b: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64).sin()).collect();
            let want = full
                .llt(faer::Side::Lower)
                .expect("SPD")
                .solve(Mat::from_fn(n, 1, |i, _| b[i]));
            let mut x = b.clone();
            cholesky_solve(&mut a, &mut x, &mut inverse_pivots).expect("SPD");
            // The border row that carried b is zero again, as all padding must be.
            let border = Dense::border_row(n);
            assert!((0..n).all(|j| a.get(border, j) == 0.0), "n {n}: border row left dirty");
            // Both are backward stable; their answers differ by about cond(A)·ε, with cond(A) up to
            // about 1e6 here (the largest eigenvalue of G², over λ).
            let scale = want.col(0).iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for i in 0..n {
                let (got, expected) = (x[i], want[(i, 0)]);
                assert!(
                    (got - expected).abs() <= 1e-8 * scale,
                    "n {n} x[{i}]: {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn indefinite_and_nan_are_refused_at_their_pivot() {
        let mut inverse_pivots = Vec::new();
        for (entries, index) in [([4.0, 2.0, 1.0], 1), ([1.0, 0.0, f64::NAN], 1)] {
            let mut a = Dense::default();
            a.reset(2);
            a.set(0, 0, entries[0]);
            a.set(1, 0, entries[1]);
            a.set(1, 1, entries[2]);
            assert_eq!(
                cholesky_solve(&mut a, &mut [1.0, 1.0], &mut inverse_pivots),
                Err(NotPositiveDefinite { index })
            );
        }
    }
}
