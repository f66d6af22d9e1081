"""nak's nonlinear ground truth against an independent getFEM solve (scripts/getfem-check runs this).

`nak datagen --regime nonlinear` makes a few samples on a mesh (or `--data` names a set it made of that
mesh). The same problems are then solved in getFEM (Debian's python3-getfem, for /usr/bin/python3)
from the mesh file and its model.toml alone, read here as src/mesh reads them: P1 tetrahedra on the
nodes in the file's `$Nodes` order, each region's compressible Mooney–Rivlin law with κ from its
Poisson ratio (docs/design.md §4), the body force of `[body]`, the `fixed` node set clamped. getFEM
solves the gravity preload first, then each grasp from it, the held nodes moved by their displacement
on top of the preloaded state, and its field relative to the preload is compared with nak's, sample by
sample: the relative L2 difference with the nodes weighted by their lumped volumes (a quarter of each
adjacent tetrahedron's), and the plain nodal one. nak's preload itself (its cache file, f64) is
compared too. Samples nak failed (NaN fields) are listed and not compared.

What getFEM provides: the discretization (`FEM_PK(3,1)`, exact one-point quadrature, since F is
constant on a P1 tetrahedron), the law (its own `Incompressible_Mooney_Rivlin` finite-strain brick,
C10 (Ī1 − 3) + C01 (Ī2 − 3), plus the volumetric term `(κ/2)(ln J)²`, or `(κ/2)(J − 1)²` where
model.toml asks for it, as a potential that getFEM differentiates itself), the body force, the tangent,
the residual, the energy and the linear solves (MUMPS). The Newton loop is this file's: getFEM's own
`Model.solve` has no guard against a step that inverts an element, where ln J is undefined, and lost
the two-grasper samples that way. It is the textbook one: load steps, halved when they fail; a tangent
predictor that moves the held DOFs, ended at 0.9 of the way to the first inverted element when it
would invert one; corrections with a line search that keeps det F > 0 and asks the energy to fall; a
tangent shifted until it gives a descent direction where it is indefinite. It shares no code with nak.

The mesh reader handles ASCII MSH 4.1 (the phantom's files). The dataset is read as
training/nak_training/dataset.py reads it, but without torch (a small safetensors reader below): the
system Python that has getFEM is not the project's .venv.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

try:
    import getfem as gf
except ImportError:  # pragma: no cover - the message is the point
    sys.exit(
        "getfem-check: getFEM's Python interface is missing: scripts/apt-install python3-getfem "
        f"(it is for the system Python, /usr/bin/python3; this is {sys.executable})"
    )

ROOT = Path(__file__).resolve().parent.parent
gf.util_trace_level(0)  # no "Global generic assembly" line per assembly
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

# The check's tolerance on the relative L2 difference of a sample both solved. nak's Newton stops at
# ‖r‖ ≤ 1e-6 of max(‖gravity‖, ‖reactions‖) and its datasets store the field in f32 (a relative
# rounding of up to 6e-8 a component); getFEM is driven to 1e-8 of the same scale here. Near the
# solution Newton cuts the residual quadratically, so the last iterate of each lies well inside its
# criterion, and a difference of nak's criterion, 1e-6, is already more than the solvers leave. What
# the check is for is far larger: the two volumetric laws differ by 15-106 %, the two equilibria of one
# grasp that docs/finite-elements.md describes by 1.3e-3-1.1e-2.
TOLERANCE = 1e-6
# getFEM's solves end when ‖r‖ over the free DOFs is below this fraction of max(‖gravity‖, ‖reactions
# at the held nodes‖), nak's measure: 1/100 of nak's criterion, and 10-100 times the round-off floor
# the residual reaches on the coarse phantom's deepest grasps (1e-10-1e-9).
RESIDUAL = 1e-8
NEWTON_ITERATIONS = 40
SMALLEST_STEP = 1.0 / 4096
SHIFTS = 12

# Gmsh element types and their node counts (MSH 4.1 reference, "elm-type"), the ones a nak mesh uses.
NODES_PER_ELEMENT = {1: 2, 2: 3, 3: 4, 4: 4, 15: 1}
TETRAHEDRON = 4


class CheckError(Exception):
    """Something the check cannot go on from: the message says what and where."""


# --- the mesh and its configuration, read as src/mesh reads them -------------------------------------


@dataclass
class Material:
    c10: float  # Pa
    c01: float  # Pa
    poisson_ratio: float

    @property
    def kappa(self) -> float:
        """κ from ν and μ0 = 2(C10 + C01), docs/design.md §4."""
        mu0 = 2.0 * (self.c10 + self.c01)
        return 2.0 * mu0 * (1.0 + self.poisson_ratio) / (3.0 * (1.0 - 2.0 * self.poisson_ratio))


@dataclass
class Mesh:
    positions: F64  # [N, 3], metres, in the file's $Nodes order
    tets: I64  # [T, 4]
    tet_region: list[str]  # region name per tetrahedron
    node_sets: dict[str, I64]  # sorted node indices
    materials: dict[str, Material]
    density: float
    gravity: F64
    volumetric_law: str

    @property
    def node_count(self) -> int:
        return int(self.positions.shape[0])

    def tet_volumes(self) -> F64:
        x = self.positions[self.tets]
        edges = x[:, 1:] - x[:, :1]
        return np.asarray(np.linalg.det(edges) / 6.0, dtype=np.float64)

    def nodal_volumes(self) -> F64:
        """A quarter of each adjacent tetrahedron's volume (nak's lumped volumes)."""
        volumes = np.zeros(self.node_count)
        np.add.at(volumes, self.tets.ravel(), np.repeat(self.tet_volumes() / 4.0, 4))
        return volumes


class Tokens:
    """The whitespace-separated fields of an MSH section, read in order."""

    def __init__(self, lines: list[str]) -> None:
        self.fields = " ".join(lines).split()
        self.pos = 0

    def next(self) -> str:
        self.pos += 1
        return self.fields[self.pos - 1]

    def integer(self) -> int:
        return int(self.next())

    def real(self) -> float:
        return float(self.next())

    def skip(self, count: int) -> None:
        self.pos += count


def read_msh(path: Path) -> tuple[F64, I64, list[str], dict[str, I64]]:
    """Nodes, tetrahedra, their regions and the named node sets of an ASCII MSH 4.1 file, as nak reads
    it (src/mesh/mod.rs, src/mesh/msh.rs): nodes numbered 0..N in `$Nodes` order, whatever their tags;
    a tetrahedron's region is the named volume physical group of its entity (`volume_<tag>` if none); a
    node set is every node of the elements of dimension 0-2 whose entity carries the set's physical
    group."""
    sections: dict[str, list[str]] = {}
    name: str | None = None
    for line in path.read_text().splitlines():
        text = line.strip()
        if text.startswith("$End"):
            name = None
        elif text.startswith("$"):
            name = text[1:]
            sections[name] = []
        elif name is not None:
            sections[name].append(text)
    version = sections.get("MeshFormat", [""])[0].split()
    if version[:2] != ["4.1", "0"]:
        raise CheckError(f"{path}: MeshFormat {version}: this check reads ASCII MSH 4.1 only")

    physical_names: dict[tuple[int, int], str] = {}
    for line in sections.get("PhysicalNames", [])[1:]:
        group_dim, group_tag, label = line.split(maxsplit=2)
        physical_names[(int(group_dim), int(group_tag))] = label.strip('"')

    entities = Tokens(sections["Entities"])
    counts = [entities.integer() for _ in range(4)]
    entity_physicals: dict[tuple[int, int], list[int]] = {}
    for dim, count in enumerate(counts):
        for _ in range(count):
            tag = entities.integer()
            entities.skip(3 if dim == 0 else 6)  # a point, or a bounding box
            entity_physicals[(dim, tag)] = [entities.integer() for _ in range(entities.integer())]
            if dim > 0:
                entities.skip(entities.integer())  # bounding entities

    nodes = Tokens(sections["Nodes"])
    blocks, total = nodes.integer(), nodes.integer()
    nodes.skip(2)  # smallest and largest tag
    tags: list[int] = []
    coords: list[list[float]] = []
    for _ in range(blocks):
        entity_dim, _, parametric, count = (nodes.integer() for _ in range(4))
        tags += [nodes.integer() for _ in range(count)]
        extra = min(max(entity_dim, 0), 3) if parametric else 0
        for _ in range(count):
            coords.append([nodes.real(), nodes.real(), nodes.real()])
            nodes.skip(extra)
    if len(tags) != total:
        raise CheckError(f"{path}: $Nodes announces {total} nodes, its blocks hold {len(tags)}")
    index = {t: i for i, t in enumerate(tags)}

    elements = Tokens(sections["Elements"])
    blocks = elements.integer()
    elements.skip(3)  # count, smallest and largest tag
    tets: list[list[int]] = []
    tet_region: list[str] = []
    node_sets: dict[str, set[int]] = {}
    for _ in range(blocks):
        entity_dim, entity_tag, element_type, count = (elements.integer() for _ in range(4))
        per = NODES_PER_ELEMENT.get(element_type)
        if per is None:
            raise CheckError(f"{path}: element type {element_type} is not one a nak mesh uses")
        block: list[list[int]] = []
        for _ in range(count):
            elements.skip(1)  # the element's tag
            block.append([index[elements.integer()] for _ in range(per)])
        physicals = entity_physicals.get((entity_dim, entity_tag), [])
        if entity_dim == 3:
            if element_type != TETRAHEDRON:
                raise CheckError(f"{path}: volume {entity_tag} holds elements of type {element_type}")
            names = [physical_names[(3, p)] for p in physicals if (3, p) in physical_names]
            tets += block
            tet_region += [names[0] if names else f"volume_{entity_tag}"] * count
        else:
            for p in physicals:
                if (entity_dim, p) in physical_names:
                    members = node_sets.setdefault(physical_names[(entity_dim, p)], set())
                    members.update(n for element in block for n in element)
    return (
        np.asarray(coords, dtype=np.float64),
        np.asarray(tets, dtype=np.int64),
        tet_region,
        {k: np.asarray(sorted(v), dtype=np.int64) for k, v in node_sets.items()},
    )


def load_mesh(path: Path) -> Mesh:
    """The mesh file and the model.toml beside it, in SI units (src/mesh/config.rs)."""
    config = tomllib.loads((path.parent / "model.toml").read_text())
    if config["mesh"]["units"] != "m":
        raise CheckError(f'{path.parent / "model.toml"}: mesh.units must be "m", as nak requires')
    positions, tets, tet_region, node_sets = read_msh(path)
    materials = {
        name: Material(float(r["c10_kpa"]) * 1e3, float(r["c01_kpa"]) * 1e3, float(r["poisson_ratio"]))
        for name, r in config["regions"].items()
    }
    missing = sorted(set(tet_region) - materials.keys())
    if missing:
        raise CheckError(f"{path}: regions {missing} have no material in model.toml")
    if "fixed" not in node_sets:
        raise CheckError(f"{path}: no `fixed` node set")
    return Mesh(
        positions=positions,
        tets=tets,
        tet_region=tet_region,
        node_sets=node_sets,
        materials=materials,
        density=float(config["body"]["density_kg_m3"]),
        gravity=np.asarray(config["body"]["gravity_m_s2"], dtype=np.float64),
        volumetric_law=str(config.get("hyperelastic", {}).get("volumetric_law", "ln-j-squared")),
    )


# --- the dataset, read as training/nak_training/dataset.py reads it -----------------------------------

DTYPES = {"F32": "<f4", "F64": "<f8", "U32": "<u4", "I64": "<i8"}


def read_safetensors(path: Path) -> dict[str, npt.NDArray[Any]]:
    """Every tensor of a safetensors file: an 8-byte little-endian header length, a JSON header naming
    each tensor's dtype, shape and byte range, then the data."""
    data = path.read_bytes()
    (length,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + length])
    tensors: dict[str, npt.NDArray[Any]] = {}
    for key, entry in header.items():
        if key == "__metadata__":
            continue
        start, end = entry["data_offsets"]
        raw = data[8 + length + start : 8 + length + end]
        tensors[key] = np.frombuffer(raw, dtype=DTYPES[entry["dtype"]]).reshape(entry["shape"])
    return tensors


