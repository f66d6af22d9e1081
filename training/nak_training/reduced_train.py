"""Training reduced-basis networks (POD, DeepONet; see reduced.py) as Base, +Res or +Reg.

The loss is the DCM's own per-sample error, ‖u_true − û‖_{L2(Ω)} / ‖u_true‖_{L2(Ω)} (docs/design.md §6),
averaged over the batch. For a POD it is exact in coefficient space; a DeepONet's is estimated on
`query_nodes` nodes drawn per step. +Reg adds λ_reg × the same relative misfit to the Kelvinlet field
of fresh q samples, whose projection onto the basis (POD) costs one field over the mesh per sample.

With `forces = true`, force_weight × the mean relative error of each grasp's force, |F̂ − F| / |F|
(the figure nak eval reports), is added; F̂ is the sum of the force head over the grasp's points, plus
the prior's own force for a +Res network on green-linear or green-tangent (what nak serves).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from .config import TrainConfig
from .dataset import Dataset, Mesh, Split
from .errors import TrainingInputError
from .kelvinlet import pad_points
from .reduced import Ensemble, ReducedNet, ceiling, project, weighted_basis
from .served import Nak, served_grasp_forces
from .train import Run

CEILING_MODES = [8, 16, 32, 48, 64, 96, 128, 192, 256]


def interaction_batch(
    mesh: Mesh, split: Split, geometry: bool, depth: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every sample's interaction points as served, padded: [S, K, 6] f32 (with `geometry`, [S, K, 10];
    with `depth` too, [S, K, 11]), the mask [S, K] and the held node ids [S, K] (padding repeats a held
    node)."""
    ids, points, displacements, mask = pad_points(
        mesh.positions,
        [torch.from_numpy(s.nodes) for s in split.samples],
        [torch.from_numpy(s.displacements) for s in split.samples],
    )
    return interaction_input(mesh, ids, points, displacements, geometry, depth), mask, ids


def interaction_input(
    mesh: Mesh,
    ids: torch.Tensor,
    points: torch.Tensor,
    displacements: torch.Tensor,
    geometry: bool,
    depth: bool = False,
) -> torch.Tensor:
    """What nak feeds an interaction graph for held nodes `ids` [..., K]: their rest positions and
    prescribed displacements, with `geometry` their surface normals and lumped nodal volumes, and with
    `depth` too the organ's depth beneath them (docs/design.md §7), f32 [..., K, 6, 10 or 11]."""
    parts = [points, displacements]
    if geometry:
        parts += [mesh.normals[ids], mesh.nodal_volumes[ids].unsqueeze(-1)]
    if depth:
        parts.append(mesh.inward_depths[ids].unsqueeze(-1))
    return torch.cat([p.float() for p in parts], dim=-1)


class GraspForces:
    """What a split's force head is scored against: per sample the grasp each padded point counts for
    ([S, K], −1 for padding), the finite-element force of each grasp and what the head must add to the
    prior's ([S, G, 3], f64) and which grasps are real ([S, G])."""

    def __init__(self, split: Split, width: int, prior: torch.Tensor | None, origin: Any) -> None:
        missing = [s.index for s in split.samples if s.forces is None]
        if missing:
            raise TrainingInputError(
                origin,
                f"samples {missing[:5]} store no grasp forces (made before nak stored them: regenerate the data)",
            )
        grasps = max(len(s.forces) for s in split.samples if s.forces is not None)
        self.point_grasp = torch.full((len(split), width), -1, dtype=torch.long)
        self.truth = torch.zeros(len(split), grasps, 3, dtype=torch.float64)
        self.real = torch.zeros(len(split), grasps, dtype=torch.bool)
        for i, s in enumerate(split.samples):
            assert s.forces is not None
            self.point_grasp[i, : len(s.grasp_of_point)] = torch.from_numpy(s.grasp_of_point)
            self.truth[i, : len(s.forces)] = torch.from_numpy(s.forces)
            self.real[i, : len(s.forces)] = True
        self.target = self.truth - (prior[:, :grasps] if prior is not None else 0.0)
        self.size = self.truth.norm(dim=-1).clamp_min(1e-12)

    def scale(self) -> torch.Tensor:
        """RMS of the target per grasp and axis: the head's output unit (it gives each grasp's share)."""
        return self.target[self.real].pow(2).mean().sqrt().clamp_min(1e-9).reshape(1).float()

    def relative_errors(self, forces: torch.Tensor, picks: torch.Tensor | slice = slice(None)) -> torch.Tensor:
        """|F̂ − F| / |F| of every real grasp of the samples `picks`, for point forces [B, K, 3]."""
        point_grasp, real = self.point_grasp[picks], self.real[picks]
        grasps = real.shape[1]
        member = (point_grasp.unsqueeze(-1) == torch.arange(grasps)).to(forces.dtype)  # [B, K, G]
        summed = torch.einsum("bkg,bkd->bgd", member, forces)
        error = (summed.double() - self.target[picks]).norm(dim=-1) / self.size[picks]
        return error[real]


