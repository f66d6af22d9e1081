"""Reduced-basis networks (docs/design.md §7, the `interaction` form): a set encoder over the K interaction
points gives M coefficients g, and the field is Φ g for a basis Φ [N, 3, M] that depends on the mesh
alone. Per request the work scales with K (and the M-term product), not with a network over N nodes.

* POD: Φ is the proper orthogonal decomposition of the training targets in L2(Ω) (lumped volumes V,
  docs/design.md §6), so Φᵀ V Φ = I and ‖Φ g − r‖²_V = ‖g − Φᵀ V r‖² + ‖r − Φ Φᵀ V r‖²_V: the model is
  trained in coefficient space and its DCM on the training targets is exact without touching a node.
* DeepONet: Φ(x) is a trunk MLP over node positions, learned with the encoder (the branch); it is
  evaluated over the mesh's nodes once, at export (a basis file) or by ONNX Runtime's constant folding
  at load (a graph holding the positions).

Three set encoders (`encoder` in the configuration):

* `linear`: linear in the prescribed displacements given the geometry, as linear elasticity is: per
  point a matrix B_k [M, 3] from the point's position and a summary of the whole set, g = mean_k
  B_k û_k, plus a nonlinear term of the summary (for what is not linear).
* `grasps`: the linear encoder summed over grasps, each point also seeing its offset from its grasp's
  centroid and its grasp's point count (which mean and max pooling cannot see, and on which the
  nonlinear fields depend strongly). The most accurate.
* `pooled`: a per-point MLP, mean and max over the points, an MLP head: few operators, so ONNX
  Runtime answers in a few tens of microseconds. The faster.

With `forces`, a force head gives the force on each interaction point from the point's normalized
input and the set's summary, in the encoder's own form: f_k = A_k û_k + c_k (a matrix and an offset per
point), so the stiffness a grasp meets may depend on where it is and what else is held. nak sums the
points of each grasp (docs/design.md §7).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import torch
from torch import nn

REDUCED_ARCHITECTURES = ("pod", "deeponet")
# Squared distance of two points' normalized displacements below which they count as one grasp's.
SAME_GRASP = 1e-10


def mlp(widths: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(widths) - 2:
            layers.append(nn.GELU())
    return nn.Sequential(*layers)


ENCODERS = ("linear", "pooled", "grasps")
# An interaction point's position and prescribed displacement; with geometry, its surface's outward unit
# normal and its lumped nodal volume after them, and with depth the organ's depth beneath it last
# (docs/design.md §7: nak fills what the graph's width asks).
INTERACTION_WIDTH = 6
GEOMETRY_WIDTH = 4


class Encoder(nn.Module):
    """interaction [B, K, 6] (rest position, prescribed displacement; metres), or [B, K, 10] with each
    point's surface geometry after them (outward unit normal, lumped nodal volume in m³; `geometry`), or
    [B, K, 11] with the organ's depth beneath it last (m; `depth`) → g [B, M], with the train split's
    statistics as buffers (part of the exported graph)."""

    x_mean: torch.Tensor
    x_std: torch.Tensor
    u_scale: torch.Tensor
    g_scale: torch.Tensor
    v_scale: torch.Tensor
    d_scale: torch.Tensor

    # What each point gives a force head without surface geometry (`point_features` counts it in): its
    # normalized position and displacement first.
    BASE_POINT_FEATURES = 6

    def __init__(self, modes: int, geometry: bool = False, depth: bool = False) -> None:
        super().__init__()
        if depth and not geometry:
            raise ValueError("the organ's depth is read after the surface geometry: it needs geometry")
        self.modes = modes
        self.geometry = geometry
        self.depth = depth
        self.point_features = self.BASE_POINT_FEATURES + (GEOMETRY_WIDTH if geometry else 0) + int(depth)
        for name, shape in [("x_mean", 3), ("x_std", 3), ("u_scale", 3), ("g_scale", modes)]:
            self.register_buffer(name, torch.ones(shape) if name != "x_mean" else torch.zeros(shape))
        if geometry:
            # The train split's mean held-node volume: nodal volumes are about 1e-8 m³.
            self.register_buffer("v_scale", torch.ones(1))
        if depth:
            # The train split's mean held-node depth: several centimetres.
            self.register_buffer("d_scale", torch.ones(1))

    def set_statistics(self, **stats: torch.Tensor) -> None:
        for name, value in stats.items():
            self.get_buffer(name).copy_(value.to(torch.float32))

    def input_shift_scale(self) -> tuple[torch.Tensor, torch.Tensor]:
        """What the input is normalized by, channel by channel: positions by the mesh's statistics,
        displacements by their RMS, normals as they are (unit), volumes and depths by their mean."""
        shift = torch.cat([self.x_mean, torch.zeros_like(self.u_scale)])
        scale = torch.cat([self.x_std, self.u_scale])
        if self.geometry:
            shift = torch.cat([shift, shift.new_zeros(GEOMETRY_WIDTH)])
            scale = torch.cat([scale, scale.new_ones(3), self.v_scale])
        if self.depth:
            shift = torch.cat([shift, shift.new_zeros(1)])
            scale = torch.cat([scale, self.d_scale])
        return shift, scale

    def normalized(self, interaction: torch.Tensor) -> torch.Tensor:
        """One subtract and one divide by constant vectors (folded once the graph is loaded)."""
        shift, scale = self.input_shift_scale()
        return (interaction - shift) / scale

    def forward(self, interaction: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return self.encode(interaction, mask)[0]

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """g [B, M], each point's features [B, K, point_features] (its normalized position and displacement
        first) and the set's summary [B, 2W], the last two for a force head."""
        raise NotImplementedError

    def grasp_sizes(self, features: torch.Tensor) -> torch.Tensor:
        """[B, K, 1]: the number of points in each point's grasp, from the point features `encode` gave."""
        return same_grasp(features).sum(-1, keepdim=True)