@dataclass
class Sample:
    index: int
    subset: str
    prescribed: list[tuple[int, F64]]  # (node, displacement) in nak's order (src/data/dataset.rs)
    grasps: list[F64]  # each grasp's displacement (m)
    field: F64  # [N, 3] nak's field relative to the preload; NaN when its solve failed
    failure: str | None


def read_dataset(root: Path, node_count: int) -> tuple[dict[str, Any], list[Sample]]:
    info = json.loads((root / "dataset.json").read_text())
    if info.get("regime") != "nonlinear":
        raise CheckError(f"{root}: regime {info.get('regime')!r}, not nonlinear")
    samples: list[Sample] = []
    for records_path in sorted(root.glob("chunk-*.json")):
        records = json.loads(records_path.read_text())
        fields = read_safetensors(records_path.with_suffix(".safetensors"))["displacement"]
        if fields.shape != (len(records), node_count, 3):
            raise CheckError(f"{records_path}: displacement {fields.shape} does not match its records")
        for record, f in zip(records, fields):
            prescribed = [
                (int(n), np.asarray(g["displacement"], dtype=np.float64)) for g in record["grasps"] for n in g["nodes"]
            ]
            solver = record.get("solver") or {}
            samples.append(
                Sample(
                    index=int(record["index"]),
                    subset=str(record["subset"]),
                    prescribed=prescribed,
                    grasps=[np.asarray(g["displacement"], dtype=np.float64) for g in record["grasps"]],
                    field=f.astype(np.float64),
                    failure=solver.get("failure"),
                )
            )
    return info, samples


