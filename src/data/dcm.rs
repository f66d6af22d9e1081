//! The paper's DCM metric (DESIGN.md §6): `100 · (1 − E[‖u_true − û‖ / ‖u_true‖])` with the L2(Ω)
//! norm approximated by lumped nodal volumes, and its unweighted nodal variant.

use serde::Serialize;

/// Relative errors of one sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampleError {
    /// ‖u_true − û‖_{L2(Ω)} / ‖u_true‖_{L2(Ω)}, ‖u‖² ≈ Σ V_n |u_n|².
    pub volume: f64,
    /// The same with every node weighted equally.
    pub nodal: f64,
}

/// Both relative errors of an estimate of `truth`; fields are row-major (N, 3).
pub fn sample_error(truth: &[f32], estimate: &[f32], nodal_volumes: &[f64]) -> SampleError {
    let (mut dv, mut tv, mut dn, mut tn) = (0.0, 0.0, 0.0, 0.0);
    for ((t, e), v) in truth.chunks_exact(3).zip(estimate.chunks_exact(3)).zip(nodal_volumes) {
        let d2: f64 = (0..3).map(|k| (t[k] as f64 - e[k] as f64).powi(2)).sum();
        let t2: f64 = (0..3).map(|k| (t[k] as f64).powi(2)).sum();
        dv += v * d2;
        tv += v * t2;
        dn += d2;
        tn += t2;
    }
    SampleError {
        volume: (dv / tv).sqrt(),
        nodal: (dn / tn).sqrt(),
    }
}

/// DCM and the distribution of the volume-weighted relative error over a set of samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Summary {
    pub samples: usize,
    /// Volume-weighted DCM, percent.
    pub dcm: f64,
    /// Nodal DCM, percent.
    pub dcm_nodal: f64,
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
    let median = if volume.len() % 2 == 1 {
        volume[volume.len() / 2]
    } else {
        (volume[volume.len() / 2 - 1] + volume[volume.len() / 2]) / 2.0
    };
    Some(Summary {
        samples: errors.len(),
        dcm: 100.0 * (1.0 - mean),
        dcm_nodal: 100.0 * (1.0 - errors.iter().map(|e| e.nodal).sum::<f64>() / n),
        mean_error: mean,
        median_error: median,
        max_error: volume[volume.len() - 1],
    })
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
