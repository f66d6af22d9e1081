//! VTK unstructured grids of tetrahedra, in and out: `.vtu` (XML, as ParaView and 3D Slicer's
//! SegmentMesher write it) and legacy `.vtk`, through the `vtkio` crate.
//!
//! Reading maps a grid onto the labelled-mesh form the MSH reader produces ([`MshFile`]), so that a
//! VTK mesh goes through exactly the same validation. What a VTK file carries:
//! - cells: linear tetrahedra (VTK type 10) only;
//! - regions: an integer cell array named `region`, or `labels` (SegmentMesher's name); each value
//!   must be the `label` of a `[regions.NAME]` in model.toml. Without one, a model.toml with a single
//!   region names every tetrahedron;
//! - node sets (`fixed`, `grasp_01`, …): one-component integer point arrays named after them,
//!   non-zero marking members.
//!
//! Writing produces the same layout (plus a `displacement` vector array and deformed points when a
//! field is given), so nak's own output reads back as a mesh.

use std::path::Path;

use vtkio::model::{
    Attribute, Attributes, ByteOrder, CellType, Cells, DataArray, DataSet, ElementType, IOBuffer, Piece,
    UnstructuredGridPiece, Version, VertexNumbers,
};

use super::msh::{ElementBlock, MshFile, POINT, TETRAHEDRON};
use super::{MeshConfig, MeshError, TetMesh};

/// Cell arrays read as region labels, in order of preference.
const REGION_ARRAYS: [&str; 2] = ["region", "labels"];

/// The two VTK file formats nak reads and writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// `.vtu`: XML.
    Xml,
    /// `.vtk`: the legacy format (binary is big-endian).
    Legacy,
}

/// The VTK format a file name says (by extension), if any.
pub fn format(path: &Path) -> Option<Format> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("vtu") => Some(Format::Xml),
        Some("vtk") => Some(Format::Legacy),
        _ => None,
    }
}

/// Reads a VTK unstructured grid from the bytes of a file as a labelled mesh; region names come from
/// `config`.
pub fn read(bytes: &[u8], origin: &str, format: Format, config: &MeshConfig) -> Result<MshFile, MeshError> {
    let error = |message: String| MeshError::Parse {
        path: origin.to_owned(),
        location: "VTK".into(),
        message,
    };
    // vtkio reports malformed input as errors, but a few of its conversions assert; a corrupt file
    // must be refused, never bring the server down.
    let imported = std::panic::catch_unwind(|| match format {
        Format::Xml => vtkio::Vtk::parse_xml(bytes),
        Format::Legacy => vtkio::Vtk::parse_legacy_be(bytes),
    });
    let vtk = match imported {
        Ok(Ok(vtk)) => vtk,
        Ok(Err(e)) => return Err(error(format!("not a readable VTK file: {e}"))),
        Err(_) => return Err(error("not a readable VTK file (the VTK reader failed on it)".into())),
    };
    let DataSet::UnstructuredGrid { pieces, .. } = vtk.data else {
        return Err(error(
            "not an unstructured grid: nak needs a volume mesh of tetrahedra (vtkUnstructuredGrid)".into(),
        ));
    };
    let mut grids = pieces.into_iter().map(|piece| match piece {
        Piece::Inline(grid) => Ok(*grid),
        _ => Err(error(
            "pieces stored in other files are not supported; merge them into one .vtu".into(),
        )),
    });
    let grid = match (grids.next(), grids.next()) {
        (Some(grid), None) => grid?,
        (None, _) => return Err(error("the grid has no piece".into())),
        (Some(_), Some(_)) => return Err(error("the grid has several pieces; merge them into one".into())),
    };
    labelled(grid, config, &error)
}

