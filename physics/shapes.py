"""Initial rod geometries for scenes: node positions and tangent frames, in SI, float64.

Every builder returns ``(p, R)`` with ``p`` (n, 3) node positions and ``R`` (n, 3, 3) node frames
whose third column (body E3) is the unit tangent of the centreline, as the rod's axis convention
requires. Planar curves keep body E2 along the plane normal, so ``E1 = E2 x E3`` lies in the plane.

Open curves use :func:`strain_free_positions`: given the node frames, each element's chord is
chosen so that the discrete shear/axial strain ``(R_a^T d + R_b^T d) / 2l`` is exactly ``E3``, so the
initial configuration stores only bending energy (stiff shear/axial modes, whose frequencies sit
near the explicit update's stability limit, start at rest). A closed loop must close, so
:func:`ellipse_loop` places its nodes on the exact ellipse with zero axial strain (a little shear
remains where the curvature changes fast).

* :func:`bent_cantilever` — a clamped rod bent as by a tip point load: curvature decreasing
  linearly from the base to zero at the tip (the small-deflection moment distribution), scaled so
  the tip cross-section is rotated by a given rotation vector.
* :func:`ellipse_loop` — a closed ellipse through the origin, equal elements, no axial strain.
* :func:`circular_arc` — a circular arc of given turning angle.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

from .checks import is_int
from .lie import so3_exp

__all__ = ["strain_free_positions", "bent_cantilever", "cantilever_rotation_for_offset",
           "planar_frames", "ellipse_loop", "ellipse_perimeter", "circular_arc"]


def strain_free_positions(R: Tensor, lengths: Sequence[float], origin=(0.0, 0.0, 0.0)) -> Tensor:
    """Node positions (n, 3) from node frames ``R`` (n, 3, 3) and element lengths (n-1,) with zero
    discrete shear and axial strain: ``d_i = 2 l_i (R_a^T + R_b^T)^{-1} E3``."""
    l = torch.as_tensor(lengths, dtype=torch.float64)
    e3 = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    A = R[:-1].transpose(-1, -2) + R[1:].transpose(-1, -2)
    d = torch.linalg.solve(A, 2 * l[:, None] * e3)
    p0 = torch.as_tensor(origin, dtype=torch.float64).reshape(1, 3)
    return torch.cat((p0, p0 + d.cumsum(0)))


def _check_node_s(node_s, where: str) -> np.ndarray:
    """Node arclengths as a float64 array: 1-D, at least two, finite, from 0, strictly increasing."""
    s = np.asarray(node_s, dtype=np.float64)
    if s.ndim != 1 or s.size < 2 or not np.isfinite(s).all() or s[0] != 0 or not (np.diff(s) > 0).all():
        raise ValueError(f"{where}: node_s must be finite node arclengths (m) from 0, strictly increasing, "
                         f"at least two, got {s.tolist()}")
    return s


def _tip_load_profile(s: np.ndarray, L: float) -> np.ndarray:
    """Rotation-angle profile g(s) of a tip-loaded cantilever, g(0) = 0, g(L) = 1."""
    x = s / L
    return 2 * x - x * x


def bent_cantilever(node_s: Sequence[float], tip_rotation: Sequence[float]) -> tuple[Tensor, Tensor]:
    """Clamped rod (base at the origin, base frame identity, axis +E3) bent as by a tip force.

    ``node_s`` node arclengths (m), last one the length ``L``; ``tip_rotation`` the rotation vector
    (rad, world = base frame) of the tip cross-section. The node frames are
    ``R(s) = exp(g(s) Theta^)`` with ``g(s) = 2 s/L - (s/L)^2``; for a rotation axis normal to E3
    this is planar bending in the plane normal to the axis. Positions: :func:`strain_free_positions`.
    """
    s = _check_node_s(node_s, "bent_cantilever")
    th = np.asarray(tip_rotation, dtype=np.float64)
    if th.shape != (3,) or not np.isfinite(th).all():
        raise ValueError(f"bent_cantilever: tip_rotation must be a finite rotation vector (3,) (rad), got {th.tolist()}")
    w = torch.tensor(_tip_load_profile(s, float(s[-1]))[:, None] * th[None, :], dtype=torch.float64)
    R = so3_exp(w)
    return strain_free_positions(R, np.diff(s)), R


def cantilever_rotation_for_offset(node_s: Sequence[float], offset: Sequence[float]) -> np.ndarray:
    """Tip rotation vector that makes :func:`bent_cantilever` put the tip node at lateral ``offset``
    (dx, dy) (m) from the straight axis (solved exactly, not by the linear ``theta = 3 d / 2L``)."""
    u = np.array([offset[0], offset[1], 0.0], dtype=np.float64)
    if not np.isfinite(u).all():
        raise ValueError(f"cantilever_rotation_for_offset: offset must be finite (m), got {list(offset)}")
    d = float(np.linalg.norm(u))
    length = float(_check_node_s(node_s, "cantilever_rotation_for_offset")[-1])
    if d == 0:
        return np.zeros(3)
    if d >= 0.9 * length:
        raise ValueError(f"tip offset {d} m is too large for a rod of length {length} m")
    u /= d
    axis = np.cross([0.0, 0.0, 1.0], u)  # rotating e3 about this axis moves the tip along u

    def lateral(theta):
        return float(bent_cantilever(node_s, theta * axis)[0][-1, :2].norm()) - d

    theta = scipy.optimize.brentq(lateral, 0.0, 0.5 * math.pi * 1.999, xtol=1e-15)
    return theta * axis


def planar_frames(tangent: np.ndarray, normal: Sequence[float] = (0.0, 0.0, 1.0)) -> Tensor:
    """Frames (n, 3, 3) with E3 = unit tangent, E2 = unit plane normal, E1 = E2 x E3; the tangents must
    lie in the plane (normal to ``normal``)."""
    tangent = np.asarray(tangent, dtype=np.float64)
    norm = np.linalg.norm(tangent, axis=-1, keepdims=True)
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) == 0:
        raise ValueError(f"planar_frames: normal must be a finite non-zero (3,) vector, got {n.tolist()}")
    if tangent.shape[-1:] != (3,) or not np.isfinite(tangent).all() or not (norm > 0).all():
        raise ValueError("planar_frames: tangent must be finite non-zero (..., 3) vectors")
    t = tangent / norm
    n = n / np.linalg.norm(n)
    off = np.abs(t @ n)
    if off.size and off.max() > 1e-9:  # the frame would not be a rotation (det 0 for a tangent along the normal)
        raise ValueError(f"planar_frames: the tangents must lie in the plane normal to {n.tolist()}; "
                         f"|tangent . normal| reaches {off.max():.3g}")
    e2 = np.broadcast_to(n, t.shape)
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


def _projected_chord(ta: float, tb: float, a: float, b: float) -> float:
    """E3 . (R_a^T d + R_b^T d) / 2 between ellipse points at parameters ta, tb (tangent frames)."""
    xa, ya, txa, tya = _ellipse_points(ta, a, b)
    xb, yb, txb, tyb = _ellipse_points(tb, a, b)
    na, nb = math.hypot(txa, tya), math.hypot(txb, tyb)
    dx, dy = xb - xa, yb - ya
    return 0.5 * ((txa / na + txb / nb) * dx + (tya / na + tyb / nb) * dy)


def _ellipse_march(n: int, a: float, b: float, l: float) -> np.ndarray:
    """Parameters of n + 1 nodes from theta = 0 with every projected chord equal to ``l``."""
    th = np.zeros(n + 1)
    hi_step = 3 * l / min(a, b)
    for i in range(n):
        ta = th[i]

        def gap(tb):
            return _projected_chord(ta, tb, a, b) - l
        hi = ta + hi_step
        if gap(hi) < 0:  # a long element on a flat ellipse: the projected chord peaks and falls within the bracket
            grid = np.linspace(ta, hi, 65)[1:]
            hi = grid[int(np.argmax([gap(x) >= 0 for x in grid]))]  # the first point past the chord's length
        th[i + 1] = scipy.optimize.brentq(gap, ta, hi, xtol=1e-14)
    return th


def ellipse_loop(n_elements: int, width: float, height: float, element_length: float | None = None,
                 min_chord_ratio: float | None = None) -> tuple[Tensor, Tensor, float]:
    """Closed ellipse in the xy-plane, width along x and height along y, with its top vertex at
    the origin, as ``n_elements`` equal elements with zero axial strain.

    Nodes are placed along the ellipse so that every element's projected chord
    ``E3 . (R_a^T d + R_b^T d) / 2`` (tangent frames, E2 = +z) is the same length ``l``, and ``l`` is
    chosen so that the loop closes: the first and last nodes coincide at the origin with the same
    frame (tangent +x). With ``element_length`` given, the ellipse is scaled uniformly (by
    ``element_length / l``) to close with that length instead (to bend one rod into several
    ellipses). Returns ``(p, R, l)``.

    A mesh too coarse for the ellipse's sharpest bends may still close, with elements turning by up to a
    right angle and more. With ``min_chord_ratio`` given, such a loop is a ``ValueError`` instead: when
    its ``n_elements`` chords add up to less than that fraction of the ellipse's perimeter. A mesh whose
    equal elements cannot close the loop at all is a ``ValueError``.
    """
    if not is_int(n_elements) or n_elements < 3:
        raise ValueError(f"ellipse_loop: n_elements must be an integer >= 3, got {n_elements!r}")
    if not all(math.isfinite(x) and x > 0 for x in (width, height)):
        raise ValueError(f"ellipse_loop: width and height must be finite and > 0 (m), got {width!r}, {height!r}")
    if element_length is not None and not (math.isfinite(element_length) and element_length > 0):
        raise ValueError(f"ellipse_loop: element_length must be finite and > 0 (m), got {element_length!r}")
    a, b = width / 2, height / 2
    guess = ellipse_perimeter(width, height) / n_elements

    def gap(l):
        try:
            th = _ellipse_march(n_elements - 1, a, b, l)
        except ValueError:  # no node reaches a projected chord this long: the chords are too long
            return -l
        return _projected_chord(th[-1], 2 * math.pi, a, b) - l  # the last element must close

    # coarse meshes: chords well short of the arcs
    lo = next((r * guess for r in (0.97, 0.8, 0.7, 0.6, 0.5, 0.4) if gap(r * guess) > 0), None)
    l = None if lo is None else scipy.optimize.brentq(gap, lo, 1.001 * guess, xtol=1e-15)
    if l is not None and min_chord_ratio is not None and l < min_chord_ratio * guess:
        raise ValueError(f"ellipse_loop: {n_elements} elements close a {width} x {height} ellipse with chords "
                         f"{l / guess:.3f} of its perimeter, below min_chord_ratio={min_chord_ratio}")
    if l is None or abs(gap(l)) > 1e-9 * guess:  # brentq stopped at a jump of the march, not at a closure
        raise ValueError(f"ellipse_loop: n_elements={n_elements} equal elements cannot close a {width} x {height} "
                         "ellipse (too few for its sharpest bends)")
    theta = np.append(_ellipse_march(n_elements - 1, a, b, l), 2 * math.pi)
    scale = 1.0 if element_length is None else element_length / l
    x, y, tx, ty = _ellipse_points(theta, a, b)
    p = scale * np.stack((x, y, np.zeros_like(x)), -1)
    p[-1] = 0.0
    t = np.stack((tx, ty, np.zeros_like(tx)), -1)
    return torch.tensor(p, dtype=torch.float64), planar_frames(t), l * scale


def circular_arc(node_s: Sequence[float], turning_angle: float) -> tuple[Tensor, Tensor]:
    """Planar circular arc in the xy-plane from the origin, start tangent +y, turning clockwise
    (about -z) by ``turning_angle`` rad over its length, close to ``p = R (1 - cos phi, sin phi, 0)``
    (:func:`strain_free_positions` lengthens each chord by about ``phi_i^2 / 6``, 1.6e-4 for 100
    elements over a half turn, which makes the clamped arc an exact discrete equilibrium)."""
    if not math.isfinite(turning_angle):
        raise ValueError(f"circular_arc: turning_angle must be finite (rad), got {turning_angle!r}")
    s = _check_node_s(node_s, "circular_arc")
    phi = np.zeros_like(s) if turning_angle == 0 else s / (s[-1] / turning_angle)  # 0: the straight rod
    t = np.stack((np.sin(phi), np.cos(phi), np.zeros_like(phi)), -1)
    R = planar_frames(t)
    return strain_free_positions(R, np.diff(s)), R
