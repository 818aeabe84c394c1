"""Time-varying coil currents for an electromagnetic navigation system, and a cheap field hook for them.

Profiles (each ``profile(t) -> (C,)`` A, float64; ``t`` a float or 0-d tensor):

* :class:`MinJerkCurrents`: hold a current vector, move to the next one along a minimum-jerk
  (quintic) path, hold, ... (the quasi-static experiments' "go to a set-point and wait");
* :class:`SinusoidCurrents`: per coil a sum of low-frequency sinusoids, faded in from zero with a
  minimum-jerk ramp, never holding still;
* :class:`BatchedCurrents`: V profiles stacked to (V, C), for batched solvers.

:class:`CoilField` is a solver field hook (:mod:`physics.loads`) for coils driven by such a profile.
The coils' unit-current maps ``beta_c(x)`` (T/A) and ``d beta_c/dx`` (T/(m A)) are evaluated exactly
(:meth:`~physics.magnetics.emns.EMNS.unit_field_and_gradient`) at the magnets, kept, and extrapolated
linearly, ``beta_c(x) ~ beta_c(x0) + d beta_c(x0) (x - x0)``, until some magnet has moved more than
``tol`` from where they were evaluated; then they are evaluated again. The field is
``B = sum_c I_c(t) beta_c`` and its gradient ``sum_c I_c(t) d beta_c(x0)``. With ``tol`` = 0.2 mm and
coils >= 65 mm away the field is within ~1e-5 and the gradient within ~0.5 % of the exact
superposition, at a fraction of its cost (an exact coil evaluation costs ~1 ms, a solver step
here ~0.1 ms). The cache is the only state: it is dropped when the hook is called at an earlier
time than before or with another batch shape (a new run). A run that starts at the very time of the last
call (two runs from t = 0) keeps the maps, which differ from its own by less than ``tol`` of motion; a run
whose result must not depend on what was evaluated before it takes :meth:`CoilField.fresh`, an independent copy.

The profiles and the hook are traceable: while traced for a compiled program (:func:`physics.programs.is_tracing`:
the LGVI's compiled blocks of steps, :meth:`physics.lgvi.LGVI.compiled_rollout`) a profile is evaluated in tensor
operations at a 0-d tensor time and the hook extrapolates from the kept maps, which are the program's inputs
(:meth:`CoilField.cache`, :meth:`CoilField.cached`); the LGVI keeps a block only if step-by-step evaluation would have
kept the maps throughout (:meth:`CoilField.block_ready`, :meth:`CoilField.drift`) and replays it eagerly otherwise,
so that the compiled rollout refreshes the maps exactly where the eager one does.
"""
from __future__ import annotations

import bisect
import contextlib
import math

import torch
from torch import Tensor

from .magnetics.coils import check_current_batch
from .magnetics.dipole import dipole_torque, force_from_gradient
from .programs import is_tracing

__all__ = ["MinJerkCurrents", "SinusoidCurrents", "BatchedCurrents", "CoilField", "min_jerk"]

_F64 = torch.float64


def min_jerk(x):
    """Quintic ``10x^3 - 15x^4 + 6x^5`` on [0, 1] (clamped outside); ``x`` a float or a tensor."""
    x = x.clamp(0.0, 1.0) if torch.is_tensor(x) else min(max(x, 0.0), 1.0)
    return x**3 * (10 - 15 * x + 6 * x * x)


def _check_matrix(name: str, v, cols: int | None = None) -> Tensor:
    v = torch.as_tensor(v, dtype=_F64)
    if v.dim() != 2 or (cols is not None and v.shape[1] != cols) or not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} must be a finite 2-D array (rows, {cols or 'C'}), got shape {tuple(v.shape)}")
    return v


def _time(t) -> float:
    """An eager profile's time as a float; NaN gave the last set-point (and inf the same, by bisection)."""
    t = float(t)
    if not math.isfinite(t):
        raise ValueError(f"t must be a finite time (s), got {t!r}")
    return t


def _positive(name: str, seq, n: int) -> tuple[float, ...]:
    try:
        out = tuple(float(x) for x in seq)
    except TypeError:  # a single number, not one per hold/move
        raise TypeError(f"{name} must be a sequence of {n} durations (s), got {seq!r}") from None
    if len(out) != n or not all(math.isfinite(x) and x >= 0 for x in out):
        raise ValueError(f"{name} must be {n} finite non-negative durations (s), got {seq!r}")
    return out


