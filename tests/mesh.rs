//! The phantom liver meshes and the loader: geometry, topology and every refusal.

mod common;

use std::collections::{BTreeSet, HashMap};
use std::path::Path;

use common::msh_fixture::Fixture;
use nak::mesh::{self, MeshConfig, MeshError, MeshSource, TetMesh};

fn phantom(file: &str) -> TetMesh {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("models/phantom-liver")
        .join(file);
    mesh::load(&MeshSource::File(path)).unwrap()
}

fn fixture_config() -> MeshConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/model.toml");
    MeshConfig::parse(&std::fs::read_to_string(path).unwrap(), "model.toml").unwrap()
}

fn load_fixture(f: &Fixture) -> Result<TetMesh, MeshError> {
    TetMesh::from_msh(f.to_msh().as_bytes(), "fixture.msh", fixture_config())
}

fn error_of(f: &Fixture) -> String {
    load_fixture(f).unwrap_err().to_string()
}

#[test]
fn phantom_meshes_are_at_the_requested_scales() {
    let fine = phantom("liver.msh");
    assert!((9_500..=11_500).contains(&fine.node_count()), "{}", fine.node_count());
    assert!((35_000..=55_000).contains(&fine.tets.len()), "{}", fine.tets.len());
    let coarse = phantom("liver-coarse.msh");
    assert!(
        (1_500..=3_000).contains(&coarse.node_count()),
        "{}",
        coarse.node_count()
    );
    // About 22 × 16 × 12 cm for the liver itself (the ducts hang below it).
    let (lo, hi) = fine.bounding_box();
    let size: Vec<f64> = (0..3).map(|k| hi[k] - lo[k]).collect();
    assert!(
        (0.20..0.25).contains(&size[0]) && (0.11..0.13).contains(&size[2]),
        "{size:?}"
    );
}

#[test]
fn phantom_has_the_three_regions_and_boundary_sets() {
    let m = phantom("liver-coarse.msh");
    let names: Vec<&str> = m.regions.iter().map(|r| r.name.as_str()).collect();
    assert_eq!(names, ["liver", "gallbladder", "ducts"]);
    let mut expected: Vec<String> = (1..=10).map(|i| format!("grasp_{i:02}")).collect();
    expected.push("fixed".into());
    for name in &expected {
        assert!(!m.node_sets[name].is_empty(), "{name} is empty");
    }
    // On the surface and pairwise disjoint.
    let mut seen = BTreeSet::new();
    for name in &expected {
        for &n in &m.node_sets[name] {
            assert!(m.is_surface[n as usize], "{name} node {n} is inside");
            assert!(seen.insert(n), "node {n} is in two boundary sets");
        }
    }
}

#[test]
fn every_tetrahedron_has_positive_volume() {
    for file in ["liver.msh", "liver-coarse.msh"] {
        let m = phantom(file);
        for (i, t) in m.tets.iter().enumerate() {
            let v = mesh::topology::tet_volume(t.map(|n| m.positions[n as usize]));
            assert!(v > 0.0, "{file}: tet {i} has volume {v}");
        }
    }
}

