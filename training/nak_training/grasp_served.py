"""The served form of grasp encoders (`reduced.GraspEncoder`, one or an ensemble): the same function of one
request's interaction points, written as ONNX Runtime answers it fastest. Export writes it; training never
runs it. Two rewrites, both exact up to float rounding (export checks the graph against the trained
network):

* **Per grasp.** What a point's B_k and head_k see of the others (its grasp's mean embedding, the other
  grasps' mean embedding, the offset of their centroid) is its grasp's, the same for each of its points.
  So the head, and the context's share of B_k's first layer, are computed once per grasp (G, one or two)
  rather than once per point (K, about ten a grasp): Σ_k head_k / size_k = Σ_grasps head_grasp. That is
  half of a member's multiply-adds per point.
* **What all members share, once.** The point features, the grasps and what is known of them before
  the first layer are computed once, not once per member.

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


class Part(nn.Module):
    """The columns `columns` of a Linear layer's input, as a 2-D constant (ONNX Runtime packs those once,
    at load, for its GEMM), with or without the layer's bias."""

    weight: torch.Tensor
    bias: torch.Tensor | None

    def __init__(self, layer: nn.Linear, columns: slice = slice(None), bias: bool = True) -> None:
        super().__init__()
        self.register_buffer("weight", layer.weight[:, columns].T.detach().clone())
        self.register_buffer("bias", layer.bias.detach().clone() if bias else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight if self.bias is None else x @ self.weight + self.bias


class ServedMember(nn.Module):
    """One grasp encoder's layers, its first layers of `matrices` and `head` split by what they read."""

    def __init__(self, member: GraspEncoder) -> None:
        super().__init__()
        features = member.point_features
        context = member.context_features
        self.embed = member.embed
        matrices, head = cast(nn.Linear, member.matrices[0]), cast(nn.Linear, member.head[0])
        self.matrices_points = Part(matrices, slice(0, features), bias=False)
        self.matrices_context = Part(matrices, slice(features, features + context), bias=False)
        self.matrices_summary = Part(matrices, slice(features + context, None))
        self.matrices_rest = member.matrices[1:]
        self.head_context = Part(head, slice(0, context), bias=False)
        self.head_summary = Part(head, slice(context, None))
        self.head_rest = member.head[1:]


class ServedGraspEncoders(nn.Module):
    """interaction [1, K, 6] (or [1, K, 10] with surface geometry) → the members' g, the point features and
    each member's summary."""

    shift: torch.Tensor
    scale: torch.Tensor
    x_std: torch.Tensor
    r_scale: torch.Tensor
    g_scale: torch.Tensor
    tile: torch.Tensor
    triples: torch.Tensor

    def __init__(self, members: list[GraspEncoder]) -> None:
        super().__init__()
        first = members[0]
        for name in SHARED_STATISTICS:
            if any(not torch.equal(m.get_buffer(name), first.get_buffer(name)) for m in members):
                raise ValueError(f"the members' {name} differ: they cannot be served as one")
        if any(
            m.geometry != first.geometry or (m.geometry and not torch.equal(m.v_scale, first.v_scale)) for m in members
        ):
            raise ValueError("the members read different inputs: they cannot be served as one")
        modes = first.modes
        shift, scale = first.input_shift_scale()
        self.register_buffer("shift", shift.detach().clone())
        self.register_buffer("scale", scale.detach().clone())
        self.register_buffer("x_std", first.x_std.clone())
        self.register_buffer("r_scale", first.r_scale.clone())
        self.register_buffer("g_scale", torch.stack([m.g_scale for m in members]).clone())  # [E, M]
        # û repeated per mode ([3, 3M]) and the sum of each mode's three products ([3M, M]): B_k is mode-major.
        self.register_buffer("tile", torch.eye(3).repeat(1, modes))
        self.register_buffer("triples", torch.eye(modes).repeat_interleave(3, dim=0))
        self.members = nn.ModuleList(ServedMember(m) for m in members)

    def forward(
        self, interaction: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
        """Each member's g [E, M] unscaled (g / g_scale), the point features [K, F], each point's grasp
        size [K, 1] and each member's summary [1, 2W], as `GraspEncoder.encode` gives them per member;
        then each member's context per grasp [G, 2W + 3] and which grasp each point is in [K, G]."""
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
        shares = (f[:, 3:6] @ self.tile) / size  # [K, 3M]: û_k per mode over its grasp's size
        gs, summaries, contexts = [], [], []
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
            b = member.matrices_rest(first)  # [K, 3M]
            gs.append((b * shares).sum(0, keepdim=True) @ self.triples + head.sum(0, keepdim=True))
            summaries.append(summary)
            contexts.append(context)
        return torch.cat(gs), features, size, summaries, contexts, member_of


class ServedForceHead(nn.Module):
    """A force head (`reduced.ForceHead`) over one request's points as 2-D tensors, its first layer split
    into the points' part and the set's: [K, F] points, [K, 1] grasp sizes, [1, S] set → [K, 3].

    Its last layer gives A_k row-major and c_k together; A_k û_k + c_k is taken as one product,
    (out ⊙ [û û û 1 1 1]) @ [row sums; I₃], with f_scale folded into that layer: ONNX Runtime's cost per
    request is mostly per operator, and this takes four fewer than slicing A and c apart."""

    pick: torch.Tensor
    ones: torch.Tensor
    sums: torch.Tensor
    last_weight: torch.Tensor
    last_bias: torch.Tensor

    def __init__(self, head: ForceHead, features: int, context: int = 0) -> None:
        """`features`: how many point features the head's encoder gives (the first layer's first columns);
        `context`: how many values of each grasp's context it reads after them (0: none), computed once
        per grasp."""
        super().__init__()
        self.points = Part(head.first, slice(0, features), bias=False)
        self.context = Part(head.first, slice(features, features + context), bias=False) if context else None
        self.set = Part(head.first, slice(features + context, None))
        self.hidden = head.rest[:-1]
        last = cast(nn.Linear, head.rest[-1])
        self.register_buffer("last_weight", (last.weight.T * head.f_scale).detach().clone())  # [H, 12]
        self.register_buffer("last_bias", (last.bias * head.f_scale).detach().clone())
        # The point's û (its features' columns 3–5) three times, then three zeros to which `ones` adds 1.
        pick = torch.zeros(features, 12)
        pick[3:6, :9] = torch.eye(3).repeat(1, 3)
        self.register_buffer("pick", pick)
        self.register_buffer("ones", torch.cat([torch.zeros(9), torch.ones(3)]))
        # The sum of each row of A (as ForceHead takes A û), then c as it is: [12, 3].
        self.register_buffer("sums", torch.cat([head.row_sums, torch.eye(3)]))

    def forward(
        self,
        points: torch.Tensor,
        seen: torch.Tensor,
        size: torch.Tensor,
        context: torch.Tensor | None = None,
        member_of: torch.Tensor | None = None,
    ) -> torch.Tensor:
        first = self.points(points) + self.set(seen)
        if self.context is not None:
            if context is None or member_of is None:
                raise ValueError("this force head reads the grasps: give it their context and each point's grasp")
            first = first + member_of @ self.context(context)
        out = self.hidden(first) @ self.last_weight + self.last_bias  # [K, 12]: A row-major, then c
        return ((out * (points @ self.pick + self.ones)) @ self.sums) / size


class ServedGraspNet(nn.Module):
    """A grasp-encoder network as served: interaction [1, K, 6 or 10] → g [1, M] and, with force heads, the
    force on each point [1, K, 3] (the members' means, as `ReducedNet.encode` gives them)."""

    def __init__(self, net: ReducedNet) -> None:
        super().__init__()
        members = served_members(net)
        self.encoders = ServedGraspEncoders(members)
        member = members[0]
        context = member.context_features if net.force_reads_grasps else 0
        self.heads = nn.ModuleList(ServedForceHead(head, member.point_features, context) for head in net.force_heads)
        self.reads_field = net.force_reads_field

    def forward(self, interaction: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        g, features, size, summaries, contexts, member_of = self.encoders(interaction)
        field = (g * self.encoders.g_scale).mean(0, keepdim=True)
        if len(self.heads) == 0:
            return field, None
        forces = [
            head(
                features,
                torch.cat([summary, g[i : i + 1]], dim=-1) if self.reads_field else summary,
                size,
                contexts[i],
                member_of,
            )
            for i, (head, summary) in enumerate(zip(self.heads, summaries, strict=True))
        ]
        # One head's forces as they are: a mean of one costs ONNX Runtime three operators a request.
        return field, (forces[0] if len(forces) == 1 else torch.stack(forces).mean(0))[None]


def served_members(net: ReducedNet) -> list[GraspEncoder]:
    if not all(isinstance(m, GraspEncoder) for m in net.members):
        raise ValueError("only grasp encoders have a served form")
    return cast(list[GraspEncoder], net.members)


def served_form(net: ReducedNet) -> ServedGraspNet | None:
    """`net` in the form that answers one request faster, if it has one (grasp encoders do)."""
    return ServedGraspNet(net).eval() if all(isinstance(m, GraspEncoder) for m in net.members) else None