class MinJerkCurrents:
    """Hold ``setpoints[0]`` for ``holds[0]`` s, move to ``setpoints[1]`` in ``moves[0]`` s (minimum jerk),
    hold it ``holds[1]`` s, ...; after the last hold the last set-point is kept. ``setpoints`` (n, C) A."""

    def __init__(self, setpoints, moves, holds):
        self.setpoints = _check_matrix("setpoints", setpoints)
        n = self.setpoints.shape[0]
        if n < 1:
            raise ValueError("setpoints must hold at least one current vector")
        self.moves = _positive("moves", moves, n - 1)
        self.holds = _positive("holds", holds, n)
        if any(m <= 0 for m in self.moves):
            raise ValueError(f"moves must be > 0 s, got {self.moves}")
        knots, t = [], 0.0
        for i in range(n):
            t += self.holds[i]
            knots.append(t)  # end of hold i
            if i < n - 1:
                t += self.moves[i]
                knots.append(t)  # end of move i
        self._knots, self.duration = knots, t
        # the moves as tensors for the traced form: move i starts at the end of hold i
        self._move_start = torch.tensor(knots[0::2][: n - 1], dtype=_F64)
        self._move_length = torch.tensor(self.moves, dtype=_F64)

    def __call__(self, t) -> Tensor:
        if is_tracing():  # traced (LGVI.compiled_rollout): every move's clamped quintic, no branch
            s = min_jerk((t - self._move_start.to(t)) / self._move_length.to(t))
            return self.setpoints[0].to(t) + s @ self.setpoints.diff(dim=0).to(t)
        t = _time(t)
        j = bisect.bisect_right(self._knots, t)
        if j >= len(self._knots):
            return self.setpoints[-1].clone()
        i = j // 2
        if j % 2 == 0:  # holding set-point i
            return self.setpoints[i].clone()
        s = min_jerk((t - self._knots[j - 1]) / self.moves[i])
        return self.setpoints[i] + s * (self.setpoints[i + 1] - self.setpoints[i])

    @property
    def peak(self) -> float:
        return float(self.setpoints.abs().max())


class SinusoidCurrents:
    """``I_c(t) = r(t) sum_k amplitudes[k, c] sin(2 pi frequencies[k] t + phases[k, c])`` with the fade-in
    ``r(t) = min_jerk(t / ramp)``; ``amplitudes``, ``phases`` (K, C), ``frequencies`` (K,) Hz."""

    def __init__(self, amplitudes, frequencies, phases, ramp: float = 2.0):
        self.amplitudes = _check_matrix("amplitudes", amplitudes)
        self.phases = _check_matrix("phases", phases, self.amplitudes.shape[1])
        self.frequencies = torch.as_tensor(frequencies, dtype=_F64).reshape(-1)
        if self.phases.shape != self.amplitudes.shape or self.frequencies.shape[0] != self.amplitudes.shape[0]:
            raise ValueError("amplitudes and phases must be (K, C) and frequencies (K,)")
        if not bool(torch.isfinite(self.frequencies).all() and (self.frequencies > 0).all()):
            raise ValueError(f"frequencies must be finite and > 0 Hz, got {self.frequencies.tolist()}")
        if not (math.isfinite(ramp) and ramp > 0):
            raise ValueError(f"ramp must be > 0 s, got {ramp!r}")
        self.ramp = float(ramp)

    def __call__(self, t) -> Tensor:
        if is_tracing():  # traced (LGVI.compiled_rollout): ``t`` a 0-d tensor
            w = torch.sin(2 * math.pi * self.frequencies[:, None].to(t) * t + self.phases.to(t))
            return min_jerk(t / self.ramp) * (self.amplitudes.to(t) * w).sum(0)
        t = _time(t)
        w = torch.sin(2 * math.pi * self.frequencies[:, None] * t + self.phases)
        return min_jerk(t / self.ramp) * (self.amplitudes * w).sum(0)

    @property
    def peak(self) -> float:
        return float(self.amplitudes.abs().sum(0).max())


class BatchedCurrents:
    """V profiles evaluated together: ``(t) -> (V, C)``."""

    def __init__(self, profiles):
        self.profiles = list(profiles)
        if not self.profiles:
            raise ValueError("profiles must not be empty")

    def __call__(self, t) -> Tensor:
        return torch.stack([p(t) for p in self.profiles])


