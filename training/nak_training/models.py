"""Networks over the mesh's nodes: PointNet, a DeepSet-style U-Net and an induced set attention
network (ISAB), which see the nodes as a set, and a mesh graph network (GNN) over the tetrahedral
edges; each in the paper's widths (`paper`) and a narrow one for two CPU cores (`cpu`).

Every network is `decode(encode(f).local, pool(encode(f).pool_in))`: a per-node encoder, a pooling
over all nodes, and a per-node decoder that reads its node's encoding and the pooled summary. When the
encoder looks at one node at a time (`row_wise`), training can exploit that a node nobody grasps has
the same input `[x, 0, 0]` in every sample (see `forward_split`). Inputs are raw SI features
`[x (3), u_s (3), a (1)]` (docs/design.md §7); normalization is part of the module and of the exported graph.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from .dataset import Mesh

CHANNELS = 7
SIZES = ("paper", "cpu")


class Normalizer(nn.Module):
    """Train-split statistics: z-scored positions, displacements scaled (zero stays zero), outputs
    de-normalized per channel."""

    x_mean: torch.Tensor
    x_std: torch.Tensor
    u_scale: torch.Tensor
    out_mean: torch.Tensor
    out_std: torch.Tensor

    def __init__(self) -> None:
        super().__init__()
        for name, value in [("x_mean", 0.0), ("x_std", 1.0), ("u_scale", 1.0), ("out_mean", 0.0), ("out_std", 1.0)]:
            self.register_buffer(name, torch.full((3,), value))

    def set(self, **stats: torch.Tensor) -> None:
        for name, value in stats.items():
            buffer = self.get_buffer(name)
            buffer.copy_(value.to(torch.float32))

    def inputs(self, f: torch.Tensor) -> torch.Tensor:
        x = (f[..., 0:3] - self.x_mean) / self.x_std
        return torch.cat([x, f[..., 3:6] / self.u_scale, f[..., 6:7]], dim=-1)

    def outputs(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.out_std + self.out_mean


def mlp(widths: list[int], last_activation: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if last_activation or i < len(widths) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


@dataclass
class Encoded:
    local: list[torch.Tensor]
    pool_in: torch.Tensor | None
    penalty: torch.Tensor = field(default_factory=lambda: torch.zeros(()))


class SetNet(nn.Module):
    """Shared plumbing: full forward for serving, split forward for training."""

    row_wise = True

    def __init__(self) -> None:
        super().__init__()
        self.normalizer = Normalizer()

    def encode(self, f: torch.Tensor, pooled: bool) -> Encoded:
        raise NotImplementedError

    def pool(self, pool_in: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def decode(self, local: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward_normalized(self, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalized output and auxiliary penalty for normalized features [B, N, 7] of whole meshes."""
        encoded = self.encode(f, pooled=True)
        assert encoded.pool_in is not None
        return self.decode(encoded.local, self.pool(encoded.pool_in)), encoded.penalty

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Raw features [B, N, 7] → displacement [B, N, 3] (metres): what the ONNX graph computes."""
        out, _ = self.forward_normalized(self.normalizer.inputs(features))
        return self.normalizer.outputs(out)

    def pool_split(self, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
        """`pool` of every node at rest [N, d] with each sample's grasped rows replaced by `moved`
        [B, K, d]. This default builds the [B, N, d] input; subclasses avoid that."""
        b, d = moved.shape[0], at_rest.shape[-1]
        pool_in = at_rest.expand(b, -1, -1).scatter(1, grasped.ids.unsqueeze(-1).expand(-1, -1, d), moved)
        return self.pool(pool_in)

    def forward_split(
        self, rest: torch.Tensor, grasped_rows: torch.Tensor, grasped: Grasped, query: torch.Tensor
    ) -> torch.Tensor:
        """The same normalized output at `query` rows, computing the encoder over the nodes at rest
        once for the whole batch.

        rest [N, 7]: every node's normalized features with nothing grasped; grasped_rows [B, K, 7]:
        the grasped rows of each sample; query [B, Q, 7]: the rows to decode. Exact for row-wise
        encoders: the pooled summary sees all N nodes.
        """
        at_rest = self.encode(rest.unsqueeze(0), pooled=True).pool_in
        moved = self.encode(grasped_rows, pooled=True).pool_in
        assert at_rest is not None and moved is not None
        summary = self.pool_split(at_rest[0], moved, grasped)
        return self.decode(self.encode(query, pooled=False).local, summary)


@dataclass(frozen=True)
class Grasped:
    """Which rows of each sample are grasped: ids [B, K] (distinct within a sample; padding repeats
    a real id) and mask [B, K] (False on padding)."""

    ids: torch.Tensor
    mask: torch.Tensor


def max_replacing(at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
    """max over nodes of the rest rows with the grasped ones replaced: [B, d], without a [B, N, d]
    tensor. The largest rest value not grasped is among each channel's K + 1 largest."""
    k = grasped.ids.shape[1]
    top = at_rest.topk(min(k + 1, at_rest.shape[0]), dim=0)  # [k+1, d]
    taken = (top.indices.unsqueeze(-1).unsqueeze(0) == grasped.ids[:, None, None, :]).any(-1)  # [B, k+1, d]
    rest_max = top.values.unsqueeze(0).masked_fill(taken, float("-inf")).amax(1)
    return torch.maximum(rest_max, moved.amax(1))


