//! `model.toml`: the configuration that travels with a mesh (units, materials, prior, sampling).
//!
//! Moduli are written in kPa, as in the paper, under keys that say so; [`MeshConfig`] holds SI values.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::MeshError;

/// Regularized Kelvinlet parameters (docs/design.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriorParams {
    pub poisson_ratio: f64,
    #[serde(rename = "epsilon_m")]
    pub epsilon: f64,
    pub lambda: f64,
}

impl Default for PriorParams {
    fn default() -> Self {
        Self {
            poisson_ratio: 0.45,
            epsilon: 0.05,
            lambda: 1e-3,
        }
    }
}

/// Material of one region, in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Linear shear modulus μ (Pa).
    pub shear_modulus: f64,
    pub poisson_ratio: f64,
    /// Mooney–Rivlin C10 (Pa).
    pub c10: f64,
    /// Mooney–Rivlin C01 (Pa).
    pub c01: f64,
}

/// The volumetric term U(J) of the hyperelastic strain energy (docs/design.md §4). Everything made
/// with the law records it (preload and Green's-function caches, datasets, model manifests), so that
/// fields of two laws are never mixed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum VolumetricLaw {
    /// `(κ/2)(ln J)²`: a barrier as J → 0 (FEBio's default for its uncoupled Mooney–Rivlin).
    #[default]
    LnJSquared,
    /// `(κ/2)(J − 1)²`: nak's law before 2026-11-26, finite at J = 0, so elements can invert under
    /// deep pushes. Nonlinear datasets and models that name no law were made with it.
    JMinusOneSquared,
}

impl VolumetricLaw {
    /// The name model.toml, dataset.json and manifests use.
    pub fn name(self) -> &'static str {
        match self {
            Self::LnJSquared => "ln-j-squared",
            Self::JMinusOneSquared => "j-minus-one-squared",
        }
    }
}

