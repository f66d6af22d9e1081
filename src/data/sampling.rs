//! The paper's grasp distribution p (docs/design.md §5), reproducible sample by sample from (seed, index).
//!
//! A grasper picks a region Ω_i with probability g(Ω_i), a surface node of that region with a
//! Gaussian radial density around the region's centre (spread: the region's RMS radius), and holds it
//! with its 3–7 nearest surface neighbours; its displacement is uniform in the cuboid
//! x, y ∈ (−90, 50) mm, z ∈ (−60, 90) mm. A second grasper draws its region with g(Ω_first) = 0 and the
//! rest renormalized.

use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::engine::Grasp;
use crate::mesh::{Sampling, TetMesh};

/// One grasp region with its sampling weights precomputed.
#[derive(Debug, Clone, PartialEq)]
pub struct RegionSampler {
    pub name: String,
    pub weight: f64,
    pub nodes: Vec<u32>,
    /// Unnormalized Gaussian weight of each node, by distance from the region's centre.
    node_weights: Vec<f64>,
}

/// Everything needed to draw grasps on one mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct GraspSampler {
    positions: Vec<[f64; 3]>,
    surface_nodes: Vec<u32>,
    /// Sorted: held by the fixture, so no grasper holds them too.
    fixed: Vec<u32>,
    regions: Vec<RegionSampler>,
    displacement_min: [f64; 3],
    displacement_max: [f64; 3],
    neighbours: (usize, usize),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SamplingError {
    #[error("grasp region {0:?} is not a node set of the mesh")]
    MissingRegion(String),
    #[error("the grasp regions' weights do not add up to a positive number")]
    NoWeight,
    #[error("{0} graspers need {0} regions with positive weight")]
    TooFewRegions(usize),
}

impl GraspSampler {
    pub fn from_mesh(mesh: &TetMesh) -> Result<Self, SamplingError> {
        let node_sets = |name: &str| mesh.node_sets.get(name).cloned();
        Self::new(&mesh.positions, &mesh.surface_nodes, &mesh.config.sampling, node_sets)
    }

    /// From raw parts, e.g. what a server reports in GetMesh.
    pub fn new(
        positions: &[[f64; 3]],
        surface_nodes: &[u32],
        sampling: &Sampling,
        node_set: impl Fn(&str) -> Option<Vec<u32>>,
    ) -> Result<Self, SamplingError> {
        let mut regions = Vec::new();
        for region in &sampling.grasp_regions {
            let nodes = node_set(&region.node_set)
                .filter(|n| !n.is_empty())
                .ok_or_else(|| SamplingError::MissingRegion(region.node_set.clone()))?;
            let points: Vec<[f64; 3]> = nodes.iter().map(|&n| positions[n as usize]).collect();
            let centre: [f64; 3] =
                std::array::from_fn(|k| points.iter().map(|p| p[k]).sum::<f64>() / points.len() as f64);
            let d2: Vec<f64> = points
                .iter()
                .map(|p| (0..3).map(|k| (p[k] - centre[k]).powi(2)).sum())
                .collect();
            let sigma2 = (d2.iter().sum::<f64>() / d2.len() as f64).max(1e-12);
            regions.push(RegionSampler {
                name: region.node_set.clone(),
                weight: region.weight,
                nodes,
                node_weights: d2.iter().map(|d| (-d / (2.0 * sigma2)).exp()).collect(),
            });
        }
        if regions.iter().map(|r| r.weight).sum::<f64>() <= 0.0 {
            return Err(SamplingError::NoWeight);
        }
        let mut fixed = node_set("fixed").unwrap_or_default();
        fixed.sort_unstable();
        Ok(Self {
            positions: positions.to_vec(),
            surface_nodes: surface_nodes.to_vec(),
            fixed,
            regions,
            displacement_min: sampling.displacement_min,
            displacement_max: sampling.displacement_max,
            neighbours: sampling.neighbours,
        })
    }

    pub fn regions(&self) -> &[RegionSampler] {
        &self.regions
    }

