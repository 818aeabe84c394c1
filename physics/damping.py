"""Distributed damping-capacity estimation filters (Paper I, (I.17)-(I.21)).

One filter per node estimates the node's damping capacity ``K_a`` (N s/m) in the dissipative
force ``-K_a o v_a`` (``o``: Hadamard product, ``v_a = (p_a^j - p_a^{j-1})/h``) from measured node
positions. Each filter mimics the node's own model: it predicts the node's next position with the
undamped LGVI fed with the *measured* positions of the node and its neighbours (the filters are
coupled through the neighbours' poses), so the one-step innovation

    r^j = y^{j+1} - p_free^{j+1}(y^j, y^{j-1}, neighbours, R^j)       equals       B^j K + noise,
    B^j = -(h^2 / m_a) diag(v_a^{j-1/2})                       (the model dissipation matrix of (I.17))

and the estimate minimises the pointwise cost (I.19) ``1/2 e^T R e + 1/2 K^T W K``:
``K = (B^T R B + W)^{-1} B^T R r`` (I.21). Rotations are not measured: each filter carries them
by the LGVI rotation update driven by the measured positions. The printed law predicts the
measurement at ``j+2`` by Taylor expansions (I.20); the measurement is at hand one step later,
so we use the exact one-step innovation instead. With ``forgetting = 0`` the estimate is the
pointwise law; ``0 < forgetting < 1`` accumulates the normal equations with exponential forgetting
(recursive least squares), which averages measurement noise and the instants where ``v_a``
crosses zero and ``B`` carries no information.

``isotropic=True`` estimates one scalar capacity per node (``B`` a column) instead of one per axis.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .lgvi import LGVI, LGVIState

__all__ = ["DampingFilterState", "DistributedDampingFilter", "run_filtered_model"]


class DampingFilterState(NamedTuple):
    t: float
    y: Tensor        # last measured positions (..., n, 3)
    v: Tensor        # measured half-step velocity (..., n, 3)
    R: Tensor        # filter-carried rotations (..., n, 3, 3)
    pi: Tensor       # filter-carried body momenta (..., n, 3)
    P: Tensor        # accumulated B^T R B (..., n, k)
    Q: Tensor        # accumulated B^T R r (..., n, k)
    K: Tensor        # current capacity estimate (..., n, 3), N s/m
    innovation: Tensor  # last one-step innovation r (..., n, 3)


@dataclass
class DistributedDampingFilter:
    """Filters for every node of the undamped model ``model`` (an :class:`LGVI` whose rod has no
    translational damping). ``R`` (1/m^2) and ``W`` ((m/(N s))^2) are the diagonal weights of
    (I.19) in SI, scalars or (3,) tensors; ``forgetting`` in [0, 1)."""

    model: LGVI
    R: float | Tensor = 1.0
    W: float | Tensor = 1e-24
    forgetting: float = 0.999
    isotropic: bool = False

    def __post_init__(self):
        if not 0.0 <= self.forgetting < 1.0:
            raise ValueError(f"DistributedDampingFilter.forgetting must lie in [0, 1), got {self.forgetting}")
        if bool((self.model.params.damping != 0).any()):
            raise ValueError("DistributedDampingFilter.model must be undamped (its rod has damping > 0)")
        kw = dict(dtype=self.model.dtype, device=self.model.device)
        self._R = torch.as_tensor(self.R, **kw)
        self._W = torch.as_tensor(self.W, **kw)
        for name, w in (("R", self._R), ("W", self._W)):
            if w.shape not in ((), (3,)):
                raise ValueError(f"DistributedDampingFilter.{name} must be a scalar or a (3,) diagonal, "
                                 f"got shape {tuple(w.shape)}")
            if not bool(torch.isfinite(w).all()):
                raise ValueError(f"DistributedDampingFilter.{name} must be finite, got {w.tolist()}")
        if bool((self._R <= 0).any()) or bool((self._W < 0).any()):
            raise ValueError("DistributedDampingFilter: R must be positive definite and W positive semi-definite")

    def init(self, y_prev: Tensor, y: Tensor, R: Tensor, pi: Tensor | None = None,
             t: float = 0.0) -> DampingFilterState:
        """Start at time ``t`` from two consecutive measurements (for the velocity), the rotations at
        ``y`` and the body momenta before the torque kick at ``t`` (default zero)."""
        m = self.model
        kw = dict(dtype=m.dtype, device=m.device)
        y, y_prev, R = (torch.as_tensor(x, **kw) for x in (y, y_prev, R))
        if y.shape != y_prev.shape or R.shape[:-1] != y.shape:
            raise ValueError(f"DistributedDampingFilter.init: y_prev {tuple(y_prev.shape)}, y {tuple(y.shape)} "
                             f"and R {tuple(R.shape)} must describe the same nodes")
        pi = torch.zeros_like(y) if pi is None else torch.as_tensor(pi, **kw)
        v = (y - y_prev) / m.dt * m._free
        k = 1 if self.isotropic else 3
        z = torch.zeros(*y.shape[:-1], k, **kw)
        return DampingFilterState(float(t), y, v, R, pi, z, z.clone(), torch.zeros_like(y), torch.zeros_like(y))

    def update(self, fs: DampingFilterState, y_next: Tensor) -> DampingFilterState:
        """One step of every node's filter given the next measurement ``y_next`` (..., n, 3)."""
        m = self.model
        h = m.dt
        _, p_free, _, R1, pi1, _, _ = m._advance(m._tensor_time(fs.t), fs.y, fs.v, fs.R, fs.pi, m.newton_iters)
        r = (y_next - p_free) * m._free
        B = -(h * h / m.params.mass[..., None]) * fs.v  # diagonal of B per axis
        Rw = self._R
        lam = self.forgetting
        if self.isotropic:
            P = lam * fs.P + (B * Rw * B).sum(-1, keepdim=True)
            Q = lam * fs.Q + (B * Rw * r).sum(-1, keepdim=True)
            den = P + self._W.mean()
        else:
            P = lam * fs.P + B * Rw * B
            Q = lam * fs.Q + B * Rw * r
            den = P + self._W
        # with W = 0, no motion yet along an axis (or a clamped node) is 0/0: no information, K = 0
        K = torch.where(den > 0, Q / den.clamp_min(torch.finfo(den.dtype).tiny), 0.0).expand_as(B)
        v_next = (y_next - fs.y) / h * m._free
        return DampingFilterState(fs.t + h, y_next, v_next, R1, pi1, P, Q, K * m._free, r)

    def run(self, measurements: Tensor, R1: Tensor, pi1: Tensor | None = None, record_every: int = 1):
        """Filter a measured series ``(..., T, n, 3)`` sampled every ``dt`` from ``t = 0``, given the
        rotations (and momenta) at the second sample; returns the final filter state and the
        estimate history ``(..., T', n, 3)``."""
        if measurements.shape[-3] < 3:
            raise ValueError("DistributedDampingFilter.run needs at least 3 measurements")
        if not (isinstance(record_every, int) and record_every >= 1):
            raise ValueError(f"DistributedDampingFilter.run: record_every must be an integer >= 1, got {record_every!r}")
        fs = self.init(measurements[..., 0, :, :], measurements[..., 1, :, :], R1, pi1, t=self.model.dt)
        hist = []
        for j in range(2, measurements.shape[-3]):
            fs = self.update(fs, measurements[..., j, :, :])
            if (j - 2) % record_every == 0:
                hist.append(fs.K)
        return fs, torch.stack(hist, -3)


def run_filtered_model(model: LGVI, state: LGVIState, filt: DistributedDampingFilter, measurements: Tensor):
    """Run ``model`` open loop from ``state`` (at the time of ``measurements[..., 0, :, :]``) while
    the filters estimate the damping online from the measurements (..., T, n, 3), one per step:
    each step uses the current estimate as the model's damping. Returns the model positions
    (..., T, n, 3) and the final filter state."""
    model = copy.copy(model)  # its damping changes every step; the filters keep the undamped one
    model._compiled = {}  # a copy's programs are its own (a shallow copy would share the original's)
    base = model.params
    model.params = base._replace(damping=torch.zeros_like(base.damping))
    state = model.step(state)
    out = [measurements[..., 0, :, :].expand_as(state.p), state.p]
    fs = filt.init(measurements[..., 0, :, :], measurements[..., 1, :, :], state.R, state.pi, t=state.t)
    for j in range(1, measurements.shape[-3] - 1):
        model.params = base._replace(damping=fs.K)
        state = model.step(state)
        out.append(state.p)
        fs = filt.update(fs, measurements[..., j + 1, :, :])
    return torch.stack(out, -3), fs
