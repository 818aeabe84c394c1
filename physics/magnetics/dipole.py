"""Point magnetic dipoles: field, field gradient, force, torque and the 3x5 gradient-to-force map.

Conventions (SI): moments ``m`` in A m^2, positions in m, fields in T. The field gradient is
``dB[..., i, j] = dB_i / dx_j``; in free space it is symmetric and traceless, so it has five
independent terms. Their order (Petruska & Nelson) is

    g = [dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz]

and the force on a dipole ``m`` is ``F = grad(m . B) = dB^T m = M(m) g`` with

    M(m) = [[ mx, my, mz,   0,  0],
            [  0, mx,  0,  my, mz],
            [-mz,  0, mx, -mz, my]].

Field of a dipole at displacement ``d`` (from the dipole to the field point), ``r = |d|``:

    B = mu0 / (4 pi) (3 d (m . d) / r^5 - m / r^3)
    dB_ij = 3 mu0 / (4 pi r^5) (m_i d_j + m_j d_i + (m . d) delta_ij - 5 (m . d) d_i d_j / r^2)

Singular distances: ``r = 0`` (or below ``min_distance``) raises ``ValueError``; an optional
``softening`` length ``eps`` replaces ``r^2`` by ``r^2 + eps^2`` everywhere (a Plummer-type
regularisation that keeps B bounded by ``~ mu0 m / (4 pi eps^3)`` and is exact for ``r >> eps``).
With softening, ``r = 0`` is allowed, but a ``min_distance`` > 0 still applies to the true distance ``r``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "MU0", "moment_from_remanence", "dipole_field", "dipole_field_gradient", "dipole_force",
    "dipole_torque", "dipole_dipole_force", "gradient_to_five", "five_to_gradient", "force_map",
    "force_from_gradient", "check_distances", "check_lengths",
]

MU0 = 4e-7 * math.pi  # vacuum permeability (T m / A); m = Br V / mu0 uses this value
_K = MU0 / (4 * math.pi)


def moment_from_remanence(Br, volume):
    """Dipole moment ``m = Br V / mu0`` (A m^2) of a uniformly magnetised body (Br in T, V in m^3).

    ``Br`` may be a scalar or a polarization vector (tensor (..., 3)), finite; ``volume`` must be > 0.
    """
    if not bool(torch.isfinite(torch.as_tensor(Br)).all()):
        raise ValueError(f"Br must be finite (T), got {Br}")
    if isinstance(volume, Tensor):
        if not bool(torch.isfinite(volume).all() and (volume > 0).all()):
            raise ValueError(f"volume must be finite and > 0 (m^3), got {volume}")
    elif not (math.isfinite(volume) and volume > 0):
        raise ValueError(f"volume must be finite and > 0 (m^3), got {volume}")
    return Br * volume / MU0


def check_distances(r2: Tensor, min_distance: float, name: str = "points") -> None:
    """Raise ``ValueError`` if any squared distance is not above ``min_distance^2`` (or is NaN).

    One reduction over ``r2``; the slow search for the offending index runs only on failure."""
    r2 = r2.detach()
    if r2.numel() == 0:
        return
    lo = r2.amin()
    if bool(lo > min_distance * min_distance):
        return
    bad = ~(r2 > min_distance * min_distance)
    idx = tuple(int(i) for i in bad.nonzero()[0])
    if r2[idx].isnan():
        raise ValueError(f"{name}: a displacement from the dipole at index {idx} is not finite (NaN)")
    raise ValueError(f"{name}: field point at distance {float(r2[idx].clamp_min(0).sqrt()):.3e} m "
                     f"(<= min_distance {min_distance:.3e} m) from a dipole at index {idx}; the point-"
                     "dipole field is singular there (move the point or pass softening=...)")


def check_lengths(softening: float, min_distance: float) -> None:
    """Raise ``ValueError`` unless ``softening`` and ``min_distance`` are finite lengths >= 0."""
    for name, length in (("softening", softening), ("min_distance", min_distance)):
        if not (math.isfinite(length) and length >= 0):
            raise ValueError(f"{name} must be a finite length >= 0 (m), got {length!r}")


def _r2(d: Tensor, softening: float, min_distance: float) -> Tensor:
    if d.shape[-1:] != (3,):
        raise ValueError(f"d (displacements from the dipoles) must have shape (..., 3), got {tuple(d.shape)}")
    check_lengths(softening, min_distance)
    r2 = (d * d).sum(-1)
    if softening == 0 or min_distance > 0:  # the true distance: softening no longer switches min_distance off
        check_distances(r2, min_distance)
    return r2 + softening * softening if softening > 0 else r2


def dipole_field(d: Tensor, m: Tensor, *, softening: float = 0.0, min_distance: float = 0.0) -> Tensor:
    """Field (..., 3) of dipoles ``m`` (..., 3) at displacements ``d`` (..., 3) (broadcast)."""
    r2 = _r2(d, softening, min_distance)
    inv_r2 = 1.0 / r2
    inv_r3 = inv_r2 * inv_r2.sqrt()
    md = (m * d).sum(-1)
    return _K * inv_r3[..., None] * (3 * (md * inv_r2)[..., None] * d - m)


def dipole_field_gradient(d: Tensor, m: Tensor, *, softening: float = 0.0, min_distance: float = 0.0) -> Tensor:
    """Gradient ``dB_i/dx_j`` (..., 3, 3) of the field of dipoles ``m`` at displacements ``d``."""
    r2 = _r2(d, softening, min_distance)
    inv_r2 = 1.0 / r2
    k = 3 * _K * inv_r2 * inv_r2 * inv_r2.sqrt()  # 3 mu0 / (4 pi r^5)
    md = (m * d).sum(-1)
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    G = (m[..., :, None] * d[..., None, :] + d[..., :, None] * m[..., None, :] + md[..., None, None] * eye
         - (5 * md * inv_r2)[..., None, None] * d[..., :, None] * d[..., None, :])
    return k[..., None, None] * G


def dipole_torque(m: Tensor, B: Tensor) -> Tensor:
    """Torque ``m x B`` (..., 3) on dipoles ``m`` in the field ``B``."""
    m, B = torch.broadcast_tensors(m, B)
    return torch.linalg.cross(m, B, dim=-1)


def force_from_gradient(m: Tensor, dB: Tensor) -> Tensor:
    """Force ``grad(m . B) = dB^T m`` (..., 3) on dipoles ``m`` (..., 3) in a field gradient (..., 3, 3)."""
    return (dB * m[..., :, None]).sum(-2)


def dipole_dipole_force(d: Tensor, m1: Tensor, m2: Tensor, *, softening: float = 0.0,
                        min_distance: float = 0.0) -> Tensor:
    """Force (..., 3) on dipole ``m2`` from dipole ``m1``, ``d = x2 - x1`` (Paper V; the force on
    ``m1`` is its negative)::

        F = 3 mu0 / (4 pi r^5) [(m1.d) m2 + (m2.d) m1 + (m1.m2) d - 5 (m1.d)(m2.d) d / r^2]
    """
    r2 = _r2(d, softening, min_distance)
    inv_r2 = 1.0 / r2
    k = 3 * _K * inv_r2 * inv_r2 * inv_r2.sqrt()
    n1 = (m1 * d).sum(-1, keepdim=True)
    n2 = (m2 * d).sum(-1, keepdim=True)
    c = (m1 * m2).sum(-1, keepdim=True)
    return k[..., None] * (n1 * m2 + n2 * m1 + c * d - 5 * n1 * n2 * inv_r2[..., None] * d)


def dipole_force(d: Tensor, m_source: Tensor, m_target: Tensor, **kw) -> Tensor:
    """Force on ``m_target`` at displacement ``d`` from the source dipole ``m_source``: ``dB^T m_target``."""
    return force_from_gradient(m_target, dipole_field_gradient(d, m_source, **kw))


def gradient_to_five(dB: Tensor) -> Tensor:
    """The five independent terms (..., 5) ``[Bxx, Bxy, Bxz, Byy, Byz]`` of a gradient (..., 3, 3)."""
    return torch.stack([dB[..., 0, 0], dB[..., 0, 1], dB[..., 0, 2], dB[..., 1, 1], dB[..., 1, 2]], -1)


def five_to_gradient(g: Tensor) -> Tensor:
    """The symmetric, traceless gradient (..., 3, 3) from its five independent terms (..., 5)."""
    gxx, gxy, gxz, gyy, gyz = g.unbind(-1)
    rows = [torch.stack([gxx, gxy, gxz], -1), torch.stack([gxy, gyy, gyz], -1),
            torch.stack([gxz, gyz, -gxx - gyy], -1)]
    return torch.stack(rows, -2)


def force_map(m: Tensor) -> Tensor:
    """The 3x5 map ``M(m)`` (..., 3, 5) with ``F = M(m) g`` for the five gradient terms ``g``."""
    mx, my, mz = m.unbind(-1)
    z = torch.zeros_like(mx)
    rows = [torch.stack([mx, my, mz, z, z], -1), torch.stack([z, mx, z, my, mz], -1),
            torch.stack([-mz, z, mx, -mz, my], -1)]
    return torch.stack(rows, -2)