class CoilField:
    """Solver field hook for ``emns`` driven by ``currents(t) -> (..., C)`` (module docstring)."""

    def __init__(self, emns, currents, tol: float = 2e-4):
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be > 0 m, got {tol!r}")
        if not callable(currents):
            raise TypeError(f"currents must be a function of time returning the coil currents (C,) or (..., C), got "
                            f"{type(currents).__name__}")
        self.emns, self.currents, self.tol = emns, currents, float(tol)
        self._clear()
        self.refreshes = 0

    def _clear(self):
        self._x0 = self._beta = self._grad = None
        self._t = -math.inf

    def fresh(self) -> "CoilField":
        return CoilField(self.emns, self.currents, self.tol)

    def _maps(self, t: float, x: Tensor):
        if is_tracing():  # a compiled block of LGVI steps: the kept maps (block_ready, drift)
            return self._beta + (self._grad * (x - self._x0)[..., :, None, None, :]).sum(-1), self._grad
        if t < self._t or self._x0 is None or self._x0.shape != x.shape or self._x0.dtype != x.dtype:
            self._clear()
        self._t = t
        if self._x0 is None or float((x.detach() - self._x0).abs().max()) > self.tol:
            self._x0 = x.detach().clone()
            self._beta, self._grad = self.emns.unit_field_and_gradient(self._x0)
            self.refreshes += 1
        d = x - self._x0
        return self._beta + (self._grad * d[..., :, None, None, :]).sum(-1), self._grad

    def field_and_gradient(self, t, positions: Tensor) -> tuple[Tensor, Tensor]:
        I = torch.as_tensor(self.currents(t), dtype=positions.dtype, device=positions.device)
        beta, grad = self._maps(t if is_tracing() else float(t), positions)
        # shapes only (traceable): (1,) currents were broadcast to every coil, (5,) for six a bare RuntimeError
        if I.shape[-1:] != beta.shape[-2:-1]:
            raise ValueError(f"currents must return the coil currents (C,) or (..., C) for the C = {beta.shape[-2]} "
                             f"coils of the eMNS, got shape {tuple(I.shape)}")
        check_current_batch(positions, I)
        B = (beta * I[..., None, :, None]).sum(-2)
        dB = (grad * I[..., None, :, None, None]).sum(-3)
        return B, dB

    def __call__(self, t, positions: Tensor) -> tuple[Tensor, Tensor]:
        return self.field_and_gradient(t, positions)

    # the LGVI's compiled blocks of steps (LGVI.compiled_rollout): traced, the hook extrapolates from the kept maps
    # with no refresh test; the block is kept only if evaluating it step by step would have kept them too, that is
    # if block_ready() held before it and drift() stayed within tol at every step, else it is replayed eagerly
    def block_ready(self, t: float, p: Tensor) -> bool:
        """Whether a compiled block from time ``t`` of a rod with node positions ``p`` (..., n, 3) may run on the kept
        maps: they exist, for this run (no earlier time), batch shape and dtype. Whether they still serve its steps,
        the first included, is :meth:`drift`'s, evaluated in the block."""
        x0 = self._x0
        return x0 is not None and t >= self._t and x0.shape[:-2] == p.shape[:-2] and x0.dtype == p.dtype

    def drift(self, positions: Tensor) -> Tensor:
        """Largest coordinate distance (m) of the magnets from where the kept maps were evaluated (traceable)."""
        return (positions.detach() - self._x0).abs().amax()

    def block_done(self, t: float):
        """A compiled block's last evaluation was at time ``t``."""
        self._t = float(t)

    def cache(self) -> tuple[Tensor, Tensor, Tensor]:
        """The kept maps: where they were evaluated, the maps and their gradients (inputs of a compiled program)."""
        return self._x0, self._beta, self._grad

    @contextlib.contextmanager
    def cached(self, cache: tuple[Tensor, Tensor, Tensor]):
        """Within, the kept maps are ``cache`` (a program's traced inputs, so that the program reads them)."""
        old = self.cache()
        self._x0, self._beta, self._grad = cache
        try:
            yield
        finally:
            self._x0, self._beta, self._grad = old

    def wrench(self, t, positions: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        B, dB = self.field_and_gradient(t, positions)
        return force_from_gradient(moments, dB), dipole_torque(moments, B)
