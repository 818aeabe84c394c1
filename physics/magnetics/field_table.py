"""Tabulated coil fields: an eMNS's unit-current field and gradient maps inside a ball, interpolated from
tables of the exact loop superposition, for closed loops that evaluate the field at every step.

Each coil of an :class:`~.emns.EMNS` is a set of coaxial loops, so its unit-current field is axisymmetric
about the coil axis: in the coil's cylindrical coordinates (``z`` along the unit axis ``n`` from a point
``c0`` on it, ``r = d - z n`` the radial vector, ``rho = |r|``, ``e = r / rho``)::

    beta = f r + g n,
    d beta = f (1 - n n^T) + (rho f_rho) e e^T + (rho f_z) e n^T + g_rho n e^T + g_z n n^T

with six scalar functions of ``(z, rho)`` only (the same decomposition as the exact loop kernel in
:mod:`.coils`). :class:`CoilFieldTable` tabulates those six on a uniform ``(z, rho)`` grid covering a
ball (``centre``, ``radius``), from the exact field of the loops at the grid points with ``rho`` signed
along one radial direction (so each function's parity in ``rho`` is in the table and a stencil at the
axis needs no special case), and interpolates them by tensor-product Lagrange polynomials of ``order``
points per axis. Coils with the same loops about the ball (the six of :func:`~.emns.six_coil_emns`) share
one table. A 2-D table is small (1 mm spacing over a 50 mm ball: 107 x 57 nodes, built in about 0.3 s),
and an evaluation is a fixed sequence of about thirty tensor operations with no data-dependent control
flow, so it also runs in programs compiled ahead of time. Over the default eMNS's workspace, at order 6,
it agrees with the exact superposition to 2.5e-9 of the field and 1.4e-8 of the gradient with a 1 mm grid
(4e-11 and 2e-10 with 0.5 mm; relative, worst at 50 mm from the centre), at a fifth of its eager cost
for two points (``scripts/report_field_table.py``, ``docs/field_table.md``; tests).

Outside the ball the tables do not hold: :meth:`CoilFieldTable.unit_field_and_gradient` raises for such a
point, and a compiled caller checks :meth:`CoilFieldTable.outside` afterwards.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .base import FieldModel, check_points
from .coils import check_current_batch, loop_field_per_amp

__all__ = ["CoilFieldTable"]

_F64 = torch.float64


def _perpendicular(n: Tensor) -> Tensor:
    """A unit vector normal to the unit vector ``n`` (3,)."""
    a = torch.zeros(3, dtype=n.dtype)
    a[int(n.abs().argmin())] = 1.0
    e = a - (a @ n) * n
    return e / e.norm()


class CoilFieldTable(FieldModel):
    """Unit-current maps of an eMNS's coils inside the ball ``|p - centre| <= radius``, interpolated (module
    docstring). Build with :meth:`from_emns`; the same interface as :class:`~.emns.EMNS` for the field
    (``unit_field_and_gradient``, ``field_and_gradient(points, currents)``, ``field``)."""

    def __init__(self, origins: Tensor, axes: Tensor, group: Tensor, tables: Tensor,
                 z0: float, spacing: float, order: int, centre: Tensor, radius: float, currents: Tensor | None):
        self.origins, self.axes, self.group = origins, axes, group  # (C, 3), (C, 3), (C,)
        self.tables = tables  # (n_tables, Nz, Nrho, 6): f, g, rho f_rho, rho f_z, g_rho, g_z
        self.spacing, self.order = spacing, order
        self.centre, self.radius, self.currents = centre, radius, currents
        self._first = torch.tensor([z0, -(order // 2) * spacing], dtype=_F64)  # the grid's first (z, rho) node
        self._flat = tables.reshape(tables.shape[0], -1, 6)  # (n_tables, Nz * Nrho, 6), z-major
        self._steps = torch.arange(order)
        self._nodes = self._steps.to(_F64)
        diff = self._nodes[:, None] - self._nodes[None, :]
        self._off_diagonal = ~torch.eye(order, dtype=torch.bool)
        self._denom = torch.where(self._off_diagonal, diff, 1.0).prod(-1)  # (order,)
        self._eye = torch.eye(3, dtype=_F64)
        self._last = torch.tensor([tables.shape[1] - order, tables.shape[2] - order], dtype=_F64)  # last stencil start

    @property
    def n_coils(self) -> int:
        return self.origins.shape[0]

    @classmethod
    def from_emns(cls, emns, radius: float = 0.05, centre=(0.0, 0.0, 0.0), spacing: float = 1e-3,
                  order: int = 6) -> "CoilFieldTable":
        """Tables of ``emns``'s coils over the ball of ``radius`` (m) about ``centre``, grid ``spacing`` (m),
        ``order`` interpolation points per axis (even, >= 2). The ball must keep clear of every wire (the
        exact field raises otherwise); ``emns.currents`` are the default currents."""
        if not (math.isfinite(radius) and radius > 0):
            raise ValueError(f"radius must be finite and > 0 (m), got {radius!r}")
        if not (math.isfinite(spacing) and 0 < spacing < radius):
            raise ValueError(f"spacing must be finite, > 0 and < radius (m), got {spacing!r}")
        if isinstance(order, bool) or not isinstance(order, int) or order < 2 or order % 2:
            raise ValueError(f"order must be an even integer >= 2, got {order!r}")
        o = torch.as_tensor(centre, dtype=_F64)
        if o.shape != (3,) or not bool(torch.isfinite(o).all()):
            raise ValueError(f"centre must be 3 finite coordinates, got {centre!r}")
        pad = order // 2
        keys, tables, origins, axes, group = [], [], [], [], []
        for i, coil in enumerate(emns.coils):
            c, n, a, w = coil.loops()
            n = n / n.norm(dim=-1, keepdim=True)
            if not bool(torch.allclose(n, n[:1].expand_as(n), atol=1e-12)):
                raise ValueError(f"coils[{i}]: its loops are not coaxial; a table needs an axisymmetric coil")
            n = n[0]
            c0 = c[0] + ((o - c[0]) @ n) * n  # the ball centre's foot on the axis
            off = c - c0
            z_l = off @ n
            if float((off - z_l[:, None] * n).norm(dim=-1).max()) > 1e-9 * float(a.max()):
                raise ValueError(f"coils[{i}]: its loop centres are not on one axis")
            rho_o = float((o - c0).norm())  # the ball centre's distance from the axis (0 for the default eMNS)
            key = (round(rho_o / spacing, 6), tuple(torch.stack([z_l, a, w], -1).flatten().round(decimals=12).tolist()))
            if key not in keys:
                keys.append(key)
                tables.append((c0, n, c, a, w, rho_o))
            origins.append(c0), axes.append(n), group.append(keys.index(key))
        nz = int(math.ceil(2 * radius / spacing)) + 2 * pad + 1
        nr = int(math.ceil((max(t[5] for t in tables) + radius) / spacing)) + 2 * pad + 1
        z = -radius - pad * spacing + spacing * torch.arange(nz, dtype=_F64)
        rho = -pad * spacing + spacing * torch.arange(nr, dtype=_F64)
        built = []
        for c0, n, c, a, w, _ in tables:
            e = _perpendicular(n)
            zz, rr = torch.meshgrid(z, rho, indexing="ij")
            pts = c0 + zz[..., None] * n + rr[..., None] * e  # signed rho along e
            B, dB = loop_field_per_amp(pts.reshape(-1, 3), c, n.expand_as(c), a, w[:, None])
            B, dB = B[:, 0], dB[:, 0]
            e2 = torch.linalg.cross(n, e, dim=-1)
            quad = lambda u, v: torch.einsum("i,pij,j->p", u, dB, v)  # noqa: E731
            f = quad(e2, e2)
            built.append(torch.stack([f, B @ n, quad(e, e) - f, quad(e, n), quad(n, e), quad(n, n)], -1)
                         .reshape(nz, nr, 6))
        currents = None if emns.currents is None else torch.as_tensor(emns.currents, dtype=_F64)
        return cls(torch.stack(origins), torch.stack(axes), torch.tensor(group),
                   torch.stack(built), float(z[0]), spacing, order, o, float(radius), currents)

    def outside(self, points: Tensor) -> Tensor:
        """Mask (...,) of points (..., 3) beyond the tabulated ball (to 1e-9 of its radius)."""
        return (points - self.centre.to(points)).norm(dim=-1) > self.radius * (1 + 1e-9)

    def unit_field_and_gradient(self, points: Tensor, gradient: bool = True, check: bool = True):
        """Unit-current maps ``beta`` (..., P, C, 3) (T/A) and ``beta_grad`` (..., P, C, 3, 3) (T/(m A)) at
        ``points`` (..., P, 3) in the tabulated ball (``check``: raise for a point outside; pass False in
        programs compiled ahead of time, which check :meth:`outside` themselves). Computed in float64 and returned
        in the points' dtype, as the exact eMNS. The maps' values hold on a coil's axis too, but not autograd
        through ``beta_grad`` there (the tabulated rho f_z and g_rho multiply the undefined radial direction); the
        exact coils' gradient is differentiable everywhere."""
        beta, grad = self._maps(points, gradient, check)
        return beta.to(points.dtype), (None if grad is None else grad.to(points.dtype))

    def _maps(self, points: Tensor, gradient: bool, check: bool):
        """:meth:`unit_field_and_gradient` in float64."""
        if check:
            check_points(points)
            bad = self.outside(points)
            if bool(bad.any()):
                i = tuple(int(j) for j in bad.nonzero()[0])
                raise ValueError(f"points{list(i)} lies {float((points[i] - self.centre.to(points)).norm()):.4g} m "
                                 f"from the centre of the tabulated ball of radius {self.radius:.4g} m")
        n = self.axes
        d = points.to(_F64)[..., :, None, :] - self.origins  # (..., P, C, 3)
        z = (d * n).sum(-1)
        r = d - z[..., None] * n
        rho = r.norm(dim=-1)
        q = self._interpolate(torch.stack([z, rho], -1))  # (..., P, C, 6)
        beta = q[..., :1] * r + q[..., 1:2] * n
        if not gradient:
            return beta, None
        # on the axis e is zero, and so are the three functions it multiplies
        u = torch.stack([r / rho.clamp_min(1e-300)[..., None], n.expand_as(r)], -2)  # (..., 2, 3): e, n
        outer = (u[..., :, None, :, None] * u[..., None, :, None, :]).flatten(-4, -3)  # (..., 4, 3, 3): ee en ne nn
        coef = torch.cat([q[..., 2:5], q[..., 5:] - q[..., :1]], -1)
        grad = (coef[..., None, None] * outer).sum(-3) + q[..., :1, None] * self._eye
        return beta, grad

    def _interpolate(self, zr: Tensor) -> Tensor:
        """The six tabulated functions (..., 6) at coil coordinates ``zr`` = (z, rho) (..., 2) of each coil (dim
        -2: C): tensor-product Lagrange interpolation on the ``order`` x ``order`` grid nodes around the point."""
        k = self.order
        u = (zr - self._first) / self.spacing
        i = u.floor() - (k // 2 - 1)  # the stencil's first nodes
        # kept inside the table (a point beyond it, or NaN, gets some value, never a read out of bounds)
        i = torch.where(i <= self._last, i, self._last)
        i = torch.where(i >= 0, i, 0.0)
        diff = (u - i)[..., None] - self._nodes  # (..., 2, k)
        w = torch.where(self._off_diagonal, diff[..., None, :], 1.0).prod(-1) / self._denom  # (..., 2, k) Lagrange
        i = i.long()
        rows = (i[..., 0, None, None] + self._steps[:, None]) * self.tables.shape[2] + i[..., 1, None, None] \
            + self._steps  # (..., C, k, k)
        vals = self._flat[self.group[:, None], rows.flatten(-2)]  # (..., C, k * k, 6)
        return ((w[..., 0, :, None] * w[..., 1, None, :]).flatten(-2)[..., None, :] @ vals)[..., 0, :]

    def _I(self, points: Tensor, currents, check: bool = True) -> Tensor:
        I = self.currents if currents is None else currents
        if I is None:
            I = torch.zeros(self.n_coils)
        I = I if isinstance(I, Tensor) else torch.as_tensor(I, dtype=_F64)  # a list: float64, not the default dtype
        if I.shape[-1:] != (self.n_coils,):
            raise ValueError(f"currents must have shape (..., {self.n_coils}), got {tuple(I.shape)}")
        check_current_batch(points, I)  # shapes only: also unchecked (check=False, compiled programs)
        if check and not bool(torch.isfinite(I).all()):
            raise ValueError("currents must be finite")
        return I.to(_F64)[..., None, :]

    def field_and_gradient(self, points: Tensor, currents: Tensor | None = None, check: bool = True):
        """B (..., P, 3) and dB (..., P, 3, 3) at ``points`` (..., P, 3) for ``currents`` (..., C) (default: the
        eMNS's; their batch dims broadcast against the points' (all but the last two)), computed in float64 and
        returned in the points' dtype."""
        I = self._I(points, currents, check)
        beta, grad = self._maps(points, True, check)
        return (beta * I[..., None]).sum(-2).to(points.dtype), (grad * I[..., None, None]).sum(-3).to(points.dtype)

    def field(self, points: Tensor, currents: Tensor | None = None) -> Tensor:
        I = self._I(points, currents)
        return (self._maps(points, False, True)[0] * I[..., None]).sum(-2).to(points.dtype)
