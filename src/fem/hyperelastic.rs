//! Compressible Mooney–Rivlin (DESIGN.md §4):
//! `W = C10(Ī1 − 3) + C01(Ī2 − 3) + (κ/2)(J − 1)²`, `Ī1 = J^{-2/3} I1`, `Ī2 = J^{-4/3} I2`,
//! with the first Piola–Kirchhoff stress `P = ∂W/∂F` and the tangent `A = ∂²W/∂F∂F` in closed form.
//!
//! Tensors are indexed by (row i, column J) of F → `3i + J`; `A[3i+J][3k+L] = ∂P_iJ/∂F_kL`.

use nalgebra::Matrix3;

use crate::mesh::Material;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MooneyRivlin {
    pub c10: f64,
    pub c01: f64,
    /// Bulk modulus κ.
    pub kappa: f64,
}

pub type Tangent = [[f64; 9]; 9];

impl MooneyRivlin {
    /// κ from Poisson's ratio and the initial shear modulus μ0 = 2(C10 + C01), as DESIGN.md §4 fixes.
    pub fn new(c10: f64, c01: f64, poisson_ratio: f64) -> Self {
        let mu0 = 2.0 * (c10 + c01);
        let kappa = 2.0 * mu0 * (1.0 + poisson_ratio) / (3.0 * (1.0 - 2.0 * poisson_ratio));
        Self { c10, c01, kappa }
    }

    pub fn from_material(m: &Material) -> Self {
        Self::new(m.c10, m.c01, m.poisson_ratio)
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
        Some(self.energy_of(j, i1, i2))
    }

    fn energy_of(&self, j: f64, i1: f64, i2: f64) -> f64 {
        self.c10 * (j.powf(-2.0 / 3.0) * i1 - 3.0)
            + self.c01 * (j.powf(-4.0 / 3.0) * i2 - 3.0)
            + 0.5 * self.kappa * (j - 1.0).powi(2)
    }

    /// The first Piola–Kirchhoff stress; `None` when J ≤ 0.
    pub fn stress(&self, f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
        self.evaluate(f, false).map(|(_, p, _)| p)
    }

    /// Stress and tangent together (they share most of the work); `None` when J ≤ 0.
    pub fn stress_and_tangent(&self, f: &Matrix3<f64>) -> Option<(Matrix3<f64>, Tangent)> {
        self.evaluate(f, true).map(|(_, p, a)| (p, a.unwrap_or([[0.0; 9]; 9])))
    }

    /// Energy density, stress and, if asked, the tangent in one pass (an element loop needs all
    /// three, and they share the determinant, invariants and powers of J); `None` when J ≤ 0.
    pub fn response(&self, f: &Matrix3<f64>, with_tangent: bool) -> Option<(f64, Matrix3<f64>, Option<Tangent>)> {
        self.evaluate(f, with_tangent)
    }

    /// Each term is `c J^a g(F)` with g ∈ {I1, I2}; its derivatives follow from the product rule with
    /// `∂J^a/∂F = a J^a F⁻ᵀ` and `∂F⁻ᵀ_iJ/∂F_kL = −F⁻ᵀ_iL F⁻ᵀ_kJ`.
    fn evaluate(&self, f: &Matrix3<f64>, with_tangent: bool) -> Option<(f64, Matrix3<f64>, Option<Tangent>)> {
        let j = f.determinant();
        if j <= 0.0 {
            return None;
        }
        let finv_t = f.try_inverse()?.transpose();
        let c = f.transpose() * f;
        let b = f * f.transpose();
        let (i1, i2) = invariants(&c);
        let d_i1 = 2.0 * f;
        let d_i2 = 2.0 * (i1 * f - f * c);
        // (c J^a, a, g, ∂g/∂F) per isochoric term.
        let terms = [
            (self.c10 * j.powf(-2.0 / 3.0), -2.0 / 3.0, i1, d_i1),
            (self.c01 * j.powf(-4.0 / 3.0), -4.0 / 3.0, i2, d_i2),
        ];
        let mut p = self.kappa * (j - 1.0) * j * finv_t;
        for &(scale, a, g, dg) in &terms {
            p += scale * (dg + a * g * finv_t);
        }
        let energy = self.energy_of(j, i1, i2);
        if !with_tangent {
            return Some((energy, p, None));
        }
        let delta = |x: usize, y: usize| if x == y { 1.0 } else { 0.0 };
        let mut t = [[0.0; 9]; 9];
        // A is a Hessian (∂²W/∂F∂F), hence symmetric: the upper triangle is computed and mirrored.
        for i in 0..3 {
            for jj in 0..3 {
                for k in 0..3 {
                    for l in 0..3 {
                        if 3 * k + l < 3 * i + jj {
                            continue;
                        }
                        let inv_outer = finv_t[(i, jj)] * finv_t[(k, l)];
                        let inv_derivative = -finv_t[(i, l)] * finv_t[(k, jj)];
                        let dd_i1 = 2.0 * delta(i, k) * delta(jj, l);
                        let dd_i2 = 4.0 * f[(k, l)] * f[(i, jj)] + 2.0 * i1 * delta(i, k) * delta(jj, l)
                            - 2.0 * (delta(i, k) * c[(l, jj)] + f[(i, l)] * f[(k, jj)] + b[(i, k)] * delta(jj, l));
                        let mut value = self.kappa * j * ((2.0 * j - 1.0) * inv_outer + (j - 1.0) * inv_derivative);
                        for (&(scale, a, g, dg), dd_g) in terms.iter().zip([dd_i1, dd_i2]) {
                            value += scale
                                * (dd_g
                                    + a * (finv_t[(i, jj)] * dg[(k, l)] + dg[(i, jj)] * finv_t[(k, l)])
                                    + a * a * g * inv_outer
                                    + a * g * inv_derivative);
                        }
                        t[3 * i + jj][3 * k + l] = value;
                        t[3 * k + l][3 * i + jj] = value;
                    }
                }
            }
        }
        Some((energy, p, Some(t)))
    }
}

/// I1 = tr C and I2 = ½((tr C)² − tr C²) of the right Cauchy–Green tensor C = FᵀF.
fn invariants(c: &Matrix3<f64>) -> (f64, f64) {
    let i1 = c.trace();
    (i1, 0.5 * (i1 * i1 - (c * c).trace()))
}
