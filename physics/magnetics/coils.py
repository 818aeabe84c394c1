"""Air-core coils: exact circular current loops, multi-turn coils, Helmholtz pairs, and the two
nested orthogonal Helmholtz pairs of Paper I that generate uniform and rotating fields.

Circular loop (radius ``a``, current ``I``, unit axis ``n``, centre ``c``). For a field point with
axial coordinate ``z = (p - c) . n`` and radial vector ``r = (p - c) - z n`` (``rho = |r|``), in
units of ``a``: ``beta^2 = (1 + rho)^2 + z^2``, ``alpha^2 = (1 - rho)^2 + z^2`` (``a alpha`` is the
distance to the wire), ``m = 4 rho / beta^2 = 1 - alpha^2/beta^2``. The exact Biot-Savart field is

    B = mu0 I / (pi a beta alpha^2) [ z (4 G / beta^2) r / a + (E - 4 rho^2 G / beta^2) n ]

with the complete elliptic integrals ``K(m)``, ``E(m)`` (parameter ``m = k^2``, scipy's
convention) and ``G(m) = (K - (2 - m) (K - E)/m) / m`` (``G(0) = 3 pi / 16``, ``G(1) = 1``). This
is the textbook form ``B_rho = ... / rho [-K + (a^2 + rho^2 + z^2)/alpha^2 E]`` rearranged so that
nothing is divided by ``rho``: ``B_rho / rho`` is finite and smooth on the axis, and there is no
``K - E`` cancellation for small ``m`` (near the axis or far away). ``K``, ``E`` and ``G`` come from
one arithmetic-geometric-mean (AGM) recursion started at the complementary modulus
``k' = alpha / beta`` (never from ``1 - m``), with the series terms scaled by ``m^2`` so that
``(K - E)/m`` and ``G`` are evaluated without cancellation. The iteration count is chosen per call
from the smallest ``k'`` in the batch (:func:`agm_iterations`: 6-9 steps for points more than 1e-3 a
from the wire, 14 for ``k' = 1e-300``) and reaches machine precision; the recursion is plain torch,
batched and differentiable by autograd. On the axis (``rho = 0``) the closed form reduces
exactly to ``mu0 I a^2 / (2 (a^2 + z^2)^{3/2}) n``.

The gradient ``dB[..., i, j] = dB_i/dx_j`` is the exact derivative of the closed form, propagated in
forward mode by hand through the AGM (tangents in ``rho`` and ``z``, then the chain rule to Cartesian
axes; about twice the cost of the field); it is symmetric and traceless off the wire, agrees with
reverse-mode autograd of the field, and is itself differentiable. A point on the wire (distance to
the wire ``<= min_distance``, default 0) raises ``ValueError``: the field is singular there.

Coils. A :class:`Coil` is a winding pack of mean radius ``radius``, axial ``length`` and radial
``thickness`` carrying ``turns`` turns with uniform turn density over its rectangular cross-section,
modelled as ``n_axial x n_radial`` coaxial loops at the Gauss-Legendre nodes of the cross-section,
each carrying its quadrature weight of the turns (a thin coil is one loop). Gauss quadrature
converges fast while the field point is farther from the winding than the node spacing; close to
the winding use more loops (see :mod:`.emns` for a measured case). Every coil model is linear in
its current: ``unit_field_and_gradient`` is the field per ampere.

Paper I setup (thesis I.4.3; Figure I.12). Two nested pairs of Helmholtz coils, an outer pair on
E1 and a smaller inner pair on E2 inside it; the thesis gives a maximum field of 45 mT but no coil
dimensions. :class:`NestedHelmholtz` defaults to an outer pair of radius 0.25 m with 1250 turns per
coil and an inner pair of radius 0.12 m with 600 turns per coil, both 4.50 mT/A at the centre, so
45 mT needs 10 A; the inner coils (planes y = +-0.06 m, rings reaching |x| <= 0.12 m) fit between
the outer coils (planes x = +-0.125 m). Over a sphere of radius 30 mm
around the centre (the 60.55 mm rod of Paper I) the field of either pair deviates from its centre
value by less than 0.5 % (inner pair, (0.03/0.12)^4 scaling) and 0.02 % (outer pair).
"""
from __future__ import annotations