#[test]
fn surface_is_closed_and_manifold() {
    let m = phantom("liver.msh");
    let mut edges: HashMap<(u32, u32), usize> = HashMap::new();
    for t in &m.surface {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *edges.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    assert!(edges.values().all(|&n| n == 2));
    // Euler characteristic 2 − 2g: the phantom has one handle (liver → gallbladder → cystic duct →
    // common duct → hilum → liver), so χ = 0.
    let v = m.surface_nodes.len() as i64;
    assert_eq!(v - edges.len() as i64 + m.surface.len() as i64, 0);
}

#[test]
fn surface_normals_point_outward() {
    // Divergence theorem: ∮ x·n dA = ∫ div x dV = 3V; exact for flat triangles up to rounding.
    for file in ["liver.msh", "liver-coarse.msh"] {
        let m = phantom(file);
        let flux: f64 = m
            .surface
            .iter()
            .map(|t| {
                let area2 = mesh::topology::triangle_area_vector(t, &m.positions);
                let c = (0..3)
                    .map(|k| t.iter().map(|&v| m.positions[v as usize][k]).sum::<f64>() / 3.0)
                    .collect::<Vec<_>>();
                (c[0] * area2[0] + c[1] * area2[1] + c[2] * area2[2]) / 2.0
            })
            .sum();
        let v = m.total_volume();
        assert!(
            ((flux - 3.0 * v) / (3.0 * v)).abs() < 1e-6,
            "{file}: {flux} vs {}",
            3.0 * v
        );
    }
}

#[test]
fn volumes_add_up() {
    let m = phantom("liver.msh");
    let regions: f64 = m.regions.iter().map(|r| r.volume).sum();
    let lumped: f64 = m.nodal_volumes.iter().sum();
    assert!((regions - m.total_volume()).abs() < 1e-12 * m.total_volume());
    assert!((lumped - m.total_volume()).abs() < 1e-12 * m.total_volume());
}

#[test]
fn vertex_normals_are_unit_on_the_surface_and_zero_inside() {
    let m = phantom("liver-coarse.msh");
    for (n, normal) in m.normals.iter().enumerate() {
        let len = mesh::topology::norm(*normal);
        if m.is_surface[n] {
            assert!((len - 1.0).abs() < 1e-12);
        } else {
            assert_eq!(len, 0.0);
        }
    }
}

#[test]
fn a_box_is_as_deep_beneath_each_face_as_it_is_across() {
    // Nodes inside a face of the 0.10 × 0.06 × 0.04 m box have that face's normal; the ray inward
    // crosses the box to the opposite face. Edge and corner nodes (averaged normals) cross it slanted.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let m = mesh::load(&MeshSource::File(dir.join("box.msh"))).unwrap();
    let depths = m.inward_depths().to_vec();
    let extent = [0.10, 0.06, 0.04];
    let mut checked = [0; 3];
    for &n in &m.surface_nodes {
        let normal = m.normals[n as usize];
        if let Some(axis) = (0..3).find(|&k| (normal[k].abs() - 1.0).abs() < 1e-12) {
            let depth = depths[n as usize];
            assert!(
                (depth - extent[axis]).abs() < 1e-12,
                "node {n}: {depth} m across axis {axis}"
            );
            checked[axis] += 1;
        } else {
            assert!(depths[n as usize] > 0.0, "node {n} on an edge: no depth");
        }
    }
    assert!(checked.iter().all(|&c| c > 0), "face nodes per axis {checked:?}");
    assert!(
        m.is_surface.iter().zip(&depths).all(|(&s, &d)| s || d == 0.0),
        "depth inside"
    );
}

#[test]
fn binary_and_ascii_files_give_the_same_mesh() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    let ascii = mesh::load(&MeshSource::File(dir.join("box.msh"))).unwrap();
    let binary = mesh::load(&MeshSource::File(dir.join("box-binary.msh"))).unwrap();
    // Gmsh writes ASCII coordinates with 16 significant digits, binary ones exactly.
    for (a, b) in ascii.positions.iter().zip(&binary.positions) {
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-15), "{a:?} vs {b:?}");
    }
    assert_eq!(ascii.positions.len(), binary.positions.len());
    assert_eq!(ascii.tets, binary.tets);
    assert_eq!(ascii.node_sets, binary.node_sets);
    assert_eq!(ascii.surface, binary.surface);
    assert!((ascii.total_volume() - 0.1 * 0.06 * 0.04).abs() < 1e-15);
}

#[test]
fn a_directory_loads_its_default_mesh_and_the_embedded_phantom_is_that_mesh() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver");
    let from_dir = mesh::load(&MeshSource::from_arg(Some(&dir))).unwrap();
    let embedded = mesh::load(&MeshSource::Embedded).unwrap();
    assert_eq!(from_dir.content_hash, embedded.content_hash);
    assert_ne!(from_dir.content_hash, phantom("liver-coarse.msh").content_hash);
}

#[test]
fn hand_made_grid_is_accepted() {
    let m = load_fixture(&Fixture::grid(2)).unwrap();
    assert_eq!(m.node_count(), 27);
    assert_eq!(m.surface_nodes.len(), 26);
    assert_eq!(m.node_region[13], Some(0));
}

#[test]
fn refuses_a_missing_file() {
    let err = mesh::load(&MeshSource::File("no/such/liver.msh".into())).unwrap_err();
    assert!(matches!(err, MeshError::Io { .. }));
    assert!(err.to_string().contains("no/such/liver.msh"), "{err}");
}

