//! Volumetric tetrahedral meshes with regions and named node sets.
//!
//! A [`TetMesh`] is built from an MSH 4.1 file and the `model.toml` beside it, and is validated on
//! load: a mesh that nak accepts has only positively oriented tetrahedra, no orphan nodes, a closed
//! manifold boundary, and boundary-condition node sets (`fixed`, the grasp regions) that lie on that
//! boundary and do not overlap.
//!
//! Node numbering: nodes are renumbered 0..N in the order they appear in the file's `$Nodes` section
//! (Gmsh's own order), whatever their Gmsh tags.

mod config;
mod depth;
pub mod msh;
pub mod quality;
mod refine;
mod source;
pub mod topology;
pub mod vtk;

use std::collections::{BTreeMap, HashMap};
use std::sync::OnceLock;

pub use config::{Body, GraspRegion, Material, MeshConfig, PriorParams, Sampling, VolumetricLaw};
pub use source::{EMBEDDED_NAME, MeshSource, config_text, load};
use topology::{Vec3, fmt_point, tet_volume};

/// Everything that can be wrong with a mesh or its configuration; messages say what and where.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {location}: {message}")]
    Parse {
        path: String,
        location: String,
        message: String,
    },
    #[error("{path}: {message}")]
    Config { path: String, message: String },
    #[error("{path}: {message}")]
    Unsupported { path: String, message: String },
    #[error("{path}: the mesh has no tetrahedra (nak needs a volume mesh of linear tetrahedra)")]
    NoTetrahedra { path: String },
    #[error(
        "{path}: {count} {kind} tetrahedra (volume {threshold}), e.g. {examples}; \
         fix the mesh or re-mesh with Gmsh's optimizer"
    )]
    BadTetrahedra {
        path: String,
        kind: &'static str,
        threshold: &'static str,
        count: usize,
        examples: String,
    },
    #[error("{path}: {count} nodes are used by no tetrahedron, e.g. {examples}")]
    UnusedNodes {
        path: String,
        count: usize,
        examples: String,
    },
    #[error("{path}: missing node set {name:?} (physical group); the file has: {available}")]
    MissingNodeSet {
        path: String,
        name: String,
        available: String,
    },
    #[error("{path}: the boundary surface is open: {edges} edges belong to one triangle only, e.g. edge {example}")]
    OpenSurface {
        path: String,
        edges: usize,
        example: String,
    },
    #[error("{path}: the mesh is not manifold: {what}")]
    NonManifold { path: String, what: String },
    #[error("{path}: node set {name:?} has {count} nodes off the boundary surface, e.g. node {example}")]
    NodeSetOffSurface {
        path: String,
        name: String,
        count: usize,
        example: String,
    },
    #[error("{path}: node sets {a:?} and {b:?} overlap in {count} nodes, e.g. node {example}")]
    NodeSetsOverlap {
        path: String,
        a: String,
        b: String,
        count: usize,
        example: String,
    },
}

/// A material region: a named volume physical group.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    pub name: String,
    /// The Gmsh physical tag.
    pub id: i32,
    /// Sum of its tetrahedra's volumes (m³).
    pub volume: f64,
}

#[derive(Debug, Clone)]
pub struct TetMesh {
    /// Where it came from (file path or `embedded:phantom-liver`).
    pub origin: String,
    pub config: MeshConfig,
    pub positions: Vec<Vec3>,
    pub tets: Vec<[u32; 4]>,
    /// Index into `regions` per tetrahedron.
    pub tet_region: Vec<u16>,
    pub regions: Vec<Region>,
    /// Region of each node when all its tetrahedra agree; `None` on interfaces.
    pub node_region: Vec<Option<u16>>,
    /// Named node sets (physical groups of dimension 0–2), sorted node indices.
    pub node_sets: BTreeMap<String, Vec<u32>>,
    /// Boundary triangles, counter-clockwise seen from outside.
    pub surface: Vec<[u32; 3]>,
    /// Sorted indices of the nodes on the boundary.
    pub surface_nodes: Vec<u32>,
    pub is_surface: Vec<bool>,
    /// Whether each node is in the `fixed` set: asked per node when requests are resolved.
    is_fixed: Vec<bool>,
    /// Area-weighted unit normals at surface nodes; zero inside.
    pub normals: Vec<Vec3>,
    pub tet_volumes: Vec<f64>,
    /// A quarter of each adjacent tetrahedron's volume.
    pub nodal_volumes: Vec<f64>,
    /// BLAKE3 of the geometry and labels (not the materials): keys caches and model manifests.
    pub content_hash: String,
    /// `inward_depths`, computed when first asked (only graphs that read it need it).
    inward_depths: OnceLock<Vec<f64>>,
}