class HeldNodes:
    """The nodes each sample's grasps hold, which nak answers with their prescribed displacement
    whatever the network gives (docs/design.md §7): the served field's squared error is the
    coefficient-space one less what the network's field misses there. That takes the served error at a
    held node to be zero, which holds because the ground truth has the prescribed displacement there
    (the finite elements' boundary condition)."""

    def __init__(self, ids: torch.Tensor, mask: torch.Tensor, targets: torch.Tensor, volumes: torch.Tensor) -> None:
        """`ids`, `mask` [S, K]: each sample's held nodes as `interaction_batch` pads them."""
        self.ids = ids  # padding repeats a held node and weighs nothing
        self.volumes = (volumes[ids] * mask).float()
        self.targets = targets[torch.arange(len(ids))[:, None], ids].float()  # [S, K, 3]

    def squared_error(
        self, basis: torch.Tensor, g: torch.Tensor, picks: torch.Tensor | slice = slice(None)
    ) -> torch.Tensor:
        """Σ_n V_n |Φ_n g − r_n|² over the held nodes of the samples `picks` [B], for coefficients g [B, M]."""
        estimate = torch.einsum("bkcm,bm->bkc", basis[self.ids[picks]].to(g.dtype), g)
        return (((estimate - self.targets[picks]) ** 2).sum(-1) * self.volumes[picks]).sum(-1)


def grasp_offset_rms(positions: torch.Tensor, split: Split) -> torch.Tensor:
    """RMS distance of a grasped node from its grasp's centroid over `split` (metres): the unit of the
    grasp encoder's offsets."""
    offsets = []
    for s in split.samples:
        x = positions[torch.from_numpy(s.nodes)]
        grasp = torch.from_numpy(s.grasp_of_point)
        for g in grasp.unique():
            points = x[grasp == g]
            offsets.append(points - points.mean(0))
    return torch.cat(offsets).pow(2).sum(-1).mean().sqrt()


def squared_norms(fields: torch.Tensor, volumes: torch.Tensor) -> torch.Tensor:
    """‖u‖²_{L2(Ω)} per sample of fields [S, N, 3]."""
    return (fields.double() ** 2).sum(-1) @ volumes.double()