#[test]
fn refuses_an_unreadable_file() {
    // A directory named like a mesh file cannot be read as one.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("liver.msh");
    std::fs::create_dir(&path).unwrap();
    let err = mesh::load(&MeshSource::File(path)).unwrap_err();
    assert!(matches!(err, MeshError::Io { .. }), "{err}");
}

#[test]
fn refuses_a_file_that_is_not_msh() {
    let err = TetMesh::from_msh(b"solid liver\nfacet normal 0 0 1\n", "liver.stl", fixture_config()).unwrap_err();
    assert!(err.to_string().contains("liver.stl: line 1"), "{err}");
}

#[test]
fn refuses_a_mesh_without_tetrahedra() {
    let mut f = Fixture::grid(1);
    f.tets.clear();
    assert!(error_of(&f).contains("no tetrahedra"));
}

#[test]
fn names_inverted_tetrahedra() {
    let mut f = Fixture::grid(2);
    f.tets[7].swap(0, 1);
    let err = error_of(&f);
    assert!(
        err.contains("1 inverted tetrahedra") && err.contains("element 8 "),
        "{err}"
    );
}

#[test]
fn names_degenerate_tetrahedra() {
    let mut f = Fixture::grid(1);
    // Four corners of one face: coplanar.
    f.tets.push([0, 1, 2, 3]);
    let err = error_of(&f);
    assert!(
        err.contains("1 degenerate tetrahedra") && err.contains("element 7 "),
        "{err}"
    );
}

#[test]
fn refuses_nodes_used_by_no_tetrahedron() {
    let mut f = Fixture::grid(1);
    f.nodes.push([0.5, 0.5, 0.5]);
    let err = error_of(&f);
    assert!(err.contains("1 nodes are used by no tetrahedron, e.g. tag 9"), "{err}");
}

#[test]
fn refuses_a_missing_node_set() {
    let mut f = Fixture::grid(1);
    f.sets.retain(|(name, _)| name != "grasp_01");
    let err = error_of(&f);
    assert!(
        err.contains("missing node set \"grasp_01\"") && err.contains("has: fixed"),
        "{err}"
    );
}

#[test]
fn refuses_a_node_set_off_the_surface() {
    let mut f = Fixture::grid(2);
    // Node 13 is the centre of the 3×3×3 grid.
    f.sets[1].1.push(13);
    let err = error_of(&f);
    assert!(
        err.contains("\"grasp_01\" has 1 nodes off the boundary surface, e.g. node 13"),
        "{err}"
    );
}

#[test]
fn refuses_overlapping_node_sets() {
    let mut f = Fixture::grid(1);
    let shared = f.sets[0].1[0];
    f.sets[1].1.push(shared);
    let err = error_of(&f);
    assert!(err.contains("\"fixed\" and \"grasp_01\" overlap in 1 nodes"), "{err}");
}

#[test]
fn refuses_two_parts_touching_along_an_edge() {
    let mut f = Fixture::grid(1);
    let other = Fixture::grid(1);
    // Shift the second cube so it shares exactly the edge x = y = 0.01 with the first, by reusing
    // that edge's node indices.
    f.append(&other, [0.01, 0.01, 0.0]);
    let edge_in_second = [8, 9]; // (0,0,0) and (0,0,1) of the second cube
    let edge_in_first = [6, 7]; // (1,1,0) and (1,1,1) of the first cube
    for t in f.tets.iter_mut() {
        for v in t.iter_mut() {
            if let Some(k) = edge_in_second.iter().position(|e| e == v) {
                *v = edge_in_first[k];
            }
        }
    }
    f.nodes[8] = [9.0, 9.0, 9.0];
    f.nodes[9] = [9.0, 9.0, 9.1];
    f.nodes.truncate(16);
    // The two unused copies are removed by moving the last nodes into their slots.
    let err = error_or_renumber(f);
    assert!(
        err.contains("not manifold") && err.contains("used by 4 triangles"),
        "{err}"
    );
}

/// Removes nodes 8 and 9 (left unused by a merge) and renumbers, then loads.
fn error_or_renumber(mut f: Fixture) -> String {
    let map = |v: usize| if v > 9 { v - 2 } else { v };
    f.nodes.drain(8..10);
    for t in f.tets.iter_mut() {
        *t = t.map(map);
    }
    error_of(&f)
}

