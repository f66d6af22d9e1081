"""A training run's configuration: one TOML file, committed beside the model it made."""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import TrainingInputError
from .models import ARCHITECTURES, SIZES
from .reduced import ENCODERS, REDUCED_ARCHITECTURES

METHODS = {"base": "direct", "res": "residual", "reg": "direct"}
PRECISIONS = ("f16", "f32")
# How a reduced network's basis is shipped: a basis file nak multiplies, or folded into the graph.
FORMS = ("basis", "graph")
# The prior +Res learns its residual to: the Kelvinlet, or an exact linear answer nak serves through
# Green's functions (green-linear: linear elasticity at rest; green-tangent: the hyperelastic model
# linearized about its gravity-preloaded state).
PRIORS = ("kelvinlet", "green-linear", "green-tangent")
FORCE_MODES = ("direct", "residual")
# What of the dataset's own samples training leaves out (TrainConfig.holdout).
HOLDOUTS = ("val+test", "val")
SUBSETS = {"single": ("single",), "multi": ("multi",), "all": ("single", "multi")}


@dataclass(frozen=True)
class TrainConfig:
    name: str
    architecture: str
    method: str  # base | res | reg (the paper's Base, Method 1, Method 2)
    size: str = "cpu"
    # Which samples train the model: single (Indiv.), multi (Comb.) or all (Multi).
    subset: str = "all"
    # Kelvinlet ε in metres, or "fit": the best of a grid over 1–8 cm on the train split.
    epsilon: float | str = "fit"
    # What +Res adds its output to (and what the manifest tells nak to compose it with).
    prior: str = "kelvinlet"
    steps: int = 3000
    batch: int = 16
    # Nodes decoded (and scored) per step; the pooled summary always sees every node.
    query_nodes: int = 1024
    lr: float = 2e-3
    weight_decay: float = 5e-5
    # Kelvinlet regularization (method reg): weight and q samples per step (docs/design.md §5).
    lambda_reg: float = 1.0
    q_batch: int = 8
    val_every: int = 250
    val_samples: int = 256
    # Reduced-basis networks (pod, deeponet): modes M, encoder width, basis storage, how it ships.
    modes: int = 64
    width: int = 256
    encoder: str = "linear"  # linear (more accurate) | pooled (fewer operators, faster)
    basis_precision: str = "f16"
    form: str = "basis"
    # What of the dataset's own samples training leaves out: "val+test", its val and test splits (test is
    # where `nak eval` scores it), or "val", only the val samples the run selects on, the rest of val and
    # all of test training too: for networks scored on a held-out set of another seed, which need no
    # test split of their own (about a fifth more samples).
    holdout: str = "val+test"
    # Train on this many samples spread over the train split (0: all): for learning curves.
    train_samples: int = 0
    # POD from the first this many train targets (0: all): the S × S Gram matrix of the POD bounds how
    # many samples it can take, not how many the encoder may learn from.
    pod_samples: int = 0
    # Train on the converged states of the train samples' load steps too (`nak datagen` keeps them
    # beside each nonlinear chunk: the organ's equilibrium with the grasps moved by that share of their
    # displacement), those at this share or more: 0 takes them all, 1 (every state is short of the
    # whole grasp) none.
    path_states_from: float = 1.0
    # Reduced networks: a second output, the force on each interaction point, trained on the data's
    # finite-element grasp forces with this weight on their mean relative error (docs/design.md §7).
    forces: bool = False
    force_weight: float = 0.1
    # "direct": the head's forces are served alone; "residual": added to the prior's own forces (+Res
    # on green-linear or green-tangent, whose (G[S,S])⁻¹ u_S are the linearization's forces).
    force_mode: str = "direct"
    # The force head's width: its cost per interaction point.
    force_width: int = 64
    # The force head also reads the field's M coefficients (once a set, beside the encoder's summary).
    force_reads_field: bool = False
    # Grasp encoders: the force head also reads what each point sees of the grasps (its grasp's mean
    # embedding, the other grasps' and their centroid's offset), once per grasp as served.
    force_reads_grasps: bool = False
    # Grasp encoders: each interaction point's surface geometry (outward unit normal, lumped nodal volume)
    # joins its position and displacement in the input, which nak then fills from the mesh
    # (docs/design.md §7): whether a grasp pushes into the surface or pulls it out, and how much of the
    # organ each held node stands for.
    interaction_geometry: bool = False
    # With the surface geometry, how much organ lies beneath each held node along its inward normal (m):
    # a push into thin tissue meets the far surface sooner and is answered stiffer. The network could
    # learn it from positions (docs/training.md, "The organ's depth beneath a grasp").
    interaction_depth: bool = False
    # POD networks: whether the loss scores the network's field at the nodes the grasps hold too. nak
    # answers those with their prescribed displacement whatever the network gives (docs/design.md §7),
    # so false trains on the served field's error alone and spends none of the basis there.
    held_nodes_in_loss: bool = True
    # POD networks: an ensemble of this many encoders, each trained on its own batches, served as the
    # mean of their coefficients in one graph (1: one encoder).
    members: int = 1
    # Decay of the exponential moving average of the weights that is validated, kept and exported
    # (e.g. 0.999: about the last thousand steps); 0: the weights as trained.
    ema: float = 0.0
    seed: int = 0
    threads: int = 2
    description: str = ""

    @property
    def mode(self) -> str:
        return METHODS[self.method]

    @property
    def reduced(self) -> bool:
        """Whether this is a reduced-basis network, served in the interaction form."""
        return self.architecture in REDUCED_ARCHITECTURES

    @property
    def head_width(self) -> int | None:
        """The force head's width, or None for a network without one."""
        return self.force_width if self.forces else None

    @property
    def subsets(self) -> tuple[str, ...]:
        return SUBSETS[self.subset]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def parse_config(values: dict[str, Any], origin: str) -> TrainConfig:
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise TrainingInputError(origin, f"unknown key(s) {unknown}; known: {sorted(known)}")
    for key in ("name", "architecture", "method"):
        if key not in values:
            raise TrainingInputError(origin, f"missing key {key!r}")
    choices: dict[str, tuple[str, ...]] = {
        "architecture": (*ARCHITECTURES, *REDUCED_ARCHITECTURES),
        "method": tuple(METHODS),
        "size": SIZES,
        "subset": tuple(SUBSETS),
        "basis_precision": PRECISIONS,
        "form": FORMS,
        "encoder": ENCODERS,
        "prior": PRIORS,
        "force_mode": FORCE_MODES,
        "holdout": HOLDOUTS,
    }
    for key, allowed in choices.items():
        if key in values and values[key] not in allowed:
            raise TrainingInputError(origin, f"{key} = {values[key]!r}: expected one of {list(allowed)}")
    epsilon = values.get("epsilon", "fit")
    if epsilon != "fit" and not (isinstance(epsilon, int | float) and 0 < epsilon < 1):
        raise TrainingInputError(origin, f'epsilon = {epsilon!r}: expected "fit" or metres in (0, 1)')
    try:
        config = TrainConfig(**values)
    except TypeError as e:
        raise TrainingInputError(origin, str(e)) from e
    for key in (
        "steps",
        "batch",
        "query_nodes",
        "val_every",
        "val_samples",
        "threads",
        "modes",
        "width",
        "force_width",
        "members",
    ):
        if int(getattr(config, key)) < 1:
            raise TrainingInputError(origin, f"{key} = {getattr(config, key)!r}: must be at least 1")
    if config.train_samples < 0:
        raise TrainingInputError(origin, f"train_samples = {config.train_samples!r}: must be 0 (all) or more")
    if config.forces and not config.reduced:
        raise TrainingInputError(
            origin, "forces = true needs a reduced architecture (pod, deeponet): forces are per interaction point"
        )
    if config.force_mode == "residual" and not (config.method == "res" and config.prior != "kelvinlet"):
        raise TrainingInputError(
            origin,
            'force_mode = "residual" adds to the prior\'s forces: it needs method = "res" on green-linear or green-tangent',
        )
    if config.interaction_geometry and not (config.reduced and config.encoder == "grasps"):
        raise TrainingInputError(
            origin, 'interaction_geometry = true needs a reduced architecture with encoder = "grasps"'
        )
    if config.interaction_depth and not config.interaction_geometry:
        raise TrainingInputError(
            origin, "interaction_depth = true needs interaction_geometry = true: it reads after it"
        )
    if config.force_reads_grasps and not (config.forces and config.encoder == "grasps"):
        raise TrainingInputError(origin, 'force_reads_grasps = true needs forces = true and encoder = "grasps"')
    if config.force_reads_field and not config.forces:
        raise TrainingInputError(origin, "force_reads_field = true needs forces = true: it shapes the force head")
    if not config.force_weight >= 0:
        raise TrainingInputError(origin, f"force_weight = {config.force_weight!r}: must be 0 or more")
    if config.members > 1 and (config.architecture != "pod" or config.method == "reg"):
        raise TrainingInputError(origin, 'members > 1 (an ensemble) needs architecture = "pod", method base or res')
    if config.holdout == "val" and config.method == "res" and config.prior != "kelvinlet":
        # nak serves green-linear's and green-tangent's fields per split (served.py), and this train
        # split would be parts of three.
        raise TrainingInputError(
            origin, f'holdout = "val" needs no prior or the Kelvinlet\'s (method = "res" on {config.prior})'
        )
    if not 0.0 <= config.ema < 1.0:
        raise TrainingInputError(origin, f"ema = {config.ema!r}: must be in [0, 1) (0: no averaging)")
    if not 0.0 <= config.path_states_from <= 1.0:
        raise TrainingInputError(
            origin,
            f"path_states_from = {config.path_states_from!r}: must be in [0, 1] (0: every load-path state, 1: none)",
        )
    if config.path_states_from < 1.0 and (config.forces or config.prior != "kelvinlet"):
        # The states carry no grasp forces, and nak serves green-linear's and green-tangent's fields per
        # sample of a split, not per state.
        raise TrainingInputError(
            origin, "path_states_from needs a network without forces on no prior or the Kelvinlet's"
        )
    if not config.held_nodes_in_loss and config.architecture != "pod":
        raise TrainingInputError(origin, 'held_nodes_in_loss = false needs architecture = "pod"')
    if config.pod_samples < 0:
        raise TrainingInputError(origin, f"pod_samples = {config.pod_samples!r}: must be 0 (all) or more")
    return config


def load_config(path: Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    return parse_config({**read_values(path), **(overrides or {})}, str(path))


def read_values(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A configuration file's keys; `extends = "other.toml"` (beside it) takes that file's keys first,
    so that a variant names only what it changes."""
    try:
        values = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise TrainingInputError(path, f"unreadable configuration ({e})") from e
    base = values.pop("extends", None)
    if base is None:
        return values
    if not isinstance(base, str):
        raise TrainingInputError(path, f"extends = {base!r}: expected the file name of another configuration")
    parent = (path.parent / base).resolve()
    if parent in seen or parent == path.resolve():
        raise TrainingInputError(path, f"extends {base}, which leads back here: a circle")
    return {**read_values(parent, (*seen, path.resolve())), **values}