/// Tetrahedra smaller than this fraction of the mean volume are degenerate.
const DEGENERATE_FRACTION: f64 = 1e-9;

impl TetMesh {
    pub fn node_count(&self) -> usize {
        self.positions.len()
    }

    /// Per node, how much organ lies beneath it (m): the distance along its inward normal to where
    /// that ray leaves the organ; zero inside. Computed on the first call (a fraction of a second on
    /// the phantom), once for every model that reads it.
    pub fn inward_depths(&self) -> &[f64] {
        self.inward_depths
            .get_or_init(|| depth::inward_depths(&self.surface, &self.positions, &self.normals, &self.surface_nodes))
    }

    /// Whether `node` is in the `fixed` set (held by the fixture: zero displacement).
    pub fn is_fixed(&self, node: u32) -> bool {
        self.is_fixed.get(node as usize).copied().unwrap_or(false)
    }

    pub fn total_volume(&self) -> f64 {
        self.tet_volumes.iter().sum()
    }

    pub fn bounding_box(&self) -> (Vec3, Vec3) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    pub fn quality(&self) -> quality::Quality {
        quality::quality(&self.tets, &self.positions)
    }

    /// Builds and validates a mesh from MSH bytes and its configuration.
    pub fn from_msh(bytes: &[u8], origin: &str, config: MeshConfig) -> Result<Self, MeshError> {
        Self::from_labelled(msh::parse(bytes, origin)?, origin, config)
    }

    /// Builds and validates a mesh from a VTK unstructured grid (`.vtu`, legacy `.vtk`) and its
    /// configuration (which names the regions by label).
    pub fn from_vtk(bytes: &[u8], origin: &str, format: vtk::Format, config: MeshConfig) -> Result<Self, MeshError> {
        Self::from_labelled(vtk::read(bytes, origin, format, &config)?, origin, config)
    }

    /// Builds and validates a mesh from its labelled form, however it was read.
    fn from_labelled(file: msh::MshFile, origin: &str, config: MeshConfig) -> Result<Self, MeshError> {
        let index: HashMap<u64, u32> = file.node_tags.iter().enumerate().map(|(i, &t)| (t, i as u32)).collect();
        let resolve = |tag: u64, element: u64| {
            index.get(&tag).copied().ok_or_else(|| MeshError::Parse {
                path: origin.to_owned(),
                location: format!("element {element}"),
                message: format!("refers to node {tag}, which is not in $Nodes"),
            })
        };
        let positions = file.node_coords.clone();

        check_finite_positions(&file, origin)?;
        check_distinct_positions(&file, origin)?;
        let (tets, tet_tags, tet_region, mut regions) = volume_elements(&file, origin, &resolve)?;
        let tet_volumes = check_volumes(&tets, &tet_tags, &positions, origin)?;
        check_all_nodes_used(&tets, &file.node_tags, origin)?;
        for (region, v) in tet_region.iter().zip(&tet_volumes) {
            regions[*region as usize].volume += v;
        }

        let surface = topology::boundary_triangles(&tets, &positions, origin)?;
        topology::check_closed_manifold(&surface, &positions, origin)?;
        topology::check_vertex_manifold(&surface, &positions, origin)?;
        let mut is_surface = vec![false; positions.len()];
        for t in &surface {
            for &v in t {
                is_surface[v as usize] = true;
            }
        }
        let surface_nodes = (0..positions.len() as u32)
            .filter(|&n| is_surface[n as usize])
            .collect();

        let node_sets = node_sets(&file, &resolve)?;
        check_boundary_sets(&config, &node_sets, &is_surface, &positions, origin)?;
        for region in &regions {
            if !config.materials.contains_key(&region.name) {
                return Err(MeshError::Config {
                    path: origin.to_owned(),
                    message: format!(
                        "region {:?} has no material: add [regions.{}] to model.toml",
                        region.name, region.name
                    ),
                });
            }
        }

        let mut node_region: Vec<Option<u16>> = vec![None; positions.len()];
        let mut conflicting = vec![false; positions.len()];
        for (tet, &r) in tets.iter().zip(&tet_region) {
            for &n in tet {
                let n = n as usize;
                match node_region[n] {
                    None if !conflicting[n] => node_region[n] = Some(r),
                    Some(existing) if existing != r => {
                        node_region[n] = None;
                        conflicting[n] = true;
                    }
                    _ => {}
                }
            }
        }

        let normals = topology::vertex_normals(&surface, &positions);
        let nodal_volumes = topology::lumped_volumes(&tets, &tet_volumes, positions.len());
        let content_hash = content_hash(&positions, &tets, &tet_region, &regions, &node_sets);
        let mut is_fixed = vec![false; positions.len()];
        for &n in node_sets.get("fixed").into_iter().flatten() {
            is_fixed[n as usize] = true;
        }
        Ok(TetMesh {
            origin: origin.to_owned(),
            config,
            positions,
            tets,
            tet_region,
            regions,
            node_region,
            node_sets,
            surface,
            surface_nodes,
            is_surface,
            is_fixed,
            normals,
            tet_volumes,
            nodal_volumes,
            content_hash,
            inward_depths: OnceLock::new(),
        })
    }
}

