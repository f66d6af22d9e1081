//! `nak predict`: one offline evaluation through the serving engine, written as .npy.

use std::path::Path;

use anyhow::{Context, bail};
use nak::engine::{Engine, Grasp, Prediction, Request, Selection};
use serde::Deserialize;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GraspFile {
    grasps: Vec<GraspJson>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GraspJson {
    #[serde(default)]
    nodes: Vec<u32>,
    point: Option<[f64; 3]>,
    #[serde(default)]
    radius: f64,
    displacement: [f64; 3],
}

pub fn read_grasps(path: &Path) -> anyhow::Result<Vec<Grasp>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let file: GraspFile = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: expected {{\"grasps\": [{{\"nodes\": [...], \"displacement\": [dx, dy, dz]}}, \
             {{\"point\": [x, y, z], \"radius\": r, \"displacement\": [...]}}]}} in metres",
            path.display()
        )
    })?;
    Ok(file
        .grasps
        .into_iter()
        .map(|g| Grasp {
            nodes: g.nodes,
            point: g.point,
            radius: g.radius,
            displacement: g.displacement,
        })
        .collect())
}

pub fn run(engine: &Engine, model: &str, grasps: Vec<Grasp>, surface_only: bool) -> anyhow::Result<Prediction> {
    let request = Request {
        model: model.to_owned(),
        grasps,
        selection: if surface_only {
            Selection::Surface
        } else {
            Selection::All
        },
        ..Request::default()
    };
    Ok(engine.predict(&request)?)
}

/// Writes row-major (n, 3) f32 displacements as a NumPy .npy file.
pub fn write_npy(path: &Path, displacements: &[f32]) -> anyhow::Result<()> {
    if !displacements.len().is_multiple_of(3) {
        bail!("displacements are not (n, 3)");
    }
    let file = std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    use npyz::WriterBuilder;
    let mut writer = npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&[(displacements.len() / 3) as u64, 3])
        .writer(std::io::BufWriter::new(file))
        .begin_nd()?;
    writer.extend(displacements.iter().copied())?;
    writer.finish()?;
    Ok(())
}
