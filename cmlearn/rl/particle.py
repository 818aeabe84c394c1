"""A 5 mm magnetic sphere on the table, pulled by the block magnet on the UR5's end-effector.

Model (SI units). The end-effector magnet is a 50 x 25 x 10 mm N35 block (``Br = 1.19 T``),
magnetised through its 10 mm thickness, pointing down, its centre ``magnet_height`` above the
table (default 0.105 m: its lower face in the thesis's plane 10 cm above the table); it is the
grid of about ``magnet_dipoles`` point dipoles of :class:`physics.magnetics.CuboidMagnet`. The
particle is a uniformly magnetised N42 sphere (``Br = 1.30 T``, 5 mm, density 7500 kg/m^3): an
exact dipole ``m = Br V / mu0``, its centre ``d/2`` above the table.

* The particle's moment aligns with the local field (``m || B``: its magnetic torque is fast
  compared with the translation), so the force is ``F = grad(m . B)`` with m held at that value.
* ``F`` depends only on the in-plane offset of the particle from the magnet's projection, so it
  is precomputed once on a grid (quadrant ``[0, extent]^2`` with ``map_spacing``; the block's two
  mirror symmetries give the rest) and bilinearly interpolated. Measured error: with 300 dipoles
  the force differs from a 8500-dipole grid by 1.1e-4 of its peak at 10 cm (8 dipoles: 4e-3), and
  the bilinear interpolation on a 2.5 mm grid differs from the direct dipole sum by < 0.3 % of
  the peak (``docs/controllers.md``; ``tests/test_rl_particle.py`` checks both).
* Table contact: normal force ``N = m g - F_z`` (the construction refuses a magnet height where
  ``F_z > m g``: the particle would jump to the magnet). Coulomb friction with
  ``mu_static = 0.2`` and ``mu_kinetic = 0.15`` and a viscous drag ``c = 5e-3 N s/m``: effective
  lumped values for a nickel-plated sphere rolling/sliding on a plastic sheet (air drag alone,
  ``6 pi eta r ~ 1e-6 N s/m``, is negligible). They give a capture radius near 9.5 cm, next to the
  thesis's 10 cm switching distance, and a following lag of about 1.5 cm at 0.1 m/s.
* Integration: symplectic Euler at a fixed sub-step, drag implicit, friction as an impulse that
  can stop but never reverse the motion (stick when at rest and ``|F_xy| <= mu_s N``). The
  linearised system ``x'' + (c/m) x' + (k/m) x = 0`` with the largest magnetic stiffness ``k`` of
  the force map is stable for ``dt < (g + sqrt(g^2 + 4 w^2)) / w^2`` (``g = c/m``, ``w^2 = k/m``);
  a sub-step above half of that raises ``ValueError``.
* The particle is *lost* when the magnet is farther than the capture radius (the in-plane pull
  cannot overcome static friction) or moves faster than ``F_max / c`` (it cannot keep up).
"""
from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass

import numpy as np

from physics.checks import is_int

__all__ = ["ParticleParams", "ForceMap", "ParticleSim", "force_map", "direct_force"]


