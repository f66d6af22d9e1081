"""The served form of grasp encoders (`reduced.GraspEncoder`, one or an ensemble) and their force heads:
the same function of one request's interaction points, written as ONNX Runtime answers it fastest. Export
writes it; training never runs it. ONNX Runtime's cost per request is mostly per operator, so each rewrite
takes operators away; all are exact up to float rounding (export checks the graph against the trained
network):

* **Per grasp.** What a point's B_k and head_k see of the others (its grasp's mean embedding, the other
  grasps' mean embedding, the offset of their centroid) is its grasp's, the same for each of its points.
  So the head, and the context's share of B_k's first layer, are computed once per grasp (G, one or two)
  rather than once per point (K, about ten a grasp): Σ_k head_k / size_k = Σ_grasps head_grasp. That is
  half of a member's multiply-adds per point.
* **What all members share, once.** The point features, the grasps and what is known of them before
  the first layer are computed once, not once per member.
* **A force head rides on its member's products.** Its first layer reads what B_k's first layer reads
  (the point, its grasp's context, the set's summary), so its columns are appended to that layer's
  (one product for both, then split), and what A_k û_k + c_k needs of û_k and the grasp's size is
  appended to the columns that give B_k its û_k / size_k.

A request is one set (batch 1, no padding); the grasps are the points that move exactly alike, as the
encoder itself counts them (`reduced.same_grasp`).
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from .reduced import ForceHead, GraspEncoder, ReducedNet, same_grasp

# The statistics every member must share to be served as one (an ensemble's are set together).
SHARED_STATISTICS = ("x_mean", "x_std", "u_scale", "r_scale")
# What a force head's last layer gives each point: A_k row-major (9), then c_k (3).
FORCE_OUTPUTS = 12


class Part(nn.Module):
    """x @ W.T (+ bias) for W [out, in] some columns of Linear layers' weights, kept as a 2-D constant
    [in, out] (ONNX Runtime packs those once, at load, for its GEMM)."""

    weight: torch.Tensor
    bias: torch.Tensor | None

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor | None = None) -> None:
        super().__init__()
        self.register_buffer("weight", weight.T.detach().clone())
        self.register_buffer("bias", None if bias is None else bias.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight if self.bias is None else x @ self.weight + self.bias


class ServedMember(nn.Module):
    """One grasp encoder's layers, its first layers of `matrices` and `head` split by what they read; with
    a force head, the head's first layer appended to that of `matrices` (its outputs after `width`)."""

    def __init__(self, member: GraspEncoder, force: ForceHead | None, force_context: int) -> None:
        """`force_context`: how many values of each grasp's context the force head reads after a point's
        features (0: none); what it reads of the field after the summary is its own (`ServedForceHead`)."""
        super().__init__()
        features, context = member.point_features, member.context_features
        self.embed = member.embed
        matrices, head = cast(nn.Linear, member.matrices[0]), cast(nn.Linear, member.head[0])
        self.width = matrices.out_features
        self.force_width = 0 if force is None else force.first.out_features
        blocks = [matrices.weight[:, :features], matrices.weight[:, features : features + context]]
        blocks.append(matrices.weight[:, features + context :])
        bias: torch.Tensor = matrices.bias
        if force is not None:
            w = force.first.weight
            summary = blocks[2].shape[1]
            set_start = features + force_context
            reads = [w[:, :features], w[:, features:set_start] if force_context else w.new_zeros(len(w), context)]
            reads.append(w[:, set_start : set_start + summary])
            blocks = [torch.cat(pair) for pair in zip(blocks, reads, strict=True)]
            bias = torch.cat([bias, force.first.bias])
        self.matrices_points, self.matrices_context = Part(blocks[0]), Part(blocks[1])
        self.matrices_summary = Part(blocks[2], bias)
        self.matrices_rest = member.matrices[1:]
        self.head_context = Part(head.weight[:, :context])
        self.head_summary = Part(head.weight[:, context:], head.bias)
        self.head_rest = member.head[1:]