import functools
from abc import abstractmethod
import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .base import FieldModel, TimeVarying, check_points
from .dipole import MU0, dipole_torque, force_from_gradient
from .elliptic import _agm, agm_iterations
from .validate import positive as _positive, real as _real, vec3 as _vec3

__all__ = [
    "loop_field_per_amp", "loop_on_axis_field", "helmholtz_centre_field",
    "CircularLoop", "Coil", "HelmholtzPair", "NestedHelmholtz", "RotatingField", "paper1_rotating_field",
]


# ----------------------------------------------------------------------------- loops
def _loop_core(d: Tensor, n: Tensor, a: Tensor, n_iter: int, gradient: bool):
    """Field per ampere (..., 3) of loops of radius ``a`` (...), unit axis ``n`` (..., 3), at ``d = p - c``,
    and, if ``gradient``, its gradient (..., 3, 3) by forward-mode differentiation written out: each
    quantity ``x(rho, z)`` (in units of ``a``) carries ``dx = (dx/drho, dx/dz)`` (..., 2), and with
    ``B = f r + g n``, ``e = r / rho``::

        dB = f (1 - n n^T) + rho f_rho e e^T + rho f_z e n^T + g_rho n e^T + g_z n n^T,   g_rho = rho f_z
    """
    z = (d * n).sum(-1)
    rv = d - z[..., None] * n
    inv_a = 1.0 / a
    zh, uh = z * inv_a, (rv * rv).sum(-1) * inv_a * inv_a
    pos = uh > torch.finfo(d.dtype).tiny
    rh = torch.where(pos, torch.sqrt(torch.where(pos, uh, 1.0)), 0.0)  # no sqrt'(0) on the axis
    beta2 = (1 + rh) ** 2 + zh * zh
    alpha2 = (1 - rh) ** 2 + zh * zh
    m = 4 * rh / beta2
    kc = torch.sqrt(alpha2 / beta2)
    pref = (MU0 / math.pi) * inv_a / (torch.sqrt(beta2) * alpha2)
    X = lambda x: x[..., None]
    if gradient:
        zero = torch.zeros_like(rh)
        dbeta2 = torch.stack([2 * (1 + rh), 2 * zh], -1)
        dalpha2 = torch.stack([-2 * (1 - rh), 2 * zh], -1)
        dm = torch.stack([4 / beta2, zero], -1) - X(m / beta2) * dbeta2
        dkc = (dalpha2 - X(alpha2 / beta2) * dbeta2) / X(2 * beta2 * kc)
        K, U, dK, dU = _agm(kc, m, n_iter, dkc, dm)
    else:
        K, U, _, _ = _agm(kc, m, n_iter)
    Pe, Pg = 1 - 0.5 * m - m * m * U, 0.5 - (2 - m) * U
    E, G = K * Pe, K * Pg
    w = G / beta2
    fh, gh = 4 * pref * zh * w, pref * (E - 4 * uh * w)
    B = X(fh * inv_a) * rv + X(gh) * n
    if not gradient:
        return B, None
    dE = X(Pe) * dK - X(K) * (X(0.5 + 2 * m * U) * dm + X(m * m) * dU)
    dG = X(Pg) * dK + X(K) * (X(U) * dm - X(2 - m) * dU)
    dpref = -X(pref) * (dbeta2 / X(2 * beta2) + dalpha2 / X(alpha2))
    dw = (dG - X(w) * dbeta2) / X(beta2)
    dfh = 4 * (dpref * X(zh * w) + X(pref * zh) * dw)
    dfh = dfh + torch.stack([zero, 4 * pref * w], -1)
    duh = torch.stack([2 * rh, zero], -1)
    dgh = dpref * X(E - 4 * uh * w) + X(pref) * (dE - 4 * (duh * X(w) + X(uh) * dw))
    # to metres and Cartesian axes
    f = fh * inv_a
    rf_r, f_z = rh * dfh[..., 0] * inv_a, dfh[..., 1] * inv_a * inv_a  # rho f_rho, f_z
    g_z = dgh[..., 1] * inv_a
    e = rv / X(torch.where(pos, rh * a, 1.0))
    outer = lambda u, v: u[..., :, None] * v[..., None, :]
    nn = outer(n, n)
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    # the field is curl-free, g_rho = rho f_z: the mixed terms are f_z (r n^T + n r^T), written with r = rho e so
    # that their own derivatives (autograd of dB) hold on the axis too, where e is undefined
    dB = (X(X(f)) * (eye - nn) + X(X(rf_r)) * outer(e, e) + X(X(f_z)) * (outer(rv, n) + outer(n, rv))
          + X(X(g_z)) * nn)
    return B, dB