@dataclass(frozen=True)
class ParticleParams:
    magnet_dims: tuple[float, float, float] = (0.05, 0.025, 0.01)
    magnet_br: float = 1.19
    magnet_height: float = 0.105
    magnet_dipoles: int = 300
    particle_diameter: float = 0.005
    particle_br: float = 1.30
    particle_density: float = 7500.0
    mu_static: float = 0.2
    mu_kinetic: float = 0.15
    viscous: float = 5e-3
    gravity: float = 9.81
    substep: float = 0.005
    map_extent: float = 0.3
    map_spacing: float = 0.0025

    def __post_init__(self):
        for name in ("magnet_br", "magnet_height", "particle_diameter", "particle_br", "particle_density",
                     "viscous", "gravity", "substep", "map_extent", "map_spacing"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise ValueError(f"{name} must be a real number, got {v!r}")
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
            object.__setattr__(self, name, float(v))  # a numpy number keys the cached maps as its float does
        if len(self.magnet_dims) != 3 or not all(math.isfinite(v) and v > 0 for v in self.magnet_dims):
            raise ValueError(f"magnet_dims must be 3 positive lengths (m), got {self.magnet_dims!r}")
        # a tuple of floats whatever sequence came in: the params key the cached force maps (hashable)
        object.__setattr__(self, "magnet_dims", tuple(float(v) for v in self.magnet_dims))
        if not (0 <= self.mu_kinetic <= self.mu_static):
            raise ValueError(f"need 0 <= mu_kinetic <= mu_static, got {self.mu_kinetic}, {self.mu_static}")
        if self.magnet_height - self.magnet_dims[2] / 2 <= self.particle_diameter:
            raise ValueError(f"magnet_height={self.magnet_height} leaves no gap above the particle")
        if not is_int(self.magnet_dipoles) or self.magnet_dipoles < 1:
            raise ValueError(f"magnet_dipoles must be an int >= 1, got {self.magnet_dipoles!r}")

    @property
    def volume(self) -> float:
        return math.pi * self.particle_diameter ** 3 / 6

    @property
    def mass(self) -> float:
        return self.particle_density * self.volume

    @property
    def moment(self) -> float:
        from physics.magnetics import moment_from_remanence
        return float(moment_from_remanence(self.particle_br, self.volume))


def direct_force(params: ParticleParams, offsets: np.ndarray, dipoles: int | None = None) -> np.ndarray:
    """Force (..., 3) on the field-aligned particle at in-plane ``offsets`` (..., 2) from the magnet's
    projection, by direct dipole summation (the reference of the force map)."""
    import torch
    from physics.magnetics import CuboidMagnet
    magnet = CuboidMagnet(dimensions=params.magnet_dims, polarization=(0.0, 0.0, -params.magnet_br),
                          position=(0.0, 0.0, params.magnet_height))
    fm = magnet.field_model(int(dipoles or params.magnet_dipoles))
    offsets = np.asarray(offsets, dtype=float)
    off = torch.as_tensor(offsets.reshape(-1, 2))
    pts = torch.cat([off, torch.full(off.shape[:-1] + (1,), params.particle_diameter / 2, dtype=off.dtype)], -1)
    B = fm.field(pts)
    m = params.moment * B / B.norm(dim=-1, keepdim=True)
    return fm.force_torque(pts, m)[0].numpy().reshape(offsets.shape[:-1] + (3,))


class ForceMap:
    """Bilinear interpolation of the magnetic force on the particle over in-plane offsets."""

    def __init__(self, params: ParticleParams):
        self.params = params
        n = int(round(params.map_extent / params.map_spacing)) + 1
        self.h, self.n = params.map_extent / (n - 1), n
        g = np.linspace(0.0, params.map_extent, n)
        X, Y = np.meshgrid(g, g, indexing="ij")
        F = direct_force(params, np.stack([X, Y], -1))
        self.grid = F  # (n, n, 3) on the quadrant x, y >= 0
        self._fx, self._fy, self._fz = (F[..., k].tolist() for k in range(3))

    def __call__(self, dx: float, dy: float) -> tuple[float, float, float]:
        """Force (N) at offset (dx, dy) (m) of the particle from the magnet's projection; 0 beyond extent."""
        sx, sy = (1.0 if dx >= 0 else -1.0), (1.0 if dy >= 0 else -1.0)
        u, v = abs(dx) / self.h, abs(dy) / self.h
        i, j = int(u), int(v)
        if i >= self.n - 1 or j >= self.n - 1:
            return 0.0, 0.0, 0.0
        a, b = u - i, v - j
        w00, w10, w01, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
        fx, fy, fz = self._fx, self._fy, self._fz
        rx0, rx1, ry0, ry1, rz0, rz1 = fx[i], fx[i + 1], fy[i], fy[i + 1], fz[i], fz[i + 1]
        return (sx * (w00 * rx0[j] + w10 * rx1[j] + w01 * rx0[j + 1] + w11 * rx1[j + 1]),
                sy * (w00 * ry0[j] + w10 * ry1[j] + w01 * ry0[j + 1] + w11 * ry1[j + 1]),
                w00 * rz0[j] + w10 * rz1[j] + w01 * rz0[j + 1] + w11 * rz1[j + 1])

    def max_stiffness(self) -> float:
        """Largest in-plane stiffness |dF/dx| (N/m) on the grid (finite differences)."""
        F = self.grid
        kx = np.abs(np.diff(F[..., 0], axis=0)).max() / self.h
        ky = np.abs(np.diff(F[..., 1], axis=1)).max() / self.h
        return float(max(kx, ky))

    def capture_radius(self) -> float:
        """Smallest, over directions, of the largest offset at which the in-plane pull still beats
        static friction: beyond it a resting particle no longer follows the magnet."""
        p = self.params
        weight = p.mass * p.gravity
        r = np.arange(0.0, p.map_extent, p.map_spacing / 2)
        best = math.inf
        for th in np.linspace(0, math.pi / 2, 7):
            f = np.array([self(x * math.cos(th), x * math.sin(th)) for x in r])
            ok = np.hypot(f[:, 0], f[:, 1]) > p.mu_static * (weight - f[:, 2])
            best = min(best, float(r[np.nonzero(ok)[0].max()]) if ok.any() else 0.0)
        return best


@functools.lru_cache(maxsize=8)
def force_map(params: ParticleParams) -> ForceMap:
    """The (cached) force map of ``params``; the lift-off check runs here."""
    fm = ForceMap(params)
    weight = params.mass * params.gravity
    fz = float(fm.grid[..., 2].max())
    if fz >= weight:
        raise ValueError(f"magnet_height={params.magnet_height}: the vertical pull {fz * 1e3:.2f} mN exceeds the "
                         f"particle's weight {weight * 1e3:.2f} mN, the particle would jump to the magnet")
    return fm


class ParticleSim:
    """State ``(x, y, vx, vy)`` of the particle; :meth:`advance` moves it while the magnet moves."""

    def __init__(self, params: ParticleParams = ParticleParams()):
        self.params = params
        self.fmap = force_map(params)
        m, c = params.mass, params.viscous
        k = self.fmap.max_stiffness()
        g, w2 = c / m, k / m
        self.dt_limit = (g + math.sqrt(g * g + 4 * w2)) / w2
        if params.substep > 0.5 * self.dt_limit:
            raise ValueError(f"substep={params.substep} s exceeds half the stable limit {self.dt_limit:.4g} s of the "
                             f"linearised magnetic spring (k={k:.3g} N/m) with drag c={c} N s/m, mass {m:.3g} kg")
        self.x = self.y = self.vx = self.vy = 0.0

    def reset(self, x: float, y: float):
        self.x, self.y, self.vx, self.vy = float(x), float(y), 0.0, 0.0

    @property
    def position(self) -> tuple[float, float]:
        return self.x, self.y

    def advance(self, magnet_from, magnet_to, duration: float, wall=None) -> bool:
        """Simulate ``duration`` s while the magnet's projection moves linearly ``magnet_from`` ->
        ``magnet_to`` (x, y). ``wall(x, y) -> bool`` is polled each sub-step; returns True (and stops)
        when the particle touches a wall."""
        if not (math.isfinite(duration) and duration >= 0):
            raise ValueError(f"duration must be finite and >= 0 (s), got {duration}")
        p = self.params
        n = max(1, math.ceil(duration / p.substep - 1e-9))
        dt = duration / n
        m, weight = p.mass, p.mass * p.gravity
        damp = 1.0 / (1.0 + dt * p.viscous / m)
        fs, fk = p.mu_static * weight, p.mu_kinetic
        x, y, vx, vy = self.x, self.y, self.vx, self.vy
        ax, ay = magnet_from
        bx, by = magnet_to
        hit = False
        for s in range(1, n + 1):
            t = s / n
            fx, fy, fz = self.fmap(x - (ax + t * (bx - ax)), y - (ay + t * (by - ay)))
            normal = weight - fz
            if vx == 0.0 and vy == 0.0 and fx * fx + fy * fy <= (p.mu_static * normal) ** 2 and fs > 0:
                continue  # static friction holds
            vx, vy = (vx + dt * fx / m) * damp, (vy + dt * fy / m) * damp
            speed = math.hypot(vx, vy)
            dv = fk * normal * dt / m
            if speed <= dv:
                vx = vy = 0.0
            else:
                scale = 1.0 - dv / speed
                vx, vy = vx * scale, vy * scale
            x, y = x + dt * vx, y + dt * vy
            if wall is not None and wall(x, y):
                hit = True
                break
        self.x, self.y, self.vx, self.vy = x, y, vx, vy
        return hit
