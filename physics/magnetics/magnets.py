"""Permanent magnets: cuboids and cylinders as grids of point dipoles, spheres as exact dipoles.

A magnet is a frozen spec (dimensions, polarization ``J = mu0 M`` in tesla in the magnet's own
frame, pose). ``magnet.field_model(count)`` splits it into cells of (nearly) equal shape, each
replaced by a dipole ``M V_cell`` at the cell centroid, and returns a :class:`MagnetField`
(a :class:`~physics.magnetics.base.FieldModel`) that refuses field points inside the magnet.

Accuracy: outside the body ``1/r`` is harmonic, so the midpoint rule over cubic cells has no
``h^2`` term and the error of an n^3 cuboid grid falls like ``(h / r)^4`` with cell size ``h``
(``scripts/report_magnet_convergence.py`` measures it against the exact cuboid field). A uniformly
magnetised sphere is exactly a dipole outside itself.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from ..checks import check_rotations
from .base import FieldModel, check_points
from .dipole import MU0
from .sources import DipoleSet
from .validate import integer as _integer, positive as _positive, rotation as _rotation, vec3 as _vec3

__all__ = ["CuboidMagnet", "CylinderMagnet", "SphereMagnet", "MagnetField"]


@dataclass(frozen=True)
class _Magnet(ABC):
    """Common fields: ``polarization`` J (T) in the magnet frame, ``position`` (m), ``orientation``."""

    polarization: Sequence[float] = (0.0, 0.0, 1.0)
    position: Sequence[float] = (0.0, 0.0, 0.0)
    orientation: Sequence[Sequence[float]] = field(default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))

    def _check_pose(self):
        object.__setattr__(self, "polarization", _vec3("polarization", self.polarization))
        object.__setattr__(self, "position", _vec3("position", self.position))
        object.__setattr__(self, "orientation", _rotation(self.orientation))

    @property
    @abstractmethod
    def volume(self) -> float:
        """Volume (m^3)."""

    @abstractmethod
    def _cells(self, count: int) -> tuple[Tensor, Tensor]:
        """Dipole positions (S, 3) in the magnet frame and the volume (S,) each stands for."""

    @property
    def moment(self) -> Tensor:
        """Total moment ``J V / mu0`` (3,) in the world frame (A m^2)."""
        R = torch.tensor(self.orientation, dtype=torch.float64)
        return R @ torch.tensor(self.polarization, dtype=torch.float64) * (self.volume / MU0)

    def to_local(self, points: Tensor) -> Tensor:
        R = torch.tensor(self.orientation, dtype=points.dtype, device=points.device)
        p = torch.tensor(self.position, dtype=points.dtype, device=points.device)
        return (points - p) @ R

    def dipoles(self, count: int = 2000, dtype=torch.float64, device=None) -> DipoleSet:
        """The magnet as about ``count`` point dipoles (world frame)."""
        cells, vol = self._cells(_integer("count", count))
        J = torch.tensor(self.polarization, dtype=torch.float64)
        local = DipoleSet(cells, (vol / MU0)[:, None] * J)
        R = torch.tensor(self.orientation, dtype=torch.float64)
        return local.transformed(R, torch.tensor(self.position, dtype=torch.float64)).to(dtype, device)

    def field_model(self, count: int = 2000, dtype=torch.float64, device=None) -> "MagnetField":
        return MagnetField(self, self.dipoles(count, dtype, device))

    def with_pose(self, position=None, orientation=None):
        """The same magnet at another pose (floats; use ``MagnetField.transformed`` for tensors/autograd)."""
        from dataclasses import replace
        return replace(self, position=self.position if position is None else position,
                       orientation=self.orientation if orientation is None else orientation)


@dataclass(frozen=True)
class CuboidMagnet(_Magnet):
    """Cuboid of edge lengths ``dimensions`` (m) along its own x, y, z axes."""

    dimensions: Sequence[float] = (0.01, 0.01, 0.01)

    def __post_init__(self):
        dims = _vec3("dimensions", self.dimensions)
        for v in dims:
            _positive("dimensions", v)
        object.__setattr__(self, "dimensions", dims)
        self._check_pose()

    @property
    def volume(self) -> float:
        a, b, c = self.dimensions
        return a * b * c

    def grid(self, count: int) -> tuple[int, int, int]:
        """Cells per axis, proportional to the edges, with a product close to ``count``."""
        h = (self.volume / _integer("count", count)) ** (1 / 3)
        return tuple(max(1, round(d / h)) for d in self.dimensions)

    def _cells(self, count):
        n = self.grid(count)
        axes = [(torch.arange(k, dtype=torch.float64) + 0.5) / k * d - d / 2 for k, d in zip(n, self.dimensions)]
        cells = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return cells, torch.full((cells.shape[0],), self.volume / cells.shape[0], dtype=torch.float64)

    def contains(self, points: Tensor) -> Tensor:
        half = torch.tensor(self.dimensions, dtype=points.dtype, device=points.device) / 2
        return (self.to_local(points).abs() < half).all(-1)


@dataclass(frozen=True)
class CylinderMagnet(_Magnet):
    """Solid cylinder of ``diameter`` and ``height`` (m), axis along its own z."""

    diameter: float = 0.01
    height: float = 0.01

    def __post_init__(self):
        object.__setattr__(self, "diameter", _positive("diameter", self.diameter))
        object.__setattr__(self, "height", _positive("height", self.height))
        self._check_pose()

    @property
    def volume(self) -> float:
        return math.pi * self.diameter ** 2 / 4 * self.height

    def _cells(self, count):
        """Layers along z; in each, rings of equal width split into near-square annular sectors; each
        dipole sits at its sector's centroid and carries that sector's volume."""
        R = self.diameter / 2
        h = (self.volume / count) ** (1 / 3)
        n_z = max(1, round(self.height / h))
        n_r = max(1, round(R / h))
        xy, area = [], []
        for j in range(n_r):
            r1, r2 = j * R / n_r, (j + 1) * R / n_r
            n_t = max(1, round(math.pi * (r1 + r2) / (r2 - r1))) if j else 1
            dth = 2 * math.pi / n_t
            rc = 0.0 if n_t == 1 else (2 / 3) * (r2 ** 3 - r1 ** 3) / (r2 ** 2 - r1 ** 2) * math.sin(dth / 2) / (dth / 2)
            th = (torch.arange(n_t, dtype=torch.float64) + 0.5) * dth
            xy.append(torch.stack([rc * th.cos(), rc * th.sin()], -1))
            area.append(torch.full((n_t,), math.pi * (r2 ** 2 - r1 ** 2) / n_t, dtype=torch.float64))
        xy, area = torch.cat(xy), torch.cat(area)
        z = (torch.arange(n_z, dtype=torch.float64) + 0.5) / n_z * self.height - self.height / 2
        cells = torch.cat([xy.repeat(n_z, 1), z.repeat_interleave(xy.shape[0])[:, None]], -1)
        return cells, area.repeat(n_z) * (self.height / n_z)

    def contains(self, points: Tensor) -> Tensor:
        q = self.to_local(points)
        return ((q[..., :2] ** 2).sum(-1) < (self.diameter / 2) ** 2) & (q[..., 2].abs() < self.height / 2)


@dataclass(frozen=True)
class SphereMagnet(_Magnet):
    """Uniformly magnetised sphere of ``diameter`` (m): exactly a dipole ``J V / mu0`` outside itself."""

    diameter: float = 0.005

    def __post_init__(self):
        object.__setattr__(self, "diameter", _positive("diameter", self.diameter))
        self._check_pose()

    @property
    def volume(self) -> float:
        return math.pi * self.diameter ** 3 / 6

    def _cells(self, count):
        return torch.zeros(1, 3, dtype=torch.float64), torch.tensor([self.volume], dtype=torch.float64)

    def contains(self, points: Tensor) -> Tensor:
        p = torch.tensor(self.position, dtype=points.dtype, device=points.device)
        return ((points - p) ** 2).sum(-1) < (self.diameter / 2) ** 2


class MagnetField(FieldModel):
    """Field of a permanent magnet represented by the dipole set ``base`` (at the magnet's own pose),
    optionally moved further by ``x -> R x + p`` (tensors, differentiable; e.g. a rotating magnet).
    Field points inside the magnet raise ``ValueError``: the dipole grid does not model its interior."""

    def __init__(self, magnet: _Magnet, base: DipoleSet, R: Tensor | None = None, p: Tensor | None = None):
        self.magnet, self.base, self.R, self.p = magnet, base, R, p
        self.dipoles = base if R is None else base.transformed(R, p)

    def transformed(self, R: Tensor, p: Tensor) -> "MagnetField":
        """The magnet moved further by ``x -> R x + p``: ``R`` (..., 3, 3) a proper rotation (orthonormal, det +1,
        to a tolerance of its dtype's precision), ``p`` (..., 3) (m)."""
        check_rotations("R", R)
        dt = self.base.positions.dtype
        R, p = torch.as_tensor(R, dtype=dt), torch.as_tensor(p, dtype=dt)
        if p.shape[-1:] != (3,) or not bool(torch.isfinite(p).all()):
            raise ValueError(f"p must be a finite translation (..., 3) (m), got shape {tuple(p.shape)}")
        if self.R is not None:
            R, p = R @ self.R, (R @ self.p[..., None]).squeeze(-1) + p
        return MagnetField(self.magnet, self.base, R, p)

    def _check_outside(self, points: Tensor) -> Tensor:
        q = check_points(points).detach().to(torch.float64)
        if self.R is not None:  # back to the magnet's own pose
            q = (q - self.p.detach().to(q.dtype)[..., None, :]) @ self.R.detach().to(q.dtype)
        inside = self.magnet.contains(q)
        if bool(inside.any()):
            idx = tuple(int(i) for i in inside.nonzero()[0])
            raise ValueError(f"points: field point {idx} lies inside the {type(self.magnet).__name__}; its dipole "
                             "model is valid only outside the magnet")
        return points

    def field(self, points):
        return self.dipoles.field(self._check_outside(points))

    def field_and_gradient(self, points):
        return self.dipoles.field_and_gradient(self._check_outside(points))

    def force_torque(self, points, moments):
        return self.dipoles.force_torque(self._check_outside(points), moments)
