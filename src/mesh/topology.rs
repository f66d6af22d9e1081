//! Geometry and topology derived from the tetrahedra: volumes, the boundary surface and its normals.

use std::collections::HashMap;

use super::MeshError;

pub type Vec3 = [f64; 3];

pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// Signed volume; positive for Gmsh's (right-handed) node order.
pub fn tet_volume(p: [Vec3; 4]) -> f64 {
    dot(sub(p[1], p[0]), cross(sub(p[2], p[0]), sub(p[3], p[0]))) / 6.0
}

/// The faces of a positively oriented tetrahedron, each ordered so its normal points away from the
/// fourth (opposite) vertex.
pub const TET_FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];

/// Boundary triangles (faces used by exactly one tetrahedron), oriented outward, in a deterministic
/// order (by tetrahedron, then local face).
pub fn boundary_triangles(tets: &[[u32; 4]], positions: &[Vec3], origin: &str) -> Result<Vec<[u32; 3]>, MeshError> {
    let mut uses: HashMap<[u32; 3], u32> = HashMap::with_capacity(tets.len() * 2);
    for tet in tets {
        for face in TET_FACES {
            *uses.entry(sorted_face(tet, face)).or_default() += 1;
        }
    }
    if let Some((face, n)) = uses.iter().find(|(_, n)| **n > 2) {
        return Err(MeshError::NonManifold {
            path: origin.to_owned(),
            what: format!(
                "face ({}, {}, {}) at {} is shared by {n} tetrahedra (at most 2 allowed)",
                face[0],
                face[1],
                face[2],
                fmt_point(positions[face[0] as usize])
            ),
        });
    }
    let mut triangles = Vec::new();
    for tet in tets {
        for face in TET_FACES {
            if uses[&sorted_face(tet, face)] == 1 {
                triangles.push([tet[face[0]], tet[face[1]], tet[face[2]]]);
            }
        }
    }
    Ok(triangles)
}

fn sorted_face(tet: &[u32; 4], face: [usize; 3]) -> [u32; 3] {
    let mut f = [tet[face[0]], tet[face[1]], tet[face[2]]];
    f.sort_unstable();
    f
}

/// Checks that the surface is closed and manifold: every edge is used by exactly two triangles, in
/// opposite directions (which also means the orientation is consistent).
pub fn check_closed_manifold(triangles: &[[u32; 3]], positions: &[Vec3], origin: &str) -> Result<(), MeshError> {
    let mut directed: HashMap<(u32, u32), u32> = HashMap::with_capacity(triangles.len() * 3);
    for t in triangles {
        for k in 0..3 {
            *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
        }
    }
    let mut open = Vec::new();
    for (&(a, b), &n) in &directed {
        let back = directed.get(&(b, a)).copied().unwrap_or(0);
        if n > 1 || back > 1 {
            return Err(MeshError::NonManifold {
                path: origin.to_owned(),
                what: format!(
                    "surface edge ({a}, {b}) at {} is used by {} triangles (expected 2)",
                    fmt_point(positions[a as usize]),
                    n + back
                ),
            });
        }
        if back == 0 {
            open.push((a, b));
        }
    }
    if let Some(&(a, b)) = open.iter().min() {
        return Err(MeshError::OpenSurface {
            path: origin.to_owned(),
            edges: open.len(),
            example: format!("({a}, {b}) at {}", fmt_point(positions[a as usize])),
        });
    }
    Ok(())
}

/// Checks that the surface is a manifold at every vertex: the triangles around a vertex form one fan
/// (two parts of the organ touching at a single node would make two).
pub fn check_vertex_manifold(triangles: &[[u32; 3]], positions: &[Vec3], origin: &str) -> Result<(), MeshError> {
    // For each vertex, the link edge (from -> to) of every triangle around it, counter-clockwise.
    let mut link: HashMap<u32, Vec<(u32, u32)>> = HashMap::new();
    for t in triangles {
        for k in 0..3 {
            link.entry(t[k]).or_default().push((t[(k + 1) % 3], t[(k + 2) % 3]));
        }
    }
    let mut vertices: Vec<_> = link.into_iter().collect();
    vertices.sort_unstable_by_key(|(v, _)| *v);
    for (vertex, edges) in vertices {
        let next: HashMap<u32, u32> = edges.iter().copied().collect();
        // Walk the fan from one link edge: a manifold vertex returns after visiting every edge.
        let start = edges[0].0;
        let (mut at, mut steps) = (start, 0);
        while let Some(&to) = next.get(&at) {
            at = to;
            steps += 1;
            if at == start || steps > edges.len() {
                break;
            }
        }
        if steps != edges.len() {
            return Err(MeshError::NonManifold {
                path: origin.to_owned(),
                what: format!(
                    "the surface is pinched at node {vertex} {}: its triangles form more than one fan",
                    fmt_point(positions[vertex as usize])
                ),
            });
        }
    }
    Ok(())
}

/// Area-weighted vertex normals of the surface, unit length; zero for nodes off the surface.
pub fn vertex_normals(triangles: &[[u32; 3]], positions: &[Vec3]) -> Vec<Vec3> {
    let mut normals = vec![[0.0; 3]; positions.len()];
    for t in triangles {
        // |a × b| is twice the area, so the cross product itself is the area weight.
        let n = triangle_area_vector(t, positions);
        for &v in t {
            for k in 0..3 {
                normals[v as usize][k] += n[k];
            }
        }
    }
    for n in &mut normals {
        let len = norm(*n);
        if len > 0.0 {
            *n = n.map(|c| c / len);
        }
    }
    normals
}

/// Twice the area times the unit normal of a triangle.
pub fn triangle_area_vector(t: &[u32; 3], positions: &[Vec3]) -> Vec3 {
    let [a, b, c] = t.map(|v| positions[v as usize]);
    cross(sub(b, a), sub(c, a))
}

/// Lumped nodal volumes: a quarter of each adjacent tetrahedron's volume (docs/design.md §6).
pub fn lumped_volumes(tets: &[[u32; 4]], volumes: &[f64], node_count: usize) -> Vec<f64> {
    let mut lumped = vec![0.0; node_count];
    for (tet, v) in tets.iter().zip(volumes) {
        for &n in tet {
            lumped[n as usize] += v / 4.0;
        }
    }
    lumped
}

pub fn fmt_point(p: Vec3) -> String {
    format!("({:.4}, {:.4}, {:.4}) m", p[0], p[1], p[2])
}
