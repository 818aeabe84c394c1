"""Collections of point dipoles as field sources (superposition), fast for many sources x points.

:class:`DipoleSet` sums the fields of S dipoles at P field points. Rather than materialising the
(P, S, 3) displacements, every pairwise quantity is reduced to (P, S) scalars obtained by matrix
products, e.g. with ``d = x - s``::

    sum_s a_ps d_ps = x_p sum_s a_ps - (a @ s)_p

so the work is a handful of (P, S) elementwise operations plus small matmuls. Coordinates are
taken relative to the sources' centroid, which keeps the cancellation error of this form at
``eps * |x - c| / r`` (harmless unless a field point is much closer to one dipole than to the
centroid; the dipole grids of permanent magnets are never evaluated inside the magnet).
"""
from __future__ import annotations

import torch
from torch import Tensor

from .base import FieldModel, check_points
from .dipole import MU0, check_distances, check_lengths

__all__ = ["DipoleSet"]

_K = MU0 / (4 * torch.pi)
_CHUNK_ELEMENTS = 1 << 16  # (points x sources) per chunk: keeps the (P, S) temporaries in cache (~0.5 MB)


class DipoleSet(FieldModel):
    """S point dipoles at ``positions`` (..., S, 3) with ``moments`` (..., S, 3) (A m^2).

    ``softening`` (m) regularises ``r^2 -> r^2 + eps^2``; a field point closer than ``min_distance`` to a
    dipole (the true distance, softened or not) raises ``ValueError``, and without softening one at a dipole
    (see :mod:`physics.magnetics.dipole`).
    """

    def __init__(self, positions: Tensor, moments: Tensor, *, softening: float = 0.0, min_distance: float = 0.0):
        positions = torch.as_tensor(positions)
        if not positions.is_floating_point():  # whole-number coordinates written as integers
            positions = positions.to(torch.get_default_dtype())
        positions = check_points(positions, "positions")
        moments = torch.as_tensor(moments, dtype=positions.dtype, device=positions.device)
        if moments.shape[-1:] != (3,) or moments.shape[-2:-1] != positions.shape[-2:-1]:
            raise ValueError(f"moments must have shape (..., S, 3) matching positions {tuple(positions.shape)}, "
                             f"got {tuple(moments.shape)}")
        if not bool(torch.isfinite(moments).all()):
            raise ValueError("moments must be finite")
        check_lengths(softening, min_distance)
        self.positions, self.moments = positions, moments
        self.softening, self.min_distance = float(softening), float(min_distance)

    @property
    def count(self) -> int:
        return self.positions.shape[-2]

    @property
    def total_moment(self) -> Tensor:
        return self.moments.sum(-2)

    def to(self, dtype=None, device=None) -> "DipoleSet":
        return DipoleSet(self.positions.to(dtype=dtype, device=device), self.moments.to(dtype=dtype, device=device),
                         softening=self.softening, min_distance=self.min_distance)

    def transformed(self, R: Tensor, p: Tensor) -> "DipoleSet":
        """The set after the rigid motion ``x -> R x + p`` (moments rotate with it); differentiable."""
        R = torch.as_tensor(R, dtype=self.positions.dtype, device=self.positions.device)
        p = torch.as_tensor(p, dtype=self.positions.dtype, device=self.positions.device)
        pos = (R[..., None, :, :] @ self.positions[..., None]).squeeze(-1) + p[..., None, :]
        mom = (R[..., None, :, :] @ self.moments[..., None]).squeeze(-1)
        return DipoleSet(pos, mom, softening=self.softening, min_distance=self.min_distance)

    # --- pairwise scalars --------------------------------------------------------------------------------
    def _pairs(self, x: Tensor):
        """Centred points x (..., P, 3), sources s, moments m, and (P, S) ``r^-2``, ``r^-3``, ``m.d``.

        ``r^2`` and ``m.d`` come out of one small matmul each on augmented coordinates
        (``[x, |x|^2, 1] . [-2 s, 1, |s|^2]`` and ``[x, 1] . [m, -s.m]``), so that each (P, S) array is
        touched only a few times."""
        c = self.positions.detach().mean(-2, keepdim=True)
        s, m = self.positions - c, self.moments
        x = x - c
        one_x = torch.ones_like(x[..., :1])
        one_s = torch.ones_like(s[..., :1])
        s2 = (s * s).sum(-1, keepdim=True) + self.softening ** 2
        X = torch.cat([x, (x * x).sum(-1, keepdim=True), one_x], -1)
        r2 = X @ torch.cat([-2 * s, one_s, s2], -1).transpose(-1, -2)
        if self.softening == 0:
            check_distances(r2, self.min_distance)
        elif self.min_distance > 0:  # on the true distance: softening no longer switches min_distance off
            check_distances(r2 - self.softening ** 2, self.min_distance)
        md = torch.cat([x, one_x], -1) @ torch.cat([m, -(s * m).sum(-1, keepdim=True)], -1).transpose(-1, -2)
        inv_r = torch.rsqrt(r2)
        inv_r2 = inv_r * inv_r
        return x, s, m, inv_r2, inv_r2 * inv_r, md

    def _chunked(self, points: Tensor, fn):
        points = check_points(points)
        points = points.to(dtype=self.positions.dtype, device=self.positions.device)
        P = points.shape[-2]
        step = max(1, _CHUNK_ELEMENTS // max(1, self.count))
        if P <= step:
            return fn(points)
        outs = [fn(points[..., i:i + step, :]) for i in range(0, P, step)]
        if isinstance(outs[0], tuple):
            return tuple(torch.cat(o, dim=-2 - k) for k, o in enumerate(zip(*outs)))  # B (..., P, 3), dB (..., P, 3, 3)
        return torch.cat(outs, dim=-2)

    # --- field, gradient, wrench -----------------------------------------------------------------------
    def field(self, points: Tensor) -> Tensor:
        """B (..., P, 3) at ``points`` (..., P, 3)."""
        return self._chunked(points, self._field)

    def _field(self, points):
        x, s, m, inv_r2, inv_r3, md = self._pairs(points)
        a = (md * inv_r3) * inv_r2  # (m.d) / r^5
        a1s = a @ torch.cat([torch.ones_like(s[..., :1]), s], -1)  # [sum_s a, sum_s a s]
        return _K * (3 * (x * a1s[..., :1] - a1s[..., 1:]) - inv_r3 @ m)

    def field_and_gradient(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """B (..., P, 3) and ``dB_i/dx_j`` (..., P, 3, 3)."""
        return self._chunked(points, self._field_and_gradient)

    def _field_and_gradient(self, points):
        x, s, m, inv_r2, inv_r3, md = self._pairs(points)
        k = 3 * inv_r2 * inv_r3  # 3 / r^5
        a = md * k
        B = _K * (x * a.sum(-1, keepdim=True) - a @ s - inv_r3 @ m)
        S = s.shape[-2]
        ms = (m[..., :, None] * s[..., None, :]).reshape(*s.shape[:-2], S, 9)
        ss = (s[..., :, None] * s[..., None, :]).reshape(*s.shape[:-2], S, 9)
        km = k @ m
        kms = (k @ ms).unflatten(-1, (3, 3))
        # sum_s k m_i d_j, symmetrised, plus the trace term
        T = km[..., :, None] * x[..., None, :] - kms
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        G = T + T.transpose(-1, -2) + a.sum(-1)[..., None, None] * eye
        # - sum_s c d_i d_j with c = 5 k (m.d) / r^2
        c = 5 * a * inv_r2
        cs = c @ s
        xx = x[..., :, None] * x[..., None, :]
        G = G - (c.sum(-1)[..., None, None] * xx - x[..., :, None] * cs[..., None, :] - cs[..., :, None] * x[..., None, :]
                 + (c @ ss).unflatten(-1, (3, 3)))
        return B, _K * G

    def force_torque(self, points: Tensor, moments: Tensor) -> tuple[Tensor, Tensor]:
        """Force ``grad(m . B)`` and torque ``m x B`` (each (..., P, 3)) on dipoles ``moments`` at ``points``;
        the force by the dipole-dipole formula, without forming the gradient."""
        points = check_points(points).to(dtype=self.positions.dtype, device=self.positions.device)
        moments = torch.as_tensor(moments, dtype=points.dtype, device=points.device)
        points, moments = torch.broadcast_tensors(points, moments)
        step = max(1, _CHUNK_ELEMENTS // max(1, self.count))
        parts = [self._wrench(points[..., i:i + step, :], moments[..., i:i + step, :])
                 for i in range(0, max(1, points.shape[-2]), step)]  # one (empty) chunk for no points
        return torch.cat([f for f, _ in parts], -2), torch.cat([t for _, t in parts], -2)

    def _wrench(self, points, mt):
        x, s, m, inv_r2, inv_r3, md = self._pairs(points)
        k = 3 * inv_r2 * inv_r3
        a = md * k
        B = _K * (x * a.sum(-1, keepdim=True) - a @ s - inv_r3 @ m)
        mtd = (mt * x).sum(-1, keepdim=True) - mt @ s.transpose(-1, -2)  # (P, S): m_t . d
        e = k * (mt @ m.transpose(-1, -2)) - 5 * a * mtd * inv_r2
        F = _K * (mt * a.sum(-1, keepdim=True) + (k * mtd) @ m + x * e.sum(-1, keepdim=True) - e @ s)
        return F, torch.linalg.cross(mt, B, dim=-1)