class ServedGraspEncoders(nn.Module):
    """interaction [1, K, 6] (or [1, K, 10] with surface geometry, [1, K, 11] with depth too) → the
    members' g and, with force heads, what each head's first layer gives and what its A_k û_k + c_k
    reads of the point."""

    shift: torch.Tensor
    scale: torch.Tensor
    x_std: torch.Tensor
    r_scale: torch.Tensor
    g_scale: torch.Tensor
    tile: torch.Tensor
    tile_bias: torch.Tensor | None
    triples: torch.Tensor

    def __init__(self, members: list[GraspEncoder], heads: list[ForceHead], force_context: int = 0) -> None:
        """`heads`: none, or one force head a member (see `ServedMember` for the rest)."""
        super().__init__()
        first = members[0]
        for name in SHARED_STATISTICS:
            if any(not torch.equal(m.get_buffer(name), first.get_buffer(name)) for m in members):
                raise ValueError(f"the members' {name} differ: they cannot be served as one")
        if any(
            m.geometry != first.geometry
            or m.depth != first.depth
            or (m.geometry and not torch.equal(m.v_scale, first.v_scale))
            or (m.depth and not torch.equal(m.d_scale, first.d_scale))
            for m in members
        ):
            raise ValueError("the members read different inputs: they cannot be served as one")
        modes = first.modes
        shift, scale = first.input_shift_scale()
        self.register_buffer("shift", shift.detach().clone())
        self.register_buffer("scale", scale.detach().clone())
        self.register_buffer("x_std", first.x_std.clone())
        self.register_buffer("r_scale", first.r_scale.clone())
        self.register_buffer("g_scale", torch.stack([m.g_scale for m in members]).clone())  # [E, M]
        # The normalized input's û (columns 3–5) repeated per mode (B_k is mode-major) and, with force heads,
        # three times more then three ones (A_k row-major, then c_k): over the grasp's size, [K, 3M (+ 12)].
        self.modes = modes
        repeats = modes + (3 if heads else 0)
        tile = torch.zeros(len(shift), 3 * repeats + (3 if heads else 0))
        tile[3:6, : 3 * repeats] = torch.eye(3).repeat(1, repeats)
        self.register_buffer("tile", tile)
        self.register_buffer("tile_bias", torch.cat([torch.zeros(3 * repeats), torch.ones(3)]) if heads else None)
        # The sum of each mode's three products: [3M, M].
        self.register_buffer("triples", torch.eye(modes).repeat_interleave(3, dim=0))
        members_heads = heads if heads else [None] * len(members)
        self.members = nn.ModuleList(
            ServedMember(m, h, force_context) for m, h in zip(members, members_heads, strict=True)
        )

    def forward(self, interaction: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor | None]:
        """Each member's g [E, M] unscaled (g / g_scale), as `GraspEncoder.encode` gives it; with force
        heads, what each head's first layer gives each point [K, H] (before the head's own input of the
        field) and [û û û 1 1 1] / size [K, 12], else an empty list and None."""
        x = interaction[0, :, :3]
        f = (interaction[0] - self.shift) / self.scale
        alike = same_grasp(f[None])[0]
        size = alike.sum(-1, keepdim=True)
        centroid = (alike @ x) / size
        features = torch.cat([f, (x - centroid) / self.r_scale, size.log()], dim=-1)
        # One row per grasp, its first point's: no earlier point moves as it does.
        earlier = torch.tril(torch.ones_like(alike), diagonal=-1)
        rows = torch.nonzero((alike * earlier).sum(-1) == 0)[:, 0]
        grasp = alike[rows]  # [G, K]
        member_of = alike[:, rows]  # [K, G]
        others = 1.0 - grasp
        others_count = others.sum(-1, keepdim=True)
        count = others_count.clamp_min(1.0)
        apart = ((others @ x) / count - centroid[rows]) / self.x_std * (others_count > 0).to(x.dtype)
        shares, force_shares = (f @ self.tile) / size, None
        if self.tile_bias is not None:
            shares, force_shares = ((f @ self.tile + self.tile_bias) / size).split(
                [3 * self.modes, FORCE_OUTPUTS], dim=-1
            )
        gs, force_firsts = [], []
        for member in self.members:
            assert isinstance(member, ServedMember)
            e = member.embed(features)  # [K, W]
            summary = torch.cat([e.mean(0), e.amax(0)])[None]  # [1, 2W]
            context = torch.cat([(grasp @ e) / size[rows], (others @ e) / count, apart], dim=-1)  # [G, 2W + 3]
            head = member.head_rest(member.head_context(context) + member.head_summary(summary))  # [G, M]
            first = (
                member.matrices_points(features)
                + member_of @ member.matrices_context(context)
                + member.matrices_summary(summary)
            )
            if member.force_width:
                first, force_first = first.split([member.width, member.force_width], dim=-1)
                force_firsts.append(force_first)
            b = member.matrices_rest(first)  # [K, 3M]
            gs.append((b * shares).sum(0, keepdim=True) @ self.triples + head.sum(0, keepdim=True))
        return torch.cat(gs), force_firsts, force_shares


