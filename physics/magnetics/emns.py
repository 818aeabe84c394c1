"""Electromagnetic navigation systems (eMNS): stationary coils, their unit-current field and gradient
maps, the actuation matrix, and current allocation under current limits (Paper II, thesis II.5.2).

Each of the C coils has a unit-current field map ``beta_i(p)`` (3) and gradient map
``beta_grad_i(p)`` (3x3) (:meth:`EMNS.unit_field_and_gradient`). By superposition the field and the
five independent gradient terms ``G(dB) = [Bxx, Bxy, Bxz, Byy, Byz]`` at a point are linear in the
currents ``I`` (C,)::

    [B; G(dB)] = A(p) I,    A(p) = [[beta_1 ... beta_C]; [G(beta_grad_1) ... G(beta_grad_C)]]   (8 x C)

and the force on a dipole ``m`` is ``M(m) G(dB)`` with the 3x5 map :func:`~.dipole.force_map`.

Current allocation (:func:`allocate_currents`, :meth:`EMNS.allocate`) solves, for requested rows
``y`` (field, gradient terms and/or forces at one or more points) with row weights ``w``::

    min_I ||w (A I - y)||^2 + lam^2 ||I||^2   subject to  |I_i| <= I_max,i

with ``lam = regularization * s_max(w A)``. Without binding limits this is the Tikhonov-filtered
pseudo-inverse (``regularization = 0``: the minimum-norm least-squares solution, which reproduces
any request in the range of ``A``). When that solution exceeds a limit, the bounded problem is solved
exactly: every assignment of the coils to {lower bound, free, upper bound} (3^C of them, batched) is
solved in closed form by pseudo-inverse and the feasible one with the least objective is kept (the
optimum is one of them); with more than :data:`MAX_ENUMERATED_COILS` coils scipy's bounded
least-squares (``lsq_linear``, float64 on the CPU) is used instead. In the bounded solve ``lam`` is at
least ``1e-9 s_max`` so that the solution is unique when ``A`` has a null space (6 coils, a field-only
request); the effect on the residual is ~1e-18 relative. Field rows are in T and gradient rows in
T/m, so a ``gradient_weight`` of a length (e.g. the workspace radius, 0.05 m) puts them on one scale.

Default geometry (:func:`six_coil_emns`; Paper II uses 6 stationary electromagnets around a 100 mm
spherical workspace [Sik+17] but gives no coil poses, so this is our choice). Three coils above and
three below the horizontal plane, at elevation +-45 deg and azimuths 0, 120, 240 deg (each lower coil
under an upper one), with their axes through the workspace centre: adjacent axes are 90 deg (above/
below) and 75.5 deg (same ring) apart. The arrangement of six coils on the faces of a cube (or any
with antiparallel axes, such as the octahedral two-ring arrangement at +-35.26 deg) has rank 5 at the
centre; this one has full rank 6 there (singular-value ratio 1/3 with gradient rows weighted by
0.05 m). Each electromagnet is an air-core coil of 1000 turns, mean radius 32.5 mm, winding
thickness 25 mm (20-45 mm), length 80 mm, centred 105 mm from the workspace centre (front face at
65 mm, 15 mm outside the workspace; every coil stays inside a 34.7 deg cone about its axis, so none
touch), modelled as 6 x 4 Gauss-Legendre loops (axial x radial); over the workspace this agrees with
a converged 64 x 16 discretisation to 5e-6 in B and 3e-5 in the gradient (relative, worst point;
4 x 4 loops: 5e-4 and 2e-3). Such a coil gives 0.65 mT/A at the centre; no iron core is modelled:
a cored electromagnet of this size (as in BigMag or OctoMag) gives roughly ten times more field per
ampere.
The default limit is 10 A per coil.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from .base import FieldModel, check_points
from .coils import CircularLoop, Coil, HelmholtzPair, check_current_batch, loop_field_per_amp
from .dipole import force_map, gradient_to_five

__all__ = ["EMNS", "Allocation", "allocate_currents", "six_coil_emns", "MAX_ENUMERATED_COILS"]

MAX_ENUMERATED_COILS = 8
_LAM_FLOOR = 1e-9  # relative Tikhonov floor of the bounded solve
_F64 = torch.float64


class Allocation(NamedTuple):
    """Result of a current allocation (leading dims ``...`` of the request; P points, R requested rows)."""

    currents: Tensor       # (..., C) A
    field: Tensor          # (..., P, 3) achieved B (T)
    gradient: Tensor       # (..., P, 5) achieved gradient terms [Bxx, Bxy, Bxz, Byy, Byz] (T/m)
    achieved: Tensor       # (..., R) achieved values of the requested rows
    residual: Tensor       # (..., R) achieved - requested
    residual_norm: Tensor  # (...,) weighted norm ||w (A I - y)||
    feasible: Tensor       # (...,) request met to tol within the limits
    limits_active: Tensor  # (...,) some coil at its limit
    at_limit: Tensor       # (..., C) which coils are at their limit


def _pinv_solve(M: Tensor, r: Tensor, lam: Tensor) -> Tensor:
    """Tikhonov-filtered pseudo-inverse solution (..., C) of ``M x = r`` (M (..., R, C), lam (...,))."""
    U, s, Vh = torch.linalg.svd(M, full_matrices=False)
    smax = s[..., :1]
    keep = s > smax * (max(M.shape[-2:]) * torch.finfo(M.dtype).eps)
    phi = torch.where(keep, s / (s * s + (lam[..., None] ** 2)).clamp_min(torch.finfo(M.dtype).tiny), 0.0)
    return (Vh.transpose(-1, -2) @ (phi * (U.transpose(-1, -2) @ r[..., None])[..., 0])[..., None])[..., 0]


def _bounded_enumerate(M: Tensor, y: Tensor, lam: Tensor, imax: Tensor) -> Tensor:
    """Exact box-constrained Tikhonov least squares by enumerating the 3^C active sets; M (N, R, C)."""
    N, R, C = M.shape
    pats = torch.tensor(list(itertools.product((-1.0, 0.0, 1.0), repeat=C)), dtype=M.dtype, device=M.device)
    free = pats == 0  # (S, C)
    eye = torch.eye(C, dtype=M.dtype, device=M.device)
    chunk = max(1, 2 ** 22 // (len(pats) * (R + C) * C))  # bounds the (chunk, S, R + C, C) work arrays
    out = []
    for k in range(0, N, chunk):
        Mk, yk, lk, ik = M[k:k + chunk], y[k:k + chunk], lam[k:k + chunk], imax[k:k + chunk]
        Ma = torch.cat([Mk, lk[:, None, None] * eye], -2)  # (n, R + C, C)
        ya = torch.cat([yk, torch.zeros_like(yk[:, :1]).expand(-1, C)], -1)
        v = torch.where(free, 0.0, pats * ik[:, None, :])  # (n, S, C): fixed values, 0 where free
        r = ya[:, None, :] - (Ma[:, None] @ v[..., None])[..., 0]
        x = _pinv_solve(Ma[:, None] * free[:, None, :], r, torch.zeros_like(r[..., 0])) * free + v
        obj = ((Ma[:, None] @ x[..., None])[..., 0] - ya[:, None, :]).pow(2).sum(-1)
        ok = (x.abs() <= ik[:, None, :] * (1 + 1e-9)).all(-1)
        best = torch.where(ok, obj, math.inf).argmin(-1)
        out.append(x[torch.arange(len(best), device=M.device), best])
    x = torch.cat(out)
    return torch.maximum(torch.minimum(x, imax), -imax)


def _bounded_scipy(M: Tensor, y: Tensor, lam: Tensor, imax: Tensor) -> Tensor:
    from scipy.optimize import lsq_linear

    C = M.shape[-1]
    Mn, yn = M.reshape(-1, *M.shape[-2:]).cpu().numpy(), y.reshape(-1, y.shape[-1]).cpu().numpy()
    ln, bn = lam.reshape(-1).cpu().numpy(), imax.reshape(-1, C).cpu().numpy()
    out = np.empty((Mn.shape[0], C))
    for k in range(Mn.shape[0]):
        Ma = np.vstack([Mn[k], ln[k] * np.eye(C)])
        ya = np.concatenate([yn[k], np.zeros(C)])
        out[k] = lsq_linear(Ma, ya, bounds=(-bn[k], bn[k]), method="bvls", tol=1e-14).x
    return torch.as_tensor(out, dtype=M.dtype, device=M.device).reshape(*M.shape[:-2], C)


def allocate_currents(A: Tensor, y: Tensor, *, weights: Tensor | None = None, regularization: float = 0.0,
                      max_current=math.inf, method: str = "auto") -> tuple[Tensor, Tensor]:
    """Currents (..., C) minimising ``||w (A I - y)||^2 + lam^2 ||I||^2`` with ``|I| <= max_current``
    (module docstring), and the mask (..., C) of coils at their limit. ``A`` (..., R, C), ``y`` (..., R),
    ``weights`` (..., R) > 0, ``max_current`` > 0 (scalar or (..., C), ``inf`` for none); computed in
    float64 and returned in ``A``'s dtype. ``method``: "auto", "enumerate" or "scipy" (bounded solve)."""
    if A.dim() < 2 or y.shape[-1] != A.shape[-2]:
        raise ValueError(f"A must be (..., R, C) and y (..., R); got {tuple(A.shape)} and {tuple(y.shape)}")
    if method not in ("auto", "enumerate", "scipy"):
        raise ValueError(f"method must be 'auto', 'enumerate' or 'scipy', got {method!r}")
    reg = float(regularization)
    if not (math.isfinite(reg) and reg >= 0):
        raise ValueError(f"regularization must be finite and >= 0, got {regularization!r}")
    C = A.shape[-1]
    w = torch.ones_like(y) if weights is None else torch.as_tensor(weights, dtype=A.dtype, device=A.device)
    if not bool(torch.isfinite(A).all()):
        raise ValueError("A (the actuation matrix) must be finite")
    if not bool(torch.isfinite(y).all()):
        raise ValueError("the requested values must be finite")
    if not bool((torch.isfinite(w) & (w > 0)).all()):
        raise ValueError("weights must be finite and > 0")
    imax = torch.as_tensor(max_current, dtype=_F64, device=A.device)
    if (imax.dim() and imax.shape[-1] != C) or not bool((imax > 0).all()):
        raise ValueError(f"max_current must be > 0 (inf for no limit), a scalar or (..., {C}), got {max_current!r}")
    M = (w[..., None] * A).to(_F64)
    yw = (w * y).to(_F64)
    batch = torch.broadcast_shapes(M.shape[:-2], yw.shape[:-1], imax.shape[:-1])
    M, yw, imax = M.expand(*batch, *M.shape[-2:]), yw.expand(*batch, yw.shape[-1]), imax.expand(*batch, C)
    smax = torch.linalg.matrix_norm(M, ord=2) if M.numel() else torch.zeros(batch, dtype=_F64)
    I = _pinv_solve(M, yw, reg * smax)
    over = (I.abs() > imax * (1 + 1e-12)).any(-1)
    if bool(over.any()):
        lam_b = torch.maximum(reg * smax, _LAM_FLOOR * smax)[over]
        use_scipy = method == "scipy" or (method == "auto" and C > MAX_ENUMERATED_COILS)
        solve = _bounded_scipy if use_scipy else _bounded_enumerate
        I = I.clone()
        I[over] = solve(M[over], yw[over], lam_b, imax[over])
    at_limit = I.abs() >= imax * (1 - 1e-9)
    return I.to(A.dtype), at_limit


