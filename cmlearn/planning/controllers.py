"""The classical baselines as Sub-controller 2 of the switching controller (``act(obs, info) -> action``).

Both see what the thesis's planners saw: the end-effector camera image (channel 0 of the
observation, taken at ``info["view_xy"]``), the end-effector and goal positions, and the bounds
of the workspace. Both turn a desired Cartesian direction into one of the 4 discrete moves
(+x, -x, +y, -y) by the largest projection, as in the thesis.

* :class:`AttractorController`: obstacles are fitted to what the camera sees *now*: the dark
  pixels (<= ``threshold``) of the view, cut into tiles of ``tile`` pixels (the thesis's robot
  "partially senses an obstacle with a maximum height and width of 2 cm"), each blob of a tile
  (``cv2.findContours``) fitted by a rotated rectangle (``cv2.minAreaRect``) and replaced by the
  superellipse circumscribing it, inflated by ``margin``; the modulated attractor
  (:mod:`cmlearn.planning.attractor`) gives the direction.
* :class:`ERRTController`: every view is pasted into a world-frame memory of seen obstacles; when
  it changes, the quadtree (:mod:`cmlearn.planning.quadtree`) turns it into rectangles and, if the
  current path now meets one (or the end-effector left the path, e.g. after a recapture),
  :class:`~cmlearn.planning.errt.ERRT` replans from the end-effector; the controller follows the
  path's next waypoint.
"""
from __future__ import annotations

import math
import numbers

import numpy as np

from physics.checks import is_finite_real, is_int

from .attractor import AttractorDynamics, Superellipse
from .errt import ERRT, segment_hits
from .quadtree import quadtree_rectangles

__all__ = ["AttractorController", "ERRTController", "direction_to_action", "fit_superellipses"]

_DIRS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


def direction_to_action(v) -> int:
    """The discrete move (+x, -x, +y, -y) closest in direction to ``v``."""
    v = np.asarray(v, dtype=float)
    if v.shape != (2,) or not np.isfinite(v).all():
        raise ValueError(f"v must be a finite 2-D direction, got {v.tolist()}")
    return int(np.argmax(_DIRS @ v))


