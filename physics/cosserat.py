"""Static Cosserat rod (Paper II appendix, thesis lines 1947-1975): spec, 13-state ODE, fixed-grid RK4.

State ``y = [p, q, n, m]`` (13 numbers): position ``p``, unit quaternion ``q = (w, x, y, z)`` of the
cross-section frame (body E3 along the undeformed axis), internal force ``n`` and moment ``m`` in
the world frame, as functions of arclength ``s``::

    p' = R v,             v = K_s^{-1} R^T n + v_hat,     K_s = diag(k G A, k G A, E A)
    q' = q (x) (0, u)/2,  u = K_b^{-1} R^T m + u_hat,     K_b = diag(E I1, E I2, G J)
    n' = -f,              f = rho A g + f_line            (distributed force per length, world)
    m' = -p' x n - tau                                    (distributed moment per length, world)

(``q (x) (0, u)/2`` is the printed ``[-q_i^T; q_r I - [q_i]x] R u / 2``.) ``R(q)`` is the
homogeneous quadratic form (equal to the rotation for unit ``q``); ``q`` is renormalised after each
RK4 step. Material is piecewise constant: the rod is a chain of :class:`Segment` s (soft body,
stiff magnet blocks), each with its own section, modulus, density and intrinsic strains.

Point loads act at grid nodes as jumps ``n(s+) = n(s-) - F``, ``m(s+) = m(s-) - M``: dead world
loads at ``CosseratRod.load_points`` and at the tip, and the magnets' wrenches. A
:class:`MagnetDipole` at ``s`` carries a body-frame moment; its world moment ``R(q(s)) mu`` and
position ``p(s)`` are taken from the state reached by the integration, and the field hook of
:mod:`physics.loads` (``field(t, positions) -> B | (B, dB)``, or a non-callable object with
``wrench(t, positions, moments)``) gives torque ``mu x B`` and force ``dB^T mu``; a magnet's
``mass`` adds the point weight ``mass g``. (The thesis calls the magnets' loads distributed; a
magnet of a few mm is taken here as a point wrench at its centre, the magnet segment itself being
stiff.)

The grid: the segment ends, magnets and load points are nodes; the ``n_nodes - 1`` RK4 steps are
shared between the intervals between them so as to make the longest step as short as possible.
The thesis's 13 nodes are 12 RK4 steps. The ODE and its RK4 shot are in :mod:`physics.cosserat_ode`,
Levenberg-Marquardt shooting in :mod:`physics.cosserat_shooting`, the compiled fast path in
:mod:`physics.cosserat_lanes`, the Paper II rod in :mod:`physics.scenes_cosserat`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from .checks import check_integer
from .rod import CircularSection, Material, SquareSection, finite_vector

__all__ = ["Segment", "MagnetDipole", "CosseratRod", "CosseratParams", "CosseratGrid", "StaticLoads", "broadcast_shape"]

_MERGE = 1e-9  # relative distance under which two breakpoints are the same node


@dataclass(frozen=True)
class Segment:
    """A piece of rod with uniform section and material. ``intrinsic_strain`` is ``v_hat`` (default
    ``(0, 0, 1)``: straight, unstretched) and ``intrinsic_curvature`` ``u_hat`` (1/m), body frame."""

    length: float
    section: CircularSection | SquareSection
    material: Material
    intrinsic_curvature: tuple[float, float, float] = (0.0, 0.0, 0.0)
    intrinsic_strain: tuple[float, float, float] = (0.0, 0.0, 1.0)
    name: str = ""

    def __post_init__(self):
        if not (math.isfinite(float(self.length)) and self.length > 0):
            raise ValueError(f"Segment.length (m) must be finite and positive, got {self.length!r}")
        if not isinstance(self.section, (CircularSection, SquareSection)):
            raise TypeError(f"Segment.section must be CircularSection or SquareSection, got {type(self.section)}")
        if not isinstance(self.material, Material):
            raise TypeError(f"Segment.material must be a Material, got {type(self.material)}")
        object.__setattr__(self, "intrinsic_curvature", finite_vector("Segment.intrinsic_curvature",
                                                                      self.intrinsic_curvature))
        object.__setattr__(self, "intrinsic_strain", finite_vector("Segment.intrinsic_strain", self.intrinsic_strain))
        if not self.intrinsic_strain[2] > 0:
            raise ValueError(f"Segment.intrinsic_strain[2] (the rest stretch along the centreline) must be > 0, got "
                             f"{self.intrinsic_strain!r}")

    def stiffness(self, shear_coefficient: float = 1.0) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """``(K_s, K_b)`` diagonals: (k G A, k G A, E A) and (E I1, E I2, G J)."""
        E, G, A = self.material.E, self.material.shear_modulus, self.section.area
        i1, i2 = self.section.second_moments
        k = shear_coefficient
        return (k * G * A, k * G * A, E * A), (E * i1, E * i2, G * self.section.torsion_constant)


@dataclass(frozen=True)
class MagnetDipole:
    """A point dipole at arclength ``s`` (m) with body-frame moment ``moment`` (A m^2) and an
    optional point ``mass`` (kg) that gravity acts on (leave 0 when a magnet segment's density
    already carries the weight)."""

    s: float
    moment: tuple[float, float, float]
    mass: float = 0.0
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "moment", finite_vector("MagnetDipole.moment", self.moment))
        if not (math.isfinite(float(self.mass)) and self.mass >= 0):
            raise ValueError(f"MagnetDipole.mass (kg) must be finite and >= 0, got {self.mass!r}")


class CosseratGrid(NamedTuple):
    """The fixed RK4 grid: node arclengths ``s`` (n_nodes), step lengths ``h`` (n_nodes - 1), the
    segment of each step, and the node of each load point (the tip last) and of each magnet."""

    s: tuple[float, ...]
    h: tuple[float, ...]
    step_segment: tuple[int, ...]
    load_nodes: tuple[int, ...]
    magnet_nodes: tuple[int, ...]


class CosseratParams(NamedTuple):
    """Per-step tensors (leading batch dims allowed): compliances ``ks_inv``, ``kb_inv`` (..., S, 3),
    ``line_density`` rho A (..., S) kg/m, ``v_hat``, ``u_hat`` (..., S, 3); magnets' body moments
    (..., K, 3) and point masses (..., K)."""

    ks_inv: Tensor
    kb_inv: Tensor
    line_density: Tensor
    v_hat: Tensor
    u_hat: Tensor
    magnet_moment: Tensor
    magnet_mass: Tensor


@dataclass(frozen=True)
class CosseratRod:
    """A rod made of ``segments`` (base to tip) on an RK4 grid of ``n_nodes`` nodes, with
    ``magnets`` and extra ``load_points`` (arclengths where dead point loads act; the tip always
    takes one). ``shear_coefficient`` is the Timoshenko k in ``K_s``."""

    segments: tuple[Segment, ...]
    n_nodes: int = 13
    magnets: tuple[MagnetDipole, ...] = ()
    load_points: tuple[float, ...] = ()
    shear_coefficient: float = 1.0
    grid: CosseratGrid = field(init=False, repr=False, compare=False)

    @classmethod
    def uniform(cls, length: float, section, material: Material, n_nodes: int = 13, **kw) -> "CosseratRod":
        """One segment; ``intrinsic_curvature``/``intrinsic_strain`` go to it, the rest to the rod."""
        seg_kw = {k: kw.pop(k) for k in ("intrinsic_curvature", "intrinsic_strain") if k in kw}
        return cls(segments=(Segment(length, section, material, **seg_kw),), n_nodes=n_nodes, **kw)

    def __post_init__(self):
        segs = tuple(self.segments)
        if not segs or not all(isinstance(s, Segment) for s in segs):
            raise TypeError("CosseratRod.segments must be a non-empty sequence of Segment")
        object.__setattr__(self, "segments", segs)
        object.__setattr__(self, "magnets", tuple(self.magnets))
        if not all(isinstance(m, MagnetDipole) for m in self.magnets):
            raise TypeError("CosseratRod.magnets must be MagnetDipole instances")
        if not (math.isfinite(float(self.shear_coefficient)) and self.shear_coefficient > 0):
            raise ValueError(f"CosseratRod.shear_coefficient must be finite and positive, got {self.shear_coefficient!r}")
        L = self.length
        for i, m in enumerate(self.magnets):
            if not (0 <= m.s <= L * (1 + 1e-12)):
                raise ValueError(f"CosseratRod.magnets[{i}].s = {m.s!r} m lies outside the rod [0, {L:g}] m")
        pts = tuple(float(x) for x in self.load_points)
        for i, x in enumerate(pts):
            if not (math.isfinite(x) and 0 <= x <= L * (1 + 1e-12)):
                raise ValueError(f"CosseratRod.load_points[{i}] = {x!r} m lies outside the rod [0, {L:g}] m")
        object.__setattr__(self, "load_points", pts)
        check_integer("CosseratRod.n_nodes", self.n_nodes, 2)
        object.__setattr__(self, "grid", self._make_grid())

    @property
    def length(self) -> float:
        return float(sum(s.length for s in self.segments))

    @property
    def segment_bounds(self) -> tuple[float, ...]:
        b = [0.0]
        for s in self.segments:
            b.append(b[-1] + s.length)
        return tuple(b)

    @property
    def bending_scale(self) -> float:
        """The smallest bending stiffness E I (N m^2): with L it scales forces (E I/L^2) and moments (E I/L)."""
        return min(min(s.stiffness(self.shear_coefficient)[1][:2]) for s in self.segments)

    def _make_grid(self) -> CosseratGrid:
        L, bounds = self.length, self.segment_bounds
        raw = sorted([*bounds, *(m.s for m in self.magnets), *self.load_points, L])
        bps = [0.0]
        for x in raw:
            if x - bps[-1] > _MERGE * L:
                bps.append(min(x, L))
        bps[-1] = L
        ell = [b - a for a, b in zip(bps, bps[1:])]
        steps = int(self.n_nodes) - 1
        if steps < len(ell):
            raise ValueError(f"CosseratRod.n_nodes must be >= {len(ell) + 1}: segment ends, magnets and load "
                             f"points make {len(ell)} intervals, each needing an RK4 step (got {self.n_nodes})")
        counts = [1] * len(ell)
        for _ in range(steps - len(ell)):
            i = max(range(len(ell)), key=lambda j: ell[j] / counts[j])
            counts[i] += 1
        s, h = [0.0], []
        for a, le, c in zip(bps, ell, counts):
            h.extend([le / c] * c)
            s.extend(a + le * (k + 1) / c for k in range(c))
        s[-1] = L

        def node(x: float) -> int:
            return min(range(len(s)), key=lambda j: abs(s[j] - x))

        def segment_of(x: float) -> int:
            return next((i for i in range(len(self.segments)) if x < bounds[i + 1]), len(self.segments) - 1)

        return CosseratGrid(tuple(s), tuple(h), tuple(segment_of(0.5 * (a + b)) for a, b in zip(s, s[1:])),
                            tuple(node(x) for x in (*self.load_points, L)), tuple(node(m.s) for m in self.magnets))

    def params(self, dtype: torch.dtype = torch.float64, device=None, youngs_modulus: Tensor | None = None,
               magnet_moments: Tensor | None = None) -> CosseratParams:
        """Per-step tensors. ``youngs_modulus`` (..., n_segments) overrides each segment's E (its shear
        modulus scales with it) and ``magnet_moments`` (..., K, 3) the magnets' body moments; both
        may carry batch dims and ``requires_grad`` (gradients w.r.t. material parameters)."""
        G = len(self.segments)
        Ks, Kb, rho, vh, uh = [], [], [], [], []
        for sg in self.segments:
            a, b = sg.stiffness(self.shear_coefficient)
            Ks.append(a), Kb.append(b), rho.append(sg.material.density * sg.section.area)
            vh.append(sg.intrinsic_strain), uh.append(sg.intrinsic_curvature)
        kw = dict(dtype=dtype, device=device)
        Ks, Kb = torch.tensor(Ks, **kw), torch.tensor(Kb, **kw)
        if youngs_modulus is not None:
            E = torch.as_tensor(youngs_modulus, **kw)
            if E.shape[-1:] != (G,):
                raise ValueError(f"youngs_modulus must have shape (..., {G}) (one per segment), got {tuple(E.shape)}")
            if not bool(torch.isfinite(E).all()) or not bool((E > 0).all()):
                raise ValueError("youngs_modulus must be finite and positive (Pa)")
            scale = E / torch.tensor([sg.material.E for sg in self.segments], **kw)
            Ks, Kb = Ks * scale[..., None], Kb * scale[..., None]
        K = len(self.magnets)
        mom = torch.tensor([m.moment for m in self.magnets], **kw).reshape(K, 3)
        if magnet_moments is not None:
            mom = torch.as_tensor(magnet_moments, **kw)
            if mom.shape[-2:] != (K, 3):
                raise ValueError(f"magnet_moments must have shape (..., {K}, 3), got {tuple(mom.shape)}")
            if not bool(torch.isfinite(mom).all()):
                raise ValueError("magnet_moments must be finite (A m^2)")
        idx = torch.tensor(self.grid.step_segment, dtype=torch.long, device=device)
        return CosseratParams(
            ks_inv=(1.0 / Ks)[..., idx, :], kb_inv=(1.0 / Kb)[..., idx, :],
            line_density=torch.tensor(rho, **kw)[idx], v_hat=torch.tensor(vh, **kw)[idx],
            u_hat=torch.tensor(uh, **kw)[idx], magnet_moment=mom,
            magnet_mass=torch.tensor([m.mass for m in self.magnets], **kw))


def broadcast_shape(*shapes) -> tuple[int, ...]:
    """Broadcast of batch shapes (a fast pure-Python ``torch.broadcast_shapes``)."""
    n = max((len(sh) for sh in shapes), default=0)
    out = [1] * n
    for sh in shapes:
        for i, d in enumerate(sh, n - len(sh)):
            if d != 1:
                if out[i] not in (1, d):
                    raise ValueError(f"batch shapes {[tuple(x) for x in shapes]} do not broadcast")
                out[i] = d
    return tuple(out)


class StaticLoads(NamedTuple):
    """Load and boundary tensors of one (batched) problem, world frame, SI: ``gravity``,
    ``line_force`` (N/m), ``line_torque`` (N m/m) (..., 3); dead point loads ``point_force``,
    ``point_torque`` (..., P, 3) at ``load_points`` then the tip; ``field_scale`` (...,) multiplies
    the field's wrench (load stepping); base pose ``base_position`` (..., 3), ``base_quaternion`` (..., 4)."""

    gravity: Tensor
    line_force: Tensor
    line_torque: Tensor
    point_force: Tensor
    point_torque: Tensor
    field_scale: Tensor
    base_position: Tensor
    base_quaternion: Tensor

    def scaled(self, alpha: float) -> "StaticLoads":
        """All loads times ``alpha`` (the base pose unchanged)."""
        a = alpha
        return self._replace(gravity=self.gravity * a, line_force=self.line_force * a,
                             line_torque=self.line_torque * a, point_force=self.point_force * a,
                             point_torque=self.point_torque * a, field_scale=self.field_scale * a)