type VolumeElements = (Vec<[u32; 4]>, Vec<u64>, Vec<u16>, Vec<Region>);

/// Linear tetrahedra with their Gmsh tags and regions; refuses other volume elements.
fn volume_elements(
    file: &msh::MshFile,
    origin: &str,
    resolve: &impl Fn(u64, u64) -> Result<u32, MeshError>,
) -> Result<VolumeElements, MeshError> {
    let mut tets = Vec::new();
    let mut tags = Vec::new();
    let mut tet_region = Vec::new();
    let mut regions: Vec<Region> = Vec::new();
    for block in file.element_blocks.iter().filter(|b| b.entity_dim == 3) {
        if block.element_type != msh::TETRAHEDRON {
            return Err(MeshError::Unsupported {
                path: origin.to_owned(),
                message: format!(
                    "volume {} holds elements of Gmsh type {}; nak supports linear tetrahedra (type 4) only",
                    block.entity_tag, block.element_type
                ),
            });
        }
        let (name, id) = volume_region(file, block.entity_tag);
        let region = match regions.iter().position(|r| r.name == name) {
            Some(i) => i,
            None => {
                regions.push(Region { name, id, volume: 0.0 });
                regions.len() - 1
            }
        } as u16;
        for (k, &tag) in block.element_tags.iter().enumerate() {
            let c = &block.connectivity[4 * k..4 * k + 4];
            tets.push([
                resolve(c[0], tag)?,
                resolve(c[1], tag)?,
                resolve(c[2], tag)?,
                resolve(c[3], tag)?,
            ]);
            tags.push(tag);
            tet_region.push(region);
        }
    }
    if tets.is_empty() {
        return Err(MeshError::NoTetrahedra {
            path: origin.to_owned(),
        });
    }
    // Regions in physical-tag order, so that ids and listings do not depend on Gmsh's entity order.
    let mut order: Vec<usize> = (0..regions.len()).collect();
    order.sort_by_key(|&i| regions[i].id);
    let mut rank = vec![0u16; regions.len()];
    for (new, &old) in order.iter().enumerate() {
        rank[old] = new as u16;
    }
    let tet_region = tet_region.into_iter().map(|r| rank[r as usize]).collect();
    let regions = order.into_iter().map(|i| regions[i].clone()).collect();
    Ok((tets, tags, tet_region, regions))
}

/// The named volume physical group of an entity; unlabelled volumes form the region `volume_<tag>`.
fn volume_region(file: &msh::MshFile, entity: i32) -> (String, i32) {
    file.entity_physicals
        .get(&(3, entity))
        .into_iter()
        .flatten()
        .find_map(|&p| file.physical_names.get(&(3, p)).map(|name| (name.clone(), p)))
        .unwrap_or_else(|| (format!("volume_{entity}"), -entity))
}