def _check_settings(grey=None, lengths=None, positive=None, counts=None) -> None:
    """ValueError naming the setting unless each of ``grey`` is a grey level in [0, 255] (a NaN threshold found no
    obstacle at all), each of ``lengths`` finite and >= 0, each of ``positive`` finite and > 0 and each of ``counts``
    an integer >= 1."""
    for name, v in (grey or {}).items():
        if not (isinstance(v, numbers.Real) and 0 <= v <= 255):
            raise ValueError(f"{name} (a grey level: darker is an obstacle) must be in [0, 255], got {v!r}")
    for name, v in (lengths or {}).items():
        if not (is_finite_real(v) and v >= 0):
            raise ValueError(f"{name} must be finite and >= 0 (m), got {v!r}")
    for name, v in (positive or {}).items():
        if not (is_finite_real(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
    for name, v in (counts or {}).items():
        if not (is_int(v) and v >= 1):
            raise ValueError(f"{name} must be an integer >= 1, got {v!r}")


def pixel_to_world(view_xy, rc, size: int, mpp: float):
    """World (x, y) of pixel centres ``rc`` (..., 2 as row, col) of a view taken at ``view_xy``."""
    rc = np.asarray(rc, dtype=float)
    return np.stack([view_xy[0] + (rc[..., 1] + 0.5 - size / 2) * mpp,
                     view_xy[1] - (rc[..., 0] + 0.5 - size / 2) * mpp], -1)


def fit_superellipses(view: np.ndarray, view_xy, mpp: float, threshold: int = 50, tile: int = 14,
                      margin: float = 0.01, n: float = 4.0, min_pixels: int = 4) -> list[Superellipse]:
    import cv2
    size = view.shape[0]
    mask = (np.asarray(view) <= threshold).astype(np.uint8)
    out = []
    for r0 in range(0, size, tile):
        for c0 in range(0, size, tile):
            sub = mask[r0:r0 + tile, c0:c0 + tile]
            if int(sub.sum()) < min_pixels:
                continue
            contours, _ = cv2.findContours(sub.copy(), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            for cnt in contours:
                if cv2.contourArea(cnt) + len(cnt) < min_pixels:
                    continue
                (cx, cy), (w, h), ang = cv2.minAreaRect(cnt.astype(np.float32))
                center = pixel_to_world(view_xy, np.array([r0 + cy, c0 + cx]), size, mpp)
                a, b = (w + 1) / 2 * mpp, (h + 1) / 2 * mpp
                k = 2 ** (1 / n)  # the superellipse through the rectangle's corners
                out.append(Superellipse((float(center[0]), float(center[1])), a * k + margin, b * k + margin,
                                        -math.radians(ang), n))
    return out


class AttractorController:
    def __init__(self, mpp: float, K: float = 2.0, rho: float = 1.0, margin: float = 0.01, tile: int = 14,
                 threshold: int = 50):
        if not (math.isfinite(mpp) and mpp > 0):
            raise ValueError(f"mpp (metres per pixel) must be finite and > 0, got {mpp}")
        _check_settings(grey={"threshold": threshold}, lengths={"margin": margin}, counts={"tile": tile})
        self.dyn = AttractorDynamics(K, rho)
        self.mpp, self.margin, self.tile, self.threshold = mpp, margin, tile, threshold
        self.obstacles: list[Superellipse] = []

    def reset(self, info=None):
        self.obstacles = []

    def act(self, obs, info) -> int:
        view = np.asarray(obs)[0]
        self.obstacles = fit_superellipses(view, info["view_xy"], self.mpp, self.threshold, self.tile, self.margin)
        v = self.dyn.velocity(np.asarray(info["ee_xy"]), np.asarray(info["goal_xy"]), self.obstacles)
        return direction_to_action(v)


class ERRTController:
    def __init__(self, mpp: float, bounds=(0.0, 0.0, 1.0, 1.0), margin: float = 0.008, min_size: int = 2, threshold: int = 50,
                 step: float = 0.02, max_nodes: int = 1500, lookahead: float = 0.012, move: float = 0.01, seed: int = 0):
        if not (math.isfinite(mpp) and mpp > 0):
            raise ValueError(f"mpp (metres per pixel) must be finite and > 0, got {mpp}")
        _check_settings(grey={"threshold": threshold}, lengths={"margin": margin},
                       positive={"lookahead": lookahead, "move": move}, counts={"min_size": min_size})
        self.mpp, self.margin, self.min_size, self.threshold = mpp, margin, min_size, threshold
        self.bounds, self.step, self.max_nodes, self.lookahead, self.seed = bounds, step, max_nodes, lookahead, seed
        self.move = move
        self.reset()

    def reset(self, info=None):
        if info is not None and "bounds" in info:
            self.bounds = info["bounds"]
        xmin, ymin, xmax, ymax = self.bounds
        pad = 0.1
        self._origin = (xmin - pad, ymax + pad)  # world (x, y) of pixel (0, 0)'s corner
        self._shape = (int((ymax - ymin + 2 * pad) / self.mpp) + 1, int((xmax - xmin + 2 * pad) / self.mpp) + 1)
        self.known = np.zeros(self._shape, dtype=bool)
        self.rects = np.zeros((0, 4))
        self.path: list | None = None
        self.planner = ERRT(self.bounds, self.step, margin=self.margin, max_nodes=self.max_nodes, seed=self.seed)
        self.replans, self.failures, self._dirty = 0, 0, False

    def _paste(self, view, view_xy):
        size = view.shape[0]
        r0 = int(round((self._origin[1] - view_xy[1]) / self.mpp - size / 2))
        c0 = int(round((view_xy[0] - self._origin[0]) / self.mpp - size / 2))
        if r0 < 0 or c0 < 0 or r0 + size > self._shape[0] or c0 + size > self._shape[1]:
            return
        new = view <= self.threshold
        region = self.known[r0:r0 + size, c0:c0 + size]
        if (new & ~region).any():
            region |= new
            self._dirty = True

    def _rectangles(self) -> np.ndarray:
        rects = quadtree_rectangles(np.where(self.known, 0, 255).astype(np.uint8), 0, self.min_size)
        if not rects:
            return np.zeros((0, 4))
        r = np.asarray(rects, dtype=float)
        ox, oy = self._origin
        return np.stack([ox + r[:, 1] * self.mpp, oy - r[:, 2] * self.mpp,
                         ox + r[:, 3] * self.mpp, oy - r[:, 0] * self.mpp], 1)

    def _path_blocked(self, p) -> bool:
        pts = [tuple(p)] + list(self.path[1:])
        return any(segment_hits(a, b, self.rects, self.margin * 0.5) for a, b in zip(pts[:-1], pts[1:]))

    def act(self, obs, info) -> int:
        view = np.asarray(obs)[0]
        self._paste(view, info["view_xy"])
        if self._dirty:
            self.rects, self._dirty = self._rectangles(), False
        p, goal = np.asarray(info["ee_xy"], dtype=float), tuple(info["goal_xy"])
        if self.path is not None and self.path[-1] != goal:
            self.path = None
        if self.path is not None and self._off_path(p):
            self.path = None
        if self.path is None or self._path_blocked(p):
            self.replans += 1
            self.path = self.planner.plan(tuple(p), goal, self.rects)
            if self.path is None:
                self.failures += 1
                return direction_to_action(np.asarray(goal) - p)
        while len(self.path) > 2 and math.dist(p, self.path[1]) < self.lookahead:
            self.path.pop(1)
        target = np.asarray(self.path[1] if len(self.path) > 1 else goal)
        if len(self.path) > 1 and math.dist(p, self.path[1]) < self.lookahead:
            target = np.asarray(goal)
        # the move toward the target whose next position keeps clear of the seen obstacles
        order = np.argsort(-(_DIRS @ (target - p)))
        for a in order[:2]:
            if ERRT.distance(p + self.move * _DIRS[a], self.rects) > self.margin / 2:
                return int(a)
        return int(order[0])

    def _off_path(self, p) -> bool:
        a, b = np.asarray(self.path[0]), np.asarray(self.path[1])
        d = b - a
        t = float(np.clip(np.dot(p - a, d) / max(float(d @ d), 1e-12), 0, 1))
        off = float(np.hypot(*(a + t * d - p)))
        self.path[0] = tuple(p)
        return off > 0.04
