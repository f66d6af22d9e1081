"""Datasets exactly as `nak datagen` writes them (src/data/dataset.rs), read without conversion.

A dataset directory holds `dataset.json`, `mesh.safetensors` (the mesh's geometry as nak loaded it)
and chunks `chunk-NNNNN.safetensors` (`displacement` f32 [B, N, 3]) with `chunk-NNNNN.json` (per
sample: index, subset, split, grasps), and for nonlinear chunks `chunk-NNNNN.path.safetensors` (the
converged states of each solve's load steps before the last). A chunk without its JSON is still being generated and is
skipped, as `nak eval` does; a chunk whose tensor does not match its JSON is refused by name.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load_file

from .errors import TrainingInputError
from .surface_depth import inward_depths

SUBSETS = ("single", "multi")
SPLITS = ("train", "val", "test")


# The law of nonlinear datasets and models that name none (nak's before 2026-11-26).
LEGACY_VOLUMETRIC_LAW = "j-minus-one-squared"


@dataclass(frozen=True)
class Mesh:
    """The geometry nak serves: node order, lumped volumes and surface normals are nak's own."""

    name: str
    content_hash: str
    positions: torch.Tensor  # f64 [N, 3], metres
    nodal_volumes: torch.Tensor  # f64 [N]
    surface_nodes: torch.Tensor  # i64 [S]
    normals: torch.Tensor  # f64 [N, 3], unit on the surface, zero inside
    prior: tuple[float, float, float]  # the mesh's Kelvinlet (ν, ε, λ)
    neighbours: tuple[int, int]  # grasp neighbour count range of the sampling distribution
    tets: torch.Tensor | None = None  # i64 [T, 4]; None in datasets made before nak wrote them

    def tetrahedra(self) -> torch.Tensor:
        """`tets`, refused by name where the dataset was made before nak wrote them."""
        if self.tets is None:
            raise TrainingInputError(
                self.name, "the dataset's mesh.safetensors has no tets: rerun its nak datagen command to add them"
            )
        return self.tets

    def edges(self) -> torch.Tensor:
        """Every edge of the tetrahedra once, i64 [2, E] (smaller node first)."""
        tets = self.tetrahedra()
        pairs = torch.cat([tets[:, [a, b]] for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
        return torch.unique(pairs.sort(dim=1).values, dim=0).T.contiguous()

    @functools.cached_property
    def inward_depths(self) -> torch.Tensor:
        """f64 [N]: how much organ lies beneath each node along its inward normal (m), zero inside, as
        nak computes it for a graph that reads it (surface_depth.py)."""
        depths = inward_depths(
            self.positions.numpy(), self.tetrahedra().numpy(), self.normals.numpy(), self.surface_nodes.numpy()
        )
        return torch.from_numpy(depths)

    @property
    def node_count(self) -> int:
        return int(self.positions.shape[0])


@dataclass(frozen=True)
class Sample:
    index: int
    subset: str
    split: str
    nodes: (
        np.ndarray
    )  # i64 [K], every grasped node once (a node two grasps hold counts for the first, as nak serves it)
    displacements: np.ndarray  # f64 [K, 3], the displacement of each grasped node
    grasp_of_point: np.ndarray  # i64 [K], the grasp each node counts for
    forces: (
        np.ndarray | None
    )  # f64 [G, 3], each grasp's finite-element force (N); None in data made before nak stored them


@dataclass(frozen=True)
class Split:
    """The samples of one split and subset selection, with their fields in memory."""

    samples: list[Sample]
    fields: torch.Tensor  # f32 [S, N, 3]

    def __len__(self) -> int:
        return len(self.samples)

    def pick(self, rows: list[int]) -> Split:
        """The samples at `rows`, in that order."""
        return Split([self.samples[i] for i in rows], self.fields[rows])


@dataclass(frozen=True)
class Dataset:
    root: Path
    info: dict[str, Any]
    mesh: Mesh
    # Sets of other seeds whose every sample joins this one's train split when it trains (`joined`).
    more: tuple[Dataset, ...] = ()

    @property
    def regime(self) -> str:
        return str(self.info["regime"])

    @property
    def seed(self) -> int:
        return int(self.info["seed"])

    @property
    def volumetric_law(self) -> str | None:
        """The hyperelastic law a nonlinear dataset was solved under (None for linear data). Nonlinear
        data from before dataset.json recorded it was solved under (κ/2)(J − 1)²."""
        if self.regime != "nonlinear":
            return None
        return str(self.info.get("volumetric_law", LEGACY_VOLUMETRIC_LAW))

    def law_of_run(self, record: dict[str, Any]) -> str | None:
        """The law of the data a run's checkpoint or summary was trained on; runs from before they
        recorded it are taken to share this dataset's regime, and so the legacy law if nonlinear."""
        return record.get("volumetric_law", self.volumetric_law and LEGACY_VOLUMETRIC_LAW)

    def chunk_count(self) -> int:
        total = int(self.info["single"]) + int(self.info["multi"])
        size = int(self.info["chunk_size"])
        return -(-total // size)

    def complete_chunks(self) -> list[int]:
        """The chunks on disk now (a chunk's JSON is written last): all of them unless the set is still
        being made."""
        return [c for c in range(self.chunk_count()) if (self.root / f"chunk-{c:05d}.json").is_file()]

    def load(self, split: str, subsets: tuple[str, ...] = SUBSETS, chunks: list[int] | None = None) -> Split:
        """Every complete, successfully solved sample of `split` in `subsets` (of `chunks` only, when
        given: a set still being made is read as it stood at one moment). Split "all" takes every split:
        a held-out set, or a set that only adds training samples."""
        if split not in SPLITS + ("all",):
            raise TrainingInputError(self.root, f"unknown split {split!r}: expected one of {SPLITS} or 'all'")
        samples: list[Sample] = []
        fields: list[np.ndarray] = []
        for chunk in self.complete_chunks() if chunks is None else chunks:
            records_path = self.root / f"chunk-{chunk:05d}.json"
            records = read_json(records_path)
            if not isinstance(records, list):
                raise TrainingInputError(records_path, "expected a list of samples")
            wanted = [
                i
                for i, r in enumerate(records)
                if split in ("all", r.get("split")) and r.get("subset") in subsets and not is_failed(r)
            ]
            if not wanted:
                continue
            field = self._chunk_field(chunk, len(records))
            for i in wanted:
                samples.append(_sample(records[i], records_path))
                fields.append(field[i])
        if not samples:
            raise TrainingInputError(
                self.root, f"no complete samples in split {split!r} for subsets {list(subsets)} (nak datagen resumes)"
            )
        return Split(samples, torch.from_numpy(np.stack(fields)))

    def load_path_states(self, samples: list[Sample], chunks: list[int], start: float) -> Split | None:
        """The converged load-step states of `samples` (of this set, in `chunks`) at `start` of their
        grasp or more, each a sample of its own: its grasps moved by that share of their displacement.
        `nak datagen` keeps them in `chunk-NNNNN.path.safetensors`; chunks made before it did have
        none. None if there are none."""
        wanted = {s.index: s for s in samples}
        states: list[Sample] = []
        fields: list[np.ndarray] = []
        for chunk in chunks:
            path = self.root / f"chunk-{chunk:05d}.path.safetensors"
            if not path.is_file():
                continue
            try:
                tensors = load_file(str(path))
            except (OSError, SafetensorError) as e:
                raise TrainingInputError(path, f"unreadable load-path states ({e})") from e
            index, load, field = (tensors.get(k) for k in ("sample", "load", "displacement"))
            if index is None or load is None or field is None or field.shape[1:] != (self.mesh.node_count, 3):
                raise TrainingInputError(path, f"expected sample, load and displacement [P, {self.mesh.node_count}, 3]")
            for p in np.flatnonzero(load >= start):
                sample = wanted.get(int(index[p]))
                if sample is not None:
                    moved = dataclasses.replace(
                        sample, displacements=sample.displacements * float(load[p]), forces=None
                    )
                    states.append(moved)
                    fields.append(field[p])
        return Split(states, torch.from_numpy(np.stack(fields))) if states else None

    def joined(self, more: list[Dataset]) -> Dataset:
        """This set, training on every sample of `more` too: each must be another seed (the same seed
        would be the same grasps twice) of the same mesh, regime and law."""
        mine = (self.mesh.content_hash, self.regime, self.volumetric_law)
        seeds = {self.seed: self.root}
        for other in more:
            theirs = (other.mesh.content_hash, other.regime, other.volumetric_law)
            if theirs != mine:
                raise TrainingInputError(
                    other.root,
                    f"is mesh {theirs[0][:12]}, {theirs[1]}, law {theirs[2]}; {self.root} is mesh {mine[0][:12]}, "
                    f"{mine[1]}, law {mine[2]}: only sets of one mesh, regime and law train together",
                )
            if other.seed in seeds:
                raise TrainingInputError(
                    other.root, f"has seed {other.seed}, as {seeds[other.seed]} has: the same grasps twice"
                )
            seeds[other.seed] = other.root
        return dataclasses.replace(self, more=tuple(more))

    def _chunk_field(self, chunk: int, count: int) -> np.ndarray:
        path = self.root / f"chunk-{chunk:05d}.safetensors"
        try:
            tensors = load_file(str(path))
        except (OSError, SafetensorError) as e:
            raise TrainingInputError(path, f"unreadable chunk ({e})") from e
        field = tensors.get("displacement")
        expected = (count, self.mesh.node_count, 3)
        if field is None or field.dtype != np.float32 or field.shape != expected:
            got = "missing" if field is None else f"{field.dtype} {field.shape}"
            raise TrainingInputError(path, f"displacement is {got}; expected float32 {expected}")
        return field


def join(splits: list[Split]) -> Split:
    """The samples of `splits` one after another (a single split is returned as it is, uncopied)."""
    if len(splits) == 1:
        return splits[0]
    return Split([s for split in splits for s in split.samples], torch.cat([split.fields for split in splits]))


def is_failed(record: dict[str, Any]) -> bool:
    solver = record.get("solver")
    return isinstance(solver, dict) and solver.get("failure") is not None


def _sample(record: dict[str, Any], origin: Path) -> Sample:
    try:
        first: dict[int, tuple[int, list[float]]] = {}
        for g, grasp in enumerate(record["grasps"]):
            for n in grasp["nodes"]:
                first.setdefault(int(n), (g, grasp["displacement"]))
        forces = [g.get("force") for g in record["grasps"]]
        return Sample(
            index=int(record["index"]),
            subset=str(record["subset"]),
            split=str(record["split"]),
            nodes=np.asarray(list(first), dtype=np.int64),
            displacements=np.asarray([d for _, d in first.values()], dtype=np.float64).reshape(-1, 3),
            grasp_of_point=np.asarray([g for g, _ in first.values()], dtype=np.int64),
            forces=None if None in forces else np.asarray(forces, dtype=np.float64).reshape(-1, 3),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise TrainingInputError(origin, f"sample {record.get('index')}: malformed grasps ({e})") from e


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise TrainingInputError(path, f"unreadable ({e})") from e


def open_dataset(root: Path) -> Dataset:
    """Reads `dataset.json` and `mesh.safetensors`, checking that they describe the same mesh."""
    info = read_json(root / "dataset.json")
    for key in ("mesh_name", "mesh_hash", "node_count", "regime", "seed", "single", "multi", "chunk_size"):
        if key not in info:
            raise TrainingInputError(root / "dataset.json", f"missing key {key!r}: not a nak dataset")
    if "shard" in info:
        shard = info["shard"]
        raise TrainingInputError(
            root / "dataset.json",
            f"holds shard {shard['index']}/{shard['count']} of a dataset, not the whole: "
            "join the shards with `nak dataset join --out DIR SHARD_DIR...`",
        )
    mesh = read_mesh(root / "mesh.safetensors")
    if mesh.content_hash != info["mesh_hash"] or mesh.node_count != int(info["node_count"]):
        raise TrainingInputError(
            root / "mesh.safetensors",
            f"mesh {mesh.name} {mesh.content_hash} ({mesh.node_count} nodes) is not the dataset's mesh "
            f"{info['mesh_name']} {info['mesh_hash']} ({info['node_count']} nodes)",
        )
    return Dataset(root, info, mesh)


def read_mesh(path: Path) -> Mesh:
    if not path.is_file():
        raise TrainingInputError(path, "missing: datasets made by nak datagen carry their mesh (regenerate it)")
    try:
        tensors = load_file(str(path))
        with open(path, "rb") as f:
            header_len = int.from_bytes(f.read(8), "little")
            metadata: dict[str, str] = json.loads(f.read(header_len)).get("__metadata__", {})
    except (OSError, SafetensorError, json.JSONDecodeError) as e:
        raise TrainingInputError(path, f"unreadable mesh ({e})") from e
    try:
        return Mesh(
            name=metadata["name"],
            content_hash=metadata["content_hash"],
            positions=torch.from_numpy(tensors["positions"]),
            nodal_volumes=torch.from_numpy(tensors["nodal_volumes"]),
            surface_nodes=torch.from_numpy(tensors["surface_nodes"].astype(np.int64)),
            normals=torch.from_numpy(tensors["normals"]),
            prior=(
                float(metadata["poisson_ratio"]),
                float(metadata["epsilon_m"]),
                float(metadata["lambda"]),
            ),
            neighbours=(int(metadata["neighbours_min"]), int(metadata["neighbours_max"])),
            tets=torch.from_numpy(tensors["tets"].astype(np.int64)) if "tets" in tensors else None,
        )
    except KeyError as e:
        raise TrainingInputError(path, f"missing {e} (made by an older nak? regenerate the dataset)") from e