def check_same_mesh(mesh: Mesh, root: Path) -> None:
    """The dataset's mesh.safetensors is nak's mesh as it loaded it: the same nodes in the same order."""
    nak = read_safetensors(root / "mesh.safetensors")
    if not np.array_equal(nak["positions"], mesh.positions):
        raise CheckError(f"{root}: mesh.safetensors' positions differ from the mesh file's $Nodes order")
    if "tets" in nak and not np.array_equal(nak["tets"].astype(np.int64), mesh.tets):
        raise CheckError(f"{root}: mesh.safetensors' tetrahedra differ from the mesh file's")
    if not np.allclose(nak["nodal_volumes"], mesh.nodal_volumes(), rtol=1e-12, atol=0.0):
        raise CheckError(f"{root}: mesh.safetensors' lumped volumes differ from the mesh file's")


def read_nak_preload(cache: Path, mesh_hash: str, node_count: int) -> F64 | None:
    """nak's preloaded state of this mesh from its cache directory, if it holds exactly one
    (src/fem/preload.rs: `preload-<mesh hash>-<materials hash>.bin`, `NAKPRE01`, a 144-byte header, f64)."""
    files = sorted(cache.glob(f"preload-{mesh_hash[:16]}-*.bin"))
    if len(files) != 1:
        return None
    data = files[0].read_bytes()
    if data[:8] != b"NAKPRE01" or len(data) != 144 + 24 * node_count:
        return None
    return np.frombuffer(data[144:], dtype="<f8").reshape(node_count, 3).astype(np.float64)


