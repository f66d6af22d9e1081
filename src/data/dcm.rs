//! The paper's DCM metric (docs/design.md §6): `100 · (1 − E[‖u_true − û‖ / ‖u_true‖])` with the L2(Ω)
//! norm approximated by lumped nodal volumes, its unweighted nodal variant, and the form the paper's
//! public code computes (and its tables report): per sample and axis the norms over nodes of error and
//! truth, `100 · (1 − mean ‖e_c‖ / mean ‖u_c‖)`, a ratio of means over the whole split.

use serde::Serialize;

/// Relative errors of one sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SampleError {
    /// ‖u_true − û‖_{L2(Ω)} / ‖u_true‖_{L2(Ω)}, ‖u‖² ≈ Σ V_n |u_n|².
    pub volume: f64,
    /// The same with every node weighted equally.
    pub nodal: f64,
    /// Per axis, the norm over nodes of the error (the paper's code form).
    pub axis_error: [f64; 3],
    /// Per axis, the norm over nodes of the truth.
    pub axis_truth: [f64; 3],
}

/// Both relative errors of an estimate of `truth`; fields are row-major (N, 3).
pub fn sample_error(truth: &[f32], estimate: &[f32], nodal_volumes: &[f64]) -> SampleError {
    let (mut dv, mut tv, mut dn, mut tn) = (0.0, 0.0, 0.0, 0.0);
    let (mut axis_error, mut axis_truth) = ([0.0; 3], [0.0; 3]);
    for ((t, e), v) in truth.chunks_exact(3).zip(estimate.chunks_exact(3)).zip(nodal_volumes) {
        let d: [f64; 3] = std::array::from_fn(|k| (t[k] as f64 - e[k] as f64).powi(2));
        let tt: [f64; 3] = std::array::from_fn(|k| (t[k] as f64).powi(2));
        for k in 0..3 {
            axis_error[k] += d[k];
            axis_truth[k] += tt[k];
        }
        let (d2, t2): (f64, f64) = (d.iter().sum(), tt.iter().sum());
        dv += v * d2;
        tv += v * t2;
        dn += d2;
        tn += t2;
    }
    SampleError {
        volume: (dv / tv).sqrt(),
        nodal: (dn / tn).sqrt(),
        axis_error: axis_error.map(f64::sqrt),
        axis_truth: axis_truth.map(f64::sqrt),
    }
}

/// DCM and the distribution of the volume-weighted relative error over a set of samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Summary {
    pub samples: usize,
    /// Volume-weighted DCM, percent.
    pub dcm: f64,
    /// Its standard error, percentage points: the sample standard deviation of the per-sample errors
    /// over √n, how far another draw of as many samples would move it (about one in three draws by
    /// more); `None` for one sample.
    pub dcm_standard_error: Option<f64>,
    /// Nodal DCM, percent.
    pub dcm_nodal: f64,
    /// The paper's code form, percent: 1 − Σ‖e_c‖ / Σ‖u_c‖ over samples and axes.
    pub dcm_code: f64,
    pub mean_error: f64,
    pub median_error: f64,
    pub max_error: f64,
}

pub fn summarize(errors: &[SampleError]) -> Option<Summary> {
    if errors.is_empty() {
        return None;
    }
    let n = errors.len() as f64;
    let mut volume: Vec<f64> = errors.iter().map(|e| e.volume).collect();
    volume.sort_by(f64::total_cmp);
    let mean = volume.iter().sum::<f64>() / n;
    let median = median_of_sorted(&volume);
    let variance = volume.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1.0);
    Some(Summary {
        samples: errors.len(),
        dcm: 100.0 * (1.0 - mean),
        dcm_standard_error: (errors.len() > 1).then(|| 100.0 * (variance / n).sqrt()),
        dcm_nodal: 100.0 * (1.0 - errors.iter().map(|e| e.nodal).sum::<f64>() / n),
        dcm_code: 100.0
            * (1.0
                - errors.iter().flat_map(|e| e.axis_error).sum::<f64>()
                    / errors.iter().flat_map(|e| e.axis_truth).sum::<f64>()),
        mean_error: mean,
        median_error: median,
        max_error: volume[volume.len() - 1],
    })
}

/// The median of sorted, non-empty `values`.
pub(crate) fn median_of_sorted(values: &[f64]) -> f64 {
    let mid = values.len() / 2;
    if values.len() % 2 == 1 {
        values[mid]
    } else {
        (values[mid - 1] + values[mid]) / 2.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_estimates_score_100_and_zero_estimates_score_0() {
        let truth = [0.01, 0.0, 0.0, 0.0, 0.02, 0.0];
        let volumes = [1.0, 3.0];
        let exact = sample_error(&truth, &truth, &volumes);
        assert_eq!((exact.volume, exact.nodal), (0.0, 0.0));
        let zero = sample_error(&truth, &[0.0; 6], &volumes);
        assert!((zero.volume - 1.0).abs() < 1e-12 && (zero.nodal - 1.0).abs() < 1e-12);
        let s = summarize(&[exact, zero]).unwrap();
        assert!((s.dcm - 50.0).abs() < 1e-9 && s.max_error == 1.0 && s.median_error == 0.5);
        assert!((s.dcm_code - 50.0).abs() < 1e-9, "{}", s.dcm_code);
        // Errors 0 and 1: sample variance 0.5, standard error √(0.5 / 2) = 0.5.
        assert!((s.dcm_standard_error.unwrap() - 50.0).abs() < 1e-9);
        assert_eq!(summarize(&[exact]).unwrap().dcm_standard_error, None);
    }

    #[test]
    fn the_code_form_is_a_ratio_of_means_so_large_fields_weigh_more() {
        // Sample A: 1 cm truth, 50 % error; sample B: 10 cm truth, exact. Mean of ratios: 25 %
        // error; the code form: 0.5 cm of error over 11 cm of truth summed over axes.
        let volumes = [1.0];
        let a = sample_error(&[0.01, 0.0, 0.0], &[0.005, 0.0, 0.0], &volumes);
        let b = sample_error(&[0.1, 0.0, 0.0], &[0.1, 0.0, 0.0], &volumes);
        let s = summarize(&[a, b]).unwrap();
        assert!((s.dcm - 75.0).abs() < 1e-6, "{}", s.dcm);
        assert!(
            (s.dcm_code - 100.0 * (1.0 - 0.005 / 0.11)).abs() < 1e-6,
            "{}",
            s.dcm_code
        );
    }

    #[test]
    fn volume_weighting_counts_large_cells_more() {
        // Error only at the node with the larger volume: the weighted error exceeds the nodal one.
        let truth = [0.01f32, 0.0, 0.0, 0.01, 0.0, 0.0];
        let estimate = [0.01f32, 0.0, 0.0, 0.0, 0.0, 0.0];
        let e = sample_error(&truth, &estimate, &[1.0, 3.0]);
        assert!((e.volume - (3.0f64 / 4.0).sqrt()).abs() < 1e-6);
        assert!((e.nodal - (1.0f64 / 2.0).sqrt()).abs() < 1e-6);
    }
}