def _check_wire(d: Tensor, n: Tensor, a: Tensor, min_distance: float) -> int:
    """Raise if a point is on (within ``min_distance`` of) a wire; return the AGM iteration count."""
    with torch.no_grad():
        z = (d * n).sum(-1)
        rho = (d - z[..., None] * n).norm(dim=-1)
        dist2 = (rho - a) ** 2 + z * z
        bad = ~(dist2 > min_distance * min_distance)
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.nonzero()[0])
            raise ValueError(
                f"points: field point at distance {float(dist2[idx].sqrt()):.3e} m (<= min_distance "
                f"{min_distance:.3e} m) from the wire of loop {idx[-1]} (radius {float(a[idx[-1]]):.4g} m); the "
                "field of a current loop is singular on its wire")
        if dist2.numel() == 0:
            return 1
        kc_min = float((dist2 / ((rho + a) ** 2 + z * z)).min().sqrt())
        if not math.isfinite(kc_min):  # inf / inf
            raise ValueError(f"points: a field point is too far from the loops for {d.dtype} (up to "
                             f"{float(d.abs().max()):.3e} m: its squared distance overflows)")
    return agm_iterations(kc_min, d.dtype)


def loop_field_per_amp(points: Tensor, centres: Tensor, axes: Tensor, radii: Tensor, weights: Tensor | None = None,
                       *, gradient: bool = True, min_distance: float = 0.0):
    """Field per ampere of ``L`` one-turn loops at ``points`` (..., P, 3).

    ``centres``/``axes`` (L, 3) (axes need not be normalised), ``radii`` (L,). Without ``weights``
    returns B (..., P, L, 3) and, if ``gradient``, dB (..., P, L, 3, 3) (else None). With a
    ``weights`` matrix (L, C) (turns of loop l in coil c) the loops are summed into C coils:
    B (..., P, C, 3), dB (..., P, C, 3, 3). ``min_distance`` (m, finite, >= 0): a point this close to a wire raises.
    """
    check_points(points)
    try:
        md = math.nan if isinstance(min_distance, bool) else float(min_distance)
    except (TypeError, ValueError):
        md = math.nan
    if not (math.isfinite(md) and md >= 0):  # NaN was refused as "the point is on the wire"
        raise ValueError(f"min_distance must be a finite distance >= 0 (m), got {min_distance!r}")
    kw = dict(dtype=points.dtype, device=points.device)
    c, n, a = (torch.as_tensor(x, **kw) for x in (centres, axes, radii))
    L = a.shape[0] if a.dim() == 1 else -1
    if a.dim() != 1 or c.shape != (L, 3) or n.shape != (L, 3):
        raise ValueError(f"centres and axes must have shape (L, 3) and radii (L,) for L loops, got centres "
                         f"{tuple(c.shape)}, axes {tuple(n.shape)} and radii {tuple(a.shape)}")
    W = None if weights is None else torch.as_tensor(weights, **kw)
    if W is not None and (W.dim() != 2 or W.shape[0] != L):
        raise ValueError(f"weights must have shape (L, C) = ({L}, C) (the turns of loop l in coil c), got "
                         f"{tuple(W.shape)}")
    ok = torch.isfinite(a) & (a > 0)
    if not bool(ok.all() & (n.norm(dim=-1) > 0).all() & torch.isfinite(c).all()
                & (True if W is None else torch.isfinite(W).all())):
        raise ValueError("radii must be finite and > 0, axes non-zero, centres finite and weights finite")
    n = n / n.norm(dim=-1, keepdim=True)
    d = points[..., :, None, :] - c
    n_iter = _check_wire(d, n, a, md)
    B, dB = _loop_core(d, n, a, n_iter, gradient)
    if W is not None:
        B = torch.einsum("...lk,lc->...ck", B, W)
        dB = None if dB is None else torch.einsum("...lij,lc->...cij", dB, W)
    return B, dB