def mean_replacing(at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
    """mean over nodes of the rest rows with the grasped ones replaced: [B, d]."""
    weight = grasped.mask.unsqueeze(-1).to(moved.dtype)
    change = ((moved - at_rest[grasped.ids]) * weight).sum(1)
    return (at_rest.sum(0) + change) / at_rest.shape[0]


def broadcast(summary: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return summary.unsqueeze(1).expand(-1, like.shape[1], -1)


class FeatureTransform(nn.Module):
    """PointNet's learned d×d feature alignment (STN), identity at initialization."""

    def __init__(self, d: int) -> None:
        super().__init__()
        self.d = d
        self.encoder = mlp([d, 64, 128, 1024])
        self.head = nn.Sequential(mlp([1024, 512, 256]), nn.Linear(256, d * d))
        last = self.head[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.encoder(h).amax(dim=1)
        eye = torch.eye(self.d, dtype=h.dtype, device=h.device)
        transform = self.head(g).reshape(-1, self.d, self.d) + eye
        penalty = ((transform @ transform.transpose(1, 2) - eye) ** 2).sum(dim=(1, 2)).mean()
        return h @ transform, penalty


class PointNet(SetNet):
    """Per-node MLP, global max-pool, and a head over [node feature, global feature] (docs/design.md §10)."""

    def __init__(self, size: str) -> None:
        super().__init__()
        if size == "paper":
            local, glob, head, with_stn = [CHANNELS, 64], [64, 128, 1024], [1088, 512, 256], True
        else:
            local, glob, head, with_stn = [CHANNELS, 32, 64], [64, 128, 256], [320, 128, 64], False
        self.local = mlp(local)
        self.stn = FeatureTransform(local[-1]) if with_stn else None
        self.row_wise = self.stn is None
        self.glob = mlp(glob)
        self.head = nn.Sequential(mlp(head), nn.Linear(head[-1], 3))

    def encode(self, f: torch.Tensor, pooled: bool) -> Encoded:
        h = self.local(f)
        penalty = torch.zeros((), device=f.device)
        if self.stn is not None:
            h, penalty = self.stn(h)
        return Encoded([h], self.glob(h) if pooled else None, penalty)

    def pool(self, pool_in: torch.Tensor) -> torch.Tensor:
        return pool_in.amax(dim=1)

    def pool_split(self, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
        return max_replacing(at_rest, moved, grasped)

    def decode(self, local: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
        h = local[0]
        return self.head(torch.cat([h, broadcast(summary, h)], dim=-1))


class DeepSetUNet(SetNet):
    """The paper's "U-Net converted into a DeepSet-style model": shared per-node MLP levels down to a
    bottleneck pooled over the set (mean and max), then levels back up with skip connections."""

    def __init__(self, size: str) -> None:
        super().__init__()
        widths = [64, 128, 256, 512] if size == "paper" else [32, 64, 128]
        self.down = nn.ModuleList(mlp([a, b]) for a, b in zip([CHANNELS, *widths[:-1]], widths, strict=True))
        up_in = [3 * widths[-1]] + [2 * w for w in reversed(widths[:-1])]
        up_out = list(reversed(widths[:-1])) + [widths[0]]
        self.up = nn.ModuleList(mlp([a, b]) for a, b in zip(up_in, up_out, strict=True))
        self.out = nn.Linear(widths[0], 3)

    def encode(self, f: torch.Tensor, pooled: bool) -> Encoded:
        levels = []
        h = f
        for layer in self.down:
            h = layer(h)
            levels.append(h)
        return Encoded(levels, levels[-1] if pooled else None)

    def pool(self, pool_in: torch.Tensor) -> torch.Tensor:
        return torch.cat([pool_in.mean(dim=1), pool_in.amax(dim=1)], dim=-1)

    def pool_split(self, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
        return torch.cat([mean_replacing(at_rest, moved, grasped), max_replacing(at_rest, moved, grasped)], dim=-1)

    def decode(self, local: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
        h = self.up[0](torch.cat([local[-1], broadcast(summary, local[-1])], dim=-1))
        for layer, skip in zip(self.up[1:], reversed(local[:-1]), strict=True):
            h = layer(torch.cat([h, skip], dim=-1))
        return self.out(h)


class Attention(nn.Module):
    """Multi-head attention written out in matmuls (exports to plain ONNX ops)."""

    def __init__(self, d: int, heads: int) -> None:
        super().__init__()
        self.heads, self.dk = heads, d // heads
        self.q, self.k, self.v, self.o = (nn.Linear(d, d) for _ in range(4))

    def forward(self, queries: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        def split(t: torch.Tensor) -> torch.Tensor:
            return t.reshape(t.shape[0], t.shape[1], self.heads, self.dk).transpose(1, 2)

        q, k, v = split(self.q(queries)), split(self.k(keys)), split(self.v(keys))
        weights = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.dk), dim=-1)
        out = (weights @ v).transpose(1, 2).reshape(queries.shape)
        return self.o(out)

    def forward_replacing(
        self, queries: torch.Tensor, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped
    ) -> torch.Tensor:
        """`forward(queries [1, m, d], keys)` for keys = the rest rows [N, d] with each sample's grasped
        rows replaced by `moved` [B, K, d], as sums: softmax-weighted sums over all rest rows (once
        per batch), minus the grasped rows' rest terms, plus their moved terms."""
        b, kk = grasped.ids.shape
        h, dk = self.heads, self.dk
        q = self.q(queries).reshape(1, -1, h, dk).transpose(1, 2)  # [1, h, m, dk]
        k_rest = self.k(at_rest).reshape(-1, h, dk).transpose(0, 1)  # [h, N, dk]
        v_rest = self.v(at_rest).reshape(-1, h, dk).transpose(0, 1)
        k_moved = self.k(moved).reshape(b, kk, h, dk).transpose(1, 2)  # [B, h, K, dk]
        v_moved = self.v(moved).reshape(b, kk, h, dk).transpose(1, 2)
        scale = 1.0 / math.sqrt(dk)
        logits_rest = (q[0] @ k_rest.transpose(-1, -2)) * scale  # [h, m, N]
        logits_moved = (q @ k_moved.transpose(-1, -2)) * scale  # [B, h, m, K]
        logits_taken = logits_rest[:, :, grasped.ids].permute(2, 0, 1, 3)  # [B, h, m, K]
        v_taken = v_rest[:, grasped.ids].permute(1, 0, 2, 3)  # [B, h, K, dk]
        real = grasped.mask[:, None, None, :]
        shift_rest = logits_rest.amax(-1, keepdim=True)  # [h, m, 1]
        shift = torch.maximum(shift_rest, logits_moved.masked_fill(~real, float("-inf")).amax(-1, keepdim=True))
        e_rest = torch.exp(logits_rest - shift_rest)
        rescale = torch.exp(shift_rest - shift)  # [B, h, m, 1]
        e_taken = torch.exp(logits_taken - shift) * real
        e_moved = torch.exp(logits_moved - shift) * real
        numerator = (e_rest @ v_rest) * rescale - e_taken @ v_taken + e_moved @ v_moved
        denominator = (
            e_rest.sum(-1, keepdim=True) * rescale - e_taken.sum(-1, keepdim=True) + e_moved.sum(-1, keepdim=True)
        )
        out = (numerator / denominator).transpose(1, 2).reshape(b, queries.shape[1], h * dk)
        return self.o(out)


class MAB(nn.Module):
    """Set Transformer's multihead attention block: H = LN(Q + Att(Q, K)), out = LN(H + FF(H))."""

    def __init__(self, d: int, heads: int) -> None:
        super().__init__()
        self.attention = Attention(d, heads)
        self.ff = mlp([d, d, d], last_activation=False)
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)

    def forward(self, queries: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
        return self.finish(queries, self.attention(queries, keys))

    def finish(self, queries: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        h = self.norm1(queries + attended)
        return self.norm2(h + self.ff(h))


class ISAB(nn.Module):
    """Induced set attention: m learned points attend to the set, then every element attends to them
    (linear in N; full self-attention over 10k nodes is quadratic)."""

    def __init__(self, d: int, heads: int, inducing: int) -> None:
        super().__init__()
        self.inducing = nn.Parameter(torch.randn(1, inducing, d) / math.sqrt(d))
        self.gather, self.spread = MAB(d, heads), MAB(d, heads)

    def summarize(self, x: torch.Tensor) -> torch.Tensor:
        return self.gather(self.inducing.expand(x.shape[0], -1, -1), x)

    def summarize_replacing(self, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
        attended = self.gather.attention.forward_replacing(self.inducing, at_rest, moved, grasped)
        return self.gather.finish(self.inducing.expand(moved.shape[0], -1, -1), attended)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.spread(x, self.summarize(x))


class SetAttentionNet(SetNet):
    """The paper's SAB model (two attention blocks and an MLP head) with induced attention blocks.
    The `cpu` size has one block, so its encoder is row-wise."""

    def __init__(self, size: str) -> None:
        super().__init__()
        d, heads, inducing, blocks = (128, 4, 32, 2) if size == "paper" else (64, 4, 16, 1)
        self.embed = mlp([CHANNELS, d, d])
        self.blocks = nn.ModuleList(ISAB(d, heads, inducing) for _ in range(blocks))
        self.row_wise = blocks == 1
        self.head = nn.Sequential(mlp([d, d]), nn.Linear(d, 3))

    def encode(self, f: torch.Tensor, pooled: bool) -> Encoded:
        x = self.embed(f)
        for block in self.blocks[:-1]:
            x = block(x)
        return Encoded([x], x if pooled else None)

    def pool(self, pool_in: torch.Tensor) -> torch.Tensor:
        last = self.blocks[-1]
        assert isinstance(last, ISAB)
        return last.summarize(pool_in).flatten(1)

    def pool_split(self, at_rest: torch.Tensor, moved: torch.Tensor, grasped: Grasped) -> torch.Tensor:
        last = self.blocks[-1]
        assert isinstance(last, ISAB)
        return last.summarize_replacing(at_rest, moved, grasped).flatten(1)

    def decode(self, local: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
        last = self.blocks[-1]
        assert isinstance(last, ISAB)
        x = local[0]
        return self.head(last.spread(x, summary.reshape(x.shape[0], -1, x.shape[-1])))


class MeshGNN(SetNet):
    """A mesh graph network in the manner of PhysGNN: message passing over the tetrahedral edges
    (each layer adds to every node an MLP of its state and the mean of its neighbours'), then a mean
    and max pooling over all nodes that every node's head reads beside its own state — a node many
    edges from a grasper still learns where and how far the organ was pulled (against the
    over-smoothing of deep message passing). The edges are a buffer: constants in the exported graph,
    so its input is the model contract's `features` like every other network's."""

    row_wise = False

    def __init__(self, size: str, edges: torch.Tensor, node_count: int) -> None:
        super().__init__()
        d, layers = (128, 6) if size == "paper" else (32, 4)
        target, source = torch.cat([edges, edges.flip(0)], dim=1)
        degree = torch.bincount(target, minlength=node_count)
        inverse_degree = 1.0 / degree.clamp_min(1).float()
        # Row i lists i's neighbours, padded with the index N of an appended zero row: the exported graph
        # gathers and sums rows (ONNX Runtime's scatter-add is 4.5× slower here).
        order = torch.argsort(target, stable=True)
        slot = torch.arange(len(target)) - (torch.cumsum(degree, 0) - degree)[target[order]]
        table = torch.full((node_count, int(degree.max())), node_count, dtype=torch.long)
        table[target[order], slot] = source[order]
        # Made from the mesh whenever the network is built, so not part of its weights.
        self.register_buffer("neighbours", table, persistent=False)
        self.register_buffer("inverse_degree", inverse_degree.unsqueeze(-1), persistent=False)
        # Training multiplies by the mean-over-neighbours matrix instead, 15× faster on CPU than the
        # gather and ONNX has no sparse product; both give the same means (tested).
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Sparse CSR tensor support is in beta state")
            self.mean_matrix = torch.sparse_coo_tensor(
                torch.stack([target, source]), inverse_degree[target], (node_count, node_count)
            ).to_sparse_csr()
        self.embed = mlp([CHANNELS, d, d])
        self.layers = nn.ModuleList(mlp([2 * d, d, d]) for _ in range(layers))
        self.head = nn.Sequential(mlp([3 * d, d, d]), nn.Linear(d, 3))

    def neighbour_mean(self, h: torch.Tensor) -> torch.Tensor:
        """Each node's mean over its mesh neighbours, h [B, N, d] → [B, N, d]."""
        b, n, d = h.shape
        if not torch.onnx.is_in_onnx_export():
            flat = h.permute(1, 0, 2).reshape(n, b * d)
            return (self.mean_matrix @ flat).reshape(n, b, d).permute(1, 0, 2)
        table = self.get_buffer("neighbours")
        padded = torch.cat([h, torch.zeros_like(h[:, :1])], dim=1)
        rows = padded[:, table.reshape(-1)].reshape(b, n, table.shape[1], d)
        return rows.sum(2) * self.get_buffer("inverse_degree")

    def encode(self, f: torch.Tensor, pooled: bool) -> Encoded:
        h = self.embed(f)
        for layer in self.layers:
            h = h + layer(torch.cat([h, self.neighbour_mean(h)], dim=-1))
        return Encoded([h], h if pooled else None)

    def pool(self, pool_in: torch.Tensor) -> torch.Tensor:
        return torch.cat([pool_in.mean(dim=1), pool_in.amax(dim=1)], dim=-1)

    def decode(self, local: list[torch.Tensor], summary: torch.Tensor) -> torch.Tensor:
        h = local[0]
        return self.head(torch.cat([h, broadcast(summary, h)], dim=-1))


SET_ARCHITECTURES: dict[str, Callable[[str], SetNet]] = {
    "pointnet": PointNet,
    "deepset": DeepSetUNet,
    "isab": SetAttentionNet,
}
# Networks over the mesh's graph: built with its edges.
GRAPH_ARCHITECTURES = ("gnn",)
ARCHITECTURES = (*SET_ARCHITECTURES, *GRAPH_ARCHITECTURES)


def build(architecture: str, size: str, mesh: Mesh | None = None) -> SetNet:
    """The network; a graph network needs the `mesh` it runs on."""
    if architecture in GRAPH_ARCHITECTURES:
        if mesh is None:
            raise ValueError(f"{architecture} is built over a mesh's edges: pass the mesh")
        return MeshGNN(size, mesh.edges(), mesh.node_count)
    return SET_ARCHITECTURES[architecture](size)


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
