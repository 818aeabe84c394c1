"""Execution-extended RRT (Bruce & Veloso 2002) over axis-aligned rectangular obstacles.

An RRT whose target point is, with probability ``p_goal``, the goal; with probability
``p_waypoint``, a random point of the *waypoint cache* (the nodes of previous plans, so that a
replanning run re-grows the old path cheaply); otherwise a uniform sample of the bounds. The
nearest tree node extends by at most ``step`` toward the target if the segment stays ``margin``
away from every rectangle; the search ends when a node can connect straight to the goal. Failure
(no path within ``max_nodes``) returns ``None``. The path is shortcut-smoothed.

Rectangles are ``(xmin, ymin, xmax, ymax)`` in metres.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["ERRT", "segment_hits"]


def segment_hits(a, b, rects: np.ndarray, margin: float = 0.0) -> bool:
    """True if segment a-b meets any rectangle (n, 4) inflated by ``margin`` (slab test, vectorised)."""
    if len(rects) == 0:
        return False
    lo = rects[:, :2] - margin
    hi = rects[:, 2:] + margin
    a = np.asarray(a, dtype=float)
    d = np.asarray(b, dtype=float) - a
    t0, t1 = np.zeros(len(rects)), np.ones(len(rects))
    for k in range(2):
        if abs(d[k]) < 1e-15:
            inside = (a[k] >= lo[:, k]) & (a[k] <= hi[:, k])
            t0 = np.where(inside, t0, 2.0)
            continue
        ta, tb = (lo[:, k] - a[k]) / d[k], (hi[:, k] - a[k]) / d[k]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    return bool((t0 <= t1).any())


class ERRT:
    def __init__(self, bounds, step: float = 0.02, p_goal: float = 0.1, p_waypoint: float = 0.5,
                 cache_size: int = 100, max_nodes: int = 3000, margin: float = 0.0, seed: int = 0):
        try:
            self.bounds = tuple(float(v) for v in bounds)
        except (TypeError, ValueError):
            self.bounds = ()
        if len(self.bounds) != 4 or not (all(map(math.isfinite, self.bounds)) and self.bounds[0] < self.bounds[2]
                                         and self.bounds[1] < self.bounds[3]):
            raise ValueError(f"bounds must be (xmin, ymin, xmax, ymax) with min < max, got {bounds!r}")
        if not (0 <= p_goal and 0 <= p_waypoint and p_goal + p_waypoint <= 1):
            raise ValueError(f"need p_goal, p_waypoint >= 0 and p_goal + p_waypoint <= 1, got {p_goal}, {p_waypoint}")
        if not (step > 0 and isinstance(max_nodes, (int, np.integer)) and max_nodes >= 1):
            raise ValueError(f"step must be > 0 and max_nodes an int >= 1, got {step!r}, {max_nodes!r}")
        if not (margin >= 0 and cache_size >= 0):
            raise ValueError(f"margin (m) and cache_size (waypoints) must be >= 0, got {margin}, {cache_size}")
        self.step, self.p_goal, self.p_waypoint = step, p_goal, p_waypoint
        self.cache_size, self.max_nodes, self.margin = cache_size, max_nodes, margin
        self.rng = np.random.default_rng(seed)
        self.waypoints: list[tuple[float, float]] = []
        self.tree: np.ndarray = np.zeros((0, 2))
        self.parents: list[int] = []

    @staticmethod
    def distance(p, rects: np.ndarray) -> float:
        """Distance from point p to the nearest rectangle (0 inside one)."""
        if len(rects) == 0:
            return math.inf
        dx = np.maximum(np.maximum(rects[:, 0] - p[0], p[0] - rects[:, 2]), 0)
        dy = np.maximum(np.maximum(rects[:, 1] - p[1], p[1] - rects[:, 3]), 0)
        return float(np.hypot(dx, dy).min())

    def plan(self, start, goal, rects) -> list[tuple[float, float]] | None:
        """Path [start, ..., goal] avoiding ``rects`` (n, 4), or None."""
        rects = np.asarray(rects, dtype=float)
        if rects.size and (rects.ndim not in (1, 2) or rects.shape[-1] != 4):
            raise ValueError(f"rects must be (n, 4) rectangles (xmin, ymin, xmax, ymax), got shape {rects.shape}")
        rects = rects.reshape(-1, 4)
        for name, p in (("start", start), ("goal", goal)):
            if np.shape(p) != (2,) or not np.isfinite(np.asarray(p, dtype=float)).all():
                raise ValueError(f"{name} must be 2 finite coordinates (m), got {p!r}")
        start, goal = tuple(map(float, start)), tuple(map(float, goal))
        # a start or goal inside an obstacle has no path; one closer to an obstacle than the margin shrinks it
        clearance = min(self.distance(start, rects), self.distance(goal, rects))
        if clearance <= 0:
            return None
        margin = min(self.margin, 0.9 * clearance)
        saved, self.margin = self.margin, margin
        try:
            return self._plan(start, goal, rects)
        finally:
            self.margin = saved

    def _plan(self, start, goal, rects):
        nodes = np.empty((self.max_nodes + 1, 2))
        nodes[0] = start
        parents, n = [-1], 1
        xmin, ymin, xmax, ymax = self.bounds
        found = None
        if not segment_hits(start, goal, rects, self.margin):
            found = 0
        iters = 0
        while found is None and n <= self.max_nodes and iters < 5 * self.max_nodes:
            iters += 1
            u = self.rng.random()
            if u < self.p_goal:
                target = goal
            elif u < self.p_goal + self.p_waypoint and self.waypoints:
                target = self.waypoints[self.rng.integers(len(self.waypoints))]
            else:
                target = (self.rng.uniform(xmin, xmax), self.rng.uniform(ymin, ymax))
            i = int(((nodes[:n] - target) ** 2).sum(1).argmin())
            d = math.dist(nodes[i], target)
            if d < 1e-9:
                continue
            s = min(1.0, self.step / d)
            new = (nodes[i, 0] + s * (target[0] - nodes[i, 0]), nodes[i, 1] + s * (target[1] - nodes[i, 1]))
            if segment_hits(nodes[i], new, rects, self.margin):
                continue
            nodes[n] = new
            parents.append(i)
            n += 1
            if math.dist(new, goal) < 2 * self.step and not segment_hits(new, goal, rects, self.margin):
                found = n - 1
        self.tree, self.parents = nodes[:n].copy(), parents
        if found is None:
            return None
        path, k = [goal], found
        while k >= 0:
            path.append(tuple(nodes[k]))
            k = parents[k]
        path = self._shortcut(path[::-1], rects)
        self._remember(path)
        return path

    def _shortcut(self, path, rects):
        out, i = [path[0]], 0
        while i < len(path) - 1:
            j = len(path) - 1
            while j > i + 1 and segment_hits(path[i], path[j], rects, self.margin):
                j -= 1
            out.append(path[j])
            i = j
        return out

    def _remember(self, path):
        """Waypoint cache: points along the last path (dense enough to re-grow it)."""
        pts = []
        for a, b in zip(path[:-1], path[1:]):
            k = max(1, int(math.dist(a, b) / self.step))
            pts += [(a[0] + (b[0] - a[0]) * t / k, a[1] + (b[1] - a[1]) * t / k) for t in range(k)]
        pts.append(path[-1])
        self.waypoints = (pts + self.waypoints)[: self.cache_size]
