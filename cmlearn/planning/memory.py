"""Explored-map memory and an optimistic grid planner over it (navigation in unknown terrain).

The camera sees 12 cm of table; a memoryless policy cannot tell, at a branch of an unknown map,
which way leads on and which ends blind. :class:`MemoryPlanner` keeps what the views have shown:

* **memory** -- an occupancy grid over the map's bounds (``resolution``, default 2.5 mm): unknown
  until a view covers a cell, then free or wall (a pixel darker than ``wall_below``); wall wins;
* **plan** -- on the lattice of end-effector moves (``step`` = 1 cm, anchored at the current
  end-effector), Dijkstra from the goal's node over the nodes at least ``clearance`` from every
  *known* wall, unknown cells counting as free (the free-space assumption: the plan is optimistic
  and is redone after every view, so a dead end is left as soon as it is seen to be one); entering
  a node costs ``1 + soft_weight * max(0, 1 - c / soft_clearance)`` with ``c`` its known clearance,
  which keeps the path, and so the magnet and the lagging particle, in the middle of the channel;
* **outputs** -- the cost of each of the 4 moves (entering the node one move away plus its
  cost-to-go; ``inf`` where blocked) and a
  ``waypoint``: ``lookahead`` moves down the plan (the goal itself when it is nearer).

It uses only what the robot has: its camera views (``info["view_xy"]`` gives where each was
taken), its end-effector position and the goal. Two uses: :class:`MemoryPlannerController`, a
classical Sub-controller 2 that takes the move of least cost-to-go, and the environment's
``waypoint_lookahead`` option (:mod:`cmlearn.rl.env`), which marks the waypoint instead of the
goal in the observation's goal half so that the learnt agent steers toward it.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

__all__ = ["MemoryPlanner", "MemoryPlannerController"]

_MOVES = ((1, 0), (-1, 0), (0, 1), (0, -1))  # +x, -x, +y, -y, as cmlearn.rl.env.ACTIONS


class MemoryPlanner:
    def __init__(self, metres_per_pixel: float, step: float = 0.01, resolution: float = 0.0025,
                 wall_below: int = 100, clearance: float = 0.012, soft_clearance: float = 0.03,
                 soft_weight: float = 0.5, lookahead: int = 8):
        for name, v in (("metres_per_pixel", metres_per_pixel), ("step", step), ("resolution", resolution),
                        ("soft_clearance", soft_clearance)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name, v in (("clearance", clearance), ("soft_weight", soft_weight)):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if not (isinstance(lookahead, int) and lookahead >= 1):
            raise ValueError(f"lookahead must be an int >= 1, got {lookahead!r}")
        if not 0 < wall_below <= 255:
            raise ValueError(f"wall_below must be in (0, 255], got {wall_below}")
        self.mpp, self.step, self.res, self.wall_below = metres_per_pixel, step, resolution, wall_below
        self.clearance, self.soft_clearance, self.soft_weight = clearance, soft_clearance, soft_weight
        self.lookahead = lookahead
        self.occ = None

    def reset(self, bounds, goal_xy, prior: np.ndarray | None = None) -> None:
        """Forget everything, or start from ``prior`` (an earlier ``occ``, e.g. of a sweep of the map);
        ``bounds`` = (xmin, ymin, xmax, ymax) of the map (outside is wall)."""
        x0, y0, x1, y1 = map(float, bounds)
        if not (all(map(math.isfinite, (x0, y0, x1, y1))) and x1 > x0 and y1 > y0):
            raise ValueError(f"bounds must be finite (xmin, ymin, xmax, ymax) with max > min, got {bounds}")
        gx, gy = (float(v) for v in goal_xy)
        if not (x0 <= gx <= x1 and y0 <= gy <= y1):
            raise ValueError(f"goal_xy must be a finite point inside bounds={bounds}, got {goal_xy!r}")
        self.bounds, self.goal = (x0, y0, x1, y1), (gx, gy)
        shape = (int(round((y1 - y0) / self.res)) + 1, int(round((x1 - x0) / self.res)) + 1)
        if prior is not None and (np.shape(prior) != shape or np.asarray(prior).dtype != np.int8):
            raise ValueError(f"prior must be an int8 occupancy grid of shape {shape}, got "
                             f"{np.asarray(prior).dtype}{np.shape(prior)}")
        # -1 unknown, 0 free, 1 wall; row 0 = largest y
        self.occ = np.full(shape, -1, np.int8) if prior is None else np.array(prior, np.int8)
        self._clear = None

    def _cells(self, x, y):
        x0, y0, x1, y1 = self.bounds
        return np.rint((y1 - np.asarray(y)) / self.res).astype(int), np.rint((np.asarray(x) - x0) / self.res).astype(int)

    def add_view(self, view: np.ndarray, view_xy) -> None:
        """Paste a grayscale camera view (n, n) taken with its centre at ``view_xy`` into the memory."""
        if self.occ is None:
            raise RuntimeError("MemoryPlanner.add_view before reset(bounds, goal_xy)")
        view = np.asarray(view)
        if view.ndim != 2 or view.shape[0] != view.shape[1]:
            raise ValueError(f"view must be a square (n, n) grayscale image, got shape {view.shape}")
        xy = np.asarray(view_xy, dtype=float)
        if xy.shape != (2,) or not np.isfinite(xy).all():  # NaN cells were masked off: the view was dropped
            raise ValueError(f"view_xy must be a finite (x, y) in metres, got {view_xy!r}")
        n = view.shape[0]
        k = (np.arange(n) + 0.5 - n / 2) * self.mpp
        r, c = np.broadcast_arrays(*self._cells(view_xy[0] + k[None, :], view_xy[1] - k[:, None]))
        ok = (r >= 0) & (r < self.occ.shape[0]) & (c >= 0) & (c < self.occ.shape[1])
        dark = view < self.wall_below
        fr, fc = r[~dark & ok], c[~dark & ok]
        self.occ[fr, fc] = np.maximum(self.occ[fr, fc], 0)  # unknown -> free; a known wall stays
        self.occ[r[dark & ok], c[dark & ok]] = 1
        self._clear = None

    def known_clearance(self) -> np.ndarray:
        """Distance (m) of every memory cell to the nearest known wall (the map's outside counts)."""
        if self._clear is None:
            self._clear = ndimage.distance_transform_edt(np.pad(self.occ != 1, 1), sampling=self.res)[1:-1, 1:-1]
        return self._clear

    def plan(self, ee_xy) -> tuple[np.ndarray, tuple[float, float]]:
        """(cost-to-go of the 4 moves from ``ee_xy`` (inf: blocked or off the map), waypoint (x, y))."""
        if self.occ is None:
            raise RuntimeError("MemoryPlanner.plan before reset(bounds, goal_xy)")
        x0, y0, x1, y1 = self.bounds
        ex, ey, s = float(ee_xy[0]), float(ee_xy[1]), self.step
        if not (math.isfinite(ex) and math.isfinite(ey)):
            raise ValueError(f"ee_xy must be 2 finite coordinates, got {ee_xy!r}")
        # the lattice through the end-effector over the bounds (and the end-effector, if it is outside)
        kx = (min(0, math.ceil((x0 - ex) / s - 1e-9)), max(0, math.floor((x1 - ex) / s + 1e-9)))
        ky = (min(0, math.ceil((y0 - ey) / s - 1e-9)), max(0, math.floor((y1 - ey) / s + 1e-9)))
        xs, ys = ex + s * np.arange(kx[0], kx[1] + 1), ey + s * np.arange(ky[0], ky[1] + 1)
        i0, j0 = -kx[0], -ky[0]
        nx, ny = len(xs), len(ys)
        r, c = np.broadcast_arrays(*self._cells(xs[:, None], ys[None, :]))
        clear = self.known_clearance()[np.clip(r, 0, self.occ.shape[0] - 1), np.clip(c, 0, self.occ.shape[1] - 1)]
        gx, gy = self.goal
        gi = int(np.clip(round((gx - xs[0]) / s), 0, nx - 1))
        gj = int(np.clip(round((gy - ys[0]) / s), 0, ny - 1))
        ok = clear >= self.clearance
        ok[i0, j0] = ok[gi, gj] = True  # start and goal nodes always count, whatever their clearance
        enter = 1.0 + self.soft_weight * np.clip(1.0 - clear / self.soft_clearance, 0.0, None)
        idx = np.arange(nx * ny).reshape(nx, ny)
        src, dst, w = [], [], []
        for di, dj in _MOVES:  # edge v -> u (u one move from v) weighs the cost of entering v
            a = idx[max(-di, 0):nx + min(-di, 0), max(-dj, 0):ny + min(-dj, 0)]  # u
            b = idx[max(di, 0):nx + min(di, 0), max(dj, 0):ny + min(dj, 0)]  # v = u + move
            keep = ok.ravel()[a.ravel()] & ok.ravel()[b.ravel()]
            src.append(b.ravel()[keep]), dst.append(a.ravel()[keep]), w.append(enter.ravel()[b.ravel()[keep]])
        graph = coo_matrix((np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(nx * ny,) * 2).tocsr()
        D = dijkstra(graph, indices=idx[gi, gj]).reshape(nx, ny)  # inf off the allowed nodes (no edges there)
        total = D + enter  # cost of a path that enters the node first
        moves = np.array([total[i0 + di, j0 + dj] if 0 <= i0 + di < nx and 0 <= j0 + dj < ny else np.inf
                          for di, dj in _MOVES])
        if not math.isfinite(D[i0, j0]):
            return moves, self.goal
        i, j = i0, j0
        for _ in range(self.lookahead):
            nxt = [(total[i + di, j + dj], i + di, j + dj) for di, dj in _MOVES if 0 <= i + di < nx and 0 <= j + dj < ny]
            d, a, b = min(nxt, default=(np.inf, i, j))
            if not d <= D[i, j] + 1e-9 or not math.isfinite(d):
                break
            i, j = a, b
            if (i, j) == (gi, gj):
                return moves, self.goal
        return moves, (float(xs[i]), float(ys[j]))


class MemoryPlannerController:
    """Classical Sub-controller 2: paste the view, take the move of least optimistic cost-to-go.

    ``prior`` (optional): a callable returning the occupancy grid the memory starts from at each
    reset, e.g. the environment's sweep of a map the robot has seen before."""

    def __init__(self, metres_per_pixel: float, prior=None, **planner_kwargs):
        self.planner = MemoryPlanner(metres_per_pixel, **planner_kwargs)
        self.prior = prior

    def reset(self, info=None) -> None:
        self.planner.reset(info["bounds"], info["goal_xy"], None if self.prior is None else self.prior())

    def act(self, obs, info) -> int:
        self.planner.add_view(np.asarray(obs)[0], info["view_xy"])
        moves, _ = self.planner.plan(info["ee_xy"])
        return int(np.argmin(moves))