impl std::fmt::Display for VolumetricLaw {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let formula = match self {
            Self::LnJSquared => "(κ/2)(ln J)²",
            Self::JMinusOneSquared => "(κ/2)(J − 1)²",
        };
        write!(f, "{} {formula}", self.name())
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Body {
    pub density: f64,
    pub gravity: [f64; 3],
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspRegion {
    pub node_set: String,
    pub weight: f64,
}

/// Parameters of the training distribution p (docs/design.md §5), in SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Sampling {
    pub displacement_min: [f64; 3],
    pub displacement_max: [f64; 3],
    pub neighbours: (usize, usize),
    pub grasp_regions: Vec<GraspRegion>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct MeshConfig {
    pub name: String,
    /// File name of the default mesh, relative to the configuration's directory.
    pub default_mesh: String,
    pub prior: PriorParams,
    pub body: Body,
    pub materials: BTreeMap<String, Material>,
    /// The hyperelastic law's volumetric term (`[hyperelastic] volumetric_law`).
    pub volumetric_law: VolumetricLaw,
    /// VTK region label → region name (`label` in `[regions.NAME]`).
    pub region_labels: BTreeMap<i32, String>,
    pub sampling: Sampling,
}

impl MeshConfig {
    /// Node sets every mesh must carry: `fixed` and the grasp regions the sampler draws from.
    pub fn required_node_sets(&self) -> Vec<&str> {
        std::iter::once("fixed")
            .chain(self.sampling.grasp_regions.iter().map(|r| r.node_set.as_str()))
            .collect()
    }

    pub fn parse(text: &str, origin: &str) -> Result<Self, MeshError> {
        let raw: RawConfig = toml::from_str(text).map_err(|e| MeshError::Config {
            path: origin.to_owned(),
            message: e.to_string(),
        })?;
        raw.into_config(origin)
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    mesh: RawMesh,
    #[serde(default)]
    prior: PriorParams,
    body: RawBody,
    regions: BTreeMap<String, RawMaterial>,
    sampling: RawSampling,
    #[serde(default)]
    hyperelastic: RawHyperelastic,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct RawHyperelastic {
    #[serde(default)]
    volumetric_law: VolumetricLaw,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMesh {
    name: String,
    default: String,
    units: String,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBody {
    density_kg_m3: f64,
    gravity_m_s2: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMaterial {
    shear_modulus_kpa: f64,
    poisson_ratio: f64,
    c10_kpa: f64,
    c01_kpa: f64,
    /// The integer marking this region in a VTK mesh's `region` (or `labels`) cell array.
    label: Option<i32>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSampling {
    displacement_min_mm: [f64; 3],
    displacement_max_mm: [f64; 3],
    neighbours_min: usize,
    neighbours_max: usize,
    grasp_regions: Vec<GraspRegion>,
}

const KPA: f64 = 1e3;
const MM: f64 = 1e-3;

impl RawConfig {
    fn into_config(self, origin: &str) -> Result<MeshConfig, MeshError> {
        let invalid = |message: String| MeshError::Config {
            path: origin.to_owned(),
            message,
        };
        if self.mesh.units != "m" {
            return Err(invalid(format!(
                "mesh.units = {:?}: nak works in metres; convert the mesh and set units = \"m\"",
                self.mesh.units
            )));
        }
        let p = self.prior;
        if !(p.poisson_ratio > -1.0 && p.poisson_ratio < 0.5) {
            return Err(invalid(format!(
                "prior.poisson_ratio = {} is outside (-1, 0.5)",
                p.poisson_ratio
            )));
        }
        if !(p.epsilon > 0.0 && p.lambda >= 0.0) {
            return Err(invalid("prior.epsilon_m must be > 0 and prior.lambda >= 0".into()));
        }
        let mut materials = BTreeMap::new();
        let mut region_labels = BTreeMap::new();
        for (name, m) in self.regions {
            if let Some(label) = m.label
                && let Some(other) = region_labels.insert(label, name.clone())
            {
                return Err(invalid(format!(
                    "regions.{other} and regions.{name} both have label = {label}"
                )));
            }
            let positive = [m.shear_modulus_kpa, m.c10_kpa, m.c01_kpa].iter().all(|v| *v > 0.0);
            if !(positive && m.poisson_ratio > -1.0 && m.poisson_ratio < 0.5) {
                return Err(invalid(format!(
                    "regions.{name}: moduli must be positive and poisson_ratio in (-1, 0.5)"
                )));
            }
            materials.insert(
                name,
                Material {
                    shear_modulus: m.shear_modulus_kpa * KPA,
                    poisson_ratio: m.poisson_ratio,
                    c10: m.c10_kpa * KPA,
                    c01: m.c01_kpa * KPA,
                },
            );
        }
        let s = self.sampling;
        if s.neighbours_min > s.neighbours_max {
            return Err(invalid("sampling.neighbours_min exceeds neighbours_max".into()));
        }
        if s.grasp_regions.is_empty() || s.grasp_regions.iter().any(|r| r.weight.is_nan() || r.weight < 0.0) {
            return Err(invalid(
                "sampling.grasp_regions must list regions with non-negative weights".into(),
            ));
        }
        if (0..3).any(|i| s.displacement_min_mm[i] >= s.displacement_max_mm[i]) {
            return Err(invalid(
                "sampling.displacement_min_mm must be below displacement_max_mm".into(),
            ));
        }
        Ok(MeshConfig {
            name: self.mesh.name,
            default_mesh: self.mesh.default,
            prior: p,
            region_labels,
            body: Body {
                density: self.body.density_kg_m3,
                gravity: self.body.gravity_m_s2,
            },
            materials,
            volumetric_law: self.hyperelastic.volumetric_law,
            sampling: Sampling {
                displacement_min: s.displacement_min_mm.map(|v| v * MM),
                displacement_max: s.displacement_max_mm.map(|v| v * MM),
                neighbours: (s.neighbours_min, s.neighbours_max),
                grasp_regions: s.grasp_regions,
            },
        })
    }
}