def check_current_batch(points: Tensor, currents: Tensor, name: str = "currents") -> None:
    """Raise ``ValueError`` unless ``currents`` (..., C) line up with field ``points`` (..., P, 3): currents with batch
    dims need points with batch dims too, which broadcast against the currents' (the points' all but the last two),
    except a single point (1, 3), the same for every member (the Cosserat solver probes a field so). Points (T, 3)
    with currents (T, C) gave a (T, T, 3) field, every frame's currents at every frame's point. Shapes only (no
    tensor values are read), so it runs in traced programs too."""
    cb, pb = currents.shape[:-1], points.shape[:-2]
    if len(cb) and points.dim() < 3 and points.shape[:-1] != (1,):
        raise ValueError(f"{name} of shape {tuple(currents.shape)} are a batch, but points {tuple(points.shape)} have "
                         "no batch dims: give points (..., P, 3) for a batch of currents (..., C), e.g. points "
                         f"(T, 1, 3) for one point per batch member or (1, P, 3) for the same points in every member")
    if not all(x == y or x == 1 or y == 1 for x, y in zip(reversed(cb), reversed(pb))):
        raise ValueError(f"{name} of shape {tuple(currents.shape)} do not line up with points of shape "
                         f"{tuple(points.shape)}: the currents' batch dims {tuple(cb)} must broadcast against the "
                         f"points' {tuple(pb)} (points (..., P, 3), currents (..., C))")


def loop_on_axis_field(z, radius: float, current: float = 1.0, turns: float = 1.0):
    """On-axis field ``mu0 n I R^2 / (2 (R^2 + z^2)^{3/2})`` (T) of a thin loop at axial offset ``z``."""
    radius = _positive("radius", radius)
    return MU0 * turns * current * radius ** 2 / (2 * (radius ** 2 + z ** 2) ** 1.5)


def helmholtz_centre_field(radius: float, turns: float = 1.0, current: float = 1.0) -> float:
    """Centre field ``(4/5)^{3/2} mu0 n I / R`` (T) of a Helmholtz pair (separation = radius)."""
    return (0.8 ** 1.5) * MU0 * turns * current / _positive("radius", radius)


@functools.lru_cache(maxsize=512)
def _cached_loops(coil):
    return coil.loops()


class _LoopSet(FieldModel):
    """A field model made of coaxial-or-not loops, linear in one current (``self.current``)."""

    @abstractmethod
    def loops(self):
        """(centres (L, 3), axes (L, 3), radii (L,), turns (L,)) as float64 CPU tensors."""

    def unit_field_and_gradient(self, points: Tensor, gradient: bool = True):
        """Field (..., P, 3) and gradient (..., P, 3, 3) per ampere of coil current."""
        c, n, a, w = _cached_loops(self)
        B, dB = loop_field_per_amp(points, c, n, a, w[:, None], gradient=gradient, min_distance=self.min_distance)
        return B[..., 0, :], (None if dB is None else dB[..., 0, :, :])

    def field_and_gradient(self, points: Tensor):
        B, dB = self.unit_field_and_gradient(points)
        return self.current * B, self.current * dB

    def field(self, points: Tensor) -> Tensor:
        return self.current * self.unit_field_and_gradient(points, gradient=False)[0]


