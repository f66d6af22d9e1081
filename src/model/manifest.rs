//! `manifest.toml`: what a model directory says about its network (docs/design.md §7).

use std::collections::BTreeMap;

use serde::Deserialize;

use super::ModelLoadError;
use crate::engine::Regime;
use crate::mesh::{PriorParams, TetMesh, VolumetricLaw};

/// The prior a model is composed with: added to a residual network's output, read by a network that
/// takes the prior as input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PriorModel {
    /// The regularized Kelvinlet with the manifest's parameters (docs/design.md §3).
    #[default]
    Kelvinlet,
    /// The exact linear FEM answer (green-linear); the Kelvinlet parameters are then unused.
    GreenLinear,
    /// The hyperelastic model linearized about its gravity-preloaded state (green-tangent).
    GreenTangent,
}

/// `[prior]`: which prior, and the Kelvinlet's parameters (kept for every model: they are the
/// regularizer's for +Reg, and the served prior's for Kelvinlet residuals).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriorSection {
    #[serde(default)]
    pub model: PriorModel,
    pub poisson_ratio: f64,
    pub epsilon_m: f64,
    pub lambda: f64,
}

impl PriorSection {
    pub fn kelvinlet(&self) -> PriorParams {
        PriorParams {
            poisson_ratio: self.poisson_ratio,
            epsilon: self.epsilon_m,
            lambda: self.lambda,
        }
    }
}

/// How the served field is made from the network's output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// prior + output (paper Method 1).
    Residual,
    /// output alone (base networks and Kelvinlet-regularized networks, paper Method 2).
    Direct,
}

/// How the network was trained: the paper's Base, Method 1 (+Res) or Method 2 (+Reg).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Regresses the field directly from FEM data.
    Base,
    /// Learns the residual to the Kelvinlet prior; served as prior + output.
    Res,
    /// Regresses the field directly, trained with a Kelvinlet regularization term.
    Reg,
}

impl Method {
    /// The serving mode this method implies.
    pub fn mode(self) -> Mode {
        match self {
            Method::Res => Mode::Residual,
            Method::Base | Method::Reg => Mode::Direct,
        }
    }
}

/// How the served grasp forces are made from a graph's `forces` output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ForcesMode {
    /// The prior's own forces (green-linear's or green-tangent's (G[S,S])⁻¹ u_S) plus the output.
    Residual,
    /// The output alone.
    Direct,
}

/// `[forces]`: present exactly when the graph gives `forces`; how they are served, and their error on
/// the test split (reported by ListModels as `forces.*`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ForcesSection {
    pub mode: ForcesMode,
    #[serde(flatten)]
    pub metrics: BTreeMap<String, toml::Value>,
}

/// Input channel groups, in the order they appear in `features`; or `interaction`, the K interaction
/// points alone (rest position and prescribed displacement, docs/design.md §7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Channel {
    Position,
    Displacement,
    Active,
    Prior,
    Interaction,
}