def pool(e: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """[mean, max] over the points of e [B, K, d] (real points only, under `mask`), and the mask's
    weights [B, K, 1] (None without a mask)."""
    if mask is None:
        return torch.cat([e.mean(1), e.amax(1)], dim=-1), None
    weights = mask.unsqueeze(-1).to(e.dtype)
    mean = (e * weights).sum(1) / weights.sum(1)
    largest = e.masked_fill(~mask.unsqueeze(-1), float("-inf")).amax(1)
    return torch.cat([mean, largest], dim=-1), weights


class PooledEncoder(Encoder):
    """Per-point MLP 6 → W → W → W, mean and max over the points, head 2W → W → M."""

    def __init__(self, modes: int, width: int) -> None:
        super().__init__(modes)
        self.embed = mlp([6, width, width, width])
        self.head = mlp([2 * width, width, modes])

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f = self.normalized(interaction)
        summary, _ = pool(self.embed(f), mask)
        return self.head(summary) * self.g_scale, f, summary


class SetEncoder(Encoder):
    """The linear encoder: g = mean_k B_k û_k + head(summary)."""

    def __init__(self, modes: int, width: int) -> None:
        super().__init__(modes)
        self.embed = mlp([6, width, width, width])
        self.matrices = mlp([3 + 2 * width, width, width, 3 * modes])
        self.head = mlp([2 * width, width, modes])

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`mask` [B, K] marks real points in a padded training batch; a served request has none.

        The first layer of `matrices`, a Linear over [x, summary], is split (`split_linear`).
        """
        f = self.normalized(interaction)
        e = self.embed(f)
        summary, weights = pool(e, mask)
        b = self.matrices[1:](split_linear(self.matrices[0], [f[..., :3]], summary)).unflatten(-1, (self.modes, 3))
        linear = (b * f[..., 3:].unsqueeze(-2)).sum(-1)  # [B, K, M]: B_k û_k
        linear = linear.mean(1) if weights is None else (linear * weights).sum(1) / weights.sum(1)
        return (linear + self.head(summary)) * self.g_scale, f, summary


def same_grasp(f: torch.Tensor) -> torch.Tensor:
    """[B, K, K]: 1 where two points move exactly alike, i.e. belong to one grasp (a request gives one
    displacement per grasp, and its points are all the grasp shows of itself)."""
    u = f[..., 3:6]
    return (((u.unsqueeze(2) - u.unsqueeze(1)) ** 2).sum(-1) < SAME_GRASP).to(f.dtype)


class GraspEncoder(Encoder):
    """The linear encoder summed over grasps, each seen whole: g = Σ_grasps (mean_{k ∈ grasp} B_k û_k +
    head_k), with B_k and head_k from the point, its grasp's mean embedding, the other grasps' mean
    embedding and the offset of their centroid from its grasp's, and the whole set's summary.

    Each point's input adds to its position and displacement its offset from its grasp's centroid (in
    units of `r_scale`, the train split's RMS offset: a few millimetres, invisible in positions
    normalized by the organ's size) and the log of its grasp's point count: how far the organ follows
    a grasp depends strongly on how much of the surface it holds, which mean and max pooling cannot
    count. Two graspers start from the sum of what each would do alone (superposition, exact in linear
    elasticity up to the grasps' coupling), which the one-grasper samples teach; what each grasp sees
    of the others carries the coupling.
    """

    r_scale: torch.Tensor

    # Position and displacement, offset from the grasp's centroid, log of the grasp's count (last); with
    # surface geometry its normal and volume after the displacement (`point_features`).
    BASE_POINT_FEATURES = 10

    def __init__(self, modes: int, width: int, geometry: bool = False, depth: bool = False) -> None:
        super().__init__(modes, geometry, depth)
        self.register_buffer("r_scale", torch.ones(1))
        self.embed = mlp([self.point_features, width, width, width])
        # What each point sees of the grasps: its own grasp's and the other grasps' mean embeddings, and
        # the offset of the others' centroid.
        self.context_features = 2 * width + 3
        self.matrices = mlp([self.point_features + self.context_features + 2 * width, width, width, 3 * modes])
        self.head = mlp([self.context_features + 2 * width, width, modes])

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        g, features, summary, _ = self.encode_with_context(interaction, mask)
        return g, features, summary

    def encode_with_context(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """`encode`'s, and what each point sees of the grasps [B, K, 2W + 3] (its grasp's mean embedding,
        the other grasps' and their centroid's offset), for a force head that reads it."""
        f = self.normalized(interaction)
        alike = same_grasp(f)
        real = torch.ones_like(alike) if mask is None else (mask.unsqueeze(1) & mask.unsqueeze(2)).to(f.dtype)
        alike = alike * real  # pairs of real points only
        others = real - alike
        size = alike.sum(-1, keepdim=True).clamp_min(1.0)  # [B, K, 1]: the point's grasp's point count
        count = others.sum(-1, keepdim=True)  # points of the other grasps (0 for one grasper)
        x = interaction[..., :3]
        centroid = (alike @ x) / size
        features = torch.cat([f, (x - centroid) / self.r_scale, size.log()], dim=-1)
        e = self.embed(features)
        summary, _ = pool(e, mask)
        apart = ((others @ x) / count.clamp_min(1.0) - centroid) / self.x_std * (count > 0).to(f.dtype)
        context = torch.cat([(alike @ e) / size, (others @ e) / count.clamp_min(1.0), apart], dim=-1)
        b = self.matrices[1:](split_linear(self.matrices[0], [features, context], summary))
        b = b.unflatten(-1, (self.modes, 3))
        head = self.head[1:](split_linear(self.head[0], [context], summary))
        per_point = (b * f[..., 3:6].unsqueeze(-2)).sum(-1) + head  # [B, K, M]
        share = 1.0 / size if mask is None else mask.unsqueeze(-1).to(f.dtype) / size
        return (per_point * share).sum(1) * self.g_scale, features, summary, context

    def grasp_sizes(self, features: torch.Tensor) -> torch.Tensor:
        """The count the features carry (their last, its log): two operators a request where counting
        the points that move alike again takes eight, a third of a force head's."""
        return features[..., -1:].exp()


def split_linear(first: nn.Module, per_point: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
    """The Linear `first` over [per-point inputs [B, K, ·]…, summary [B, S]], its summary columns applied
    once per set rather than to a copy per point: ONNX Runtime's cost per request is mostly per operator
    and per value, and slices of weights are constants folded when the graph is loaded."""
    assert isinstance(first, nn.Linear)
    out = (summary @ first.weight[:, -summary.shape[-1] :].T + first.bias).unsqueeze(1)
    start = 0
    for part in per_point:
        out = out + part @ first.weight[:, start : start + part.shape[-1]].T
        start += part.shape[-1]
    return out


class Ensemble(Encoder):
    """Several encoders of one kind, each trained on its own batches from its own initial weights; g is
    the mean of theirs, in one graph. Where a network fits its few samples closely (the nonlinear
    regime), the members' errors on new grasps partly cancel in the mean."""

    def __init__(self, members: list[Encoder]) -> None:
        super().__init__(members[0].modes)
        self.members = nn.ModuleList(members)

    @property
    def encoders(self) -> list[Encoder]:
        return [cast(Encoder, member) for member in self.members]

    def set_statistics(self, **stats: torch.Tensor) -> None:
        own = dict(self.named_buffers(recurse=False))
        super().set_statistics(**{name: value for name, value in stats.items() if name in own})
        for member in self.encoders:
            member.set_statistics(**stats)

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The members' mean g, with the first member's point features and summary."""
        outputs = [member.encode(interaction, mask) for member in self.encoders]
        g = torch.stack([g for g, _, _ in outputs]).mean(0)
        return g, outputs[0][1], outputs[0][2]


class ForceHead(nn.Module):
    """The force (N) on each interaction point: its grasp's share of (A_k û_k + c_k) · f_scale, with
    A_k [3, 3] and c_k from an MLP over the point's features from the encoder (its normalized input, and
    with the grasp encoder its grasp's size and shape) and the set's summary (its first layer split as
    in SetEncoder, so the summary is transformed once per set).

    nak sums the points of each grasp; each point gives its value divided by the number of points moved
    exactly as it is, which is its grasp's size (the interaction input marks no grasps, and points that
    move alike are the only grasp it shows). How the force grows with that size (on the phantom, about
    1.9 N at 4 held nodes to 3.4 N at 8, docs/reports/forces.md) the head learns from the encoder's
    point features, which with the grasp encoder include the size."""

    f_scale: torch.Tensor
    row_sums: torch.Tensor

    def __init__(
        self,
        width: int,
        hidden: int,
        point_features: int = Encoder.BASE_POINT_FEATURES,
        coefficients: int = 0,
        context: int = 0,
    ) -> None:
        """`width`: the encoder's (its summary has 2 × width values); `hidden`: the head's own, which sets
        its cost per point; `point_features`: what the encoder gives of each point; `coefficients`: how
        many of the network's own coefficients it reads beside the summary (0: none); `context`: how many
        values of what each point sees of the grasps it reads after its features (0: none)."""
        super().__init__()
        self.first = nn.Linear(point_features + context + 2 * width + coefficients, hidden)
        self.rest = nn.Sequential(nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, 12))
        self.register_buffer("f_scale", torch.ones(1))
        # [9, 3]: 1 at (3i + j, i), summing each row of A (row-major, the MLP's first nine outputs).
        self.register_buffer("row_sums", torch.eye(3).repeat_interleave(3, dim=0), persistent=False)

    def forward(
        self,
        points: torch.Tensor,
        summary: torch.Tensor,
        grasp_sizes: torch.Tensor,
        context: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """`grasp_sizes` [B, K, 1]: the encoder's count of each point's grasp (`Encoder.grasp_sizes`);
        `context` [B, K, C]: what each point sees of the grasps, for a head made to read it.

        A_k û_k is taken as (A_k's entries ⊙ û_k three times) @ `row_sums`, flat: the [3, 3] reshape of
        a tensor whose leading axes are dynamic costs ONNX Runtime five operators a request, this two."""
        per_point = [points] if context is None else [points, context]
        out = self.rest(split_linear(self.first, per_point, summary))
        u = points[..., 3:6]
        a_u = (out[..., :9] * torch.cat([u, u, u], dim=-1)) @ self.row_sums
        return (a_u + out[..., 9:]) * (self.f_scale / grasp_sizes)


class Trunk(nn.Module):
    """DeepONet's trunk: node positions [N, 3] → basis [N, 3, M]."""

    x_mean: torch.Tensor
    x_std: torch.Tensor

    def __init__(self, modes: int, width: int) -> None:
        super().__init__()
        self.modes = modes
        self.net = mlp([3, width, width, width, 3 * modes])
        self.register_buffer("x_mean", torch.zeros(3))
        self.register_buffer("x_std", torch.ones(3))
        self.scale = nn.Parameter(torch.tensor(1.0))

    def forward(self, positions: torch.Tensor) -> torch.Tensor:
        x = (positions - self.x_mean) / self.x_std
        return self.net(x).unflatten(-1, (3, self.modes)) * self.scale


class ReducedNet(nn.Module):
    """The encoder, and the trunk for a DeepONet (a POD's basis is data, not parameters)."""

    def __init__(
        self,
        architecture: str,
        modes: int,
        width: int,
        encoder: str = "linear",
        force_width: int | None = None,
        members: int = 1,
        force_reads_field: bool = False,
        geometry: bool = False,
        force_reads_grasps: bool = False,
        depth: bool = False,
    ) -> None:
        """`force_width`: the force head's width (None: no force head); `members`: encoders averaged;
        `force_reads_field`: the force head also reads the field's coefficients (normalized), once a set;
        `geometry`: the input carries each point's surface normal and nodal volume (grasp encoders);
        `force_reads_grasps`: the force head reads what each point sees of the grasps (grasp encoders);
        `depth`: after the surface geometry, the organ's depth beneath each point (grasp encoders)."""
        super().__init__()

        if force_reads_grasps and force_width is None:
            raise ValueError("force_reads_grasps needs a force head (force_width)")
        if force_reads_grasps and encoder != "grasps":
            raise ValueError(f"a force head reads the grasps of grasp encoders only, not of {encoder!r}")
        if geometry and encoder != "grasps":
            raise ValueError(f"surface geometry is an input of grasp encoders only, not of {encoder!r}")
        kinds: dict[str, Callable[[int, int], Encoder]] = {
            "linear": SetEncoder,
            "pooled": PooledEncoder,
            "grasps": lambda m, w: GraspEncoder(m, w, geometry, depth),
        }
        encoders = [kinds[encoder](modes, width) for _ in range(members)]
        self.encoder: Encoder = encoders[0] if members == 1 else Ensemble(encoders)
        self.trunk = Trunk(modes, width) if architecture == "deeponet" else None
        self.force_reads_field = force_reads_field
        read = modes if force_reads_field else 0
        # An ensemble's members each have a head, fed by their own features, and serve the mean force.
        # One encoder keeps its head unlisted, so its weights keep the names shipped models were saved with.
        self.force_reads_grasps = force_reads_grasps
        context = cast(GraspEncoder, encoders[0]).context_features if force_reads_grasps else 0
        heads = (
            []
            if force_width is None
            else [ForceHead(width, force_width, e.point_features, read, context) for e in encoders]
        )
        self.forces: nn.Module | None = None if not heads else heads[0] if members == 1 else nn.ModuleList(heads)

    @property
    def members(self) -> list[Encoder]:
        return self.encoder.encoders if isinstance(self.encoder, Ensemble) else [self.encoder]

    @property
    def force_heads(self) -> list[ForceHead]:
        """One per member; none without forces."""
        if isinstance(self.forces, nn.ModuleList):
            return [cast(ForceHead, head) for head in self.forces]
        return [] if self.forces is None else [cast(ForceHead, self.forces)]

    def encode(
        self, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """g [B, M] and, with force heads, the force on each point [B, K, 3]: an ensemble's means."""
        if self.forces is None:
            return self.encoder(interaction, mask), None
        outputs = [self.encode_member(i, interaction, mask) for i in range(len(self.members))]
        if len(outputs) == 1:
            return outputs[0]
        g = torch.stack([g for g, _ in outputs]).mean(0)
        forces = torch.stack([f for _, f in outputs if f is not None]).mean(0)
        return g, forces

    def encode_member(
        self, member: int, interaction: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One member's g and, with force heads, its head's force on each point."""
        encoder = self.members[member]
        if self.forces is not None and self.force_reads_grasps:
            g, f, summary, context = cast(GraspEncoder, encoder).encode_with_context(interaction, mask)
        else:
            (g, f, summary), context = encoder.encode(interaction, mask), None
        if self.forces is None:
            return g, None
        if self.force_reads_field:
            summary = torch.cat([summary, g / encoder.g_scale], dim=-1)
        return g, self.force_heads[member](f, summary, encoder.grasp_sizes(f), context)


class InteractionGraph(nn.Module):
    """What is exported: interaction [1, K, 6 or 10] → coefficients [1, M], or → displacement [1, N, 3] with
    the basis in the graph (`folded`: Φ itself, or the trunk over the node positions, which ONNX
    Runtime folds into a constant when it loads the graph)."""

    def __init__(
        self,
        net: ReducedNet,
        basis: torch.Tensor | None,
        positions: torch.Tensor,
        folded: bool,
        served: nn.Module | None = None,
    ) -> None:
        """`served`: the encoders in a form that computes `net.encode` faster for one request
        (grasp_served.py), used in its place."""
        super().__init__()
        self.net = net
        self.served = served
        self.folded = folded
        self.register_buffer("positions", positions.float())
        self.register_buffer("basis", basis.float() if basis is not None else torch.zeros(0))

    def forward(self, interaction: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        g, forces = self.net.encode(interaction) if self.served is None else self.served(interaction)
        out = g
        if self.folded:
            phi = self.net.trunk(self.positions) if self.net.trunk is not None else self.basis
            out = torch.einsum("nkm,bm->bnk", phi, g)
        return out if forces is None else (out, forces)


def weighted_basis(
    fields: torch.Tensor,
    volumes: torch.Tensor,
    modes: int,
    oversample: int = 64,
    power_iterations: int = 2,
    block: int = 2048,
) -> tuple[torch.Tensor, torch.Tensor]:
    """POD in L2(Ω) of fields [S, N, 3]: Φ [N, 3, M] (f64) with Φᵀ V Φ = I, and the singular values.

    The leading right singular vectors of the volume-weighted fields X [S, 3N], by a randomized range
    finder with power iterations (Halko, Martinsson and Tropp 2011, algorithms 4.4 and 5.1), in f64,
    reading X a block of `block` samples at a time. With 20,000 samples S is no longer ≪ 3N: the S × S
    Gram matrix and its eigendecomposition took 2·10¹³ flops (over 20 minutes on one core) and 10 GB,
    this takes a tenth of the work and holds no more than X's f32 fields. Exact (to rounding) when the
    sketch, M + `oversample` wide, is as wide as S.
    """
    s, n, _ = fields.shape
    sqrt_v = volumes.double().sqrt().repeat_interleave(3)
    flat = fields.reshape(s, -1)
    starts = range(0, s, block)

    def weighted(start: int) -> torch.Tensor:
        return flat[start : start + block].double() * sqrt_v

    def times(z: torch.Tensor) -> torch.Tensor:  # X z
        return torch.cat([weighted(i) @ z for i in starts])

    def transposed_times(y: torch.Tensor) -> torch.Tensor:  # Xᵀ y
        out = torch.zeros(3 * n, y.shape[1], dtype=torch.float64)
        for i in starts:
            out += weighted(i).T @ y[i : i + block]
        return out

    width = min(modes + oversample, s)
    sketch = torch.randn(s, width, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    q = torch.linalg.qr(transposed_times(sketch)).Q  # an orthonormal basis of (nearly) X's row space
    for _ in range(power_iterations):
        q = torch.linalg.qr(transposed_times(torch.linalg.qr(times(q)).Q)).Q
    # X ≈ X Q Qᵀ = U Σ (Q W)ᵀ from the small SVD X Q = U Σ Wᵀ.
    _, singular, wt = torch.linalg.svd(times(q), full_matrices=False)
    psi = q @ wt[:modes].T  # orthonormal columns [3N, M]
    return (psi / sqrt_v.unsqueeze(1)).reshape(n, 3, -1), singular[:modes]


def project(fields: torch.Tensor, basis: torch.Tensor, volumes: torch.Tensor, chunk: int = 512) -> dict[str, Any]:
    """Per sample: coefficients Φᵀ V r [S, M], the squared L2(Ω) norm of what Φ misses [S], and of r [S]."""
    v3 = volumes.double().repeat_interleave(3)
    phi = basis.reshape(-1, basis.shape[-1])
    g, missed, norm = [], [], []
    for start in range(0, fields.shape[0], chunk):
        r = fields[start : start + chunk].reshape(-1, phi.shape[0]).double()
        total = (r * r) @ v3
        coefficients = (r * v3) @ phi
        g.append(coefficients)
        norm.append(total)
        missed.append((total - (coefficients**2).sum(1)).clamp_min(0))
    return {"g": torch.cat(g).float(), "missed": torch.cat(missed), "norm": torch.cat(norm)}


def ceiling(projection: dict[str, Any], truth_norm: torch.Tensor, modes: list[int]) -> dict[int, float]:
    """DCM (volume form) of the best M-term approximation of each target, for each M in `modes`."""
    g = projection["g"].double()
    out = {}
    for m in modes:
        missed = projection["norm"] - (g[:, :m] ** 2).sum(1)
        out[m] = float(100.0 * (1.0 - (missed.clamp_min(0).sqrt() / truth_norm.sqrt()).mean()))
    return out