@dataclass(frozen=True)
class CircularLoop(_LoopSet):
    """A thin circular coil: ``turns`` turns of radius ``radius`` (m) carrying ``current`` (A), centred at
    ``centre`` with unit normal ``axis`` (right-hand rule: positive current gives +axis field inside)."""

    radius: float
    current: float = 1.0
    turns: float = 1.0
    centre: Sequence[float] = (0.0, 0.0, 0.0)
    axis: Sequence[float] = (0.0, 0.0, 1.0)
    min_distance: float = 0.0

    def __post_init__(self):
        cls = type(self).__name__
        object.__setattr__(self, "radius", _positive(f"{cls}.radius (m)", self.radius))
        object.__setattr__(self, "current", _real(f"{cls}.current (A)", self.current))
        object.__setattr__(self, "turns", _positive(f"{cls}.turns", self.turns))
        object.__setattr__(self, "centre", _vec3(f"{cls}.centre (m)", self.centre))
        object.__setattr__(self, "axis", _vec3(f"{cls}.axis", self.axis, nonzero=True))
        if _real(f"{cls}.min_distance (m)", self.min_distance) < 0:
            raise ValueError(f"{cls}.min_distance must be >= 0, got {self.min_distance!r}")

    def loops(self):
        t = lambda v: torch.tensor([v], dtype=torch.float64)
        return t(self.centre), t(self.axis), t(self.radius).reshape(1), t(self.turns).reshape(1)


@dataclass(frozen=True)
class Coil(CircularLoop):
    """A multi-turn coil with a rectangular winding pack (mean ``radius``, axial ``length``, radial
    ``thickness``) as ``n_axial x n_radial`` Gauss-Legendre loops (module docstring). Defaults: a thin coil.
    A coil with a ``length`` needs ``n_axial`` and one with a ``thickness`` ``n_radial`` (no default: one loop
    would model the pack as a thin coil, which near the coil is tens of % off); ``None`` means 1, for no extent."""

    length: float = 0.0
    thickness: float = 0.0
    n_axial: int | None = None
    n_radial: int | None = None

    def __post_init__(self):
        super().__post_init__()
        for name in ("length", "thickness"):
            if _real(f"Coil.{name} (m)", getattr(self, name)) < 0:
                raise ValueError(f"Coil.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.thickness >= 2 * self.radius:
            raise ValueError(f"Coil.thickness must be < 2 radius (inner radius > 0), got {self.thickness!r}")
        for name, extent, along in (("n_axial", "length", "along"), ("n_radial", "thickness", "across")):
            v = getattr(self, name)
            if v is None:  # kept None (not 1): a copy with another extent (dataclasses.replace) is checked again
                if getattr(self, extent) > 0:
                    raise ValueError(f"Coil.{name} must be given for a coil of {extent} {getattr(self, extent)!r} m: "
                                     f"the number of Gauss-Legendre loops {along} the winding pack's {extent} "
                                     "(six_coil_emns uses n_axial=6, n_radial=4; 1 is one loop in the pack's middle)")
                continue
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"Coil.{name} must be an integer >= 1, got {v!r}")
            object.__setattr__(self, name, int(v))

    def loops(self):
        f64 = dict(dtype=torch.float64)
        xa, wa = (torch.as_tensor(v, **f64) for v in np.polynomial.legendre.leggauss(self.n_axial or 1))
        xr, wr = (torch.as_tensor(v, **f64) for v in np.polynomial.legendre.leggauss(self.n_radial or 1))
        s, r = torch.meshgrid(0.5 * self.length * xa, self.radius + 0.5 * self.thickness * xr, indexing="ij")
        axis, centre = torch.tensor(self.axis, **f64), torch.tensor(self.centre, **f64)
        L = s.numel()
        return (centre + s.reshape(L, 1) * axis, axis.expand(L, 3), r.reshape(L),
                (self.turns * 0.25 * wa[:, None] * wr[None, :]).reshape(L))


@dataclass(frozen=True)
class HelmholtzPair(_LoopSet):
    """Two coaxial thin coils (``turns`` each, radius ``radius``) at ``centre +- separation/2 axis``,
    in series (same current). ``separation=None`` is the Helmholtz spacing ``separation = radius``."""

    radius: float
    turns: float = 1.0
    current: float = 1.0
    centre: Sequence[float] = (0.0, 0.0, 0.0)
    axis: Sequence[float] = (0.0, 0.0, 1.0)
    separation: float | None = None
    min_distance: float = 0.0

    def __post_init__(self):
        CircularLoop.__post_init__(self)
        sep = self.radius if self.separation is None else _positive("HelmholtzPair.separation (m)", self.separation)
        object.__setattr__(self, "separation", sep)

    def loops(self):
        f64 = dict(dtype=torch.float64)
        axis, centre = torch.tensor(self.axis, **f64), torch.tensor(self.centre, **f64)
        h = 0.5 * self.separation * torch.tensor([[-1.0], [1.0]], **f64)
        return centre + h * axis, axis.expand(2, 3), torch.full((2,), self.radius, **f64), \
            torch.full((2,), self.turns, **f64)

    @property
    def centre_field_per_amp(self) -> float:
        """Exact field (T/A) at the centre, along ``axis`` (any separation)."""
        return 2 * loop_on_axis_field(0.5 * self.separation, self.radius, 1.0, self.turns)


