//! What a graph takes and gives under the model contract (docs/design.md §7), read from its declared
//! inputs and outputs so that a wrong graph is refused at load with a message naming the tensor.

use ort::session::Session;
use ort::value::{Outlet, TensorElementType, ValueType};

use super::ModelLoadError;

pub const FEATURES: &str = "features";
pub const INTERACTION: &str = "interaction";
pub const DISPLACEMENT: &str = "displacement";
pub const COEFFICIENTS: &str = "coefficients";
/// The optional second output of an interaction graph: the force (N) on each interaction point.
pub const FORCES: &str = "forces";
/// Per interaction point: rest position (3) and prescribed displacement (3).
pub const INTERACTION_WIDTH: usize = 6;
/// The same, then the point's surface geometry: outward unit normal (3) and lumped nodal volume (1, m³).
pub const INTERACTION_GEOMETRY_WIDTH: usize = 10;
/// The same, then how much organ lies beneath the point along its inward normal (1, m).
pub const INTERACTION_DEPTH_WIDTH: usize = 11;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    /// `features` f32 [B, N, C]: every node's channels.
    Features,
    /// `interaction` f32 [B, K, 6, 10 or 11]: only the K interaction points (10: with their surface
    /// geometry; 11: and the organ's depth beneath them).
    Interaction,
}

impl Input {
    /// The input's name in the graph.
    pub fn name(self) -> &'static str {
        match self {
            Input::Features => FEATURES,
            Input::Interaction => INTERACTION,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    /// `displacement` f32 [B, N, 3].
    Displacement,
    /// `coefficients` f32 [B, M] of a basis beside the graph; M if the graph fixes it.
    Coefficients { modes: Option<usize> },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Signature {
    pub input: Input,
    pub output: Output,
    /// Whether the graph also gives `forces` f32 [B, K, 3] (interaction graphs only).
    pub forces: bool,
    /// Whether the `interaction` input also carries each point's surface geometry ([B, K, 10]).
    pub geometry: bool,
    /// Whether it carries the organ's depth beneath each point after that ([B, K, 11]).
    pub depth: bool,
}

impl Signature {
    /// Values per interaction point the graph reads.
    pub fn interaction_width(&self) -> usize {
        match (self.geometry, self.depth) {
            (_, true) => INTERACTION_DEPTH_WIDTH,
            (true, false) => INTERACTION_GEOMETRY_WIDTH,
            (false, false) => INTERACTION_WIDTH,
        }
    }
}

/// Reads `session`'s signature: one input (`features` [B, N, channels] or `interaction` [B, K, 6], or
/// [B, K, 10] with each point's surface geometry, or [B, K, 11] with the organ's depth beneath it too)
/// and one output (`displacement` [B, N, 3], or `coefficients` [B, M] after `interaction`), f32, with
/// B either 1 or symbolic; an interaction graph may add `forces` [B, K, 3].
pub fn read(session: &Session, channels: usize, n: usize, origin: &str) -> Result<Signature, ModelLoadError> {
    let inputs: Vec<&Outlet> = session.inputs().iter().collect();
    let input = single(&inputs, "input", [FEATURES, INTERACTION], origin)?;
    let (input, geometry, depth) = match input.name() {
        FEATURES => {
            check_shape(input, "input", &[Some(n), Some(channels)], "[batch, N, C]", origin)?;
            (Input::Features, false, false)
        }
        _ => {
            let shape = check_shape(input, "input", &[None, None], "[batch, K, 6, 10 or 11]", origin)?;
            let (geometry, depth) = match usize::try_from(shape[2]) {
                Ok(INTERACTION_WIDTH) => (false, false),
                Ok(INTERACTION_GEOMETRY_WIDTH) => (true, false),
                Ok(INTERACTION_DEPTH_WIDTH) => (true, true),
                _ => {
                    // A symbolic width would leave nak to guess what the graph reads.
                    let width = if shape[2] < 0 {
                        "a symbolic number of".to_string()
                    } else {
                        shape[2].to_string()
                    };
                    return Err(ModelLoadError::new(
                        origin,
                        format!(
                            "{INTERACTION:?} has {width} values a point; the contract gives {INTERACTION_WIDTH} \
                             (position, displacement), {INTERACTION_GEOMETRY_WIDTH} (then normal, nodal volume) \
                             or {INTERACTION_DEPTH_WIDTH} (then the organ's depth beneath it)"
                        ),
                    ));
                }
            };
            if shape[1] >= 0 {
                return Err(ModelLoadError::new(
                    origin,
                    format!(
                        "{INTERACTION:?} fixes K = {}; the contract needs K dynamic (1 to the server's limit)",
                        shape[1]
                    ),
                ));
            }
            (Input::Interaction, geometry, depth)
        }
    };
    let (main, forces): (Vec<&Outlet>, Vec<&Outlet>) = session.outputs().iter().partition(|o| o.name() != FORCES);
    let forces = match (&forces[..], input) {
        ([], _) => false,
        ([outlet], Input::Interaction) => {
            check_shape(outlet, "output", &[None, Some(3)], "[batch, K, 3]", origin)?;
            true
        }
        ([_], Input::Features) => {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "output {FORCES:?} gives a force per interaction point, which needs input {INTERACTION:?}; \
                     this graph reads {FEATURES:?}"
                ),
            ));
        }
        _ => {
            return Err(ModelLoadError::new(
                origin,
                format!("more than one output named {FORCES:?}"),
            ));
        }
    };
    let output = single(&main, "output", [DISPLACEMENT, COEFFICIENTS], origin)?;
    let output = match (output.name(), input) {
        (DISPLACEMENT, _) => {
            check_shape(output, "output", &[Some(n), Some(3)], "[batch, N, 3]", origin)?;
            Output::Displacement
        }
        (_, Input::Interaction) => {
            let shape = check_shape(output, "output", &[None], "[batch, M]", origin)?;
            Output::Coefficients {
                modes: usize::try_from(shape[1]).ok(),
            }
        }
        (_, Input::Features) => {
            return Err(ModelLoadError::new(
                origin,
                format!("output {COEFFICIENTS:?} needs input {INTERACTION:?}; this graph reads {FEATURES:?}"),
            ));
        }
    };
    Ok(Signature {
        input,
        output,
        forces,
        geometry,
        depth,
    })
}

