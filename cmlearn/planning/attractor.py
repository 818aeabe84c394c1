"""Attractor dynamics with obstacle modulation (thesis Section 4.1.2.2; Khansari-Zadeh & Billard 2012).

Nominal system ``p' = A p + B u`` with the state feedback ``u = G P_g - K p`` and
``G = [K I] [[A, B], [I, 0]]^{-1} [0; I]`` (eq. 4.2); with ``A = B = I`` (the thesis's choice)
this gives ``f(p) = (K - I)(P_g - p)``, a linear attractor at ``P_g`` for ``K > I``.

Obstacles are superellipses ``Gamma(p) = |x'/a|^n + |y'/b|^n`` (``x', y'`` in the obstacle's
rotated frame; ``Gamma = 1`` on the boundary, > 1 outside). The modulation matrix
``M = E D E^{-1}`` with ``E = [n, t]`` (normal ``grad Gamma`` and tangent) and
``D = diag(1 - w / Gamma^(1/rho), 1 + w / Gamma^(1/rho))`` removes the velocity component into
the obstacle at its boundary, so a trajectory of ``p' = M f(p)`` that starts outside a convex
obstacle never enters it. Several obstacles: the product of their matrices with the weights
``w_k = prod_{i != k} (Gamma_i - 1) / ((Gamma_k - 1) + (Gamma_i - 1))`` of KB12 (eq. 23).
The discretisation of the thesis, ``p_{k+1} = p_k + h M f(p_k)``, is :meth:`AttractorDynamics.step`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Superellipse", "AttractorDynamics", "feedback_gain_G"]


def feedback_gain_G(K: np.ndarray, A: np.ndarray | None = None, B: np.ndarray | None = None) -> np.ndarray:
    """``G = [K I] [[A, B], [I, 0]]^{-1} [0; I]`` (eq. 4.2)."""
    K = np.asarray(K, dtype=float)
    n = K.shape[0]
    A = np.eye(n) if A is None else np.asarray(A, dtype=float)
    B = np.eye(n) if B is None else np.asarray(B, dtype=float)
    big = np.block([[A, B], [np.eye(n), np.zeros((n, n))]])
    return np.hstack([K, np.eye(n)]) @ np.linalg.solve(big, np.vstack([np.zeros((n, n)), np.eye(n)]))


@dataclass(frozen=True)
class Superellipse:
    center: tuple[float, float]
    a: float
    b: float
    angle: float = 0.0
    n: float = 4.0

    def __post_init__(self):
        if not (self.a > 0 and self.b > 0 and self.n >= 2):
            raise ValueError(f"need a, b > 0 and n >= 2, got a={self.a}, b={self.b}, n={self.n}")
        if not (len(self.center) == 2 and all(map(math.isfinite, (*self.center, self.a, self.b, self.angle, self.n)))):
            raise ValueError(f"center, a, b, angle and n must be finite (center 2 coordinates), got center="
                             f"{self.center!r}, a={self.a}, b={self.b}, angle={self.angle}, n={self.n}")

    def local(self, p) -> tuple[float, float]:
        c, s = math.cos(self.angle), math.sin(self.angle)
        dx, dy = p[0] - self.center[0], p[1] - self.center[1]
        return c * dx + s * dy, -s * dx + c * dy

    def gamma(self, p) -> float:
        x, y = self.local(p)
        return abs(x / self.a) ** self.n + abs(y / self.b) ** self.n

    def normal(self, p) -> np.ndarray:
        """Unit outward normal (gradient of Gamma) in the world frame."""
        x, y = self.local(p)
        gx = self.n * abs(x / self.a) ** (self.n - 1) * math.copysign(1.0, x) / self.a
        gy = self.n * abs(y / self.b) ** (self.n - 1) * math.copysign(1.0, y) / self.b
        c, s = math.cos(self.angle), math.sin(self.angle)
        g = np.array([c * gx - s * gy, s * gx + c * gy])
        norm = float(np.hypot(*g))
        if norm < 1e-12:  # at the centre: any direction
            return np.array([1.0, 0.0])
        return g / norm


class AttractorDynamics:
    def __init__(self, K=2.0, rho: float = 1.0, A=None, B=None):
        K = np.asarray(K, dtype=float)
        self.K = K * np.eye(2) if K.ndim == 0 else K
        if self.K.shape != (2, 2) or not np.isfinite(self.K).all():
            raise ValueError(f"K must be a finite scalar or 2x2, got {self.K.tolist()}")
        self.A = np.eye(2) if A is None else np.asarray(A, dtype=float)
        self.B = np.eye(2) if B is None else np.asarray(B, dtype=float)
        if self.A.shape != (2, 2) or self.B.shape != (2, 2):
            raise ValueError(f"A and B must be 2x2, got shapes {self.A.shape}, {self.B.shape}")
        if not rho > 0:
            raise ValueError(f"rho must be > 0, got {rho}")
        self.G, self.rho = feedback_gain_G(self.K, self.A, self.B), float(rho)
        closed = self.A - self.B @ self.K
        if (np.linalg.eigvals(closed).real >= 0).any():
            raise ValueError(f"K={self.K.tolist()} does not stabilise A - B K (eigenvalues "
                             f"{np.linalg.eigvals(closed).tolist()}); use K > I")

    def nominal(self, p, goal) -> np.ndarray:
        p, goal = np.asarray(p, dtype=float), np.asarray(goal, dtype=float)
        for name, v in (("p", p), ("goal", goal)):
            if v.shape != (2,) or not np.isfinite(v).all():
                raise ValueError(f"{name} must be 2 finite coordinates, got {v.tolist()}")
        u = self.G @ goal - self.K @ p
        return self.A @ p + self.B @ u

    def modulation(self, p, obstacles: list[Superellipse]) -> np.ndarray:
        M = np.eye(2)
        gammas = [max(o.gamma(p), 1.0 + 1e-12) for o in obstacles]
        for k, (o, gk) in enumerate(zip(obstacles, gammas)):
            w = 1.0
            for i, gi in enumerate(gammas):
                if i != k:
                    w *= (gi - 1) / ((gk - 1) + (gi - 1))
            nrm = o.normal(p)
            E = np.array([[nrm[0], -nrm[1]], [nrm[1], nrm[0]]])
            lam = w / gk ** (1 / self.rho)
            D = np.diag([1 - lam, 1 + lam])
            M = (E @ D @ E.T) @ M  # E is orthonormal: E^{-1} = E^T
        return M

    def velocity(self, p, goal, obstacles: list[Superellipse]) -> np.ndarray:
        """``M(p) f(p)``; inside an obstacle (Gamma < 1), the outward normal of the deepest one."""
        f = self.nominal(p, goal)
        if not obstacles:
            return f
        inside = [(o.gamma(p), o) for o in obstacles if o.gamma(p) < 1.0]
        if inside:
            return min(inside, key=lambda t: t[0])[1].normal(p) * float(np.hypot(*f) + 1e-3)
        return self.modulation(p, obstacles) @ f

    def step(self, p, goal, obstacles, h: float) -> np.ndarray:
        """``p + h M f(p)`` (the thesis's difference scheme)."""
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"h (the step size) must be finite and > 0, got {h}")
        return np.asarray(p, dtype=float) + h * self.velocity(p, goal, obstacles)