@dataclass(frozen=True)
class NestedHelmholtz(FieldModel):
    """Two nested orthogonal Helmholtz pairs (Paper I): ``outer`` on E1, ``inner`` on E2, with a common
    centre (module docstring for the default dimensions). ``currents`` (A) = (outer, inner); the
    pairs' own ``current`` fields are ignored."""

    outer: HelmholtzPair = HelmholtzPair(0.25, turns=1250, axis=(1.0, 0.0, 0.0))
    inner: HelmholtzPair = HelmholtzPair(0.12, turns=600, axis=(0.0, 1.0, 0.0))
    currents: tuple = (0.0, 0.0)

    def __post_init__(self):
        for name in ("outer", "inner"):
            if not isinstance(getattr(self, name), HelmholtzPair):
                raise TypeError(f"NestedHelmholtz.{name} must be a HelmholtzPair")
        if len(self.currents) != 2:
            raise ValueError(f"NestedHelmholtz.currents must be (outer, inner), got {self.currents!r}")
        object.__setattr__(self, "currents", tuple(_real("NestedHelmholtz.currents (A)", c) for c in self.currents))

    def unit_field_and_gradient(self, points: Tensor, gradient: bool = True):
        """Per-ampere fields (..., P, 2, 3) and gradients (..., P, 2, 3, 3) of (outer, inner)."""
        outs = [pair.unit_field_and_gradient(points, gradient) for pair in (self.outer, self.inner)]
        B = torch.stack([o[0] for o in outs], -2)
        return B, (torch.stack([o[1] for o in outs], -3) if gradient else None)

    def field_and_gradient(self, points: Tensor, currents: Tensor | None = None):
        """Field and gradient at ``points`` (..., P, 3) for ``currents`` (..., 2) (default ``self.currents``); the
        currents' batch dims broadcast against the points' (..., all but the last two)."""
        I = self._currents(points, currents)
        B, dB = self.unit_field_and_gradient(points)
        return (B * I[..., None, :, None]).sum(-2), (dB * I[..., None, :, None, None]).sum(-3)

    def field(self, points: Tensor, currents: Tensor | None = None) -> Tensor:
        I = self._currents(points, currents)[..., None, :, None]
        return (self.unit_field_and_gradient(points, False)[0] * I).sum(-2)

    def _currents(self, points, currents):
        I = self.currents if currents is None else currents
        I = torch.as_tensor(I, dtype=points.dtype, device=points.device)
        if I.shape[-1:] != (2,) or not bool(torch.isfinite(I).all()):
            raise ValueError(f"currents must be finite with shape (..., 2) (outer, inner), got {tuple(I.shape)}")
        check_current_batch(points, I)
        return I

    def centre_matrix(self) -> Tensor:
        """The 3x2 map (T/A) from (outer, inner) currents to the field at the common centre."""
        centre = torch.tensor(self.outer.centre, dtype=torch.float64)[None]
        return self.unit_field_and_gradient(centre, gradient=False)[0][0].T

    def currents_for_field(self, B: Tensor, centre_matrix: Tensor | None = None) -> Tensor:
        """Currents (..., 2) giving the field ``B`` (..., 3) at the centre (it must lie in the plane of the two
        pairs' axes: the E1E2 plane for the default coils). ``centre_matrix`` may pass a cached
        :meth:`centre_matrix`."""
        B = torch.as_tensor(B, dtype=torch.get_default_dtype()) if not isinstance(B, Tensor) else B
        if B.shape[-1:] != (3,) or not bool(torch.isfinite(B).all()):
            raise ValueError(f"B must be a finite (..., 3) field, got shape {tuple(B.shape)}"
                             f"{'' if bool(torch.isfinite(B).all()) else ' with non-finite values'}")
        A = (self.centre_matrix() if centre_matrix is None else centre_matrix).to(dtype=torch.float64, device=B.device)
        Bd = B.to(torch.float64)
        I = (torch.linalg.pinv(A) @ Bd[..., None])[..., 0]
        tol = max(1e-9, 16 * torch.finfo(B.dtype).eps)  # B's own rounding (float32) leaves the plane by ~eps
        if bool(((A @ I[..., None])[..., 0] - Bd).norm(dim=-1).gt(tol * Bd.norm(dim=-1).clamp_min(1e-300)).any()):
            raise ValueError(f"B must lie in the plane of the pairs' axes {self.outer.axis} and {self.inner.axis} "
                             "(the E1E2 plane for the default coils)")
        return I.to(B.dtype)

    def with_currents(self, currents) -> "NestedHelmholtz":
        return replace(self, currents=tuple(float(c) for c in currents))


