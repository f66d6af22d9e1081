"""Fields nak serves, for training. The exact linear answers (green-linear, green-tangent) live in nak,
through its cached Green's functions; a network trained on such a prior learns its residual against
exactly the field nak adds to it when serving, written once per split by `nak dataset fields` and kept in
the run's directory.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load_file

from .dataset import Dataset, Split
from .errors import TrainingInputError


@dataclass(frozen=True)
class Nak:
    """The nak binary and the mesh of the datasets it is asked about."""

    binary: Path
    mesh: Path

    def run(self, *args: str) -> str:
        if not self.binary.is_file():
            raise TrainingInputError(
                self.binary, "nak binary not found: build it with `cargo build --release` (or pass --nak)"
            )
        command = [str(self.binary), *args, "--mesh", str(self.mesh)]
        result = subprocess.run(command, capture_output=True, text=True)
        if result.returncode != 0:
            raise TrainingInputError(" ".join(command), f"nak failed:\n{result.stderr.strip()}")
        return result.stdout


def served_fields(nak: Nak, dataset: Dataset, split_name: str, split: Split, model: str, cache: Path) -> torch.Tensor:
    """`model`'s field, as nak serves it, for every sample of `split` (drawn from `split_name`): f32
    [S, N, 3]. Written by nak on first use and read from `cache` after."""
    field = _served(nak, dataset, split_name, split, model, cache, "displacement")
    if field.shape != tuple(split.fields.shape):
        raise TrainingInputError(
            cache, f"{model} fields of shape {field.shape}; the split's are {tuple(split.fields.shape)}"
        )
    return torch.from_numpy(field)


def served_grasp_forces(
    nak: Nak, dataset: Dataset, split_name: str, split: Split, model: str, cache: Path
) -> torch.Tensor:
    """`model`'s force on each grasp, as nak serves it, for every sample of `split`: f64 [S, G, 3], zero
    past a sample's own grasps (from the same file as `served_fields`)."""
    return torch.from_numpy(_served(nak, dataset, split_name, split, model, cache, "grasp_forces")).double()


def _served(
    nak: Nak, dataset: Dataset, split_name: str, split: Split, model: str, cache: Path, tensor: str
) -> np.ndarray:
    """Tensor `tensor` of `nak dataset fields` for `model`, rows in `split`'s sample order."""
    path = cache / f"{model}-{split_name}.safetensors"
    if not path.is_file():
        partial = path.with_suffix(".partial")
        nak.run(
            "dataset",
            "fields",
            "--data",
            str(dataset.root),
            "--model",
            model,
            "--split",
            split_name,
            "--out",
            str(partial),
        )
        partial.replace(path)
    try:
        tensors = load_file(str(path))
    except (OSError, SafetensorError) as e:
        raise TrainingInputError(path, f"unreadable ({e}); delete it to have nak write it again") from e
    if tensor not in tensors:
        raise TrainingInputError(
            path,
            f"has no {tensor!r} (written by an older nak, or {model} gives none): delete it to have nak write it again",
        )
    row_of = {int(index): row for row, index in enumerate(tensors["index"])}
    missing = [s.index for s in split.samples if s.index not in row_of]
    if missing:
        raise TrainingInputError(
            path, f"has no field for samples {missing[:5]} (of {len(missing)}): delete it to have nak write it again"
        )
    rows = np.asarray([row_of[s.index] for s in split.samples])
    values: np.ndarray = tensors[tensor][rows]
    return values
