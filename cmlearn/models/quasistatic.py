"""The learned dynamics of the quasi-static hybrid surrogate of the magnetic rod: how the magnets deviate
from the static Cosserat rod under the same currents (:mod:`cmlearn.data.quasistatic` defines the static
state ``s`` and the deviation ``d``, 12 coordinates each).

The step, from the deviations of frames k-eta..k and the static states of frames k+1-n..k+1 (n =
``increments``; frame k+1's static state is known ahead, from the currents alone)::

    d(k+1) = L [d(k-eta..k), s(k+2-n..k+1) - s(k+1-n..k)] + f(d(k-eta..k), s(k+2-n..k+1) - s(k+1-n..k), s(k+1))

``L`` is a linear map fitted by least squares (:meth:`QuasiStaticCorrection.fit_linear`: the rod's linear
response, a damped lag behind the moving equilibrium) and kept fixed; ``f`` is Paper II's node network on
these inputs (input I, the deviation history, through an LSTM; input II, the static increments and state,
through a dense layer, with ``margin`` also the static solutions' stability margins of frames k+1-n..k+1, and with
``fold_clock`` the frames since the static track last jumped over a fold at frame k+1
(:func:`~cmlearn.data.quasistatic.fold_clock`, at most ``fold_clock`` frames);
concatenated; a dense head), less its output at rest (so that a rod at rest stays
there exactly), zero at initialisation and trained on free-running rollouts
(:mod:`cmlearn.surrogate.quasistatic_training`). Without ``L`` the same network ran away on the held-out
profile; without ``f`` the linear step errs more than the static rod alone (``docs/surrogates.md``, "A
quasi-static hybrid for the magnetic rod").
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

__all__ = ["QuasiStaticConfig", "QuasiStaticCorrection"]

N = 12  # coordinates of s and d (cmlearn.data.quasistatic.N_COORDS)


@dataclass
class QuasiStaticConfig:
    eta: int = 2  # deviation history: frames k-eta..k (the LSTM's sequence)
    increments: int = 3  # static increments s(k+1-j) - s(k-j), j = 0..increments-1
    hidden: int = 32  # LSTM units
    width: int = 64  # dense widths
    dev_scale: tuple[float, ...] = (1.0,) * N  # per coordinate: mm and deg
    inc_scale: tuple[float, ...] = (1.0,) * N
    state_mean: tuple[float, ...] = (0.0,) * N
    state_scale: tuple[float, ...] = (1.0,) * N
    rest_state: tuple[float, ...] = (0.0,) * N  # s of the rod at rest (the network's output there is removed)
    margin: bool = False  # the network also sees the static solutions' stability margins (a 13th static column)
    margin_scale: float = 1.0
    rest_margin: float = 0.0  # the margin at rest
    fold_clock: float = 0.0  # > 0: the network also sees the fold clock of frame k+1, capped at this many frames

    def __post_init__(self):
        for name, lo in (("eta", 0), ("increments", 1), ("hidden", 1), ("width", 1)):
            v = getattr(self, name)
            if not isinstance(v, int) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        for name in ("dev_scale", "inc_scale", "state_mean", "state_scale", "rest_state"):
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != N:
                raise ValueError(f"{name} must hold {N} numbers, got {len(v)}")
            if name.endswith("scale") and not all(x > 0 for x in v):
                raise ValueError(f"{name} must be positive, got {v}")
            setattr(self, name, v)
        if not self.margin_scale > 0:
            raise ValueError(f"margin_scale must be positive, got {self.margin_scale}")
        if not (self.fold_clock >= 0 and math.isfinite(self.fold_clock)):
            raise ValueError(f"fold_clock must be a finite number of frames >= 0 (0: off), got {self.fold_clock}")
        if self.fold_clock and not self.margin:
            raise ValueError("fold_clock needs margin: the clock is read from the margins before a fold")

    def to_dict(self) -> dict:
        return asdict(self)


class QuasiStaticCorrection(nn.Module):
    """The step above; ``forward(dev, static)``: ``dev`` (B, eta+1, 12) and ``static`` (B, increments+1, 12, 13
    or 14), each oldest first, ``static`` ending at frame k+1 (its 13th column the stability margins, which the
    network reads where ``config.margin``, its 14th the fold clock, read where ``config.fold_clock``); returns
    ``d(k+1)`` (B, 12)."""

    def __init__(self, config: QuasiStaticConfig):
        super().__init__()
        self.config = c = config
        self.lstm = nn.LSTM(N, c.hidden, batch_first=True)
        n_in = N * c.increments + N + (c.increments + 1) * c.margin + (c.fold_clock > 0)
        self.dense = nn.Sequential(nn.Linear(n_in, c.width), nn.Tanh())
        self.head = nn.Sequential(nn.Linear(c.hidden + c.width, c.width), nn.Tanh(), nn.Linear(c.width, N))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)
        self.register_buffer("linear", torch.zeros(self.n_regressors, N))
        for name in ("dev_scale", "inc_scale", "state_mean", "state_scale", "rest_state"):
            self.register_buffer(name, torch.tensor(getattr(c, name), dtype=torch.float32))

    @property
    def n_regressors(self) -> int:
        return N * (self.config.eta + 1 + self.config.increments)

    def regressors(self, dev: Tensor, static: Tensor) -> Tensor:
        """The inputs of ``L`` (B, n_regressors): the deviations and the static increments, flattened."""
        s = static[..., :N]
        return torch.cat([dev.flatten(1), (s[:, 1:] - s[:, :-1]).flatten(1)], -1)

    def _check(self, dev: Tensor, static: Tensor):
        c = self.config
        if dev.dim() != 3 or dev.shape[1:] != (c.eta + 1, N):
            raise ValueError(f"dev must be (B, {c.eta + 1}, {N}), got {tuple(dev.shape)}")
        # a margin (clock) column is there or not, unless the network reads it
        cols = (N + 2,) if c.fold_clock else (N + 1, N + 2) if c.margin else (N, N + 1, N + 2)
        if static.dim() != 3 or static.shape[1] != c.increments + 1 or static.shape[2] not in cols or \
                static.shape[0] != dev.shape[0]:
            raise ValueError(f"static must be ({dev.shape[0]}, {c.increments + 1}, {' or '.join(map(str, cols))}), "
                             f"got {tuple(static.shape)}")

    def _network(self, dev: Tensor, inc: Tensor, state: Tensor, margins: Tensor | None,
                 clock: Tensor | None = None) -> Tensor:
        h = self.lstm(dev / self.dev_scale)[0][:, -1]
        x = [(inc / self.inc_scale).flatten(1), (state - self.state_mean) / self.state_scale]
        if margins is not None:
            x.append(margins / self.config.margin_scale)
        if clock is not None:
            x.append(clock[:, None] / self.config.fold_clock)
        return self.head(torch.cat([h, self.dense(torch.cat(x, -1))], -1)) * self.dev_scale

    def rest_output(self) -> Tensor:
        """The network's output (1, 12) at rest (no deviation, no motion, the rest state and margin): what the
        rest anchor subtracts; constant along a rollout, so compute it once and pass it to :meth:`forward`."""
        c = self.config
        z = self.rest_state.new_zeros
        margins = z(1, c.increments + 1) + c.rest_margin if c.margin else None
        clock = z(1) + c.fold_clock if c.fold_clock else None  # no fold for as long as the clock counts
        return self._network(z(1, c.eta + 1, N), z(1, c.increments, N), self.rest_state[None], margins, clock)

    def forward(self, dev: Tensor, static: Tensor, rest: Tensor | None = None) -> Tensor:
        """``rest``: :meth:`rest_output` (computed here when not given)."""
        self._check(dev, static)
        s = static[..., :N]
        linear = self.regressors(dev, static) @ self.linear
        margins = static[..., N] if self.config.margin else None
        clock = static[:, -1, N + 1] if self.config.fold_clock else None
        # the rest anchor: at rest the step is exactly zero
        rest = self.rest_output() if rest is None else rest
        return linear + self._network(dev, s[:, 1:] - s[:, :-1], s[:, -1], margins, clock) - rest

    def rollout(self, dev: Tensor, static: Tensor) -> Tensor:
        """Free-running deviations (B, H, 12) after the history ``dev`` (B, eta+1, 12) ending at frame k0, along
        the static states ``static`` (B, H + increments, 12, 13 or 14) of frames k0+1-increments .. k0+H."""
        n = self.config.increments
        H = static.shape[1] - n
        if H < 1:
            raise ValueError(f"static must hold more than increments = {n} frames, got {static.shape[1]}")
        out, rest = [], self.rest_output()
        for h in range(H):
            d = self(dev, static[:, h:h + n + 1], rest)
            out.append(d)
            dev = torch.cat([dev[:, 1:], d[:, None]], 1)
        return torch.stack(out, 1)

    @torch.no_grad()
    def fit_linear(self, dev: Tensor, static: Tensor, ranges) -> float:
        """Least-squares ``L`` of one-step predictions over trajectories ``dev`` (V, T, 12), ``static`` (V, T, 12
        or 13) on the frame ranges [(variant, first, last)] (steps first..last-1 whose inputs lie in the range);
        sets the buffer and returns the residual's RMS over the targets' RMS."""
        c = self.config
        lo = max(c.eta, c.increments - 1)
        X, Y = [], []
        for v, a, b in ranges:
            for k in range(max(a, lo), b):
                X.append(self.regressors(dev[v, None, k - c.eta:k + 1], static[v, None, k + 1 - c.increments:k + 2]))
                Y.append(dev[v, None, k + 1])
        if not X:
            raise ValueError("ranges hold no step with a full history")
        X, Y = torch.cat(X).double(), torch.cat(Y).double()
        L = torch.linalg.lstsq(X, Y, driver="gelsd").solution
        self.linear.copy_(L.to(self.linear))
        return float((X @ L - Y).pow(2).mean().sqrt() / Y.pow(2).mean().sqrt())
