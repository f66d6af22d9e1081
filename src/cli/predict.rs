//! `nak predict`: one offline evaluation through the serving engine, written as .npy, or as the
//! deformed mesh for ParaView (.vtu, legacy .vtk).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use nak::engine::{Engine, Grasp, Prediction, Request, Selection};
use serde::Deserialize;

use super::engine::ModelArgs;

#[derive(clap::Args)]
pub struct PredictArgs {
    /// A model directory or a mesh file (.msh, .vtu, legacy .vtk) with model.toml beside it
    /// [default: the embedded phantom liver].
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Model to evaluate.
    #[arg(long, default_value = "kelvinlet")]
    model: String,
    /// JSON: {"grasps": [{"nodes": [...], "displacement": [dx, dy, dz]}, {"point": [x, y, z],
    /// "radius": r, "displacement": [...]}]}, metres.
    #[arg(long)]
    grasps: PathBuf,
    /// Output: .npy (float32, N × 3), or .vtu / .vtk: the deformed mesh with the displacement,
    /// regions and node sets as point and cell data (ParaView).
    #[arg(long)]
    out: PathBuf,
    /// Write the surface nodes only (Mesh.surface_nodes order) instead of every node.
    #[arg(long)]
    surface_only: bool,
    #[command(flatten)]
    models: ModelArgs,
}

pub fn run(args: PredictArgs) -> anyhow::Result<()> {
    let engine = args.models.engine(args.mesh, &args.model)?;
    let grasps = read_grasps(&args.grasps)?;
    let as_mesh = nak::mesh::vtk::format(&args.out).is_some();
    if as_mesh && args.surface_only {
        bail!("--surface-only writes rows, not a mesh: write .npy, or drop --surface-only for .vtu/.vtk");
    }
    let prediction = evaluate(&engine, &args.model, grasps, args.surface_only)?;
    if as_mesh {
        nak::mesh::vtk::write(engine.mesh(), Some(&prediction.displacements), &args.out)?;
    } else {
        write_npy(&args.out, &prediction.displacements)?;
    }
    print!("{}", summary(&prediction, &args.out));
    Ok(())
}

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

pub fn evaluate(engine: &Engine, model: &str, grasps: Vec<Grasp>, surface_only: bool) -> anyhow::Result<Prediction> {
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

/// What `nak predict` prints: the field's size and reach, the time, and each grasper's force.
pub fn summary(prediction: &Prediction, written: &Path) -> String {
    let largest = prediction
        .displacements
        .chunks(3)
        .map(|u| (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt())
        .fold(0.0f32, f32::max);
    let mut text = format!(
        "{}: {} nodes, {} interaction points, largest displacement {:.2} mm, {:.0} µs → {}\n",
        prediction.model,
        prediction.displacements.len() / 3,
        prediction.interaction_points,
        largest * 1e3,
        prediction.timing.total_us,
        written.display()
    );
    match &prediction.grasp_forces {
        Some(forces) => {
            for (g, f) in forces.iter().enumerate() {
                let magnitude = f.iter().map(|v| v * v).sum::<f64>().sqrt();
                text += &format!(
                    "  grasps[{g}] exerts ({:+.4}, {:+.4}, {:+.4}) N on the tissue, |F| = {magnitude:.4} N\n",
                    f[0], f[1], f[2]
                );
            }
        }
        None => text += "  (this model gives no grasp forces; kelvinlet estimates them, green-linear is exact)\n",
    }
    text
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
