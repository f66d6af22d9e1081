//! How far a model's grasp forces are from the finite-element ones: per grasp, the relative error of
//! the force vector, the ratio of magnitudes and the angle between them (a force can be of the right
//! size and point the wrong way, or the reverse; a haptic device renders both mistakes).

use serde::Serialize;

use super::dcm::median_of_sorted;

/// One grasp's force against the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraspForceError {
    /// |f̂ − f| / |f|.
    pub relative: f64,
    /// |f̂| / |f|.
    pub magnitude_ratio: f64,
    /// Angle between f̂ and f, degrees.
    pub angle_deg: f64,
}

fn norm(v: &[f64; 3]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The error of `estimate` against `truth`; `None` when the true force is zero (nothing to compare
/// against: a grasp that holds no node of its own).
pub fn grasp_force_error(truth: &[f64; 3], estimate: &[f64; 3]) -> Option<GraspForceError> {
    let (t, e) = (norm(truth), norm(estimate));
    if t == 0.0 {
        return None;
    }
    let difference: [f64; 3] = std::array::from_fn(|k| estimate[k] - truth[k]);
    let cosine = if e == 0.0 {
        0.0
    } else {
        (truth.iter().zip(estimate).map(|(a, b)| a * b).sum::<f64>() / (t * e)).clamp(-1.0, 1.0)
    };
    Some(GraspForceError {
        relative: norm(&difference) / t,
        magnitude_ratio: e / t,
        angle_deg: cosine.acos().to_degrees(),
    })
}

/// Grasp force errors over a set of samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ForceSummary {
    pub grasps: usize,
    pub mean_relative_error: f64,
    pub median_relative_error: f64,
    pub median_magnitude_ratio: f64,
    pub median_angle_deg: f64,
}

pub fn summarize(errors: &[GraspForceError]) -> Option<ForceSummary> {
    if errors.is_empty() {
        return None;
    }
    let median = |f: fn(&GraspForceError) -> f64| {
        let mut values: Vec<f64> = errors.iter().map(f).collect();
        values.sort_by(f64::total_cmp);
        median_of_sorted(&values)
    };
    Some(ForceSummary {
        grasps: errors.len(),
        mean_relative_error: errors.iter().map(|e| e.relative).sum::<f64>() / errors.len() as f64,
        median_relative_error: median(|e| e.relative),
        median_magnitude_ratio: median(|e| e.magnitude_ratio),
        median_angle_deg: median(|e| e.angle_deg),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_separate_size_from_direction() {
        let truth = [0.0, 2.0, 0.0];
        let exact = grasp_force_error(&truth, &truth).unwrap();
        assert_eq!(
            (exact.relative, exact.magnitude_ratio, exact.angle_deg),
            (0.0, 1.0, 0.0)
        );
        let doubled = grasp_force_error(&truth, &[0.0, 4.0, 0.0]).unwrap();
        assert!((doubled.relative - 1.0).abs() < 1e-12 && doubled.angle_deg.abs() < 1e-9);
        let turned = grasp_force_error(&truth, &[2.0, 0.0, 0.0]).unwrap();
        assert!((turned.magnitude_ratio - 1.0).abs() < 1e-12 && (turned.angle_deg - 90.0).abs() < 1e-9);
        assert!((turned.relative - 2f64.sqrt()).abs() < 1e-12);
        assert!(grasp_force_error(&[0.0; 3], &truth).is_none());
        let s = summarize(&[exact, doubled, turned]).unwrap();
        assert!((s.mean_relative_error - (1.0 + 2f64.sqrt()) / 3.0).abs() < 1e-12);
        assert_eq!(
            (s.grasps, s.median_relative_error, s.median_magnitude_ratio),
            (3, 1.0, 1.0)
        );
    }
}
