"""Initial rod geometries for scenes: node positions and tangent frames, in SI, float64.

Every builder returns ``(p, R)`` with ``p`` (n, 3) node positions and ``R`` (n, 3, 3) node frames
whose third column (body E3) is the unit tangent of the centreline, as the rod's axis convention
requires. Planar curves keep body E2 along the plane normal, so ``E1 = E2 x E3`` lies in the plane.

* :func:`bent_cantilever` — a clamped rod bent as by a tip point load: curvature decreasing
  linearly from the base to zero at the tip (the small-deflection moment distribution), scaled so
  the tip cross-section is rotated by a given rotation vector; positions are the exact integral of
  the tangent (Gauss-Legendre per element), so the shape is inextensible for any angle.
* :func:`ellipse_loop` — a closed ellipse through the origin with equal-arclength nodes.
* :func:`circular_arc` — a circular arc of given turning angle.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

from .lie import so3_exp

__all__ = ["bent_cantilever", "cantilever_rotation_for_offset", "planar_frames", "ellipse_loop",
           "ellipse_perimeter", "circular_arc"]

_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)


def _tip_load_profile(s: np.ndarray, L: float) -> np.ndarray:
    """Rotation-angle profile g(s) of a tip-loaded cantilever, g(0) = 0, g(L) = 1."""
    x = s / L
    return 2 * x - x * x


def _rotate_e3(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """exp(angle axis^) e3 for a unit axis (3,) and angles (...): Rodrigues on e3."""
    e3 = np.array([0.0, 0.0, 1.0])
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return c * e3 + s * np.cross(axis, e3) + (1 - c) * axis[2] * axis


def bent_cantilever(node_s: Sequence[float], tip_rotation: Sequence[float]) -> tuple[Tensor, Tensor]:
    """Clamped rod (base at the origin, base frame identity, axis +E3) bent as by a tip force.

    ``node_s`` node arclengths (m), last one the length ``L``; ``tip_rotation`` the rotation vector
    (rad, world = base frame) of the tip cross-section. The node frames are
    ``R(s) = exp(g(s) Theta^)`` with ``g(s) = 2 s/L - (s/L)^2``; for a rotation axis normal to E3
    this is planar bending in the plane normal to the axis.
    """
    s = np.asarray(node_s, dtype=np.float64)
    th = np.asarray(tip_rotation, dtype=np.float64)
    L = float(s[-1])
    angle = float(np.linalg.norm(th))
    axis = th / angle if angle > 0 else np.array([1.0, 0.0, 0.0])
    p = np.zeros((len(s), 3))
    for i in range(len(s) - 1):  # integrate the tangent over each element
        a, b = s[i], s[i + 1]
        q = 0.5 * (b - a) * _GL_X + 0.5 * (a + b)
        t = _rotate_e3(axis, angle * _tip_load_profile(q, L))
        p[i + 1] = p[i] + 0.5 * (b - a) * (_GL_W[:, None] * t).sum(0)
    w = torch.tensor(_tip_load_profile(s, L)[:, None] * th[None, :], dtype=torch.float64)
    return torch.tensor(p, dtype=torch.float64), so3_exp(w)


def cantilever_rotation_for_offset(length: float, offset: Sequence[float]) -> np.ndarray:
    """Tip rotation vector that makes :func:`bent_cantilever` put the tip at lateral ``offset``
    (dx, dy) (m) from the straight axis. Solved exactly (not by the linear ``theta = 3 d / 2L``)."""
    u = np.array([offset[0], offset[1], 0.0], dtype=np.float64)
    d = float(np.linalg.norm(u))
    if d == 0:
        return np.zeros(3)
    if d >= 0.9 * length:
        raise ValueError(f"tip offset {d} m is too large for a rod of length {length} m")
    u /= d
    axis = np.cross([0.0, 0.0, 1.0], u)  # rotating e3 about this axis moves the tip along u

    def lateral(theta):
        q = 0.5 * length * (_GL_X + 1)
        return 0.5 * length * float((_GL_W * np.sin(theta * _tip_load_profile(q, length))).sum()) - d

    theta = scipy.optimize.brentq(lateral, 0.0, 0.5 * math.pi * 1.999, xtol=1e-15)
    return theta * axis


def planar_frames(tangent: np.ndarray, normal: Sequence[float] = (0.0, 0.0, 1.0)) -> Tensor:
    """Frames (n, 3, 3) with E3 = unit tangent, E2 = plane normal, E1 = E2 x E3."""
    t = tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)
    e2 = np.broadcast_to(np.asarray(normal, dtype=np.float64), t.shape)
    e1 = np.cross(e2, t)
    return torch.tensor(np.stack((e1, e2, t), -1), dtype=torch.float64)


def _ellipse_points(theta, a, b):
    """x = a sin(theta), y = b (cos(theta) - 1): starts at the origin heading +x, turning clockwise."""
    x = a * np.sin(theta)
    y = b * (np.cos(theta) - 1.0)
    tx, ty = a * np.cos(theta), -b * np.sin(theta)
    return x, y, tx, ty


def _ellipse_arclength(a: float, b: float, n_grid: int = 400_001):
    th = np.linspace(0.0, 2 * math.pi, n_grid)
    speed = np.hypot(a * np.cos(th), b * np.sin(th))
    ds = 0.5 * (speed[1:] + speed[:-1]) * np.diff(th)
    return th, np.concatenate(([0.0], np.cumsum(ds)))


def ellipse_perimeter(width: float, height: float) -> float:
    """Perimeter (m) of an ellipse with full axes ``width`` (x) and ``height`` (y)."""
    return float(_ellipse_arclength(width / 2, height / 2)[1][-1])


def ellipse_loop(n_elements: int, width: float, height: float) -> tuple[Tensor, Tensor]:
    """Closed ellipse in the xy-plane, width along x and height along y, with its top vertex at
    the origin (centre ``(0, -height/2)``). ``n_elements + 1`` nodes at equal arclength; the first
    and last nodes coincide at the origin with the same frame (tangent +x, E2 = +z)."""
    a, b = width / 2, height / 2
    th, s = _ellipse_arclength(a, b)
    target = np.linspace(0.0, s[-1], n_elements + 1)
    theta = np.interp(target, s, th)
    theta[-1] = 2 * math.pi
    x, y, tx, ty = _ellipse_points(theta, a, b)
    p = np.stack((x, y, np.zeros_like(x)), -1)
    p[-1] = 0.0
    t = np.stack((tx, ty, np.zeros_like(tx)), -1)
    return torch.tensor(p, dtype=torch.float64), planar_frames(t)


def circular_arc(node_s: Sequence[float], turning_angle: float) -> tuple[Tensor, Tensor]:
    """Planar circular arc in the xy-plane from the origin, start tangent +y, turning clockwise
    (about -z) by ``turning_angle`` rad over its length: ``p = R (1 - cos phi, sin phi, 0)``."""
    s = np.asarray(node_s, dtype=np.float64)
    R = s[-1] / turning_angle
    phi = s / R
    p = np.stack((R * (1 - np.cos(phi)), R * np.sin(phi), np.zeros_like(phi)), -1)
    t = np.stack((np.sin(phi), np.cos(phi), np.zeros_like(phi)), -1)
    return torch.tensor(p, dtype=torch.float64), planar_frames(t)
