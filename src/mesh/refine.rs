//! Uniform refinement: every tetrahedron split into eight at its edge midpoints (Bey's "red"
//! refinement), for a finer mesh of the same organ: about seven times the nodes per level.

use std::collections::{HashMap, HashSet};

use super::msh::{ElementBlock, MshFile, POINT, TETRAHEDRON};
use super::topology::{Vec3, tet_volume};
use super::{MeshError, TetMesh};

/// The nodes of the refined mesh: the old ones, then one per split edge.
struct Nodes {
    positions: Vec<Vec3>,
    midpoints: HashMap<(u32, u32), u32>,
}

impl Nodes {
    fn midpoint(&mut self, a: u32, b: u32) -> u32 {
        let positions = &mut self.positions;
        *self.midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
            let (p, q) = (positions[a as usize], positions[b as usize]);
            positions.push(std::array::from_fn(|k| 0.5 * (p[k] + q[k])));
            (positions.len() - 1) as u32
        })
    }

    fn squared_distance(&self, a: u32, b: u32) -> f64 {
        let (p, q) = (self.positions[a as usize], self.positions[b as usize]);
        (0..3).map(|k| (p[k] - q[k]).powi(2)).sum()
    }

    /// `tet` with two vertices swapped if it is negatively oriented.
    fn positively_oriented(&self, [a, b, c, d]: [u32; 4]) -> [u32; 4] {
        let volume = tet_volume([a, b, c, d].map(|n| self.positions[n as usize]));
        if volume < 0.0 { [a, c, b, d] } else { [a, b, c, d] }
    }
}

impl TetMesh {
    /// The mesh with each tetrahedron split into eight. Nodes keep their indices; the midpoints
    /// follow them. Each child keeps its parent's region. A node set gains the midpoints of the
    /// boundary edges between two of its nodes, so that it stays the same patch of the surface. The
    /// result is validated as any loaded mesh is.
    pub fn refined(&self) -> Result<TetMesh, MeshError> {
        let mut nodes = Nodes {
            positions: self.positions.clone(),
            midpoints: HashMap::new(),
        };
        let mut tets = Vec::with_capacity(8 * self.tets.len());
        for &[v0, v1, v2, v3] in &self.tets {
            let (m01, m02, m03) = (nodes.midpoint(v0, v1), nodes.midpoint(v0, v2), nodes.midpoint(v0, v3));
            let (m12, m13, m23) = (nodes.midpoint(v1, v2), nodes.midpoint(v1, v3), nodes.midpoint(v2, v3));
            tets.extend([
                [v0, m01, m02, m03],
                [m01, v1, m12, m13],
                [m02, m12, v2, m23],
                [m03, m13, m23, v3],
            ]);
            // The inner octahedron, cut along its shortest diagonal into four tetrahedra around it;
            // each ring lists the other four midpoints so that neighbours in it share an edge.
            let cuts = [
                ((m02, m13), [m01, m03, m23, m12]),
                ((m01, m23), [m02, m03, m13, m12]),
                ((m03, m12), [m01, m02, m23, m13]),
            ];
            let ((p, q), ring) = cuts
                .into_iter()
                .min_by(|x, y| {
                    nodes
                        .squared_distance(x.0.0, x.0.1)
                        .total_cmp(&nodes.squared_distance(y.0.0, y.0.1))
                })
                .unwrap_or(cuts[0]);
            tets.extend((0..4).map(|k| [p, q, ring[k], ring[(k + 1) % 4]]));
        }
        let tets: Vec<[u32; 4]> = tets.into_iter().map(|t| nodes.positively_oriented(t)).collect();
        let file = self.labelled(&nodes, &tets);
        TetMesh::from_labelled(file, &format!("{} (refined)", self.origin), self.config.clone())
    }

    /// The refined mesh in the labelled form a mesh is built from: one volume block per region
    /// (children follow their parents, eight each), one point block per node set.
    fn labelled(&self, nodes: &Nodes, tets: &[[u32; 4]]) -> MshFile {
        let mut file = MshFile {
            node_tags: (1..=nodes.positions.len() as u64).collect(),
            node_coords: nodes.positions.clone(),
            ..MshFile::default()
        };
        for (index, region) in self.regions.iter().enumerate() {
            let entity = index as i32 + 1;
            let members: Vec<usize> = (0..tets.len())
                .filter(|&t| usize::from(self.tet_region[t / 8]) == index)
                .collect();
            file.entity_physicals.insert((3, entity), vec![region.id]);
            file.physical_names.insert((3, region.id), region.name.clone());
            file.element_blocks.push(ElementBlock {
                entity_dim: 3,
                entity_tag: entity,
                element_type: TETRAHEDRON,
                element_tags: members.iter().map(|&t| t as u64 + 1).collect(),
                connectivity: members
                    .iter()
                    .flat_map(|&t| tets[t].map(|n| u64::from(n) + 1))
                    .collect(),
                nodes_per_element: 4,
            });
        }
        let boundary_edges: HashSet<(u32, u32)> = self
            .surface
            .iter()
            .flat_map(|&[a, b, c]| [(a, b), (b, c), (c, a)])
            .map(|(a, b)| (a.min(b), a.max(b)))
            .collect();
        for (set, (name, members)) in self.node_sets.iter().enumerate() {
            let inside: HashSet<u32> = members.iter().copied().collect();
            let mut grown: Vec<u32> = members.clone();
            grown.extend(
                nodes
                    .midpoints
                    .iter()
                    .filter(|(edge, _)| {
                        inside.contains(&edge.0) && inside.contains(&edge.1) && boundary_edges.contains(edge)
                    })
                    .map(|(_, &m)| m),
            );
            grown.sort_unstable();
            // Entity and physical tags of their own: dimension 0 keeps them apart from the volumes'.
            let tag = set as i32 + 1;
            file.entity_physicals.insert((0, tag), vec![tag]);
            file.physical_names.insert((0, tag), name.clone());
            file.element_blocks.push(ElementBlock {
                entity_dim: 0,
                entity_tag: tag,
                element_type: POINT,
                element_tags: (1..=grown.len() as u64).collect(),
                connectivity: grown.iter().map(|&n| u64::from(n) + 1).collect(),
                nodes_per_element: 1,
            });
        }
        file
    }
}
