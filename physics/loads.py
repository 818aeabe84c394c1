"""External loads on a discrete rod: gravity, node wrenches, and the magnet/field hook.

The field hook. ``Loads.field`` is any object that either (every
:class:`physics.magnetics.FieldModel` does both)

* has ``wrench(t, positions, moments) -> (force, torque)`` (world frame, each (..., K, 3)), or
* is callable as ``field(t, positions) -> B`` or ``-> (B, dB)`` with ``B`` (..., K, 3) in tesla and
  ``dB[..., i, j] = dB_i/dx_j`` (..., K, 3, 3); the torque is ``m x B`` and the force
  ``grad(m . B) = dB^T m``; without ``dB`` the field is taken as locally uniform (no force).

``positions`` and world-frame ``moments`` of the K magnets are interpolated inside their element
(position linearly, orientation as ``R_a cay(xi psi)``), and the resulting force and torque are
shared between the two nodes with the weights ``(1 - xi, xi)`` used for the magnet's mass.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from .lie import cay
from .magnetics.base import UniformField
from .rod import RodParams

__all__ = ["Loads", "UniformField", "magnet_poses", "magnet_node_loads"]

TensorOrFn = Tensor | Callable[[float], Tensor] | None


def _value(x: TensorOrFn, t: float):
    return x(t) if callable(x) else x


@dataclass(frozen=True)
class Loads:
    """External loads. ``gravity`` (3,) m/s^2; ``force``/``torque`` world-frame per node
    (..., n, 3) as tensors or functions of time; ``field`` the magnet hook (module docstring)."""

    gravity: Sequence[float] | Tensor | None = None
    force: TensorOrFn = None
    torque: TensorOrFn = None
    field: object | None = None

    def evaluate_force(self, t: float):
        return _value(self.force, t)

    def evaluate_torque(self, t: float):
        return _value(self.torque, t)


def magnet_positions(p: Tensor, prm: RodParams) -> Tensor:
    """Magnet positions (..., K, 3) from the node positions."""
    e, xi = prm.magnet_elem, prm.magnet_xi
    pa, pb = p[..., e, :], p[..., e + 1, :]
    return pa + xi[:, None] * (pb - pa)


def magnet_poses(p: Tensor, R: Tensor, psi: Tensor, prm: RodParams):
    """Positions (..., K, 3), orientations (..., K, 3, 3) and world moments (..., K, 3)."""
    e, xi = prm.magnet_elem, prm.magnet_xi
    pos = magnet_positions(p, prm)
    Rm = R[..., e, :, :] @ cay(xi[:, None] * psi[..., e, :])
    moments = (Rm * prm.magnet_moment[..., None, :]).sum(-1)
    return pos, Rm, moments


def magnet_node_loads(field, t: float, p: Tensor, R: Tensor, psi: Tensor, prm: RodParams):
    """World forces and body torques (each (..., n, 3)) on the nodes from the field on the magnets."""
    pos, _, mom = magnet_poses(p, R, psi, prm)
    if hasattr(field, "wrench"):
        F, T = field.wrench(t, pos, mom)
    else:
        out = field(t, pos)
        B, dB = (out if isinstance(out, tuple) else (out, None))
        T = torch.linalg.cross(mom, B.expand_as(mom), dim=-1)
        F = torch.zeros_like(T) if dB is None else (dB * mom[..., :, None]).sum(-2)
    e, xi = prm.magnet_elem, prm.magnet_xi
    wa, wb = (1 - xi)[:, None], xi[:, None]
    force = torch.zeros_like(p)
    force = force.index_add(-2, e, wa * F).index_add(-2, e + 1, wb * F)
    Ta = (R[..., e, :, :] * T[..., :, None]).sum(-2)  # R_a^T T
    Tb = (R[..., e + 1, :, :] * T[..., :, None]).sum(-2)
    torque = torch.zeros_like(p).index_add(-2, e, wa * Ta).index_add(-2, e + 1, wb * Tb)
    return force, torque