class RotatingField(TimeVarying):
    """A static plus rotating field generated by :class:`NestedHelmholtz` coils:

        B(t) = static + amplitude (cos(omega t + phase) u + sin(omega t + phase) v),

    ``u``, ``v`` orthonormal in the E1E2 plane (default ``u = E2``, ``v = E1``). At each time the
    pair currents are those giving ``B(t)`` at the centre (:meth:`currents`), and the field at the
    points is the full (slightly non-uniform) coil field.
    """

    def __init__(self, coils: NestedHelmholtz, static=(0.0, 0.0, 0.0), amplitude: float = 0.0, omega: float = 0.0,
                 phase: float = 0.0, u=(0.0, 1.0, 0.0), v=(1.0, 0.0, 0.0)):
        self.coils = coils
        self.static = torch.tensor(_vec3("static (T)", static), dtype=torch.float64)
        self.amplitude, self.omega = _real("amplitude (T)", amplitude), _real("omega (rad/s)", omega)
        self.phase = _real("phase (rad)", phase)
        self.u = torch.tensor(_vec3("u", u, nonzero=True), dtype=torch.float64)
        self.v = torch.tensor(_vec3("v", v, nonzero=True), dtype=torch.float64)
        if abs(float(self.u @ self.v)) > 1e-12:
            raise ValueError("u and v must be orthogonal")
        self._centre_matrix = coils.centre_matrix()
        super().__init__(lambda t: self.coils.with_currents(self.currents(t).tolist()))

    def requested_field(self, t) -> Tensor:
        """The commanded centre field (..., 3) at time(s) ``t``."""
        th = self.omega * torch.as_tensor(t, dtype=torch.float64) + self.phase
        return self.static + self.amplitude * (torch.cos(th)[..., None] * self.u + torch.sin(th)[..., None] * self.v)

    def currents(self, t) -> Tensor:
        """(outer, inner) currents (..., 2) (A) at time(s) ``t``."""
        return self.coils.currents_for_field(self.requested_field(t), self._centre_matrix)

    def __call__(self, t, positions: Tensor):
        I = self.currents(t).to(dtype=positions.dtype, device=positions.device)
        return self.coils.field_and_gradient(positions, I)

    def wrench(self, t, positions: Tensor, moments: Tensor):
        B, dB = self(t, positions)
        return force_from_gradient(moments, dB), dipole_torque(moments, B)


def paper1_rotating_field(omega: float, coils: NestedHelmholtz | None = None, phase: float = 0.0) -> RotatingField:
    """The circular-motion experiment of Paper I: a 7.75 mT gravity-compensating field on E2 plus a
    14.5 mT field rotating in the E1E2 plane, ``B(t) = 7.75 mT e2 + 14.5 mT (cos wt e2 + sin wt e1)``."""
    return RotatingField(coils or NestedHelmholtz(), static=(0.0, 7.75e-3, 0.0), amplitude=14.5e-3, omega=omega,
                         phase=phase)