# --- getFEM ------------------------------------------------------------------------------------------


@dataclass
class SolveStats:
    load_steps: int = 0
    halvings: int = 0
    shortened: int = 0  # load steps ended early by a predictor that would have inverted an element
    newton_iterations: int = 0
    residual: float = 0.0  # relative, at the end
    seconds: float = 0.0


@dataclass
class Problem:
    """The mesh in getFEM with the map from nak's (node, component) to getFEM's DOFs."""

    mesh: Mesh
    gmesh: Any
    mf: Any
    mim: Any
    dof: I64  # [N, 3]
    regions: dict[str, int] = field(default_factory=dict)

    @staticmethod
    def build(mesh: Mesh) -> Problem:
        gmesh = gf.Mesh("empty", 3)
        ids = np.asarray(gmesh.add_point(np.ascontiguousarray(mesh.positions.T)))
        if not np.array_equal(ids, np.arange(mesh.node_count)):
            raise CheckError("getFEM merged or renumbered nodes")
        convexes = np.asarray(
            gmesh.add_convex(
                gf.GeoTrans("GT_PK(3,1)"), np.ascontiguousarray(mesh.positions[mesh.tets].transpose(2, 1, 0))
            )
        )
        points, _ = gmesh.pid_from_cvid(convexes)
        if not np.array_equal(np.asarray(points), mesh.tets.ravel()):
            raise CheckError("getFEM's tetrahedra do not hold the mesh's nodes in order")
        regions: dict[str, int] = {}
        names = np.asarray(mesh.tet_region)
        for number, name in enumerate(sorted(set(mesh.tet_region)), start=1):
            gmesh.set_region(number, convexes[names == name].reshape(1, -1))
            regions[name] = number
        # P1 vector field: the DOFs of a node are its scalar DOF's three components.
        scalar = gf.MeshFem(gmesh, 1)
        scalar.set_classical_fem(1)
        mf = gf.MeshFem(gmesh, 3)
        mf.set_classical_fem(1)
        dofs, _ = scalar.basic_dof_from_cvid(convexes)
        node_dof = np.full(mesh.node_count, -1, dtype=np.int64)
        node_dof[mesh.tets.ravel()] = np.asarray(dofs, dtype=np.int64)
        if np.any(node_dof < 0) or not np.allclose(
            np.asarray(scalar.basic_dof_nodes())[:, node_dof].T, mesh.positions, rtol=0.0, atol=1e-12
        ):
            raise CheckError("getFEM's P1 DOFs do not sit on the mesh's nodes")
        dof = 3 * node_dof[:, None] + np.arange(3)[None, :]
        mim = gf.MeshIm(gmesh, gf.Integ("IM_TETRAHEDRON(1)"))  # exact: F is constant on a P1 tetrahedron
        problem = Problem(mesh, gmesh, mf, mim, dof, regions)
        problem.check_dof_map()
        return problem

    def to_dofs(self, u: F64) -> F64:
        vector = np.zeros(self.mf.nbdof())
        vector[self.dof.ravel()] = u.ravel()
        return vector

    def from_dofs(self, vector: F64) -> F64:
        return np.asarray(vector, dtype=np.float64)[self.dof]

    def check_dof_map(self) -> None:
        """The field u(x) = x, written through the map, has ∇u = I: nodes and components line up."""
        md = gf.Model("real")
        md.add_fem_variable("u", self.mf)
        md.set_variable("u", self.to_dofs(self.mesh.positions))
        gradient = np.asarray(gf.asm("generic", self.mim, 0, "Grad_u", -1, md)).reshape(3, 3)
        if not np.allclose(gradient / self.mesh.tet_volumes().sum(), np.eye(3), atol=1e-12):
            raise CheckError(f"getFEM's DOF map is wrong: ∫∇u / V = {gradient.tolist()} for u(x) = x")

    def model(self) -> Any:
        """The hyperelastic model under gravity (scaled by the data `gravity_scale`). No boundary
        condition: `equilibrium` eliminates the fixed and held DOFs itself."""
        md = gf.Model("real")
        md.add_fem_variable("u", self.mf)
        for name, region in self.regions.items():
            material = self.mesh.materials[name]
            md.add_initialized_data(f"mr_{region}", [material.c10, material.c01])
            md.add_initialized_data(f"kappa_{region}", [material.kappa])
            md.add_finite_strain_elasticity_brick(self.mim, "Incompressible_Mooney_Rivlin", "u", f"mr_{region}", region)
            md.add_nonlinear_term(self.mim, self.volumetric(region), region)
        md.add_initialized_data("gravity_scale", [1.0])
        md.add_initialized_data("body_force", self.mesh.density * self.mesh.gravity)
        md.add_source_term(self.mim, "gravity_scale*body_force.Test_u")
        return md

    def volumetric(self, region: int) -> str:
        """The volumetric term U(J) as a potential, which getFEM differentiates itself."""
        law = {
            "ln-j-squared": "0.5*kappa_{r}*sqr(log(Det(Id(3)+Grad_u)))",
            "j-minus-one-squared": "0.5*kappa_{r}*sqr(Det(Id(3)+Grad_u)-1)",
        }.get(self.mesh.volumetric_law)
        if law is None:
            raise CheckError(f"unknown volumetric law {self.mesh.volumetric_law!r}")
        return law.format(r=region)

    def energy(self, md: Any) -> tuple[float, float]:
        """The potential energy at the model's state (J), and the size of its terms (for round-off)."""
        terms = [
            float(
                gf.asm(
                    "generic",
                    self.mim,
                    0,
                    f"Incompressible_Mooney_Rivlin_potential(Grad_u, mr_{r}) + {self.volumetric(r)}",
                    r,
                    md,
                )
            )
            for r in self.regions.values()
        ]
        terms.append(-float(gf.asm("generic", self.mim, 0, "gravity_scale*body_force.u", -1, md)))
        return sum(terms), sum(abs(t) for t in terms)

    def gravity_norm(self) -> float:
        md = gf.Model("real")
        md.add_fem_variable("u", self.mf)
        md.add_initialized_data("body_force", self.mesh.density * self.mesh.gravity)
        return float(np.linalg.norm(gf.asm("generic", self.mim, 1, "body_force.Test_u", -1, md)))

    def min_jacobian(self, vector: F64) -> float:
        """The smallest det F over the tetrahedra for the state `vector` (getFEM's DOF order)."""
        x = self.mesh.positions + self.from_dofs(vector)
        deformed = x[self.mesh.tets]
        reference = self.mesh.positions[self.mesh.tets]
        ratio = np.linalg.det(deformed[:, 1:] - deformed[:, :1]) / np.linalg.det(reference[:, 1:] - reference[:, :1])
        return float(ratio.min())

    def equilibrium(
        self,
        start: F64,
        held: I64,
        held_path: Callable[[float], F64],
        gravity_path: Callable[[float], float],
        first_step: float,
        reaction_dofs: I64,
    ) -> tuple[F64, SolveStats]:
        """Follows the load t = 0 → 1 from `start` ([N, 3], an equilibrium at t = 0) in load steps: the
        DOFs `held` at `held_path(t)`, gravity scaled by `gravity_path(t)`. A load step that fails is
        undone and halved, one that converges easily lets the next grow by half. Returns the state at
        t = 1 ([N, 3], from the reference configuration)."""
        started = time.perf_counter()
        stats = SolveStats()
        md = self.model()
        free = np.ones(self.mf.nbdof(), dtype=bool)
        free[held] = False
        context = Newton(self, md, np.flatnonzero(free), held, reaction_dofs, self.gravity_norm())
        current = self.to_dofs(start)
        done, step = 0.0, first_step
        while done < 1.0:
            target = min(1.0, done + step)
            outcome = context.load_step(current, held_path(done), held_path(target), gravity_path, (done, target))
            stats.newton_iterations += outcome.iterations
            if outcome.state is None:
                stats.halvings += 1
                step /= 2.0
                if step < SMALLEST_STEP:
                    raise CheckError(f"getFEM: no equilibrium at load {target:.4f}: {outcome.why}")
                continue
            stats.load_steps += 1
            stats.residual = outcome.residual
            stats.shortened += outcome.reached < target
            current, step = (
                outcome.state,
                min(1.0, (outcome.reached - done) * (1.5 if outcome.iterations <= 8 else 1.0)),
            )
            done = outcome.reached
        stats.seconds = time.perf_counter() - started
        return self.from_dofs(current), stats


