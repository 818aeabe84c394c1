"""Step baselines a node surrogate must beat, with its interface: :func:`~cmlearn.surrogate.evaluate.one_step`,
:func:`~cmlearn.surrogate.evaluate.free_running` and :func:`~cmlearn.surrogate.magnetic.nudged_free_running`
take them in place of a :class:`~cmlearn.models.NodeLSTMSurrogate`.

:class:`LinearStep` predicts every modelled node's second difference ``p(t+1) - 2 p(t) + p(t-1)`` as an affine
map of the displacements from the reference shape over the last ``eta + 1`` frames and the node forces, fitted
by ridge least squares on training trajectories (:meth:`LinearStep.fit`):

* ``local``: one map per node from its own and its two neighbours' frames and its own force, what a node
  model sees (Paper II's distributed model, the same neighbours);
* global: every node from all tracked points and every node's force.

Unfitted (all weights zero) it is the constant-velocity step ``p(t+1) = 2 p(t) - p(t-1)``, the Verlet-form
surrogate with a zero network output. A surrogate's one-step error means something only beside these; on
their own predictions (free-running) the linear maps of a nonlinear rod are where they fail.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from cmlearn.models import NodeLSTMConfig, NodeLSTMSurrogate

__all__ = ["LinearStep"]


class LinearStep(nn.Module):
    """See the module docstring. ``config``: the node structure (``n_tracked``, ``modeled``, ``left``, ``right``,
    ``eta``; a surrogate's own config gives it the same neighbours and history)."""

    rollout = NodeLSTMSurrogate.rollout  # the same free-running loop (anchors, closed-loop wrench) as the network

    def __init__(self, config: NodeLSTMConfig, local: bool = True):
        super().__init__()
        config = NodeLSTMConfig(n_tracked=config.n_tracked, modeled=config.modeled, left=config.left,
                                right=config.right, eta=config.eta)  # the structure alone: no anchor, mirror, projection
        self.config, self.local = config, local
        self.register_buffer("idx_modeled", torch.tensor(config.modeled, dtype=torch.long), persistent=False)
        self.register_buffer("nodes", torch.tensor([config.left, config.modeled, config.right]).t(), persistent=False)
        K, W, N = len(config.modeled), config.eta + 1, config.n_tracked
        F = 9 * W + 4 if local else 3 * W * N + 3 * K + 1  # frames, forces and the constant
        shape = (K, F) if local else (F,)
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("scale", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("weight", torch.zeros(*shape, 3 if local else 3 * K, dtype=torch.float64))

    def _features(self, hist: Tensor, wrench: Tensor, ref: Tensor) -> Tensor:
        """(B, W, n_tracked, 3), (B, K, 3), (B, n_tracked, 3) -> (B, K, F) local or (B, F) global."""
        disp = (hist - ref[:, None]).double()
        one = disp.new_ones(disp.shape[0], 1)
        if not self.local:
            return torch.cat([disp.flatten(1), wrench.double().flatten(1), one], 1)
        own = disp[:, :, self.nodes].permute(0, 2, 1, 3, 4).flatten(2)  # (B, K, W * 3 * 3)
        return torch.cat([own, wrench.double(), one[:, None].expand(-1, own.shape[1], 1)], 2)

    def _accel(self, hist: Tensor, wrench: Tensor, ref: Tensor) -> Tensor:
        x = (self._features(hist, wrench, ref) - self.mean) / self.scale
        if self.local:
            return torch.einsum("bkf,kfd->bkd", x, self.weight)
        return (x @ self.weight).unflatten(1, (-1, 3))

    def forward(self, hist: Tensor, wrench: Tensor, ref: Tensor, rest: Tensor | None = None) -> Tensor:
        """One step, as :meth:`NodeLSTMSurrogate.forward`: the modelled nodes' next positions (B, K, 3)."""
        if hist.shape[1] != self.config.eta + 1:
            raise ValueError(f"hist must hold eta + 1 = {self.config.eta + 1} frames, got {hist.shape[1]}")
        pk = hist[:, -1, self.idx_modeled]
        return (2 * pk - hist[:, -2, self.idx_modeled] + self._accel(hist, wrench, ref).to(pk.dtype))

    @torch.no_grad()
    def fit(self, positions: Tensor, wrench: Tensor, ranges, ridge: float = 1e-6) -> "LinearStep":
        """Fit on every step inside ``ranges`` [(variant, first_frame, last_frame)] of ``positions`` (V, T,
        n_tracked, 3) under the modelled nodes' forces ``wrench`` (V, T-1, K, 3), each variant's reference its
        first frame (as :func:`~cmlearn.data.windows.split_ranges` gives for a dataset). ``ridge``: the penalty on
        the standardised features' weights. Returns self."""
        if not ridge >= 0:
            raise ValueError(f"ridge must be >= 0, got {ridge!r}")
        N, K = self.config.n_tracked, len(self.config.modeled)
        if positions.dim() != 4 or positions.shape[-2:] != (N, 3):
            raise ValueError(f"positions must be (V, T, n_tracked={N}, 3), got shape {tuple(positions.shape)}")
        V, T = positions.shape[:2]
        if wrench.dim() != 4 or wrench.shape[0] != V or wrench.shape[1] < T - 1 or wrench.shape[-2:] != (K, 3):
            raise ValueError(f"wrench must be (V={V}, T-1={T - 1}, K={K}, 3): the modelled nodes' forces, got shape "
                             f"{tuple(wrench.shape)}")
        ranges = [tuple(r) for r in ranges]
        for v, a, b in ranges:
            if not (0 <= v < V and 0 <= a and b <= T - 1):
                raise ValueError(f"range {(v, a, b)} lies outside positions' {V} variants of frames 0..{T - 1}")
        W = self.config.eta + 1
        X, Y = [], []
        for v, a, b in ranges:
            if b <= a + W - 1:
                continue
            t = torch.arange(a + W - 1, b)
            p = positions[v].double()
            hist = torch.stack([p[t - W + 1 + j] for j in range(W)], 1)
            X.append(self._features(hist, wrench[v, t].double(), p[:1].expand(len(t), -1, -1)))
            Y.append((p[t + 1] - 2 * p[t] + p[t - 1])[:, self.idx_modeled])
        if not X:
            raise ValueError(f"ranges hold no step with eta + 1 = {W} frames before it")
        X, Y = torch.cat(X), torch.cat(Y)
        if not (bool(torch.isfinite(X).all()) and bool(torch.isfinite(Y).all())):  # lstsq: an internal assert in MKL
            raise ValueError("positions and wrench must be finite on the steps of ranges (a NaN frame, e.g. of a "
                             "diverged or truncated run: cut it out of the ranges)")
        if self.local:
            X, Y = X.transpose(0, 1), Y.transpose(0, 1)  # (K, S, F), (K, S, 3)
        else:
            Y = Y.flatten(1)
        mean, scale = X.mean(-2), X.std(-2)
        mean[..., -1] = 0.0  # the constant stays one (its zero spread, as any constant feature's, scales by one)
        scale = torch.where(scale > 0, scale, torch.ones_like(scale))
        Xn = (X - mean.unsqueeze(-2)) / scale.unsqueeze(-2)
        # ridge as extra rows (least squares of [Xn; sqrt(ridge S) I] against [Y; 0]): rank-deficient features (an
        # anchor that never moves, a free end's missing neighbour) need no special case
        eye = (ridge * Xn.shape[-2]) ** 0.5 * torch.eye(Xn.shape[-1], dtype=Xn.dtype).expand(*Xn.shape[:-2], -1, -1)
        A = torch.cat([Xn, eye], -2)
        B = torch.cat([Y, Y.new_zeros(*Y.shape[:-2], Xn.shape[-1], Y.shape[-1])], -2)
        self.mean.copy_(mean)
        self.scale.copy_(scale)
        self.weight.copy_(torch.linalg.lstsq(A, B, driver="gelsd").solution)
        return self
