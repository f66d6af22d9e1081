"""Your own organ for nak: a closed triangle surface (STL, OBJ, PLY) in, a labelled tetrahedral mesh
(MSH 4.1 with node sets `fixed` and the grasp regions) and the `model.toml` that nak serves it with out.

Run `python -m nak_organ mesh --help`; docs/your-own-organ.md describes the step.
"""