fn labelled(
    grid: UnstructuredGridPiece,
    config: &MeshConfig,
    error: &impl Fn(String) -> MeshError,
) -> Result<MshFile, MeshError> {
    let coords: Vec<f64> = grid
        .points
        .cast_into()
        .ok_or_else(|| error("points are not numbers".into()))?;
    if !coords.len().is_multiple_of(3) {
        return Err(error(format!(
            "{} point coordinates is not a multiple of 3",
            coords.len()
        )));
    }
    let node_count = coords.len() / 3;
    let mut file = MshFile {
        node_tags: (1..=node_count as u64).collect(),
        node_coords: coords.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        ..MshFile::default()
    };
    let tets = tetrahedra(grid.cells, node_count, error)?;
    let labels = region_labels(&grid.data.cell, tets.len(), config, error)?;

    // One element block per run of equal labels (the MSH form's volume entity), keeping the file's
    // element order, with its region label as the physical group.
    for (k, (tet, &label)) in tets.iter().zip(&labels).enumerate() {
        let same_run = file
            .element_blocks
            .last()
            .is_some_and(|b| file.entity_physicals[&(3, b.entity_tag)] == [label]);
        if !same_run {
            let entity = file.element_blocks.len() as i32 + 1;
            let name = config
                .region_labels
                .get(&label)
                .cloned()
                .unwrap_or_else(|| single_region(config));
            file.entity_physicals.insert((3, entity), vec![label]);
            file.physical_names.insert((3, label), name);
            file.element_blocks.push(ElementBlock {
                entity_dim: 3,
                entity_tag: entity,
                element_type: TETRAHEDRON,
                element_tags: Vec::new(),
                connectivity: Vec::new(),
                nodes_per_element: 4,
            });
        }
        if let Some(block) = file.element_blocks.last_mut() {
            block.element_tags.push(k as u64 + 1);
            block.connectivity.extend(tet.iter().map(|&n| u64::from(n) + 1));
        }
    }

    for (set, array) in arrays(&grid.data.point).iter().enumerate() {
        let Some(members) = node_set(array, node_count) else {
            continue;
        };
        // Entity and physical tags of their own: dimension 0 keeps them apart from the volumes'.
        let tag = set as i32 + 1;
        file.entity_physicals.insert((0, tag), vec![tag]);
        file.physical_names.insert((0, tag), array.name.to_owned());
        file.element_blocks.push(ElementBlock {
            entity_dim: 0,
            entity_tag: tag,
            element_type: POINT,
            element_tags: (0..members.len() as u64).collect(),
            connectivity: members.iter().map(|&n| n as u64 + 1).collect(),
            nodes_per_element: 1,
        });
    }
    Ok(file)
}

/// One named array of point or cell data, whether stored as a data array or inside a legacy FIELD
/// (VTK's legacy writer stores every array but the active scalars that way).
struct NamedArray<'a> {
    name: &'a str,
    components: usize,
    data: &'a IOBuffer,
}

fn arrays(attributes: &[Attribute]) -> Vec<NamedArray<'_>> {
    attributes
        .iter()
        .flat_map(|attribute| match attribute {
            Attribute::DataArray(a) => vec![NamedArray {
                name: &a.name,
                components: a.elem.num_comp() as usize,
                data: &a.data,
            }],
            Attribute::Field { data_array, .. } => data_array
                .iter()
                .map(|a| NamedArray {
                    name: &a.name,
                    components: a.elem as usize,
                    data: &a.data,
                })
                .collect(),
        })
        .collect()
}

/// The name of a model.toml's only region (used when a grid has no region array).
fn single_region(config: &MeshConfig) -> String {
    config.materials.keys().next().cloned().unwrap_or_default()
}

/// The grid's cells as 0-based tetrahedra; any other cell type is refused.
fn tetrahedra(
    cells: Cells,
    node_count: usize,
    error: &impl Fn(String) -> MeshError,
) -> Result<Vec<[u32; 4]>, MeshError> {
    if let Some((k, other)) = cells.types.iter().enumerate().find(|(_, t)| **t != CellType::Tetra) {
        return Err(error(format!(
            "cell {k} is a {other:?}: nak supports linear tetrahedra (VTK_TETRA, type 10) only"
        )));
    }
    let count = cells.types.len();
    let tets: Vec<[u64; 4]> = match cells.cell_verts {
        VertexNumbers::Legacy { vertices, .. } => {
            if vertices.len() != 5 * count || vertices.chunks_exact(5).any(|c| c[0] != 4) {
                return Err(error("the cell list does not hold four points per tetrahedron".into()));
            }
            vertices
                .chunks_exact(5)
                .map(|c| [c[1], c[2], c[3], c[4]].map(u64::from))
                .collect()
        }
        VertexNumbers::XML { connectivity, offsets } => {
            // Offsets mark each cell's end, after an optional leading zero.
            let ends = offsets
                .strip_prefix(&[0])
                .filter(|o| o.len() == count)
                .unwrap_or(&offsets);
            let regular = ends.len() == count && ends.iter().enumerate().all(|(k, &e)| e == 4 * (k as u64 + 1));
            if !regular || connectivity.len() != 4 * count {
                return Err(error("the cell offsets do not give four points per tetrahedron".into()));
            }
            connectivity.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect()
        }
    };
    tets.into_iter()
        .enumerate()
        .map(|(k, tet)| match tet.iter().find(|&&n| n >= node_count as u64) {
            Some(n) => Err(error(format!(
                "cell {k} refers to point {n}, but the grid has {node_count} points"
            ))),
            None => Ok(tet.map(|n| n as u32)),
        })
        .collect()
}

/// Each tetrahedron's region label, from the first region array present.
fn region_labels(
    cell_data: &[Attribute],
    count: usize,
    config: &MeshConfig,
    error: &impl Fn(String) -> MeshError,
) -> Result<Vec<i32>, MeshError> {
    let candidates = arrays(cell_data);
    let array = REGION_ARRAYS
        .iter()
        .find_map(|name| candidates.iter().find(|a| a.name == *name));
    let Some(array) = array else {
        return match config.materials.len() {
            1 => Ok(vec![0; count]),
            _ => Err(error(format!(
                "no `region` (or `labels`) cell array, and model.toml has {} regions: say which tetrahedron \
                 is which",
                config.materials.len()
            ))),
        };
    };
    let labels: Vec<i32> =
        integers(array.data).ok_or_else(|| error(format!("the cell array {:?} does not hold integers", array.name)))?;
    if array.components != 1 || labels.len() != count {
        return Err(error(format!(
            "the cell array {:?} holds {} values for {count} tetrahedra",
            array.name,
            labels.len()
        )));
    }
    if let Some(unknown) = labels.iter().find(|l| !config.region_labels.contains_key(l)) {
        return Err(error(format!(
            "region label {unknown} (cell array {:?}) is no region's `label` in model.toml; known: {:?}",
            array.name, config.region_labels
        )));
    }
    Ok(labels)
}

