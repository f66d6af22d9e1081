//! Compressible Mooney–Rivlin (docs/design.md §4):
//! `W = C10(Ī1 − 3) + C01(Ī2 − 3) + U(J)`, `Ī1 = J^{-2/3} I1`, `Ī2 = J^{-4/3} I2`, with the volumetric
//! term `U = (κ/2)(ln J)²` (or, for data made before the change, `(κ/2)(J − 1)²`), and the first
//! Piola–Kirchhoff stress `P = ∂W/∂F` and the tangent `A = ∂²W/∂F∂F` in closed form.
//!
//! Tensors are indexed by (row i, column J) of F → `3i + J`; `A[3i+J][3k+L] = ∂P_iJ/∂F_kL`.

use nalgebra::{Matrix3, Vector3};

use crate::mesh::{Material, VolumetricLaw};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MooneyRivlin {
    pub c10: f64,
    pub c01: f64,
    /// Bulk modulus κ.
    pub kappa: f64,
    pub volumetric: VolumetricLaw,
}

pub type Tangent = [[f64; 9]; 9];

impl MooneyRivlin {
    /// κ from Poisson's ratio and the initial shear modulus μ0 = 2(C10 + C01), as docs/design.md §4 fixes.
    pub fn new(c10: f64, c01: f64, poisson_ratio: f64, volumetric: VolumetricLaw) -> Self {
        let mu0 = 2.0 * (c10 + c01);
        let kappa = 2.0 * mu0 * (1.0 + poisson_ratio) / (3.0 * (1.0 - 2.0 * poisson_ratio));
        Self {
            c10,
            c01,
            kappa,
            volumetric,
        }
    }

    pub fn from_material(m: &Material, volumetric: VolumetricLaw) -> Self {
        Self::new(m.c10, m.c01, m.poisson_ratio, volumetric)
    }

    /// U(J), J U′(J) and J² U″(J): the volumetric term and the two scalars its stress
    /// (`J U′ F⁻ᵀ`) and tangent (`(J U′ + J² U″) H⊗H − J U′ H_iL H_kJ`) need.
    fn volumetric(&self, j: f64) -> (f64, f64, f64) {
        let k = self.kappa;
        match self.volumetric {
            VolumetricLaw::LnJSquared => {
                let ln_j = j.ln();
                (0.5 * k * ln_j * ln_j, k * ln_j, k * (1.0 - ln_j))
            }
            VolumetricLaw::JMinusOneSquared => (0.5 * k * (j - 1.0).powi(2), k * (j - 1.0) * j, k * j * j),
        }
    }

    /// The small-strain shear modulus and Lamé λ this law linearizes to.
    pub fn linearized_lame(&self) -> (f64, f64) {
        let mu = 2.0 * (self.c10 + self.c01);
        (mu, self.kappa - 2.0 * mu / 3.0)
    }

    /// Strain energy density; `None` for an inverted or collapsed element (J ≤ 0).
    pub fn energy(&self, f: &Matrix3<f64>) -> Option<f64> {
        let j = f.determinant();
        if j <= 0.0 {
            return None;
        }
        let (i1, i2) = invariants(&(f.transpose() * f));
        let j23 = inverse_cube_root_squared(j);
        Some(self.isochoric_energy(j23, i1, i2) + self.volumetric(j).0)
    }

    /// W's isochoric part from J^{-2/3} and the invariants.
    fn isochoric_energy(&self, j23: f64, i1: f64, i2: f64) -> f64 {
        self.c10 * (j23 * i1 - 3.0) + self.c01 * (j23 * j23 * i2 - 3.0)
    }

    /// The first Piola–Kirchhoff stress; `None` when J ≤ 0.
    pub fn stress(&self, f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
        self.response(f).map(|r| r.stress)
    }

    /// Stress and the tangent as a 9 × 9 matrix; `None` when J ≤ 0.
    pub fn stress_and_tangent(&self, f: &Matrix3<f64>) -> Option<(Matrix3<f64>, Tangent)> {
        self.response(f).map(|r| (r.stress, r.tangent.matrix()))
    }

    /// Energy density, stress and the tangent's terms in one pass (an element loop needs all three,
    /// and they share the determinant, invariants and powers of J); `None` when J ≤ 0.
    ///
    /// Each isochoric term is `c J^a g(F)` with g ∈ {I1, I2}; its derivatives follow from the
    /// product rule with `∂J^a/∂F = a J^a F⁻ᵀ` and `∂F⁻ᵀ_iJ/∂F_kL = −F⁻ᵀ_iL F⁻ᵀ_kJ`.
    pub fn response(&self, f: &Matrix3<f64>) -> Option<Response> {
        let j = f.determinant();
        if j <= 0.0 {
            return None;
        }
        let h = f.try_inverse()?.transpose();
        let c = f.transpose() * f;
        let b = f * f.transpose();
        let (i1, i2) = invariants(&c);
        let j23 = inverse_cube_root_squared(j);
        // (c J^a, a, g) per isochoric term; ∂I1/∂F = 2F, ∂I2/∂F = 2(I1 F − F C).
        let (s1, a1) = (self.c10 * j23, -2.0 / 3.0);
        let (s2, a2) = (self.c01 * j23 * j23, -4.0 / 3.0);
        let d = 2.0 * (i1 * f - f * c);
        let (u, ju1, jju2) = self.volumetric(j);
        let stress = ju1 * h + s1 * (2.0 * f + a1 * i1 * h) + s2 * (d + a2 * i2 * h);
        let tangent = TangentTerms {
            h,
            f: *f,
            d,
            c,
            b,
            hh: ju1 + jju2 + s1 * a1 * a1 * i1 + s2 * a2 * a2 * i2,
            hh_swapped: ju1 + s1 * a1 * i1 + s2 * a2 * i2,
            hf: 2.0 * s1 * a1,
            hd: s2 * a2,
            ff: 4.0 * s2,
            ff_swapped: 2.0 * s2,
            identity: 2.0 * s1 + 2.0 * s2 * i1,
            two_s2: 2.0 * s2,
        };
        Some(Response {
            energy: self.isochoric_energy(j23, i1, i2) + u,
            stress,
            tangent,
        })
    }
}