@dataclass
class StepOutcome:
    state: F64 | None  # the equilibrium reached, None when the step failed
    reached: float  # the load it is the equilibrium of (a shortened predictor ends the step early)
    iterations: int
    residual: float
    why: str = ""


@dataclass
class Newton:
    """Newton's method on the free DOFs with getFEM's tangent and residual (MUMPS for the solves):
    a tangent predictor that moves the held DOFs (shortened to 0.9 of the way to the first collapsed
    element when it would invert one: the load step then ends where it lands), then corrections with a
    line search that keeps every det F > 0 and asks the potential energy to fall (Armijo)."""

    problem: Problem
    md: Any
    free: I64
    held: I64
    reaction_dofs: I64
    gravity: float

    def assemble(self, vector: F64) -> tuple[Any, F64]:
        self.md.set_variable("u", vector)
        self.md.assembly("build_all")
        return self.md.tangent_matrix(), np.asarray(self.md.rhs(), dtype=np.float64)

    def residual(self, rhs: F64, gravity_scale: float) -> float:
        """‖r‖ over the free DOFs relative to max(‖gravity‖, ‖reactions at the held nodes‖), nak's measure."""
        scale = max(abs(gravity_scale) * self.gravity, float(np.linalg.norm(rhs[self.reaction_dofs])))
        return float(np.linalg.norm(rhs[self.free])) / scale

    def solve(self, tangent: Any, rhs: F64, shift: float = 0.0) -> F64:
        block = gf.Spmat("copy", tangent, self.free.tolist(), self.free.tolist())
        if shift > 0.0:
            block = gf.Spmat("add", block, gf.Spmat("diag", np.full(len(self.free), shift)))
        return np.asarray(gf.linsolve_mumps(block, rhs), dtype=np.float64).ravel()

    def feasible(self, vector: F64, direction: F64, alpha: float) -> float:
        """The largest α' ≤ α, halving, at which no tetrahedron is inverted or flat."""
        while alpha > 1e-12 and self.problem.min_jacobian(vector + alpha * direction) <= 0.0:
            alpha /= 2.0
        return alpha

    def load_step(
        self,
        vector: F64,
        held_from: F64,
        held_to: F64,
        gravity_path: Callable[[float], float],
        loads: tuple[float, float],
    ) -> StepOutcome:
        done, target = loads
        self.md.set_variable("gravity_scale", [gravity_path(target)])
        tangent, rhs = self.assemble(vector)
        # Predictor: the held DOFs move to their targets, the free ones as the tangent says.
        direction = np.zeros_like(vector)
        direction[self.held] = held_to - held_from
        coupling = np.asarray(tangent.mult(direction), dtype=np.float64)
        direction[self.free] = self.solve(tangent, rhs[self.free] - coupling[self.free])
        alpha = self.feasible(vector, direction, 1.0)
        if alpha < 1.0:
            # Bisect to the first collapse, then stop at 0.9 of the way (as nak's shortened predictor).
            lo, hi = alpha, 2.0 * alpha
            for _ in range(20):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if self.problem.min_jacobian(vector + mid * direction) > 0.0 else (lo, mid)
            alpha = 0.9 * lo
            target = done + alpha * (target - done)
            self.md.set_variable("gravity_scale", [gravity_path(target)])
        state = vector + alpha * direction
        gravity_scale = gravity_path(target)
        residual = float("inf")
        for iteration in range(1, NEWTON_ITERATIONS + 1):
            tangent, rhs = self.assemble(state)
            residual = self.residual(rhs, gravity_scale)
            if not np.isfinite(residual):
                return StepOutcome(None, target, iteration, residual, "a non-finite residual")
            if residual <= RESIDUAL:
                return StepOutcome(state, target, iteration, residual)
            gradient = rhs[self.free]  # −∂Π/∂u on the free DOFs
            correction = self.solve(tangent, gradient)
            shift = 1e-6 * float(np.max(np.abs(np.asarray(tangent.csc_val()))))
            for _ in range(SHIFTS):
                if float(gradient @ correction) > 0.0:
                    break
                # An indefinite tangent (tissue buckling under the graspers): shift it until it descends.
                correction = self.solve(tangent, gradient, shift)
                shift *= 10.0
            else:
                return StepOutcome(
                    None, target, iteration, residual, "no shift of the tangent gave a descent direction"
                )
            direction = np.zeros_like(state)
            direction[self.free] = correction
            moved = self.line_search(state, direction, float(gradient @ correction))
            if moved is None:
                return StepOutcome(
                    None, target, iteration, residual, f"the line search failed at residual {residual:.1e}"
                )
            state = moved
        return StepOutcome(None, target, NEWTON_ITERATIONS, residual, f"Newton stalled at residual {residual:.1e}")

    def line_search(self, state: F64, direction: F64, slope: float) -> F64 | None:
        """A feasible step along `direction` that lowers the energy by at least 1e-4 of the predicted
        fall; near the solution, where the fall is below the energy's round-off, the full feasible step."""
        self.md.set_variable("u", state)
        energy, size = self.problem.energy(self.md)
        alpha = self.feasible(state, direction, 1.0)
        if slope * alpha <= 1e-11 * size:
            return state + alpha * direction
        for _ in range(30):
            trial = state + alpha * direction
            self.md.set_variable("u", trial)
            fallen, _ = self.problem.energy(self.md)
            if np.isfinite(fallen) and fallen <= energy - 1e-4 * alpha * slope:
                return trial
            alpha /= 2.0
        return None