class ReducedTrainer(Run):
    model: ReducedNet

    def __init__(
        self, config: TrainConfig, dataset: Dataset, run_dir: Path, log: Any = print, nak: Nak | None = None
    ) -> None:
        super().__init__(config, dataset, run_dir, log, nak)
        self.residual = config.method == "res"
        self.train_targets = self._targets(self.train, "train")
        self.val_targets = self._targets(self.val, "val")
        self.train_norm = squared_norms(self.train.fields, self.mesh.nodal_volumes).float()
        self.val_norm = squared_norms(self.val.fields, self.mesh.nodal_volumes).float()
        self.mean_norm = self.train_norm.mean()
        geometry, depth = config.interaction_geometry, config.interaction_depth
        self.train_points, self.train_mask, train_ids = interaction_batch(self.mesh, self.train, geometry, depth)
        self.val_points, self.val_mask, val_ids = interaction_batch(self.mesh, self.val, geometry, depth)
        net = reduced_net(config)
        self.train_forces = self._grasp_forces(self.train, "train", self.train_points.shape[1])
        self.val_forces = self._grasp_forces(self.val, "val", self.val_points.shape[1])
        if self.train_forces is not None:
            for head in net.force_heads:
                head.f_scale.copy_(self.train_forces.scale())
        positions = self.mesh.positions
        u = self.train_points[..., 3:6][self.train_mask]
        net.encoder.set_statistics(x_mean=positions.mean(0), x_std=positions.std(0), u_scale=(u**2).mean(0).sqrt())
        if config.encoder == "grasps":
            net.encoder.set_statistics(r_scale=grasp_offset_rms(positions, self.train).reshape(1))
        if geometry:
            held_volumes = self.mesh.nodal_volumes[train_ids][self.train_mask]
            net.encoder.set_statistics(v_scale=held_volumes.mean().reshape(1))
        if depth:
            held_depths = self.mesh.inward_depths[train_ids][self.train_mask]
            net.encoder.set_statistics(d_scale=held_depths.mean().reshape(1))
        volumes = self.mesh.nodal_volumes
        self.val_held = HeldNodes(val_ids, self.val_mask, self.val_targets, volumes)
        self.train_held = (
            None if config.held_nodes_in_loss else HeldNodes(train_ids, self.train_mask, self.train_targets, volumes)
        )
        self.basis: torch.Tensor | None = None
        if net.trunk is None:
            self.basis = self._pod_basis()
            self.train_projection = project(self.train_targets, self.basis, self.mesh.nodal_volumes)
            self.val_projection = project(self.val_targets, self.basis, self.mesh.nodal_volumes)
            net.encoder.set_statistics(g_scale=self.train_projection["g"].std(0).clamp_min(1e-12))
        else:
            net.trunk.x_mean.copy_(positions.mean(0).float())
            net.trunk.x_std.copy_(positions.std(0).float())
            rms = self.train_targets.pow(2).mean().sqrt()
            net.encoder.set_statistics(g_scale=torch.full((config.modes,), float(rms)))
        self.positions = positions.float()
        self._start(net)

    # -- data -----------------------------------------------------------------------------------

    def _targets(self, split: Split, name: str) -> torch.Tensor:
        """What the network's Φ g must match: u_true (Base, +Reg) or u_true − prior (+Res)."""
        if not self.residual:
            return split.fields
        self.log(f"prior over the {name} split ({len(split)} samples)…")
        return split.fields - self.residual_prior(split, name)

    def _grasp_forces(self, split: Split, name: str, width: int) -> GraspForces | None:
        """The force targets of `split` when the network learns forces; on a Green's-function prior of a
        +Res network, relative to the prior's own forces as nak serves them."""
        if not self.config.forces:
            return None
        prior = None
        if self.config.force_mode == "residual":
            assert self.nak is not None  # residual_prior needed it already
            prior = served_grasp_forces(self.nak, self.dataset, name, split, self.config.prior, self.run_dir)
        return GraspForces(split, width, prior, self.dataset.root)

    def _pod_basis(self) -> torch.Tensor:
        """The POD of the train targets, computed once per run (kept in basis.pt for resume and export)."""
        path = self.run_dir / "basis.pt"
        if path.is_file():
            try:
                saved: dict[str, Any] = torch.load(path, weights_only=True)
                basis: torch.Tensor = saved["basis"]
                if basis.shape == (self.mesh.node_count, 3, self.config.modes):
                    return basis
            except (RuntimeError, KeyError) as e:
                raise TrainingInputError(path, f"unreadable basis ({e}); delete it to recompute") from e
        pod_samples = min(self.config.pod_samples or self.sample_count, self.sample_count)
        if self.config.modes > pod_samples:
            raise TrainingInputError(
                self.dataset.root, f"modes = {self.config.modes} exceeds the {pod_samples} train samples of the POD"
            )
        targets = self.train_targets[:pod_samples]
        self.log(f"POD of {len(targets)} of {len(self.train)} train targets in L2(Ω)…")
        basis, singular = weighted_basis(targets, self.mesh.nodal_volumes, max(CEILING_MODES))
        # The ceiling on samples the POD did not see: the test split, or the val samples when test trains.
        unseen, name = (
            (self.dataset.load("test", self.config.subsets), "test")
            if self.config.holdout == "val+test"
            else (self.val, "val")
        )
        projection = project(self._targets(unseen, name), basis, self.mesh.nodal_volumes)
        ceilings = ceiling(projection, squared_norms(unseen.fields, self.mesh.nodal_volumes), CEILING_MODES)
        for m, value in ceilings.items():
            self.log(f"  best {m:>3}-term approximation of the {name} targets: DCM {value:6.2f} %")
        kept = basis[..., : self.config.modes].contiguous()
        torch.save({"basis": kept, "singular": singular, "ceiling": ceilings}, path)
        return kept

    # -- one step -------------------------------------------------------------------------------

    def _step(self) -> float:
        c = self.config
        if isinstance(self.model.encoder, Ensemble):
            return self._ensemble_step(self.model.encoder)
        picks = torch.randint(len(self.train), (c.batch,), generator=self.generator)
        g, forces = self.model.encode(self.train_points[picks], self.train_mask[picks])
        if self.basis is not None:
            loss = self._train_error(g, picks).mean()
        else:
            query = torch.randperm(self.mesh.node_count, generator=self.generator)[: c.query_nodes]
            target = self.train_targets[picks[:, None], query[None, :]]
            truth = self.train.fields[picks[:, None], query[None, :]]
            loss = self._field_error(g, query, target, (truth**2).sum(-1) @ self.volumes[query]).mean()
        if self.q is not None:
            loss = loss + c.lambda_reg * self._regularization()
        return self._descend(loss + self._force_loss(forces, picks))

    def _ensemble_step(self, ensemble: Ensemble) -> float:
        """Each member (and its force head) on its own batch, towards the POD coefficients (the config
        allows no other)."""
        c = self.config
        losses = []
        for member in range(len(ensemble.encoders)):
            picks = torch.randint(len(self.train), (c.batch,), generator=self.generator)
            g, forces = self.model.encode_member(member, self.train_points[picks], self.train_mask[picks])
            loss = self._train_error(g, picks).mean()
            losses.append(loss + self._force_loss(forces, picks))
        return self._descend(torch.stack(losses).mean())

    def _force_loss(self, forces: torch.Tensor | None, picks: torch.Tensor) -> torch.Tensor | float:
        """force_weight × the mean relative grasp-force error of the samples `picks` (0 without forces)."""
        if forces is None or self.train_forces is None:
            return 0.0
        return self.config.force_weight * self.train_forces.relative_errors(forces, picks).mean().float()

    def _train_error(self, g: torch.Tensor, picks: torch.Tensor) -> torch.Tensor:
        """The loss's per-sample error of the train samples `picks`: the served field's, or with
        `held_nodes_in_loss` the network's own field's, held nodes included."""
        assert self.basis is not None
        p = self.train_projection
        held = None if self.train_held is None else self.train_held.squared_error(self.basis, g, picks)
        return self._coefficient_error(g, p["g"][picks], p["missed"][picks], self.train_norm[picks], held)

    @staticmethod
    def _coefficient_error(
        g: torch.Tensor, target: torch.Tensor, missed: Any, norm: torch.Tensor, held: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Per sample ‖Φ g − r‖_V / ‖u‖_V for an L2(Ω)-orthonormal Φ; less the squared error `held` at
        the held nodes, which nak answers exactly (the served field's error)."""
        squared = ((g - target) ** 2).sum(1) + missed.float()
        if held is not None:
            squared = (squared - held).clamp_min(1e-12 * norm)
        return squared.sqrt() / norm.sqrt()

    def _field_error(
        self, g: torch.Tensor, query: torch.Tensor, target: torch.Tensor, norm: torch.Tensor
    ) -> torch.Tensor:
        """The same ratio estimated on the `query` nodes (DeepONet, whose Φ changes every step), for
        the squared norms `norm` [B] measured on those nodes."""
        assert self.model.trunk is not None
        phi = self.model.trunk(self.positions[query])  # [Q, 3, M]
        estimate = torch.einsum("qkm,bm->bqk", phi, g)
        v = self.volumes[query]
        error = ((estimate - target) ** 2).sum(-1) @ v
        return (error / norm.clamp_min(1e-30) + 1e-12).sqrt()

    def _regularization(self) -> torch.Tensor:
        """Misfit of the direct field to the Kelvinlet field on fresh q samples, relative to the train
        fields' mean norm (not each Kelvinlet field's own: a localized Kelvinlet field is far smaller
        than the FEM field of a similar grasp, and dividing by it lets the regularizer swamp the data)."""
        assert self.q is not None
        nodes, displacements = self.q.draw(self.config.q_batch)
        ids, points, disp, mask = pad_points(self.mesh.positions, nodes, displacements)
        interaction = interaction_input(
            self.mesh, ids, points, disp, self.config.interaction_geometry, self.config.interaction_depth
        )
        g = self.model.encoder(interaction, mask)
        if self.basis is not None:
            kelvinlet = self.prior.evaluate(self.mesh.positions, points, disp, mask).float()
            p = project(kelvinlet, self.basis, self.mesh.nodal_volumes)
            return self._coefficient_error(g, p["g"], p["missed"], self.mean_norm.expand(len(g))).mean()
        query = torch.randperm(self.mesh.node_count, generator=self.generator)[: self.config.query_nodes]
        kelvinlet = self.prior.evaluate(self.mesh.positions[query], points, disp, mask).float()
        share = self.volumes[query].sum() / self.volumes.sum()
        return self._field_error(g, query, kelvinlet, (self.mean_norm * share).expand(len(g))).mean()

    # -- validation -----------------------------------------------------------------------------

    @torch.no_grad()
    def validate(self) -> float:
        """Volume-weighted DCM of the served field (held nodes answered exactly) on the val samples:
        exact, over every node."""
        self.model.eval()
        g, forces = self.model.encode(self.val_points, self.val_mask)
        if forces is not None and self.val_forces is not None:
            errors = self.val_forces.relative_errors(forces)
            self.log(
                f"  val grasp forces: mean relative error {100 * float(errors.mean()):.1f} %, median "
                f"{100 * float(errors.median()):.1f} % ({len(errors)} grasps)"
            )
        if self.basis is not None:
            p = self.val_projection
            held = self.val_held.squared_error(self.basis, g)
            errors = self._coefficient_error(g, p["g"], p["missed"], self.val_norm, held)
        else:
            assert self.model.trunk is not None
            phi = self.model.trunk(self.positions)
            estimate = torch.einsum("nkm,bm->bnk", phi, g)
            samples, ids = torch.arange(len(self.val))[:, None], self.val_held.ids
            estimate[samples, ids] = self.val_targets[samples, ids].to(estimate.dtype)
            errors = (squared_norms(estimate - self.val_targets, self.mesh.nodal_volumes) / self.val_norm).sqrt()
        self.model.train()
        return float(100.0 * (1.0 - errors.mean()))


def reduced_net(config: TrainConfig) -> ReducedNet:
    """The untrained network `config` describes."""
    return ReducedNet(
        config.architecture,
        config.modes,
        config.width,
        config.encoder,
        config.head_width,
        config.members,
        config.force_reads_field,
        config.interaction_geometry,
        config.force_reads_grasps,
        config.interaction_depth,
    )


def load_reduced(run_dir: Path, config: TrainConfig) -> tuple[ReducedNet, torch.Tensor | None]:
    """The best network of a finished run, and its POD basis (None for a DeepONet)."""
    path = run_dir / "best.pt"
    if not path.is_file():
        raise TrainingInputError(path, "missing: train the model first")
    net = reduced_net(config)
    net.load_state_dict(torch.load(path, weights_only=True))
    net.eval()
    if net.trunk is not None:
        return net, None
    basis_path = run_dir / "basis.pt"
    if not basis_path.is_file():
        raise TrainingInputError(basis_path, "missing: the run's POD basis (train the model first)")
    basis: torch.Tensor = torch.load(basis_path, weights_only=True)["basis"]
    return net, basis


def basis_ceiling(run_dir: Path) -> dict[int, float]:
    """The test targets' best M-term DCM, as recorded when the POD was computed."""
    saved: dict[str, Any] = torch.load(run_dir / "basis.pt", weights_only=True)
    return {int(k): float(v) for k, v in saved["ceiling"].items()}
