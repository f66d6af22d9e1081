//! The regularized Kelvinlet prior (docs/design.md §3, with the ε² term the paper's equation drops).
//!
//! For interaction points `x_j` with prescribed displacements `u_j`, the coefficients `k` solve
//! `(ΓᵀΓ + λI) k = Γᵀu` (f64, [`solve`]), and the field `u(x) = Σ_j Γ_j(x) k_j` is evaluated over
//! the nodes in f32 by a vectorized, multi-core kernel ([`kernel`]) or on the GPU ([`gpu`]), as
//! [`backend`] decides per node cloud ([`cloud`]).

pub mod backend;
pub mod cloud;
mod dense;
pub mod gpu;
pub mod kernel;
pub mod solve;

pub use backend::PriorBackend;
pub use cloud::{NodeCloud, Resident};
pub use gpu::GpuPhases;
pub use solve::{Coefficients, SolveError, Workspace};

use crate::mesh::PriorParams;

/// Constants of the rescaled regularized Kelvinlet for one (ν, ε).
///
/// `Γ(r) = s · [ (a/r_ε + b/r_ε³) I + r rᵀ/r_ε³ ]` with `s = ε/(5−6ν)`, `a = 3−4ν`,
/// `b = 2(1−ν)ε²`, `r_ε = sqrt(|r|² + ε²)`; `Γ(0) = I`, so a lone point moves by exactly `u_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kelvinlet {
    pub params: PriorParams,
    pub scale: f64,
    pub a: f64,
    pub b: f64,
    pub epsilon_sq: f64,
}

impl Kelvinlet {
    pub fn new(params: PriorParams) -> Self {
        let (nu, eps) = (params.poisson_ratio, params.epsilon);
        Self {
            params,
            scale: eps / (5.0 - 6.0 * nu),
            a: 3.0 - 4.0 * nu,
            b: 2.0 * (1.0 - nu) * eps * eps,
            epsilon_sq: eps * eps,
        }
    }

    /// The 3×3 response `Γ(r)` (row-major) to a unit coefficient at offset `r = x − x_s`.
    pub fn response(&self, r: [f64; 3]) -> [[f64; 3]; 3] {
        let r_eps = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + self.epsilon_sq).sqrt();
        let inv3 = 1.0 / (r_eps * r_eps * r_eps);
        let diagonal = self.a / r_eps + self.b * inv3;
        let mut m = [[0.0; 3]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                let identity = if i == j { diagonal } else { 0.0 };
                *v = self.scale * (identity + r[i] * r[j] * inv3);
            }
        }
        m
    }
}

/// Interaction points: where the tissue is held and how far each point is moved (metres).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InteractionPoints {
    pub nodes: Vec<u32>,
    pub positions: Vec<[f64; 3]>,
    pub displacements: Vec<[f64; 3]>,
    /// Where each grasp's points end (exclusive), when the points were resolved from grasps: grasp
    /// `g` holds points `grasp_ends[g-1]..grasp_ends[g]`. Empty: the points form one group.
    pub grasp_ends: Vec<usize>,
}

impl InteractionPoints {
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    pub fn clear(&mut self) {
        self.nodes.clear();
        self.positions.clear();
        self.displacements.clear();
        self.grasp_ends.clear();
    }

    /// Marks the points pushed since the last call as one grasp's.
    pub fn end_grasp(&mut self) {
        self.grasp_ends.push(self.len());
    }

    /// The points of each grasp, in order (one range over every point when none was marked).
    pub fn grasp_ranges(&self) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
        let whole = self.grasp_ends.is_empty().then_some(self.len());
        self.grasp_ends.iter().copied().chain(whole).scan(0, |start, end| {
            let range = *start..end;
            *start = end;
            Some(range)
        })
    }

    pub fn push(&mut self, node: u32, position: [f64; 3], displacement: [f64; 3]) {
        self.nodes.push(node);
        self.positions.push(position);
        self.displacements.push(displacement);
    }
}