# --- the check ---------------------------------------------------------------------------------------


@dataclass
class Difference:
    weighted: float  # relative L2, nodes weighted by their lumped volumes
    nodal: float  # relative L2 over the nodes
    largest_mm: float  # the largest difference at a node

    def within(self, tolerance: float) -> bool:
        return self.weighted <= tolerance and self.nodal <= tolerance


def difference(nak: F64, reference: F64, volumes: F64) -> Difference:
    gap = np.sum((nak - reference) ** 2, axis=1)
    size = np.sum(reference**2, axis=1)
    return Difference(
        weighted=float(np.sqrt(np.sum(volumes * gap) / np.sum(volumes * size))),
        nodal=float(np.sqrt(np.sum(gap) / np.sum(size))),
        largest_mm=float(np.sqrt(gap.max()) * 1e3),
    )


def run_datagen(nak: Path, mesh: Path, args: argparse.Namespace, out: Path, cache: Path) -> float:
    if not nak.is_file():
        raise CheckError(f"{nak} not found: cargo build --release --bin nak (this check does not build)")
    command = [str(nak), "datagen", "--mesh", str(mesh), "--regime", "nonlinear"]
    command += ["--single", str(args.single), "--multi", str(args.multi), "--seed", str(args.seed)]
    command += ["--out", str(out), "--cache-dir", str(cache)]
    print("$", " ".join(command), flush=True)
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise CheckError(f"nak datagen failed ({done.returncode}):\n{done.stderr[-4000:]}")
    return time.perf_counter() - started