def _expands_to(shape, target) -> bool:
    """Whether a tensor of ``shape`` broadcasts to ``target`` (without growing it)."""
    return len(shape) <= len(target) and all(x in (1, y) for x, y in zip(reversed(shape), reversed(target)))


def _coil_loops(coils):
    cs, ns, rs, ws = [], [], [], []
    C = len(coils)
    for i, coil in enumerate(coils):
        c, n, r, t = coil.loops()
        cs.append(c), ns.append(n), rs.append(r)
        w = torch.zeros(len(r), C, dtype=_F64)
        w[:, i] = t
        ws.append(w)
    return torch.cat(cs), torch.cat(ns), torch.cat(rs), torch.cat(ws)


@dataclass(frozen=True, eq=False)
class EMNS(FieldModel):
    """Stationary coils driven by independent currents. ``coils``: :class:`~.coils.Coil`,
    :class:`~.coils.CircularLoop` or :class:`~.coils.HelmholtzPair` specs (their own ``current`` is
    ignored); ``currents`` (C,) or (..., C) A, the currents used by :meth:`field_and_gradient` (default
    zero); ``max_current`` (A) per coil (scalar or (C,)); ``min_distance`` as for the loops."""

    coils: Sequence
    currents: Tensor | Sequence[float] | None = None
    max_current: float | Sequence[float] = 10.0
    min_distance: float = 0.0

    def __post_init__(self):
        coils = tuple(self.coils)
        if not coils:
            raise ValueError("EMNS.coils must not be empty")
        for i, c in enumerate(coils):
            if not isinstance(c, (CircularLoop, HelmholtzPair)):
                raise TypeError(f"EMNS.coils[{i}] must be a Coil, CircularLoop or HelmholtzPair, "
                                f"got {type(c).__name__}")
        object.__setattr__(self, "coils", coils)
        C = len(coils)
        imax = torch.as_tensor(self.max_current, dtype=_F64)
        imax = imax.expand(C).clone() if imax.dim() == 0 else imax
        if imax.shape != (C,) or not bool((imax > 0).all()):
            raise ValueError(f"EMNS.max_current must be > 0, a scalar or ({C},), got {self.max_current!r}")
        object.__setattr__(self, "max_current", imax)
        if self.currents is not None:
            object.__setattr__(self, "currents", self._check_currents(self.currents, "EMNS.currents"))
        if not (math.isfinite(float(self.min_distance)) and float(self.min_distance) >= 0):
            raise ValueError(f"EMNS.min_distance must be finite and >= 0, got {self.min_distance!r}")
        object.__setattr__(self, "_loops", _coil_loops(coils))

    @property
    def n_coils(self) -> int:
        return len(self.coils)

    def _check_currents(self, I, name="currents") -> Tensor:
        I = I if isinstance(I, Tensor) else torch.as_tensor(I, dtype=_F64)
        if I.shape[-1:] != (self.n_coils,):
            raise ValueError(f"{name} must have shape (..., {self.n_coils}), got {tuple(I.shape)}")
        if not bool(torch.isfinite(I).all()):
            raise ValueError(f"{name} must be finite")
        return I

    def with_currents(self, currents) -> "EMNS":
        return replace(self, currents=currents, max_current=tuple(self.max_current.tolist()))

    def unit_field_and_gradient(self, points: Tensor, gradient: bool = True):
        """Unit-current maps: ``beta`` (..., P, C, 3) (T/A) and ``beta_grad`` (..., P, C, 3, 3) (T/(m A))."""
        c, n, r, w = self._loops
        return loop_field_per_amp(points, c, n, r, w, gradient=gradient, min_distance=self.min_distance)

    def actuation_matrix(self, points: Tensor) -> Tensor:
        """``A(p)`` (..., P, 8, C): rows ``[Bx, By, Bz, Bxx, Bxy, Bxz, Byy, Byz]`` per ampere of each coil."""
        B, dB = self.unit_field_and_gradient(points)
        return torch.cat([B, gradient_to_five(dB)], -1).transpose(-1, -2)

    def _I(self, points, currents):
        I = self.currents if currents is None else self._check_currents(currents)
        if I is None:
            I = torch.zeros(self.n_coils)
        check_current_batch(points, I, "currents" if currents is not None else "EMNS.currents")
        return I.to(dtype=points.dtype, device=points.device)[..., None, :]

    def field_and_gradient(self, points: Tensor, currents: Tensor | None = None):
        """B (..., P, 3) and dB (..., P, 3, 3) at ``points`` (..., P, 3) for ``currents`` (..., C) (default
        ``self.currents``); the currents' batch dims broadcast against the points' (all but the last two)."""
        I = self._I(points, currents)
        B, dB = self.unit_field_and_gradient(points)
        return (B * I[..., None]).sum(-2), (dB * I[..., None, None]).sum(-3)

    def field(self, points: Tensor, currents: Tensor | None = None) -> Tensor:
        I = self._I(points, currents)
        return (self.unit_field_and_gradient(points, gradient=False)[0] * I[..., None]).sum(-2)

    def allocate(self, points: Tensor, field: Tensor | None = None, gradient: Tensor | None = None,
                 force: Tensor | None = None, moment: Tensor | None = None, *, field_weight=1.0,
                 gradient_weight=1.0, force_weight=1.0, regularization: float = 0.0, max_current=None,
                 tol: float = 1e-6, method: str = "auto") -> Allocation:
        """Currents for a requested ``field`` (..., P, 3) (T), ``gradient`` terms (..., P, 5) (T/m) and/or
        ``force`` (..., P, 3) (N) on dipoles ``moment`` (..., P, 3) (A m^2) at ``points`` (..., P, 3).

        Rows are stacked per point (field, gradient, force) and weighted by the ``*_weight`` weights (> 0): a
        scalar, one per row ((3,) for the field, (5,) for the gradient) or one per point and row ((..., P, 3),
        broadcast against the request like ``field``); ``max_current`` defaults to the system's limits.
        ``feasible`` is ``residual_norm <= tol * ||w y||`` (the request is met within the limits; ``tol`` >= 0)."""
        check_points(points)
        if field is None and gradient is None and force is None:
            raise ValueError("request at least one of field, gradient or force")
        if (force is None) != (moment is None):
            raise ValueError("force and moment must be given together")
        try:
            tol_ok = not isinstance(tol, bool) and math.isfinite(float(tol)) and float(tol) >= 0
        except (TypeError, ValueError):
            tol_ok = False
        if not tol_ok:  # a negative or NaN tol made every allocation infeasible
            raise ValueError(f"tol must be a finite relative residual >= 0, got {tol!r}")
        A = self.actuation_matrix(points)  # (..., P, 8, C)
        rows, ys, ws = [], [], []
        kw = dict(dtype=points.dtype, device=points.device)

        def weight(name, wt, k):
            wt = torch.as_tensor(wt, **kw)
            if wt.dim() and wt.shape[-1] not in (1, k):
                raise ValueError(f"{name} must be a scalar, one weight per row ({k},) or one per point and row "
                                 f"(..., P, {k}), got shape {tuple(wt.shape)}")
            if not bool((torch.isfinite(wt) & (wt > 0)).all()):
                raise ValueError(f"{name} (the rows' weights) must be finite and > 0")
            return (name, wt.expand(*wt.shape[:-1], k) if wt.dim() else wt.expand(k))

        for name, val, Ar, wt, k in (("field", field, A[..., :3, :], field_weight, 3),
                                     ("gradient", gradient, A[..., 3:, :], gradient_weight, 5)):
            if val is not None:
                val = torch.as_tensor(val, **kw)
                if val.shape[-1:] != (k,):
                    raise ValueError(f"{name} must have shape (..., P, {k}), got {tuple(val.shape)}")
                rows.append(Ar), ys.append(val), ws.append(weight(f"{name}_weight", wt, k))
        if force is not None:
            force, moment = torch.as_tensor(force, **kw), torch.as_tensor(moment, **kw)
            if force.shape[-1:] != (3,) or moment.shape[-1:] != (3,):
                raise ValueError(f"force and moment must have shape (..., P, 3), got {tuple(force.shape)}, "
                                 f"{tuple(moment.shape)}")
            if not bool(torch.isfinite(moment).all()):
                raise ValueError("moment must be finite")
            rows.append(force_map(moment) @ A[..., 3:, :]), ys.append(force)
            ws.append(weight("force_weight", force_weight, 3))
        batch = torch.broadcast_shapes(*(r.shape[:-2] for r in rows), *(v.shape[:-1] for v in ys))
        for name, wt in ws:  # per-point weights follow the request's points; they add no batch of their own
            if not _expands_to(wt.shape[:-1], batch):
                raise ValueError(f"{name} of shape {tuple(wt.shape)} does not broadcast against the request's "
                                 f"(..., P, rows) = {(*batch, wt.shape[-1])}: give one weight per row "
                                 f"({wt.shape[-1]},) or one per point and row (..., P, {wt.shape[-1]})")
        Ar = torch.cat([r.expand(*batch, *r.shape[-2:]) for r in rows], -2)  # (..., P, R1, C)
        y = torch.cat([v.expand(*batch, v.shape[-1]) for v in ys], -1)
        w = torch.cat([wt.expand(*batch, wt.shape[-1]) for _, wt in ws], -1)
        Af, yf, wf = Ar.flatten(-3, -2), y.flatten(-2), w.flatten(-2)
        imax = self.max_current if max_current is None else max_current
        I, at_limit = allocate_currents(Af, yf, weights=wf, regularization=regularization, max_current=imax,
                                        method=method)
        achieved = (Af @ I[..., None])[..., 0]
        res = achieved - yf
        rnorm = (wf * res).norm(dim=-1)
        feasible = rnorm <= tol * (wf * yf).norm(dim=-1)
        Ib = I[..., None, :, None]
        return Allocation(I, (A[..., :3, :] @ Ib)[..., 0], (A[..., 3:, :] @ Ib)[..., 0], achieved, res, rnorm,
                          feasible, at_limit.any(-1), at_limit)


def six_coil_emns(*, elevation_deg: float = 45.0, distance: float = 0.105, radius: float = 0.0325,
                  thickness: float = 0.025, length: float = 0.08, turns: float = 1000.0, max_current: float = 10.0,
                  n_axial: int = 6, n_radial: int = 4, currents=None) -> EMNS:
    """The default six-coil eMNS around a 100 mm spherical workspace (module docstring): coils at
    elevation +-``elevation_deg`` and azimuths 0/120/240 deg, centred ``distance`` from the origin,
    axes pointing at the origin (a positive current gives a field towards the origin)."""
    coils = []
    for s in (1.0, -1.0):
        for k in range(3):
            phi, th = math.radians(120.0 * k), s * math.radians(elevation_deg)
            u = (math.cos(th) * math.cos(phi), math.cos(th) * math.sin(phi), math.sin(th))
            coils.append(Coil(radius, turns=turns, centre=tuple(distance * x for x in u), axis=tuple(-x for x in u),
                              length=length, thickness=thickness, n_axial=n_axial, n_radial=n_radial))
    return EMNS(coils, currents=currents, max_current=max_current)
