//! The serving engine as the subcommands assemble it from flags: the mesh, the Kelvinlet prior, the
//! shipped networks, every model directory (a model that cannot be loaded is refused, the others
//! served), and green-linear and green-tangent when asked for.

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use nak::engine::{DeformationModel, Engine, RefusedModel};
use nak::fem::{GreenFunctions, Stiffness};
use nak::mesh::{self, MeshSource, TetMesh};
use nak::model::{GreenModel, LoadContext};
use nak::prior::PriorBackend;
use nak::serve::ServeConfig;
use tracing::info;

/// Where networks come from, and the exact linear model.
#[derive(clap::Args)]
pub struct ModelArgs {
    /// Also serve `green-linear`, the exact linear FEM answer through precomputed Green's functions
    /// (computed on first use and cached; see --cache-dir).
    #[arg(long)]
    pub green_linear: bool,
    /// Also serve `green-tangent`, the hyperelastic model linearized about its gravity-preloaded state
    /// (the exact answer of the nonlinear regime for small grasps), through Green's functions computed
    /// on first use and cached.
    #[arg(long)]
    pub green_tangent: bool,
    /// Where Green's functions and the preloaded state are cached [default: $NAK_CACHE_DIR, else
    /// $XDG_CACHE_HOME/nak or ~/.cache/nak].
    #[arg(long, value_name = "DIR")]
    pub cache_dir: Option<PathBuf>,
    /// A directory whose subdirectories are models (manifest.toml + model.onnx); repeatable. A --mesh
    /// directory is always searched.
    #[arg(long = "models", value_name = "DIR")]
    pub dirs: Vec<PathBuf>,
    /// ONNX Runtime shared library (libonnxruntime.so.1.31.1) [default: $ORT_DYLIB_PATH].
    #[arg(long, value_name = "PATH")]
    pub ort_dylib: Option<PathBuf>,
    /// Where the Kelvinlet field is evaluated; `auto` times both at start-up [default: cpu].
    #[arg(long, value_enum)]
    pub prior_backend: Option<PriorBackend>,
}

impl ModelArgs {
    /// The engine these flags ask for on `mesh`, with `model` (the one the subcommand evaluates) served
    /// even when it is green-linear or green-tangent and the flag was not given.
    pub fn engine(self, mesh: Option<PathBuf>, model: &str) -> anyhow::Result<Engine> {
        build_engine(&ServeConfig {
            mesh,
            models: self.dirs,
            ort_dylib: self.ort_dylib,
            green_linear: self.green_linear || model == GreenModel::LINEAR,
            green_tangent: self.green_tangent || model == GreenModel::TANGENT,
            cache_dir: self.cache_dir,
            prior_backend: self.prior_backend.unwrap_or_default(),
            ..ServeConfig::default()
        })
    }
}

pub fn load_mesh(path: Option<&Path>) -> anyhow::Result<TetMesh> {
    let source = MeshSource::from_arg(path);
    mesh::load(&source).with_context(|| format!("cannot load mesh {source}"))
}

/// The mesh, the Kelvinlet prior and every model found under the configured directories.
pub fn build_engine(config: &ServeConfig) -> anyhow::Result<Engine> {
    let mesh = Arc::new(load_mesh(config.mesh.as_deref())?);
    let mut engine = Engine::new(mesh.clone(), config.limits());
    let choice = engine
        .use_prior_backend(config.prior_backend)
        .context("cannot use the GPU prior (--prior-backend gpu); `auto` falls back to the CPU")?;
    info!("{choice}");
    // Green's functions are made (or read from the cache) once per stiffness, when the first model
    // needs them: a network trained on that prior, or green-linear or green-tangent itself.
    let made: RefCell<HashMap<Stiffness, Arc<GreenFunctions>>> = RefCell::new(HashMap::new());
    let cache = config.cache_dir.clone().unwrap_or_else(default_cache_dir);
    let green = |stiffness: Stiffness| -> anyhow::Result<Arc<GreenFunctions>> {
        if let Some(green) = made.borrow().get(&stiffness) {
            return Ok(green.clone());
        }
        let green = Arc::new(load_green(&mesh, stiffness, &cache)?);
        made.borrow_mut().insert(stiffness, green.clone());
        Ok(green)
    };
    let green_source = |stiffness| green(stiffness).map_err(|e| format!("{e:#}"));
    let context = LoadContext {
        ort_dylib: config.ort_dylib.as_deref(),
        green: Some(&green_source),
    };
    if config.mesh.is_none() {
        load_shipped_models(&mut engine, &mesh, context)?;
    }
    for root in config.model_roots() {
        let models = nak::model::load_each(&root, &mesh, context)
            .with_context(|| format!("cannot load the models in {}", root.display()))?;
        for model in models {
            match model {
                Ok(model) => {
                    info!(model = %model.info().name, from = %root.display(), "model loaded and warmed up");
                    engine.add_model(Arc::new(model));
                }
                // One bad model must not take the others down: refuse it loudly and serve the rest.
                Err(e) => {
                    tracing::error!(model = %e.origin, "model refused, not served: {}", e.message);
                    engine.refuse_model(RefusedModel {
                        origin: e.origin,
                        reason: e.message,
                    });
                }
            }
        }
    }
    for (wanted, stiffness) in [
        (config.green_linear, Stiffness::Linear),
        (config.green_tangent, Stiffness::PreloadTangent),
    ] {
        if wanted {
            engine.add_model(Arc::new(GreenModel::new(&mesh, green(stiffness)?)));
        }
    }
    if let Some(regime) = config.regime {
        let chosen = engine
            .default_to_most_accurate(regime)
            .with_context(|| format!("--regime {regime}: no model to answer requests that name none"))?;
        info!(
            model = chosen,
            "requests naming no model get the most accurate {regime} model"
        );
    }
    Ok(engine)
}

/// The networks shipped with the embedded phantom. Without ONNX Runtime the server still starts and
/// serves the prior, saying what it left out and how to get it.
fn load_shipped_models(engine: &mut Engine, mesh: &TetMesh, context: LoadContext<'_>) -> anyhow::Result<()> {
    let shipped = nak::model::shipped::SHIPPED;
    if shipped.is_empty() {
        return Ok(());
    }
    if let Err(e) = nak::model::runtime::locate(context.ort_dylib) {
        let names: Vec<&str> = shipped.iter().map(|m| m.name).collect();
        tracing::warn!("the shipped networks {names:?} are not served: {e}");
        return Ok(());
    }
    for model in nak::model::shipped::load(mesh, context).context("cannot load the shipped networks")? {
        info!(model = %model.info().name, "shipped model loaded and warmed up");
        engine.add_model(Arc::new(model));
    }
    Ok(())
}

/// Loads the Green's functions of `stiffness` from the cache, computing them with a progress bar first.
pub fn load_green(mesh: &TetMesh, stiffness: Stiffness, cache: &Path) -> anyhow::Result<GreenFunctions> {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("Green's functions {bar:30} {pos}/{len} columns, ETA {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let name = stiffness.model_name();
    let green = GreenFunctions::load_or_compute(mesh, stiffness, cache, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("cannot prepare {name} (cache {})", cache.display()))?;
    bar.finish_and_clear();
    info!(cache = %green.path.display(), candidates = green.candidates().len(), "{name} ready");
    Ok(green)
}

pub fn default_cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("NAK_CACHE_DIR") {
        return PathBuf::from(dir);
    }
    std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(std::env::temp_dir)
        .join("nak")
}