/// The one input (or output, as `role` says) of a graph, named one of `names`.
fn single<'a>(
    outlets: &[&'a Outlet],
    role: &str,
    names: [&str; 2],
    origin: &str,
) -> Result<&'a Outlet, ModelLoadError> {
    let [a, b] = names;
    let [outlet] = outlets else {
        return Err(ModelLoadError::new(
            origin,
            format!("expected one {role}, {a:?} or {b:?}; found: {}", describe(outlets)),
        ));
    };
    if !names.contains(&outlet.name()) {
        return Err(ModelLoadError::new(
            origin,
            format!(
                "the {role} is named {:?}; the model contract names it {a:?} or {b:?}",
                outlet.name()
            ),
        ));
    }
    Ok(*outlet)
}

/// Checks that `outlet` (an input or output, as `role` says) is f32 [batch, dims...] where each
/// `Some` dimension is fixed or symbolic and each `None` one is free; returns the declared shape.
fn check_shape(
    outlet: &Outlet,
    role: &str,
    dims: &[Option<usize>],
    expected: &str,
    origin: &str,
) -> Result<Vec<i64>, ModelLoadError> {
    let name = outlet.name();
    let ValueType::Tensor { ty, shape, .. } = outlet.dtype() else {
        return Err(ModelLoadError::new(origin, format!("{role} {name:?} is not a tensor")));
    };
    let fits = |dim: i64, want: Option<usize>| dim < 0 || want.is_none_or(|w| dim == w as i64);
    let ok = *ty == TensorElementType::Float32
        && shape.len() == dims.len() + 1
        && fits(shape[0], Some(1))
        && shape[1..].iter().zip(dims).all(|(&d, &w)| fits(d, w));
    if !ok {
        let wanted = dims
            .iter()
            .map(|d| d.map_or("any".to_owned(), |v| v.to_string()))
            .collect::<Vec<_>>()
            .join(", ");
        return Err(ModelLoadError::new(
            origin,
            format!(
                "{role} {name:?} is {ty:?} {:?}; expected Float32 {expected} = [batch, {wanted}] (fixed or symbolic)",
                shape.to_vec()
            ),
        ));
    }
    Ok(shape.to_vec())
}

fn describe(outlets: &[&Outlet]) -> String {
    outlets
        .iter()
        .map(|o| format!("{} {:?}", o.name(), o.dtype().tensor_shape().map(|s| s.to_vec())))
        .collect::<Vec<_>>()
        .join(", ")
}
