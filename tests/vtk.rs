//! VTK meshes in and out: nak's writer read back by its reader gives the same mesh (content hash),
//! predictions written for ParaView carry the field, and malformed grids are refused naming the
//! problem. An independent reader and writer (meshio) checks the files in tests/python/test_vtk.py.

mod common;

use std::path::{Path, PathBuf};

use common::models::two_graspers;
use nak::engine::{Engine, Grasp, Request};
use nak::mesh::{self, MeshError, MeshSource, TetMesh, vtk};

fn phantom_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver")
}

/// A directory holding `model.toml` from `config_dir`, where mesh files can be written.
fn beside_config(config_dir: &Path) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(config_dir.join("model.toml"), dir.path().join("model.toml")).unwrap();
    dir
}

#[test]
fn the_phantom_round_trips_through_vtu_and_legacy_vtk_unchanged() {
    let original = mesh::load(&MeshSource::File(phantom_dir().join("liver-coarse.msh"))).unwrap();
    let dir = beside_config(&phantom_dir());
    for name in ["liver.vtu", "liver.vtk"] {
        let path = dir.path().join(name);
        vtk::write(&original, None, &path).unwrap();
        let read = mesh::load(&MeshSource::File(path)).unwrap();
        // The hash covers positions, tetrahedra, regions and node sets: a model trained on the .msh
        // is served on the .vtu.
        assert_eq!(read.content_hash, original.content_hash, "{name}");
        assert_eq!(read.regions, original.regions, "{name}");
    }
}

#[test]
fn a_prediction_written_for_paraview_is_the_deformed_mesh_with_its_field() {
    let original = mesh::load(&MeshSource::File(phantom_dir().join("liver-coarse.msh"))).unwrap();
    let engine = Engine::new(std::sync::Arc::new(original.clone()), Default::default());
    // Half the shared test grasps: at their full 3–3.5 cm the Kelvinlet, whose held nodes nak answers
    // exactly, inverts one element beside a grasp, which nak's reader would refuse to read back.
    let grasps = two_graspers(&original)
        .into_iter()
        .map(|g| Grasp {
            displacement: g.displacement.map(|u| u / 2.0),
            ..g
        })
        .collect();
    let prediction = engine
        .predict(&Request {
            grasps,
            ..Request::default()
        })
        .unwrap();
    let dir = beside_config(&phantom_dir());
    let path = dir.path().join("deformed.vtu");
    vtk::write(&original, Some(&prediction.displacements), &path).unwrap();
    let deformed = mesh::load(&MeshSource::File(path)).unwrap();
    assert_eq!(deformed.tets, original.tets);
    assert_eq!(deformed.node_sets, original.node_sets);
    let mut largest = 0.0f64;
    for (n, (moved, rest)) in deformed.positions.iter().zip(&original.positions).enumerate() {
        for k in 0..3 {
            let u = f64::from(prediction.displacements[3 * n + k]);
            assert!((moved[k] - rest[k] - u).abs() < 1e-12, "node {n}");
            largest = largest.max(u.abs());
        }
    }
    assert!(largest > 1e-3, "the field moved the mesh ({largest} m)");
}

/// A legacy ASCII VTK unstructured grid with the given body after the header.
fn legacy(dir: &Path, body: &str) -> Result<TetMesh, MeshError> {
    let path = dir.join("grid.vtk");
    let text = format!("# vtk DataFile Version 4.2\ntest\nASCII\nDATASET UNSTRUCTURED_GRID\n{body}");
    std::fs::write(&path, text).unwrap();
    mesh::load(&MeshSource::File(path))
}

const POINTS: &str = "POINTS 4 double\n0 0 0 1 0 0 0 1 0 0 0 1\n";

#[test]
fn malformed_grids_are_refused_naming_the_problem() {
    let phantom = beside_config(&phantom_dir());
    let single_region = beside_config(&Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures"));
    let tet = "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n10\n";
    let cases: [(&Path, String, &str); 8] = [
        (phantom.path(), "this is not VTK".into(), "not a readable VTK file"),
        (
            phantom.path(),
            format!("{POINTS}CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n9\n"),
            "cell 0 is a Quad: nak supports linear tetrahedra",
        ),
        (
            phantom.path(),
            format!("{POINTS}CELLS 1 5\n4 0 1 2 7\nCELL_TYPES 1\n10\n"),
            "cell 0 refers to point 7, but the grid has 4 points",
        ),
        (
            phantom.path(),
            format!("{POINTS}{tet}"),
            "no `region` (or `labels`) cell array, and model.toml has 3 regions",
        ),
        (
            phantom.path(),
            format!("{POINTS}{tet}CELL_DATA 1\nSCALARS region int 1\nLOOKUP_TABLE default\n9\n"),
            "region label 9 (cell array \"region\") is no region's `label` in model.toml",
        ),
        (
            phantom.path(),
            format!("{POINTS}{tet}CELL_DATA 1\nSCALARS labels float 1\nLOOKUP_TABLE default\n1.5\n"),
            "the cell array \"labels\" does not hold integers",
        ),
        // Arrays inside a legacy FIELD, as VTK's writer stores all but the active scalars.
        (
            phantom.path(),
            format!("{POINTS}{tet}CELL_DATA 1\nFIELD FieldData 1\nlabels 1 1 int\n7\n"),
            "region label 7 (cell array \"labels\")",
        ),
        // Read, then refused by the same checks as an MSH file: no node sets here.
        (
            single_region.path(),
            format!("{POINTS}{tet}"),
            "missing node set \"fixed\"",
        ),
    ];
    for (dir, body, expected) in cases {
        let err = legacy(dir, &body).unwrap_err().to_string();
        assert!(err.contains(expected), "expected {expected:?} in: {err}");
        assert!(err.contains("grid.vtk"), "the error names the file: {err}");
    }
}