/// The members of a node set stored as a one-component integer point array (non-zero: member);
/// `None` for arrays that are not node sets (vectors, floats).
fn node_set(array: &NamedArray, node_count: usize) -> Option<Vec<usize>> {
    if array.components != 1 {
        return None;
    }
    let flags = integers(array.data)?;
    (flags.len() == node_count).then(|| (0..node_count).filter(|&n| flags[n] != 0).collect())
}

/// An integer array's values; `None` for floats, and for values beyond i32 (no label or flag is that
/// large, and truncating one would put a tetrahedron in the wrong region).
fn integers(buffer: &IOBuffer) -> Option<Vec<i32>> {
    if matches!(buffer, IOBuffer::F32(_) | IOBuffer::F64(_)) {
        return None;
    }
    buffer
        .cast_into::<i64>()?
        .into_iter()
        .map(|x| i32::try_from(x).ok())
        .collect()
}

/// Writes `mesh` as a VTK unstructured grid (`.vtu` XML or legacy `.vtk`, by extension): points
/// moved by `displacement` (row-major N×3, metres) when given, which is also written as the point
/// array `displacement`; regions as the cell array `region` (their labels); node sets as point
/// arrays. ParaView shows the deformed organ as is, or the reference with Warp By Vector.
pub fn write(mesh: &TetMesh, displacement: Option<&[f32]>, path: &Path) -> Result<(), MeshError> {
    let io_error = |message: String| MeshError::Io {
        path: path.display().to_string(),
        source: std::io::Error::other(message),
    };
    let Some(format) = format(path) else {
        return Err(io_error("a VTK file name ends in .vtu or .vtk".into()));
    };
    let points: Vec<f64> = mesh
        .positions
        .iter()
        .enumerate()
        .flat_map(|(n, p)| {
            let u = displacement.map_or([0.0; 3], |u| [u[3 * n], u[3 * n + 1], u[3 * n + 2]].map(f64::from));
            [p[0] + u[0], p[1] + u[1], p[2] + u[2]]
        })
        .collect();
    let mut point_data = Vec::new();
    if let Some(u) = displacement {
        point_data.push(Attribute::DataArray(DataArray {
            name: "displacement".into(),
            elem: ElementType::Vectors,
            data: IOBuffer::F32(u.to_vec()),
        }));
    }
    for (name, nodes) in &mesh.node_sets {
        let mut flags = vec![0u8; mesh.node_count()];
        for &n in nodes {
            flags[n as usize] = 1;
        }
        point_data.push(Attribute::DataArray(DataArray {
            name: name.clone(),
            elem: ElementType::Scalars {
                num_comp: 1,
                lookup_table: None,
            },
            data: IOBuffer::U8(flags),
        }));
    }
    let regions: Vec<i32> = mesh.tet_region.iter().map(|&r| mesh.regions[r as usize].id).collect();
    let grid = UnstructuredGridPiece {
        points: IOBuffer::F64(points),
        cells: Cells {
            cell_verts: VertexNumbers::XML {
                connectivity: mesh.tets.iter().flatten().map(|&n| u64::from(n)).collect(),
                offsets: (1..=mesh.tets.len() as u64).map(|k| 4 * k).collect(),
            },
            types: vec![CellType::Tetra; mesh.tets.len()],
        },
        data: Attributes {
            point: point_data,
            cell: vec![Attribute::DataArray(DataArray {
                name: "region".into(),
                elem: ElementType::Scalars {
                    num_comp: 1,
                    lookup_table: None,
                },
                data: IOBuffer::I32(regions),
            })],
        },
    };
    let legacy = format == Format::Legacy;
    let vtk = vtkio::Vtk {
        version: if legacy {
            Version::new_legacy(4, 2)
        } else {
            Version::new_xml(1, 0)
        },
        title: format!("{} ({})", mesh.config.name, mesh.content_hash),
        // Legacy binary VTK is big-endian by definition; XML records its own order.
        byte_order: if legacy {
            ByteOrder::BigEndian
        } else {
            ByteOrder::LittleEndian
        },
        data: DataSet::inline(grid),
        file_path: None,
    };
    vtk.export(path).map_err(|e| match e {
        vtkio::Error::IO(source) => MeshError::Io {
            path: path.display().to_string(),
            source,
        },
        other => io_error(format!("cannot write VTK: {other}")),
    })
}