#[test]
fn refuses_two_parts_touching_at_one_node() {
    let mut f = Fixture::grid(1);
    f.append(&Fixture::grid(1), [0.01, 0.01, 0.01]);
    // Merge the second cube's corner (0,0,0) = node 8 into the first cube's corner (1,1,1) = node 7.
    for t in f.tets.iter_mut() {
        for v in t.iter_mut() {
            *v = match *v {
                8 => 7,
                v if v > 8 => v - 1,
                v => v,
            };
        }
    }
    f.nodes.remove(8);
    let err = error_of(&f);
    assert!(err.contains("pinched at node 7"), "{err}");
}

#[test]
fn refuses_regions_that_do_not_share_their_interface() {
    let mut f = Fixture::grid(1);
    f.append(&Fixture::grid(1), [0.01, 0.0, 0.0]);
    let err = error_of(&f);
    assert!(err.contains("4 nodes coincide with another node"), "{err}");
}

#[test]
fn open_surfaces_are_named() {
    // A tetrahedral mesh's boundary is closed by construction; the check guards surfaces built
    // from anything else, so it is exercised on an open triangle fan directly.
    let positions = vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]];
    let err = mesh::topology::check_closed_manifold(&[[0, 1, 2], [1, 3, 2]], &positions, "fan").unwrap_err();
    assert!(
        err.to_string().contains("fan: the boundary surface is open: 4 edges"),
        "{err}"
    );
}

#[test]
fn refuses_second_order_elements() {
    let text = Fixture::grid(1).to_msh().replace("\n3 1 4 6\n", "\n3 1 11 6\n");
    let err = TetMesh::from_msh(text.as_bytes(), "p2.msh", fixture_config()).unwrap_err();
    // The ten-node connectivity does not match the four-node rows, so the parser stops first.
    assert!(err.to_string().starts_with("p2.msh"), "{err}");
}

#[test]
fn refuses_a_mesh_without_configuration() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("liver.msh");
    std::fs::write(&path, Fixture::grid(1).to_msh()).unwrap();
    let err = mesh::load(&MeshSource::File(path)).unwrap_err().to_string();
    assert!(
        err.contains("model.toml") && err.contains("needs a model.toml beside it"),
        "{err}"
    );
}

#[test]
fn refinement_splits_every_tetrahedron_in_eight_and_keeps_the_organ() {
    let coarse = phantom("liver-coarse.msh");
    let fine = coarse.refined().unwrap();
    let edges: BTreeSet<(u32, u32)> = coarse
        .tets
        .iter()
        .flat_map(|t| [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)].map(|(i, j)| (t[i].min(t[j]), t[i].max(t[j]))))
        .collect();
    assert_eq!(fine.node_count(), coarse.node_count() + edges.len());
    assert_eq!(fine.tets.len(), 8 * coarse.tets.len());
    assert_eq!(fine.surface.len(), 4 * coarse.surface.len());
    assert_eq!(&fine.positions[..coarse.node_count()], &coarse.positions[..]);
    // The same organ: each region's volume (to rounding), and the boundary conditions where they were.
    for (f, c) in fine.regions.iter().zip(&coarse.regions) {
        assert_eq!(f.name, c.name);
        assert!(
            (f.volume - c.volume).abs() <= 1e-12 * c.volume,
            "{}: {} vs {}",
            c.name,
            f.volume,
            c.volume
        );
    }
    for (name, nodes) in &coarse.node_sets {
        let refined = &fine.node_sets[name];
        assert!(
            nodes.iter().all(|n| refined.binary_search(n).is_ok()),
            "{name} lost nodes"
        );
        assert!(refined.len() > nodes.len(), "{name} gained no midpoints");
        assert!(
            refined.iter().all(|&n| fine.is_surface[n as usize]),
            "{name} left the surface"
        );
    }
    assert_ne!(fine.content_hash, coarse.content_hash);
    // No sliver from the octahedra: the worst children are no flatter than a fraction of the
    // parents' worst.
    let (qc, qf) = (coarse.quality(), fine.quality());
    assert!(qf.min_dihedral_deg >= 0.5 * qc.min_dihedral_deg, "{qf:?} vs {qc:?}");
}
