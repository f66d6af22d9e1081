//! Element quality: dihedral angles and the normalized radius-ratio aspect.

use super::topology::{Vec3, cross, dot, norm, sub, tet_volume};

/// Summary of element quality over a mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quality {
    /// Smallest dihedral angle of any tetrahedron (degrees; 70.53° for a regular one).
    pub min_dihedral_deg: f64,
    /// Largest dihedral angle (degrees).
    pub max_dihedral_deg: f64,
    /// Aspect ratio = circumradius / (3 × inradius): 1 for a regular tetrahedron, growing without bound
    /// as it flattens.
    pub max_aspect: f64,
    pub mean_aspect: f64,
}

pub fn quality(tets: &[[u32; 4]], positions: &[Vec3]) -> Quality {
    let mut q = Quality {
        min_dihedral_deg: f64::INFINITY,
        max_dihedral_deg: 0.0,
        max_aspect: 0.0,
        mean_aspect: 0.0,
    };
    for tet in tets {
        let p = tet.map(|n| positions[n as usize]);
        for angle in dihedral_angles_deg(p) {
            q.min_dihedral_deg = q.min_dihedral_deg.min(angle);
            q.max_dihedral_deg = q.max_dihedral_deg.max(angle);
        }
        let a = aspect_ratio(p);
        q.max_aspect = q.max_aspect.max(a);
        q.mean_aspect += a;
    }
    if !tets.is_empty() {
        q.mean_aspect /= tets.len() as f64;
    }
    q
}

/// The six dihedral angles, one per edge, from the outward face normals: π minus the angle between them.
pub fn dihedral_angles_deg(p: [Vec3; 4]) -> [f64; 6] {
    // Outward normal of the face opposite vertex i.
    let normal = |i: usize| {
        let [a, b, c] = match i {
            0 => [p[1], p[2], p[3]],
            1 => [p[0], p[3], p[2]],
            2 => [p[0], p[1], p[3]],
            _ => [p[0], p[2], p[1]],
        };
        let n = cross(sub(b, a), sub(c, a));
        let len = norm(n);
        n.map(|c| c / len)
    };
    let n = [normal(0), normal(1), normal(2), normal(3)];
    let pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
    pairs.map(|(i, j)| {
        let c = dot(n[i], n[j]).clamp(-1.0, 1.0);
        180.0 - c.acos().to_degrees()
    })
}

pub fn aspect_ratio(p: [Vec3; 4]) -> f64 {
    let volume = tet_volume(p).abs();
    let area = |a: Vec3, b: Vec3, c: Vec3| norm(cross(sub(b, a), sub(c, a))) / 2.0;
    let surface = area(p[1], p[2], p[3]) + area(p[0], p[3], p[2]) + area(p[0], p[1], p[3]) + area(p[0], p[2], p[1]);
    let inradius = 3.0 * volume / surface;
    // Circumradius: |α|/(12V) with α the standard product-of-opposite-edges expression.
    let d = |i: usize, j: usize| norm(sub(p[i], p[j]));
    let (a, b, c) = (d(0, 1) * d(2, 3), d(0, 2) * d(1, 3), d(0, 3) * d(1, 2));
    let product = (a + b + c) * (a + b - c) * (a - b + c) * (-a + b + c);
    let circumradius = product.max(0.0).sqrt() / (24.0 * volume);
    circumradius / (3.0 * inradius)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn regular() -> [Vec3; 4] {
        let s = 1.0 / 2f64.sqrt();
        [[1.0, 0.0, -s], [-1.0, 0.0, -s], [0.0, 1.0, s], [0.0, -1.0, s]]
    }

    #[test]
    fn regular_tetrahedron_has_unit_aspect_and_arccos_third_dihedrals() {
        let mut p = regular();
        if tet_volume(p) < 0.0 {
            p.swap(0, 1);
        }
        assert!((aspect_ratio(p) - 1.0).abs() < 1e-12);
        for a in dihedral_angles_deg(p) {
            assert!((a - (1.0f64 / 3.0).acos().to_degrees()).abs() < 1e-9, "{a}");
        }
    }

    #[test]
    fn right_corner_tetrahedron_has_right_dihedrals_at_the_corner() {
        let p = [[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let angles = dihedral_angles_deg(p);
        assert_eq!(angles.iter().filter(|a| (**a - 90.0).abs() < 1e-9).count(), 3);
        assert!(aspect_ratio(p) > 1.0);
    }
}
