"""Writing `model.toml`: the phantom's configuration (models/phantom-liver/model.toml) for one organ.

The prior, body and hyperelastic law are the phantom's; the one region has the paper's liver constants;
the sampling distribution keeps the phantom's neighbour counts and scales its displacement cuboid by the
organ's size, so that a kidney is not pulled as far as a liver.
"""

from __future__ import annotations

import json
from pathlib import Path

from .msh import REGION, REGION_TAG

# The phantom liver's bounding-box diagonal (models/phantom-liver/liver.msh: 231 × 183 × 120 mm;
# tests/python/test_organ.py checks it against the file) and its displacement cuboid (mm).
PHANTOM_DIAGONAL_M = 0.3182
PHANTOM_DISPLACEMENT_MIN_MM = (-90.0, -90.0, -60.0)
PHANTOM_DISPLACEMENT_MAX_MM = (50.0, 50.0, 90.0)


def scaled_displacements(diagonal_m: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The phantom's displacement cuboid scaled by an organ's diagonal over the phantom's (mm, 0.1 mm)."""
    scale = diagonal_m / PHANTOM_DIAGONAL_M
    return (
        tuple(round(v * scale, 1) for v in PHANTOM_DISPLACEMENT_MIN_MM),
        tuple(round(v * scale, 1) for v in PHANTOM_DISPLACEMENT_MAX_MM),
    )


def _vector(values: tuple[float, ...]) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in values) + "]"


def model_toml(
    name: str,
    source: Path,
    msh_name: str,
    diagonal_m: float,
    grasp_regions: list[str],
    displacement_mm: tuple[tuple[float, ...], tuple[float, ...]] | None,
) -> str:
    """The text of model.toml. `displacement_mm` (min, max) overrides the scaled cuboid when given."""
    if displacement_mm is None:
        low, high = scaled_displacements(diagonal_m)
        cuboid = (
            "# The displacement cuboid is the phantom's (x and y -90 to 50 mm, z -60 to 90 mm) scaled by this\n"
            f"# organ's bounding-box diagonal, {diagonal_m * 1000:.1f} mm, over the phantom's, "
            f"{PHANTOM_DIAGONAL_M * 1000:.1f} mm\n"
            f"# (models/phantom-liver/liver.msh): × {diagonal_m / PHANTOM_DIAGONAL_M:.3f}.\n"
        )
    else:
        low, high = displacement_mm
        cuboid = (
            "# The displacement cuboid was given on the command line (--displacement-min-mm/--displacement-max-mm).\n"
        )
    weight = repr(1.0 / len(grasp_regions))
    regions = "".join(f'\n[[sampling.grasp_regions]]\nnode_set = "{r}"\nweight = {weight}\n' for r in grasp_regions)
    return f"""# nak mesh configuration for {json.dumps(name)}, made by `python -m nak_organ mesh` from {source.name}
# (docs/your-own-organ.md). Units: SI (metres, pascals, kilograms) unless a key says otherwise; moduli
# are given in kPa as in the paper and converted to Pa when loaded.

[mesh]
name = {json.dumps(name)}
# The mesh served when this directory is passed as --mesh.
default = {json.dumps(msh_name)}
units = "m"

# Regularized Kelvinlet prior (docs/design.md §3). A network trained with one prior must be served with it.
[prior]
poisson_ratio = 0.45
epsilon_m = 0.05
lambda = 1e-3

[body]
density_kg_m3 = 1000.0
# Gravity points along -y.
gravity_m_s2 = [0.0, -9.81, 0.0]

# The hyperelastic law's volumetric term (docs/design.md §4): "ln-j-squared", (κ/2)(ln J)², a barrier
# that keeps elements from inverting, or "j-minus-one-squared", (κ/2)(J − 1)².
[hyperelastic]
volumetric_law = "ln-j-squared"

# One region, the whole organ, with the paper's liver constants: linear shear modulus μ = 0.69 kPa and
# ν = 0.45; Mooney–Rivlin C10 = 1.62 kPa, C01 = 1.97 kPa. For another tissue change shear_modulus_kpa,
# poisson_ratio (below 0.5), c10_kpa and c01_kpa; keep label = {REGION_TAG} (the mesh's physical tag for
# "{REGION}"). A network is trained for one set of materials: train again after a change.
[regions.{REGION}]
label = {REGION_TAG}
shear_modulus_kpa = 0.69
poisson_ratio = 0.45
c10_kpa = 1.62
c01_kpa = 1.97

# Training/evaluation distribution p (docs/design.md §5): grasp regions Ω_i with prior weights g(Ω_i),
# here {len(grasp_regions)} regions sampled equally.
{cuboid}[sampling]
displacement_min_mm = {_vector(low)}
displacement_max_mm = {_vector(high)}
neighbours_min = 3
neighbours_max = 7
{regions}"""