impl Channel {
    pub fn width(self) -> usize {
        match self {
            Channel::Active => 1,
            Channel::Interaction => 6,
            _ => 3,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub model: ModelSection,
    pub mesh: MeshSection,
    pub prior: PriorSection,
    /// Measured on the test split (DCM per subset, …), reported by ListModels.
    #[serde(default)]
    pub metrics: BTreeMap<String, toml::Value>,
    #[serde(default)]
    pub provenance: BTreeMap<String, toml::Value>,
    /// For graphs with a `forces` output.
    #[serde(default)]
    pub forces: Option<ForcesSection>,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSection {
    pub name: String,
    pub mode: Mode,
    pub method: Method,
    pub regime: String,
    pub inputs: Vec<Channel>,
    #[serde(default)]
    pub description: String,
    /// The hyperelastic law of the data a nonlinear model was trained on (see
    /// [`Manifest::volumetric_law`]).
    #[serde(default)]
    pub volumetric_law: Option<VolumetricLaw>,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshSection {
    pub name: String,
    pub content_hash: String,
    pub node_count: usize,
}

/// The paper's feature vector f = [x; u_s; a]: every model reads these first.
const REQUIRED: [Channel; 3] = [Channel::Position, Channel::Displacement, Channel::Active];

impl Manifest {
    /// The law a nonlinear model's training data was solved under: the manifest's, or for models
    /// exported before manifests named it, (κ/2)(J − 1)². `None` for linear models.
    pub fn volumetric_law(&self) -> Option<VolumetricLaw> {
        (self.model.regime == Regime::Nonlinear.name())
            .then(|| self.model.volumetric_law.unwrap_or(VolumetricLaw::JMinusOneSquared))
    }

    pub fn parse(text: &str, origin: &str) -> Result<Self, ModelLoadError> {
        let manifest: Manifest = toml::from_str(text).map_err(|e| ModelLoadError::new(origin, e.to_string()))?;
        let inputs = &manifest.model.inputs;
        let per_node = matches!(&inputs[..], [a, b, c] | [a, b, c, Channel::Prior] if [*a, *b, *c] == REQUIRED);
        if !per_node && inputs[..] != [Channel::Interaction] {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "model.inputs = {inputs:?}: the contract is [\"position\", \"displacement\", \"active\"], \
                     optionally followed by \"prior\", or [\"interaction\"]"
                ),
            ));
        }
        if Regime::from_name(&manifest.model.regime).is_none() {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "model.regime = {:?}: expected \"linear\" or \"nonlinear\"",
                    manifest.model.regime
                ),
            ));
        }
        let method = manifest.model.method;
        if method.mode() != manifest.model.mode {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "model.method = {method:?} is served in mode {:?}, but model.mode = {:?}",
                    method.mode(),
                    manifest.model.mode
                ),
            ));
        }
        if let Some(forces) = &manifest.forces {
            if !manifest.reads_interaction() {
                return Err(ModelLoadError::new(
                    origin,
                    "[forces]: learned forces are per interaction point, so the model's inputs must be \
                     [\"interaction\"]",
                ));
            }
            let prior_has_forces = matches!(manifest.prior.model, PriorModel::GreenLinear | PriorModel::GreenTangent);
            if forces.mode == ForcesMode::Residual && !(prior_has_forces && manifest.model.mode == Mode::Residual) {
                return Err(ModelLoadError::new(
                    origin,
                    format!(
                        "forces.mode = \"residual\" adds the output to the prior's forces: it needs model.mode = \
                         \"residual\" on prior.model = \"green-linear\" or \"green-tangent\" (this model: {:?} on \
                         {:?})",
                        manifest.model.mode, manifest.prior.model
                    ),
                ));
            }
        }
        let prior = manifest.prior.kelvinlet();
        let valid = prior.poisson_ratio > 0.0
            && prior.poisson_ratio < 0.5
            && prior.epsilon > 0.0
            && prior.epsilon.is_finite()
            && prior.lambda >= 0.0
            && prior.lambda.is_finite();
        if !valid {
            return Err(ModelLoadError::new(
                origin,
                format!("prior {prior:?}: expected 0 < poisson_ratio < 0.5, epsilon_m > 0 and lambda >= 0"),
            ));
        }
        Ok(manifest)
    }

    /// Whether the graph reads the interaction points alone (`interaction`) rather than `features`.
    pub fn reads_interaction(&self) -> bool {
        self.model.inputs == [Channel::Interaction]
    }

    /// Channels per node in `features` (per point in `interaction`).
    pub fn channels(&self) -> usize {
        self.model.inputs.iter().map(|c| c.width()).sum()
    }

    pub fn reads_prior(&self) -> bool {
        self.model.inputs.contains(&Channel::Prior)
    }

    /// Refuses a model made for another mesh. The prior is the model's own (it is served with the
    /// parameters it was trained with), so it may differ from the mesh's.
    pub fn check_against(&self, mesh: &TetMesh, origin: &str) -> Result<(), ModelLoadError> {
        if self.mesh.node_count != mesh.node_count() {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "made for a mesh of {} nodes; the served mesh {:?} has {}",
                    self.mesh.node_count,
                    mesh.config.name,
                    mesh.node_count()
                ),
            ));
        }
        if self.mesh.content_hash != mesh.content_hash {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "made for mesh {} ({}); the served mesh {:?} is {}",
                    self.mesh.name, self.mesh.content_hash, mesh.config.name, mesh.content_hash
                ),
            ));
        }
        // A nonlinear network answers under the law of its training data; served beside a mesh of
        // another law it would disagree with the mesh's own green-tangent and ground truth.
        if let Some(law) = self.volumetric_law()
            && law != mesh.config.volumetric_law
        {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "trained on data solved under the volumetric law {law}; the served mesh {:?} is solved \
                     under {}: retrain it on data of the mesh's law",
                    mesh.config.name, mesh.config.volumetric_law
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest(regime: &str, law: &str) -> Manifest {
        let text = format!(
            "[model]\nname = \"m\"\nmode = \"direct\"\nmethod = \"base\"\nregime = \"{regime}\"\n{law}\
             inputs = [\"interaction\"]\n[mesh]\nname = \"box\"\ncontent_hash = \"0\"\nnode_count = 1\n\
             [prior]\npoisson_ratio = 0.45\nepsilon_m = 0.01\nlambda = 0.001\n"
        );
        Manifest::parse(&text, "manifest.toml").unwrap()
    }

    #[test]
    fn a_nonlinear_model_names_its_law_and_one_that_does_not_was_made_under_the_old_one() {
        let law = "volumetric_law = \"ln-j-squared\"\n";
        assert_eq!(
            manifest("nonlinear", law).volumetric_law(),
            Some(VolumetricLaw::LnJSquared)
        );
        assert_eq!(
            manifest("nonlinear", "").volumetric_law(),
            Some(VolumetricLaw::JMinusOneSquared)
        );
        assert_eq!(manifest("linear", "").volumetric_law(), None);
        let unknown = "volumetric_law = \"neo-hookean\"\n";
        let text = format!("[model]\nname = \"m\"\n{unknown}");
        let error = Manifest::parse(&text, "manifest.toml").unwrap_err().to_string();
        assert!(
            error.contains("neo-hookean") && error.contains("ln-j-squared"),
            "{error}"
        );
    }

    #[test]
    fn a_nonlinear_model_of_another_law_than_the_served_mesh_is_refused_naming_both() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
        let mesh = crate::mesh::load(&crate::mesh::MeshSource::File(path)).unwrap();
        assert_eq!(mesh.config.volumetric_law, VolumetricLaw::LnJSquared);
        let made_for = |regime: &str, law: &str| {
            let mut m = manifest(regime, law);
            m.mesh.content_hash = mesh.content_hash.clone();
            m.mesh.node_count = mesh.node_count();
            m
        };
        let old = made_for("nonlinear", "volumetric_law = \"j-minus-one-squared\"\n");
        let error = old.check_against(&mesh, "models/m").unwrap_err().to_string();
        assert!(
            error.contains("models/m") && error.contains("j-minus-one-squared") && error.contains("ln-j-squared"),
            "{error}"
        );
        // A nonlinear model from before manifests named a law was made under the old one.
        assert!(made_for("nonlinear", "").check_against(&mesh, "m").is_err());
        let today = made_for("nonlinear", "volumetric_law = \"ln-j-squared\"\n");
        assert!(today.check_against(&mesh, "m").is_ok());
        assert!(made_for("linear", "").check_against(&mesh, "m").is_ok());
    }
}
