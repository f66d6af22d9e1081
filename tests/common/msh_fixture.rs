//! Small hand-made MSH 4.1 meshes for the loader's error paths: each test builds one malformed case.

use std::fmt::Write;

/// A labelled tetrahedral mesh to be written as ASCII MSH 4.1.
#[derive(Clone)]
pub struct Fixture {
    pub nodes: Vec<[f64; 3]>,
    /// 0-based node indices; written with tags index + 1.
    pub tets: Vec<[usize; 4]>,
    /// Node sets, written as physical points (one point element per node).
    pub sets: Vec<(String, Vec<usize>)>,
}

impl Fixture {
    /// An n×n×n grid of unit-0.01 m cubes, each split into six positively oriented tetrahedra (Kuhn),
    /// with `fixed` on the face x = 0 and `grasp_01` on the face x = max.
    pub fn grid(n: usize) -> Self {
        Self::bar([n, n, n], [0.01; 3])
    }

    /// A box of nx×ny×nz cells of size h (per axis), Kuhn-split, `fixed` at x = 0, `grasp_01` at x = max.
    pub fn bar(cells: [usize; 3], h: [f64; 3]) -> Self {
        let [nx, ny, nz] = cells;
        let id = |i: usize, j: usize, k: usize| (i * (ny + 1) + j) * (nz + 1) + k;
        let mut nodes = Vec::new();
        for i in 0..=nx {
            for j in 0..=ny {
                for k in 0..=nz {
                    nodes.push([i as f64 * h[0], j as f64 * h[1], k as f64 * h[2]]);
                }
            }
        }
        let mut tets = Vec::new();
        let perms = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    for p in perms {
                        let mut c = [i, j, k];
                        let mut tet = [id(c[0], c[1], c[2]); 4];
                        for (step, axis) in p.iter().enumerate() {
                            c[*axis] += 1;
                            tet[step + 1] = id(c[0], c[1], c[2]);
                        }
                        tets.push(tet);
                    }
                }
            }
        }
        let mut f = Fixture {
            nodes,
            tets,
            sets: Vec::new(),
        };
        f.orient();
        let face = |i: usize| -> Vec<usize> {
            (0..=ny)
                .flat_map(|j| (0..=nz).map(move |k| (j, k)))
                .map(|(j, k)| id(i, j, k))
                .collect()
        };
        f.sets.push(("fixed".into(), face(0)));
        f.sets.push(("grasp_01".into(), face(nx)));
        f
    }

    pub fn volume(&self, tet: [usize; 4]) -> f64 {
        let p = tet.map(|i| self.nodes[i]);
        let d = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let (a, b, c) = (d(p[1], p[0]), d(p[2], p[0]), d(p[3], p[0]));
        (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0]))
            / 6.0
    }

    fn orient(&mut self) {
        for t in 0..self.tets.len() {
            if self.volume(self.tets[t]) < 0.0 {
                self.tets[t].swap(2, 3);
            }
        }
    }

    /// Appends another fixture's nodes and tetrahedra (its node sets are dropped).
    pub fn append(&mut self, other: &Fixture, offset: [f64; 3]) {
        let base = self.nodes.len();
        self.nodes.extend(
            other
                .nodes
                .iter()
                .map(|p| [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]]),
        );
        self.tets.extend(other.tets.iter().map(|t| t.map(|i| i + base)));
    }

    pub fn to_msh(&self) -> String {
        let mut s = String::new();
        let w = &mut s;
        writeln!(w, "$MeshFormat\n4.1 0 8\n$EndMeshFormat").unwrap();
        writeln!(w, "$PhysicalNames\n{}\n3 1 \"liver\"", self.sets.len() + 1).unwrap();
        for (k, (name, _)) in self.sets.iter().enumerate() {
            writeln!(w, "0 {} \"{name}\"", 100 + k).unwrap();
        }
        writeln!(w, "$EndPhysicalNames").unwrap();
        // Entities: one point entity per node-set member, one volume.
        let points: Vec<(usize, usize)> = self
            .sets
            .iter()
            .enumerate()
            .flat_map(|(k, (_, nodes))| nodes.iter().map(move |&n| (k, n)))
            .collect();
        writeln!(w, "$Entities\n{} 0 0 1", points.len()).unwrap();
        for (e, (k, n)) in points.iter().enumerate() {
            let p = self.nodes[*n];
            writeln!(w, "{} {} {} {} 1 {}", e + 1, p[0], p[1], p[2], 100 + k).unwrap();
        }
        writeln!(w, "1 0 0 0 1 1 1 1 1 0\n$EndEntities").unwrap();
        let n = self.nodes.len();
        writeln!(w, "$Nodes\n1 {n} 1 {n}\n3 1 0 {n}").unwrap();
        for i in 0..n {
            writeln!(w, "{}", i + 1).unwrap();
        }
        for p in &self.nodes {
            writeln!(w, "{} {} {}", p[0], p[1], p[2]).unwrap();
        }
        writeln!(w, "$EndNodes").unwrap();
        let total = self.tets.len() + points.len();
        let blocks = 1 + points.len();
        writeln!(w, "$Elements\n{blocks} {total} 1 {total}\n3 1 4 {}", self.tets.len()).unwrap();
        for (e, t) in self.tets.iter().enumerate() {
            writeln!(w, "{} {} {} {} {}", e + 1, t[0] + 1, t[1] + 1, t[2] + 1, t[3] + 1).unwrap();
        }
        for (e, (_, node)) in points.iter().enumerate() {
            let tag = self.tets.len() + e + 1;
            writeln!(w, "0 {} 15 1\n{tag} {}", e + 1, node + 1).unwrap();
        }
        writeln!(w, "$EndElements").unwrap();
        s
    }
}