/// What [`MooneyRivlin::response`] gives for one deformation gradient.
#[derive(Debug, Clone, Copy)]
pub struct Response {
    /// Strain energy density W (J/m³).
    pub energy: f64,
    /// First Piola–Kirchhoff stress P = ∂W/∂F.
    pub stress: Matrix3<f64>,
    pub tangent: TangentTerms,
}

/// The tangent A = ∂²W/∂F∂F as a sum of a few structured terms, with H = F⁻ᵀ, D = ∂I2/∂F,
/// C = FᵀF, b = FFᵀ:
///
/// ```text
/// A_iJkL = hh H_iJ H_kL − hh_swapped H_iL H_kJ + hf (H_iJ F_kL + F_iJ H_kL) + hd (H_iJ D_kL + D_iJ H_kL)
///        + ff F_iJ F_kL − ff_swapped F_iL F_kJ + identity δ_ik δ_JL − two_s2 (δ_ik C_LJ + b_ik δ_JL)
/// ```
///
/// Kept in this form because an element matrix contracts each term with the shape gradients
/// separately ([`TangentTerms::element_block`]): outer products of 3-vectors instead of a
/// 9 × 9 × 12 × 12 contraction, a third of the arithmetic.
#[derive(Debug, Clone, Copy)]
pub struct TangentTerms {
    h: Matrix3<f64>,
    f: Matrix3<f64>,
    d: Matrix3<f64>,
    c: Matrix3<f64>,
    b: Matrix3<f64>,
    hh: f64,
    hh_swapped: f64,
    hf: f64,
    hd: f64,
    ff: f64,
    ff_swapped: f64,
    identity: f64,
    two_s2: f64,
}

/// One node's shape gradient pushed through the tangent's tensors: H g, F g and D g.
#[derive(Debug, Clone, Copy)]
pub struct NodeTerms {
    g: Vector3<f64>,
    h: Vector3<f64>,
    f: Vector3<f64>,
    d: Vector3<f64>,
}

impl TangentTerms {
    /// A_iJkL at (3i + J, 3k + L).
    pub fn matrix(&self) -> Tangent {
        let delta = |x: usize, y: usize| if x == y { 1.0 } else { 0.0 };
        let (h, f, d, c, b) = (&self.h, &self.f, &self.d, &self.c, &self.b);
        std::array::from_fn(|row| {
            std::array::from_fn(|col| {
                let (i, jj, k, l) = (row / 3, row % 3, col / 3, col % 3);
                self.hh * h[(i, jj)] * h[(k, l)] - self.hh_swapped * h[(i, l)] * h[(k, jj)]
                    + self.hf * (h[(i, jj)] * f[(k, l)] + f[(i, jj)] * h[(k, l)])
                    + self.hd * (h[(i, jj)] * d[(k, l)] + d[(i, jj)] * h[(k, l)])
                    + self.ff * f[(i, jj)] * f[(k, l)]
                    - self.ff_swapped * f[(i, l)] * f[(k, jj)]
                    + self.identity * delta(i, k) * delta(jj, l)
                    - self.two_s2 * (delta(i, k) * c[(l, jj)] + b[(i, k)] * delta(jj, l))
            })
        })
    }

    /// The vectors [`TangentTerms::element_block`] needs of a node with shape gradient `g`.
    pub fn node(&self, g: &[f64; 3]) -> NodeTerms {
        let g = Vector3::from(*g);
        NodeTerms {
            g,
            h: self.h * g,
            f: self.f * g,
            d: self.d * g,
        }
    }

    /// The 3 × 3 block `Σ_JL A_iJkL g_aJ g_bL` of the element matrix (before the volume) coupling
    /// node a's component i with node b's component k.
    pub fn element_block(&self, a: &NodeTerms, b: &NodeTerms) -> Matrix3<f64> {
        let gg = a.g.dot(&b.g);
        let gcg = a.g.dot(&(self.c * b.g));
        // The terms of the form x_a y_bᵀ, gathered by their left vector.
        let right_of_h = self.hh * b.h + self.hf * b.f + self.hd * b.d;
        let right_of_f = self.hf * b.h + self.ff * b.f;
        let right_of_d = self.hd * b.h;
        a.h * right_of_h.transpose() + a.f * right_of_f.transpose() + a.d * right_of_d.transpose()
            - self.hh_swapped * b.h * a.h.transpose()
            - self.ff_swapped * b.f * a.f.transpose()
            - self.two_s2 * gg * self.b
            + Matrix3::from_diagonal_element(self.identity * gg - self.two_s2 * gcg)
    }
}

/// J^{-2/3}: a cube root is several times cheaper than `powf`.
fn inverse_cube_root_squared(j: f64) -> f64 {
    let root = j.cbrt();
    1.0 / (root * root)
}

/// I1 = tr C and I2 = ½((tr C)² − tr C²) of the right Cauchy–Green tensor C = FᵀF.
fn invariants(c: &Matrix3<f64>) -> (f64, f64) {
    let i1 = c.trace();
    (i1, 0.5 * (i1 * i1 - (c * c).trace()))
}