def held_nodes(sample: Sample, fixed: set[int]) -> tuple[I64, F64]:
    """The nodes a sample holds and their displacements, as nak imposes them (src/fem/nonlinear.rs):
    every grasp's nodes moved by its displacement, a node listed twice by its last grasp, a fixed node
    left fixed."""
    moved: dict[int, F64] = {}
    for node, displacement in sample.prescribed:
        if node not in fixed:
            moved[node] = displacement
    nodes = np.asarray(list(moved), dtype=np.int64)
    return nodes, np.asarray(list(moved.values()), dtype=np.float64).reshape(-1, 3)


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()}, {os.cpu_count()} CPUs"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def say(text: str) -> None:
    print(text, flush=True)


def check(args: argparse.Namespace, workdir: Path) -> bool:
    started = time.perf_counter()
    mesh = load_mesh(args.mesh)
    if args.data is None:
        data, cache = workdir / "data", workdir / "cache"
        seconds = run_datagen(args.nak, args.mesh, args, data, cache)
        say(f"nak datagen: {seconds:.1f} s (its gravity preload solved afresh in {cache})")
    else:
        data, cache = args.data, args.cache_dir
    info, samples = read_dataset(data, mesh.node_count)
    law = str(info.get("volumetric_law", "j-minus-one-squared"))
    if law != mesh.volumetric_law:
        raise CheckError(
            f"{data}: solved under {law}, but {args.mesh.parent / 'model.toml'} asks for {mesh.volumetric_law}"
        )
    check_same_mesh(mesh, data)
    volumes = mesh.nodal_volumes()

    problem = Problem.build(mesh)
    regions = ", ".join(f"{n} ({mesh.tet_region.count(n)})" for n in problem.regions)
    say(
        f"mesh {args.mesh}: {mesh.node_count} nodes, {len(mesh.tets)} tetrahedra ({regions}), "
        f"{len(mesh.node_sets['fixed'])} fixed nodes; law {mesh.volumetric_law}; tolerance {args.tolerance:g}"
    )
    fixed_nodes = mesh.node_sets["fixed"]
    fixed = problem.dof[fixed_nodes].ravel()
    no_reactions = np.zeros(0, dtype=np.int64)
    rest, stats = problem.equilibrium(
        np.zeros((mesh.node_count, 3)), fixed, lambda t: np.zeros(len(fixed)), lambda t: t, 1.0, no_reactions
    )
    sag = np.linalg.norm(rest, axis=1) * 1e3
    say(
        f"preload: getFEM {stats.load_steps} load step(s), {stats.newton_iterations} Newton iterations, "
        f"{stats.seconds:.1f} s, residual {stats.residual:.1e}; sag {sag.mean():.1f} mm mean, {sag.max():.1f} mm at most"
    )
    passed = True
    nak_rest = None if cache is None else read_nak_preload(cache, str(info["mesh_hash"]), mesh.node_count)
    if nak_rest is not None:
        d = difference(nak_rest, rest, volumes)
        passed &= d.within(args.tolerance)
        say(
            f"preload: nak's (its cache, f64) against getFEM's: relative L2 {d.weighted:.2e} volume-weighted, "
            f"{d.nodal:.2e} nodal, {d.largest_mm:.2e} mm at most{'' if d.within(args.tolerance) else ' OVER THE TOLERANCE'}"
        )

    say(
        "\n| sample | subset | held nodes | grasps (mm) | getFEM: load steps / Newton iterations / s "
        "| largest displacement (mm) | relative L2 difference, volume-weighted | nodal "
        "| getFEM's own f32 rounding | components not nak's f32 value | largest difference (mm) |"
    )
    say("|---|---|---|---|---|---|---|---|---|---|---|")
    fixed_set = set(int(n) for n in fixed_nodes)
    compared = unsolved = 0
    for sample in samples:
        nodes, displacements = held_nodes(sample, fixed_set)
        grasps = ", ".join(f"{np.linalg.norm(g) * 1e3:.0f}" for g in sample.grasps)
        prefix = f"| {sample.index} | {sample.subset} | {len(nodes)} | {grasps} |"
        if sample.failure is not None or not np.all(np.isfinite(sample.field)):
            why = (sample.failure or "a NaN field").split("; residual history")[0]
            say(f"{prefix} nak failed, not compared: {why} ||||||")
            continue
        held = np.concatenate([fixed, problem.dof[nodes].ravel()])
        start = np.concatenate([np.zeros(len(fixed)), rest[nodes].ravel()])
        path = np.concatenate([np.zeros(len(fixed)), displacements.ravel()])
        try:
            state, stats = problem.equilibrium(
                rest, held, lambda t: start + t * path, lambda t: 1.0, args.first_step, problem.dof[nodes].ravel()
            )
        except CheckError as e:
            say(f"{prefix} {e} ||||||")
            unsolved += 1
            continue
        reference = state - rest
        d = difference(sample.field, reference, volumes)
        # nak stores f32: what rounding getFEM's field to f32 alone costs, and how many of the 3N
        # components then still differ from nak's stored values (by an ulp or more).
        rounded = reference.astype(np.float32)
        rounding = difference(rounded.astype(np.float64), reference, volumes)
        off = int(np.count_nonzero(rounded != sample.field.astype(np.float32)))
        passed &= d.within(args.tolerance)
        compared += 1
        say(
            f"{prefix} {stats.load_steps} / {stats.newton_iterations} / {stats.seconds:.1f} "
            f"| {np.linalg.norm(reference, axis=1).max() * 1e3:.1f} | {d.weighted:.2e} | {d.nodal:.2e} "
            f"| {rounding.weighted:.2e} | {off} of {rounded.size} "
            f"| {d.largest_mm:.2e}{'' if d.within(args.tolerance) else ' OVER THE TOLERANCE'} |"
        )
    failed = sum(s.failure is not None for s in samples)
    say(
        f"\n{compared} samples compared, {failed} failed in nak, {unsolved} not solved by getFEM; "
        f"{time.perf_counter() - started:.1f} s in all on {cpu_name()}"
    )
    if unsolved or compared == 0:
        say("getfem-check: FAILED: " + ("some samples went unchecked" if unsolved else "no sample to compare"))
        return False
    say(f"getfem-check: {'passed' if passed else 'FAILED'} (tolerance {args.tolerance:g} relative L2)")
    return passed


def main() -> None:
    parser = argparse.ArgumentParser(prog="scripts/getfem-check", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--mesh",
        type=Path,
        default=ROOT / "models/phantom-liver/liver-coarse.msh",
        help="an ASCII MSH 4.1 file with its model.toml beside it (default: the coarse phantom)",
    )
    parser.add_argument("--nak", type=Path, default=ROOT / "target/release/nak", help="the nak binary")
    parser.add_argument("--single", type=int, default=2, help="single-grasper samples")
    parser.add_argument("--multi", type=int, default=1, help="two-grasper samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, help="check this nonlinear dataset of --mesh instead of making one")
    parser.add_argument("--cache-dir", type=Path, help="with --data: nak's cache, to compare its preload too")
    parser.add_argument("--tolerance", type=float, default=TOLERANCE, help="largest relative L2 difference")
    parser.add_argument("--first-step", type=float, default=0.25, help="getFEM's first load step of a grasp")
    args = parser.parse_args()
    try:
        with tempfile.TemporaryDirectory(prefix="getfem-check-") as workdir:
            ok = check(args, Path(workdir))
    except CheckError as e:
        sys.exit(f"getfem-check: {e}")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