    /// Sample `index` of the stream `seed`: `graspers` grasps in distinct regions, with the index of
    /// each grasp's region.
    pub fn sample(&self, seed: u64, index: u64, graspers: usize) -> Result<Vec<(usize, Grasp)>, SamplingError> {
        let positive = self.regions.iter().filter(|r| r.weight > 0.0).count();
        if graspers > positive {
            return Err(SamplingError::TooFewRegions(graspers));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(index);
        let mut weights: Vec<f64> = self.regions.iter().map(|r| r.weight).collect();
        let mut grasps: Vec<(usize, Grasp)> = Vec::with_capacity(graspers);
        for _ in 0..graspers {
            let r = pick(&mut rng, &weights);
            weights[r] = 0.0;
            // Two graspers cannot hold the same tissue: a node held by one is no neighbour of another.
            let held: Vec<u32> = grasps.iter().flat_map(|(_, g)| g.nodes.iter().copied()).collect();
            grasps.push((r, self.grasp_in(&mut rng, &self.regions[r], &held)));
        }
        Ok(grasps)
    }

    fn grasp_in(&self, rng: &mut ChaCha8Rng, region: &RegionSampler, held: &[u32]) -> Grasp {
        let free: Vec<f64> = region
            .nodes
            .iter()
            .zip(&region.node_weights)
            .map(|(n, &w)| if held.contains(n) { 0.0 } else { w })
            .collect();
        // A region is never covered by another grasper's handful of nodes; if it were, fall back to it.
        let weights = if free.iter().sum::<f64>() > 0.0 {
            &free
        } else {
            &region.node_weights
        };
        let centre = region.nodes[pick(rng, weights)];
        let extra = rng.random_range(self.neighbours.0..=self.neighbours.1);
        let c = self.positions[centre as usize];
        // A grasp next to the fixed surface holds free nodes only: a fixed node cannot be moved (and
        // its zero column would make the exact models' G[S,S] singular).
        let mut by_distance: Vec<(f64, u32)> = self
            .surface_nodes
            .iter()
            .filter(|&&n| n != centre && !held.contains(&n) && self.fixed.binary_search(&n).is_err())
            .map(|&n| {
                let p = self.positions[n as usize];
                ((0..3).map(|k| (p[k] - c[k]).powi(2)).sum(), n)
            })
            .collect();
        let extra = extra.min(by_distance.len());
        if extra > 0 {
            by_distance.select_nth_unstable_by(extra - 1, |a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        }
        let mut nodes = vec![centre];
        nodes.extend(by_distance[..extra].iter().map(|&(_, n)| n));
        let displacement =
            std::array::from_fn(|k| rng.random_range(self.displacement_min[k]..self.displacement_max[k]));
        Grasp {
            nodes,
            displacement,
            ..Grasp::default()
        }
    }
}

/// An index drawn with probability proportional to `weights` (not all zero).
fn pick(rng: &mut impl Rng, weights: &[f64]) -> usize {
    let total: f64 = weights.iter().sum();
    let mut target = rng.random_range(0.0..total);
    for (i, w) in weights.iter().enumerate() {
        if target < *w {
            return i;
        }
        target -= w;
    }
    weights.iter().rposition(|w| *w > 0.0).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{self, MeshSource};

    fn sampler() -> (TetMesh, GraspSampler) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
        let m = mesh::load(&MeshSource::File(path)).unwrap();
        let s = GraspSampler::from_mesh(&m).unwrap();
        (m, s)
    }

    #[test]
    fn samples_are_reproducible_from_seed_and_index() {
        let (_, s) = sampler();
        assert_eq!(s.sample(7, 123, 2).unwrap(), s.sample(7, 123, 2).unwrap());
        assert_ne!(s.sample(7, 123, 2).unwrap(), s.sample(7, 124, 2).unwrap());
        assert_ne!(s.sample(7, 123, 2).unwrap(), s.sample(8, 123, 2).unwrap());
    }

    #[test]
    fn grasps_follow_the_papers_distribution() {
        let (m, s) = sampler();
        let (lo, hi) = (m.config.sampling.displacement_min, m.config.sampling.displacement_max);
        let mut region_counts = vec![0usize; s.regions().len()];
        for i in 0..2000 {
            let grasps = s.sample(1, i, 2).unwrap();
            assert_ne!(grasps[0].0, grasps[1].0, "two graspers in one region");
            assert!(
                grasps[0].1.nodes.iter().all(|n| !grasps[1].1.nodes.contains(n)),
                "shared node"
            );
            for (r, g) in &grasps {
                region_counts[*r] += 1;
                assert!((4..=8).contains(&g.nodes.len()));
                assert!(s.regions()[*r].nodes.contains(&g.nodes[0]));
                assert!(g.nodes.iter().all(|&n| m.is_surface[n as usize]));
                for k in 0..3 {
                    assert!(lo[k] <= g.displacement[k] && g.displacement[k] < hi[k]);
                }
            }
        }
        // Equal weights: each region gets about a tenth of 4,000 grasps.
        for c in region_counts {
            assert!((300..500).contains(&c), "{c}");
        }
    }
}
