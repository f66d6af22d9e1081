//! The two regimes nak's data and models come in, and which served model answers a regime best: the
//! model a request that names none gets when the server is told the regime its organ is in.

use super::model::{ModelInfo, ModelKind};

/// The manifest figure models are ranked by: combined DCM (%) on held-out samples, measured through
/// `nak eval` and reported by `ListModels` (docs/design.md §6).
pub const ACCURACY_KEY: &str = "metrics.dcm_combined";

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Regime {
    /// Small grasps of the organ at rest, as linear elasticity answers them.
    Linear,
    /// The organ hanging under gravity from its fixed area (its preloaded state), grasped as a
    /// Mooney–Rivlin solid: large rotations and deep pushes, the regime surgery lives in.
    Nonlinear,
}

impl Regime {
    /// The name models' `regime` fields and datasets use.
    pub const fn name(self) -> &'static str {
        match self {
            Regime::Linear => "linear",
            Regime::Nonlinear => "nonlinear",
        }
    }

    /// The regime a model's manifest or a dataset names; `None` for any other word.
    pub fn from_name(name: &str) -> Option<Self> {
        [Regime::Linear, Regime::Nonlinear]
            .into_iter()
            .find(|r| r.name() == name)
    }
}

impl std::fmt::Display for Regime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The most accurate of `models` in `regime`. The linear regime's data is the linear FEM, so an exact
/// model of it (green-linear) answers it exactly and comes first; otherwise the model with the highest
/// held-out DCM in its manifest ([`ACCURACY_KEY`]). Models without that figure are never chosen: an
/// unscored model's accuracy is unknown (green-tangent is exact only for small grasps).
pub fn most_accurate<'a>(models: impl Iterator<Item = &'a ModelInfo>, regime: Regime) -> Option<&'a ModelInfo> {
    let rank = |info: &ModelInfo| -> Option<f64> {
        if info.regime != regime.name() {
            return None;
        }
        if regime == Regime::Linear && info.kind == ModelKind::Exact {
            return Some(f64::INFINITY);
        }
        info.metadata
            .get(ACCURACY_KEY)?
            .parse::<f64>()
            .ok()
            .filter(|dcm| dcm.is_finite())
    };
    models
        .filter_map(|info| rank(info).map(|score| (score, info)))
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, info)| info)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::engine::Forces;

    fn info(name: &str, kind: ModelKind, regime: &str, dcm: Option<&str>) -> ModelInfo {
        ModelInfo {
            name: name.into(),
            kind,
            mesh: String::new(),
            regime: regime.into(),
            metadata: dcm
                .map(|d| BTreeMap::from([(ACCURACY_KEY.to_owned(), d.to_owned())]))
                .unwrap_or_default(),
            forces: Forces::Unavailable,
        }
    }

    #[test]
    fn the_highest_held_out_dcm_of_the_regime_wins() {
        let models = [
            info("kelvinlet", ModelKind::Prior, "", None),
            info("green-tangent", ModelKind::Exact, "nonlinear", None),
            info("pod-res", ModelKind::Neural, "linear", Some("99.5")),
            info("pod-res-gl-nl", ModelKind::Neural, "nonlinear", Some("65.75")),
            info("pod-base-nl", ModelKind::Neural, "nonlinear", Some("71.029")),
            info("broken", ModelKind::Neural, "nonlinear", Some("NaN")),
        ];
        let best = most_accurate(models.iter(), Regime::Nonlinear).map(|m| m.name.as_str());
        assert_eq!(best, Some("pod-base-nl"));
        let linear = most_accurate(models.iter(), Regime::Linear).map(|m| m.name.as_str());
        assert_eq!(linear, Some("pod-res"));
    }

    #[test]
    fn a_regime_is_read_back_from_its_name_and_no_other_word() {
        for regime in [Regime::Linear, Regime::Nonlinear] {
            assert_eq!(Regime::from_name(regime.name()), Some(regime));
        }
        assert_eq!(Regime::from_name("Nonlinear"), None);
    }

    #[test]
    fn the_exact_linear_model_answers_the_linear_regime_and_unscored_models_are_never_chosen() {
        let models = [
            info("pod-res", ModelKind::Neural, "linear", Some("99.5")),
            info("green-linear", ModelKind::Exact, "linear", None),
            info("green-tangent", ModelKind::Exact, "nonlinear", None),
        ];
        let linear = most_accurate(models.iter(), Regime::Linear).map(|m| m.name.as_str());
        assert_eq!(linear, Some("green-linear"));
        assert!(most_accurate(models.iter(), Regime::Nonlinear).is_none());
    }
}