class ServedForceHead(nn.Module):
    """A force head (`reduced.ForceHead`) after its first layer (computed with its member's, see
    `ServedMember`) but for the columns that read the field: [K, H] and the member's g [1, M] → its last
    layer [K, 12], A_k row-major then c_k, f_scale folded in."""

    last_weight: torch.Tensor
    last_bias: torch.Tensor

    def __init__(self, head: ForceHead, coefficients: int = 0) -> None:
        """`coefficients`: how many of the field's coefficients the head reads last (0: none)."""
        super().__init__()
        self.field = Part(head.first.weight[:, -coefficients:]) if coefficients else None
        self.hidden = head.rest[:-1]
        last = cast(nn.Linear, head.rest[-1])
        self.register_buffer("last_weight", (last.weight.T * head.f_scale).detach().clone())  # [H, 12]
        self.register_buffer("last_bias", (last.bias * head.f_scale).detach().clone())

    def forward(self, first: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        if self.field is not None:
            first = first + self.field(g)
        return self.hidden(first) @ self.last_weight + self.last_bias


class ServedGraspNet(nn.Module):
    """A grasp-encoder network as served: interaction [1, K, 6 or 10] → g [1, M] and, with force heads, the
    force on each point [1, K, 3] (the members' means, as `ReducedNet.encode` gives them)."""

    sums: torch.Tensor | None

    def __init__(self, net: ReducedNet) -> None:
        super().__init__()
        members = served_members(net)
        context = members[0].context_features if net.force_reads_grasps else 0
        self.encoders = ServedGraspEncoders(members, net.force_heads, context)
        coefficients = members[0].modes if net.force_reads_field else 0
        self.heads = nn.ModuleList(ServedForceHead(head, coefficients) for head in net.force_heads)
        # The sum of each row of A (as ForceHead takes A û), then c as it is: [1, 12, 3], so that the
        # product is the output's [1, K, 3] itself.
        heads = net.force_heads
        self.register_buffer("sums", torch.cat([heads[0].row_sums, torch.eye(3)])[None] if heads else None)

    def forward(self, interaction: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        g, force_firsts, force_shares = self.encoders(interaction)
        field = (g * self.encoders.g_scale).mean(0, keepdim=True)
        if force_shares is None or self.sums is None:
            return field, None
        outs = [head(first, g[i : i + 1]) for i, (head, first) in enumerate(zip(self.heads, force_firsts, strict=True))]
        # The members' mean before the product, which is linear in it: one head's output as it is.
        out = outs[0] if len(outs) == 1 else torch.stack(outs).mean(0)
        return field, (out * force_shares) @ self.sums


def served_members(net: ReducedNet) -> list[GraspEncoder]:
    if not all(isinstance(m, GraspEncoder) for m in net.members):
        raise ValueError("only grasp encoders have a served form")
    return cast(list[GraspEncoder], net.members)


def served_form(net: ReducedNet) -> ServedGraspNet | None:
    """`net` in the form that answers one request faster, if it has one (grasp encoders do)."""
    return ServedGraspNet(net).eval() if all(isinstance(m, GraspEncoder) for m in net.members) else None