fn check_volumes(tets: &[[u32; 4]], tags: &[u64], positions: &[Vec3], origin: &str) -> Result<Vec<f64>, MeshError> {
    let volumes: Vec<f64> = tets
        .iter()
        .map(|t| tet_volume(t.map(|n| positions[n as usize])))
        .collect();
    // Finite coordinates can still overflow a volume (found by fuzzing: 1e300 m), and a NaN volume
    // passes every comparison below.
    if let Some(i) = volumes.iter().position(|v| !v.is_finite()) {
        return Err(MeshError::Parse {
            path: origin.to_owned(),
            location: format!("element {}", tags[i]),
            message: "its volume overflows: the node coordinates are far too large for metres".into(),
        });
    }
    let mean = volumes.iter().map(|v| v.abs()).sum::<f64>() / volumes.len() as f64;
    let describe = |bad: &[usize]| {
        bad.iter()
            .take(5)
            .map(|&i| format!("element {} (volume {:.3e} m³)", tags[i], volumes[i]))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let inverted: Vec<usize> = (0..tets.len())
        .filter(|&i| volumes[i] < -DEGENERATE_FRACTION * mean)
        .collect();
    if !inverted.is_empty() {
        return Err(MeshError::BadTetrahedra {
            path: origin.to_owned(),
            kind: "inverted",
            threshold: "< 0",
            count: inverted.len(),
            examples: describe(&inverted),
        });
    }
    let degenerate: Vec<usize> = (0..tets.len())
        .filter(|&i| volumes[i] <= DEGENERATE_FRACTION * mean)
        .collect();
    if !degenerate.is_empty() {
        return Err(MeshError::BadTetrahedra {
            path: origin.to_owned(),
            kind: "degenerate",
            threshold: "≈ 0",
            count: degenerate.len(),
            examples: describe(&degenerate),
        });
    }
    Ok(volumes)
}

/// Coincident nodes mean regions were meshed separately: their interfaces would not be shared.
/// NaN or infinite coordinates pass every comparison-based check after them (found by fuzzing).
fn check_finite_positions(file: &msh::MshFile, origin: &str) -> Result<(), MeshError> {
    match file.node_coords.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        None => Ok(()),
        Some(i) => Err(MeshError::Parse {
            path: origin.to_owned(),
            location: format!("node {}", file.node_tags[i]),
            message: format!("coordinates {:?} are not finite numbers", file.node_coords[i]),
        }),
    }
}

fn check_distinct_positions(file: &msh::MshFile, origin: &str) -> Result<(), MeshError> {
    let mut order: Vec<usize> = (0..file.node_coords.len()).collect();
    let key = |i: usize| file.node_coords[i].map(f64::to_bits);
    order.sort_unstable_by_key(|&i| key(i));
    let duplicates: Vec<(usize, usize)> = order
        .windows(2)
        .filter(|w| key(w[0]) == key(w[1]))
        .map(|w| (w[0], w[1]))
        .collect();
    match duplicates.first() {
        None => Ok(()),
        Some(&(a, b)) => Err(MeshError::NonManifold {
            path: origin.to_owned(),
            what: format!(
                "{} nodes coincide with another node, e.g. tags {} and {} at {}: regions must share \
                 their interface nodes (Gmsh: fragment the volumes before meshing, or Coherence Mesh)",
                duplicates.len(),
                file.node_tags[a],
                file.node_tags[b],
                fmt_point(file.node_coords[a])
            ),
        }),
    }
}

fn check_all_nodes_used(tets: &[[u32; 4]], node_tags: &[u64], origin: &str) -> Result<(), MeshError> {
    let mut used = vec![false; node_tags.len()];
    for t in tets {
        for &n in t {
            used[n as usize] = true;
        }
    }
    let unused: Vec<usize> = (0..used.len()).filter(|&i| !used[i]).collect();
    if unused.is_empty() {
        return Ok(());
    }
    Err(MeshError::UnusedNodes {
        path: origin.to_owned(),
        count: unused.len(),
        examples: unused
            .iter()
            .take(5)
            .map(|&i| format!("tag {}", node_tags[i]))
            .collect::<Vec<_>>()
            .join(", "),
    })
}

