"""The contract every field model follows, and the adapters that plug it into the rod solvers.

A field model implements ``field_and_gradient(points) -> (B, dB)`` for field points (..., P, 3)
(B (..., P, 3) in T, ``dB[..., i, j] = dB_i/dx_j`` (..., P, 3, 3)) and, where cheaper, ``field``.
From these the base class derives ``force_torque(points, moments)`` on dipoles and the solvers'
field hook (see :mod:`physics.loads`): ``model(t, positions) -> (B, dB)`` and
``model.wrench(t, positions, moments) -> (force, torque)``; a static model ignores ``t``.
Models add by superposition: ``a + b`` is a :class:`Superposition`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Callable

import torch
from torch import Tensor

from .dipole import dipole_torque, force_from_gradient

__all__ = ["FieldModel", "Superposition", "TimeVarying", "UniformField"]


def check_points(points: Tensor, name: str = "points") -> Tensor:
    if not isinstance(points, Tensor):
        raise TypeError(f"{name} must be a tensor (..., 3), got {type(points).__name__}")
    if not points.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {points.dtype}")
    if points.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {tuple(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError(f"{name} must be finite")
    return points


class FieldModel(ABC):
    """Base class of static field models (subclasses implement ``field_and_gradient``)."""

    @abstractmethod
    def field_and_gradient(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """B (..., P, 3) and dB_i/dx_j (..., P, 3, 3) at ``points`` (..., P, 3)."""

    def field(self, points: Tensor) -> Tensor:
        return self.field_and_gradient(points)[0]

    def force_torque(self, points: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        """Force ``grad(m . B)`` and torque ``m x B`` (each (..., P, 3)) on dipoles ``moments`` at ``points``."""
        B, dB = self.field_and_gradient(points)
        return force_from_gradient(moments, dB), dipole_torque(moments, B)

    def wrench(self, t, positions: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        """Solver hook: :meth:`force_torque` at time ``t`` (ignored by static models)."""
        return self.force_torque(positions, moments)

    def __call__(self, t, positions: Tensor) -> tuple[Tensor, Tensor]:
        return self.field_and_gradient(positions)

    def __add__(self, other: "FieldModel") -> "Superposition":
        return Superposition([self, other])


class Superposition(FieldModel):
    """Sum of field models."""

    def __init__(self, models):
        flat = []
        for mdl in models:
            flat.extend(mdl.models if isinstance(mdl, Superposition) else [mdl])
        if not flat:
            raise ValueError("models must not be empty")
        self.models = flat

    def field_and_gradient(self, points):
        outs = [mdl.field_and_gradient(points) for mdl in self.models]
        return sum(o[0] for o in outs), sum(o[1] for o in outs)

    def field(self, points):
        return sum(mdl.field(points) for mdl in self.models)

    def __call__(self, t, positions: Tensor) -> tuple[Tensor, Tensor]:
        """Solver hook: the parts' fields at time ``t`` summed (a part that gives ``B`` alone adds no gradient)."""
        B, dB = 0, None
        for mdl in self.models:
            out = mdl(t, positions)
            if isinstance(out, tuple):
                B, dB = B + out[0], out[1] if dB is None else dB + out[1]
            else:
                B = B + out
        return B, torch.zeros(*B.shape, 3, dtype=B.dtype, device=B.device) if dB is None else dB

    def wrench(self, t, positions: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        """Solver hook: the parts' wrenches at time ``t`` summed."""
        parts = [mdl.wrench(t, positions, moments) for mdl in self.models]
        return sum(p[0] for p in parts), sum(p[1] for p in parts)


class TimeVarying:
    """A time-dependent field for the solvers' hook: ``make(t) -> FieldModel`` evaluated at each call
    (e.g. a magnet on a moving pose, coil currents following a schedule)."""

    def __init__(self, make: Callable[[Tensor], FieldModel]):
        self.make = make

    def __call__(self, t, positions: Tensor) -> tuple[Tensor, Tensor]:
        return self.make(t).field_and_gradient(positions)

    def wrench(self, t, positions: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        return self.make(t).force_torque(positions, moments)


def _check_uniform(B, finite: bool = True) -> Tensor:
    """``B`` as a tensor of shape (3,) or (..., 1, 3); ``finite=False`` (a field evaluated at each step)
    checks the shape alone, which keeps a compiled step in one graph."""
    B = torch.as_tensor(B)
    bad = not bool(torch.isfinite(B).all()) if finite else False
    if B.shape[-1:] != (3,) or (B.dim() > 1 and B.shape[-2] != 1) or bad:
        raise ValueError(f"B must be a finite field in tesla of shape (3,) or, one per batch member, (..., 1, 3) "
                         f"(the 1 spans the field points), got shape {tuple(B.shape)}"
                         f"{' with non-finite values' if bad else ''}")
    return B


class UniformField(FieldModel):
    """A spatially uniform field ``B`` (3,) in T, or ``B(t)`` a function of time (e.g. the ideal field at
    the centre of Helmholtz coils). As a solver hook it returns ``B`` alone: no gradient, no force.

    A batch of fields is ``B`` (..., 1, 3): it broadcasts against field points (..., P, 3), so each
    batch member's field acts on all its points. A (V, 3) ``B`` is refused, since it would line the
    batch up with the points."""

    def __init__(self, B):
        self.B = B if callable(B) else _check_uniform(B)

    def _at(self, t, points: Tensor) -> Tensor:
        if callable(self.B) and t is None:
            raise ValueError("UniformField: B is a function of time; evaluate it at a time t as a solver hook, "
                             "model(t, points) or model.wrench(t, points, moments)")
        B = _check_uniform(self.B(t), finite=False) if callable(self.B) else self.B
        B = B.to(dtype=points.dtype, device=points.device)
        try:
            return B.expand(torch.broadcast_shapes(B.shape, points.shape))
        except RuntimeError:
            raise ValueError(f"UniformField: B of shape {tuple(B.shape)} does not broadcast against "
                             f"points of shape {tuple(points.shape)}") from None

    def field_and_gradient(self, points):
        B = self._at(None, check_points(points))
        return B, torch.zeros(*B.shape, 3, dtype=B.dtype, device=B.device)

    def field(self, points):
        return self._at(None, check_points(points))

    def __call__(self, t, positions: Tensor) -> Tensor:
        return self._at(t, positions)

    def wrench(self, t, positions: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        torque = dipole_torque(moments, self._at(t, positions))
        return torch.zeros_like(torque), torque
