"""The regularized Kelvinlet prior exactly as nak serves it (docs/design.md §3; src/prior), batched in torch.

`Γ(r) = s · [(a/r_ε + b/r_ε³) I + r rᵀ/r_ε³]`, s = ε/(5−6ν), a = 3−4ν, b = 2(1−ν)ε², so Γ(0) = I.
Coefficients solve `(ΓᵀΓ + λI) k = Γᵀu` (a single point takes k = u, as nak does); the field is
`u(x) = Σ_j Γ(x − x_j) k_j`. Everything runs in f64: nak solves in f64 and evaluates in f32, so the
two agree to f32 rounding (tests/test_kelvinlet.py checks 1e-5 against a running server).

Batches hold samples with different numbers of points: they are padded to the largest K and
`mask` marks the real points. A padded point gets an identity row and a zero right-hand side, so
its coefficient is exactly zero and it changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Prior:
    poisson_ratio: float
    epsilon: float
    lam: float

    @property
    def scale(self) -> float:
        return self.epsilon / (5.0 - 6.0 * self.poisson_ratio)

    def response(self, r: torch.Tensor) -> torch.Tensor:
        """Γ(r) for offsets r [..., 3]: [..., 3, 3]."""
        nu, eps = self.poisson_ratio, self.epsilon
        r_eps2 = (r * r).sum(-1) + eps * eps
        r_eps = r_eps2.sqrt()
        inv3 = 1.0 / (r_eps2 * r_eps)
        diagonal = (3.0 - 4.0 * nu) / r_eps + 2.0 * (1.0 - nu) * eps * eps * inv3
        eye = torch.eye(3, dtype=r.dtype, device=r.device)
        outer = r.unsqueeze(-1) * r.unsqueeze(-2) * inv3[..., None, None]
        return self.scale * (diagonal[..., None, None] * eye + outer)

    def coefficients(self, points: torch.Tensor, displacements: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """k [B, K, 3] for points [B, K, 3], displacements [B, K, 3], mask [B, K] (bool)."""
        b, k, _ = points.shape
        gamma = self.response(points[:, :, None, :] - points[:, None, :, :])  # [B, K(i), K(j), 3, 3]
        pair = (mask[:, :, None] & mask[:, None, :]).to(gamma.dtype)
        gamma = gamma * pair[..., None, None]
        gamma = gamma.permute(0, 1, 3, 2, 4).reshape(b, 3 * k, 3 * k)  # rows (i, a), columns (j, c)
        padded = (~mask).repeat_interleave(3, dim=1).to(gamma.dtype)
        gamma = gamma + torch.diag_embed(padded)
        u = (displacements * mask[..., None].to(displacements.dtype)).reshape(b, 3 * k, 1)
        normal = gamma.transpose(1, 2) @ gamma
        normal = normal + self.lam * torch.eye(3 * k, dtype=gamma.dtype, device=gamma.device)
        solved = torch.cholesky_solve(gamma.transpose(1, 2) @ u, torch.linalg.cholesky(normal)).reshape(b, k, 3)
        # nak moves a lone point by exactly its displacement: Γ(0) = I needs no system (and no λ).
        lone = (mask.sum(1) == 1)[:, None, None]
        return torch.where(lone, displacements * mask[..., None].to(displacements.dtype), solved)

    def field(self, nodes: torch.Tensor, points: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
        """u [B, M, 3] at nodes [M, 3] (shared) or [B, M, 3], from points and coefficients [B, K, 3].

        `Γ(r) k = s [(a/r_ε + b/r_ε³) k + r (r·k)/r_ε³]`, as nak's kernel computes it: no 3×3 blocks.
        """
        if nodes.dim() == 2:
            nodes = nodes.unsqueeze(0).expand(points.shape[0], -1, -1)
        nu, eps = self.poisson_ratio, self.epsilon
        r = nodes[:, :, None, :] - points[:, None, :, :]  # [B, M, K, 3]
        r_eps2 = (r * r).sum(-1) + eps * eps
        r_eps = r_eps2.sqrt()
        inv3 = 1.0 / (r_eps2 * r_eps)
        diagonal = (3.0 - 4.0 * nu) / r_eps + 2.0 * (1.0 - nu) * eps * eps * inv3  # [B, M, K]
        k = coefficients[:, None, :, :]
        along = (r * k).sum(-1) * inv3
        return self.scale * (diagonal.unsqueeze(-1) * k + r * along.unsqueeze(-1)).sum(2)

    def evaluate(
        self, nodes: torch.Tensor, points: torch.Tensor, displacements: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """The prior field over `nodes` for interaction points with prescribed displacements."""
        return self.field(nodes, points, self.coefficients(points, displacements, mask))


def pad_points(
    positions: torch.Tensor, nodes: list[torch.Tensor], displacements: list[torch.Tensor]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pads per-sample node ids [K_b] and displacements [K_b, 3] into a batch.

    Returns (node ids [B, K] (padding repeats the first node), points [B, K, 3], displacements
    [B, K, 3] (zero padding), mask [B, K]).
    """
    k = max(len(n) for n in nodes)
    b = len(nodes)
    ids = torch.zeros(b, k, dtype=torch.long)
    disp = torch.zeros(b, k, 3, dtype=positions.dtype)
    mask = torch.zeros(b, k, dtype=torch.bool)
    for i, (n, d) in enumerate(zip(nodes, displacements, strict=True)):
        ids[i, : len(n)] = n
        ids[i, len(n) :] = n[0]
        disp[i, : len(n)] = d.to(positions.dtype)
        mask[i, : len(n)] = True
    return ids, positions[ids], disp, mask