/// Nodes of every named physical group of dimension 0, 1 or 2.
fn node_sets(
    file: &msh::MshFile,
    resolve: &impl Fn(u64, u64) -> Result<u32, MeshError>,
) -> Result<BTreeMap<String, Vec<u32>>, MeshError> {
    let mut sets: BTreeMap<String, Vec<u32>> = BTreeMap::new();
    for block in file.element_blocks.iter().filter(|b| b.entity_dim < 3) {
        let Some(physicals) = file.entity_physicals.get(&(block.entity_dim, block.entity_tag)) else {
            continue;
        };
        for p in physicals {
            let Some(name) = file.physical_names.get(&(block.entity_dim, *p)) else {
                continue;
            };
            let set = sets.entry(name.clone()).or_default();
            for (k, &tag) in block.element_tags.iter().enumerate() {
                let per = block.nodes_per_element;
                for &node in &block.connectivity[per * k..per * (k + 1)] {
                    set.push(resolve(node, tag)?);
                }
            }
        }
    }
    for set in sets.values_mut() {
        set.sort_unstable();
        set.dedup();
    }
    Ok(sets)
}

/// `fixed` and the grasp regions must exist, be non-empty, lie on the surface and be disjoint.
fn check_boundary_sets(
    config: &MeshConfig,
    sets: &BTreeMap<String, Vec<u32>>,
    is_surface: &[bool],
    positions: &[Vec3],
    origin: &str,
) -> Result<(), MeshError> {
    let required = config.required_node_sets();
    let mut owner: HashMap<u32, &str> = HashMap::new();
    for name in required {
        let nodes = sets
            .get(name)
            .filter(|s| !s.is_empty())
            .ok_or_else(|| MeshError::MissingNodeSet {
                path: origin.to_owned(),
                name: name.to_owned(),
                available: if sets.is_empty() {
                    "no node sets".to_owned()
                } else {
                    sets.keys().cloned().collect::<Vec<_>>().join(", ")
                },
            })?;
        let off: Vec<u32> = nodes.iter().copied().filter(|&n| !is_surface[n as usize]).collect();
        if let Some(&first) = off.first() {
            return Err(MeshError::NodeSetOffSurface {
                path: origin.to_owned(),
                name: name.to_owned(),
                count: off.len(),
                example: format!("{first} at {}", fmt_point(positions[first as usize])),
            });
        }
        for &n in nodes {
            if let Some(other) = owner.insert(n, name) {
                let theirs = &sets[other];
                let count = nodes.iter().filter(|m| theirs.binary_search(m).is_ok()).count();
                return Err(MeshError::NodeSetsOverlap {
                    path: origin.to_owned(),
                    a: other.to_owned(),
                    b: name.to_owned(),
                    count,
                    example: format!("{n} at {}", fmt_point(positions[n as usize])),
                });
            }
        }
    }
    Ok(())
}

fn content_hash(
    positions: &[Vec3],
    tets: &[[u32; 4]],
    tet_region: &[u16],
    regions: &[Region],
    node_sets: &BTreeMap<String, Vec<u32>>,
) -> String {
    let mut h = blake3::Hasher::new();
    h.update(b"nak-mesh-v1");
    h.update(&(positions.len() as u64).to_le_bytes());
    for p in positions {
        for c in p {
            h.update(&c.to_le_bytes());
        }
    }
    h.update(&(tets.len() as u64).to_le_bytes());
    for (t, r) in tets.iter().zip(tet_region) {
        for n in t {
            h.update(&n.to_le_bytes());
        }
        h.update(regions[*r as usize].name.as_bytes());
        h.update(&[0]);
    }
    for (name, nodes) in node_sets {
        h.update(name.as_bytes());
        h.update(&[0]);
        h.update(&(nodes.len() as u64).to_le_bytes());
        for n in nodes {
            h.update(&n.to_le_bytes());
        }
    }
    h.finalize().to_hex().to_string()
}
