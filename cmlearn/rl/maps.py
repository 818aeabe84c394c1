"""2-D constrained workspaces: intestine-like procedural maps and maps loaded from grayscale PNGs.

A :class:`Map` is a grayscale image (row 0 = largest y, column 0 = smallest x, as seen from
above) placed on the table: ``resolution`` metres per pixel, ``origin`` the world (x, y) of its
lower-left corner. Dark pixels (< ``wall_level``, default 128) are walls; outside the image is a
wall too. The free space is sampled on a grid of ``step`` (1 cm: the grid of the camera atlas and
of the discrete actions); a grid node is *safe* when its clearance to the walls is at least
``clearance``. Starts and goals are safe nodes connected through safe nodes (4-neighbours).

:func:`procedural_map` draws, from a seed, a random spanning tree over a jittered lattice, keeps
its longest path (a winding channel) plus a few short side branches (dead ends), and renders
each edge as a channel whose width varies between its nodes, with occasional narrowings.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from physics.checks import check_integer, is_finite_real, is_int

__all__ = ["Map", "procedural_map", "load_map", "map_seeds"]

FREE_LEVEL, WALL_LEVEL = 235, 20


def map_seeds(split: str, count: int) -> tuple[int, ...]:
    """Seeds of the procedural training maps (``"train"``: 0, 1, ...) or unseen maps (``"unseen"``: 10000, ...)."""
    if split not in ("train", "unseen"):
        raise ValueError(f"split must be 'train' or 'unseen', got {split!r}")
    count = check_integer("count", count, lo=0)  # a negative count gave no maps
    return tuple(range(count)) if split == "train" else tuple(range(10_000, 10_000 + count))


@dataclass(eq=False)
class Map:
    image: np.ndarray
    resolution: float = 0.002
    origin: tuple[float, float] = (-0.2, 0.25)
    step: float = 0.01
    clearance: float = 0.012
    wall_level: int = 128
    name: str = "map"
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        img = np.asarray(self.image)
        if img.ndim != 2 or img.dtype != np.uint8 or min(img.shape) < 2:
            raise ValueError(f"image must be a 2-D uint8 grayscale array, got {img.dtype} {img.shape}")
        for name in ("resolution", "step", "clearance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0 (m), got {v}")
        self.image = np.ascontiguousarray(img)
        self.origin = tuple(float(v) for v in self.origin)
        if len(self.origin) != 2 or not all(map(math.isfinite, self.origin)):
            raise ValueError(f"origin must be 2 finite coordinates (m), got {self.origin!r}")
        from scipy.ndimage import distance_transform_edt
        free = self.image >= self.wall_level
        padded = np.pad(free, 1, constant_values=False)  # the outside is a wall
        self.clear_px = (distance_transform_edt(padded)[1:-1, 1:-1] - 0.5).clip(0) * self.resolution
        self._clear_list = self.clear_px.tolist()
        H, W = self.image.shape
        self.nx = int(math.floor(W * self.resolution / self.step + 1e-9))
        self.ny = int(math.floor(H * self.resolution / self.step + 1e-9))
        if self.nx < 1 or self.ny < 1:
            raise ValueError(f"map of {W}x{H} px at {self.resolution} m/px is smaller than one grid step {self.step} m")
        self.node_clear = np.array([[self.clearance_at(*self.node_xy(i, j)) for j in range(self.ny)]
                                    for i in range(self.nx)])
        self.safe = self.node_clear >= self.clearance
        if not self.safe.any():
            raise ValueError(f"map {self.name!r} has no free cell: no grid node has {self.clearance} m clearance "
                             "from the walls (dark pixels are walls)")

    # --------------------------------------------------------------- geometry
    @property
    def size(self) -> tuple[float, float]:
        H, W = self.image.shape
        return W * self.resolution, H * self.resolution

    def to_pixel(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the world point (x, y) (may lie outside the image)."""
        H = self.image.shape[0]
        return H - 1 - int(math.floor((y - self.origin[1]) / self.resolution)), \
            int(math.floor((x - self.origin[0]) / self.resolution))

    def clearance_at(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the nearest wall; 0 on a wall or outside the map."""
        r, c = self.to_pixel(x, y)
        if r < 0 or c < 0 or r >= self.image.shape[0] or c >= self.image.shape[1]:
            return 0.0
        return self._clear_list[r][c]

    def touches_wall(self, x: float, y: float, radius: float) -> bool:
        return self.clearance_at(x, y) < radius

    def node_xy(self, i: int, j: int) -> tuple[float, float]:
        return self.origin[0] + (i + 0.5) * self.step, self.origin[1] + (j + 0.5) * self.step

    def nearest_node(self, x: float, y: float) -> tuple[int, int]:
        i = int(round((x - self.origin[0]) / self.step - 0.5))
        j = int(round((y - self.origin[1]) / self.step - 0.5))
        return min(max(i, 0), self.nx - 1), min(max(j, 0), self.ny - 1)

    def check_node(self, name: str, node) -> tuple[int, int]:
        """``node`` as a grid node (i, j); ValueError naming ``name`` unless it is two integers inside the grid (a
        negative index wrapped round to a node at the other side, a fractional one was truncated)."""
        if not (len(np.shape(node)) == 1 and len(node) == 2 and all(
                is_int(v) for v in node)
                and 0 <= node[0] < self.nx and 0 <= node[1] < self.ny):
            raise ValueError(f"{name} must be a grid node: integers (i, j) with 0 <= i < {self.nx} and "
                             f"0 <= j < {self.ny}, got {node!r}")
        return int(node[0]), int(node[1])

    # --------------------------------------------------------------- graph
    def geodesic(self, goal_node: tuple[int, int], kind: str = "free") -> np.ndarray:
        """Shortest 4-neighbour path length (m) from every node to ``goal_node`` through the
        ``"free"`` nodes (clearance > 2.5 mm, the particle's radius) or the ``"safe"`` ones; ``inf``
        where unreachable. Cached per goal."""
        key = (self.check_node("goal_node", goal_node), kind)
        if key in self._cache:
            return self._cache[key]
        if kind not in ("free", "safe"):
            raise ValueError(f"kind must be 'free' or 'safe', got {kind!r}")
        mask = (self.node_clear > 0.0025) if kind == "free" else self.safe
        dist = np.full((self.nx, self.ny), np.inf)
        gi, gj = key[0]
        if mask[gi, gj]:
            dist[gi, gj] = 0.0
            queue = deque([(gi, gj)])
            m, d_ = mask.tolist(), dist.tolist()
            while queue:
                i, j = queue.popleft()
                d = d_[i][j] + self.step
                for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
                    if 0 <= a < self.nx and 0 <= b < self.ny and m[a][b] and d_[a][b] == math.inf:
                        d_[a][b] = d
                        queue.append((a, b))
            dist = np.array(d_)
        if len(self._cache) > 512:
            self._cache.clear()
        self._cache[key] = dist
        return dist

    def check_point(self, name: str, xy) -> tuple[int, int]:
        """Grid node of a user start/goal; ``ValueError`` if it is inside (or too close to) a wall."""
        x, y = (float(v) for v in xy) if np.shape(xy) == (2,) else (math.nan, math.nan)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"{name} must be 2 finite coordinates (m), got {xy!r}")
        node = self.nearest_node(x, y)
        if self.clearance_at(x, y) < self.clearance or not self.safe[node]:
            raise ValueError(f"{name}={[round(x, 4), round(y, 4)]} lies inside a wall or closer than "
                             f"clearance={self.clearance} m to one")
        return node

    def check_reachable(self, start_node, goal_node):
        if not np.isfinite(self.geodesic(goal_node, "safe")[self.check_node("start_node", start_node)]):
            raise ValueError(f"goal node {tuple(goal_node)} is not reachable from start node {tuple(start_node)} "
                             f"through free space with {self.clearance} m clearance")

    def sample_partner(self, rng: np.random.Generator, node, min_distance: float = 0.1) -> tuple[int, int]:
        """A random safe node connected to ``node`` and at least ``min_distance`` from it along the free space
        (the start of a given goal, or the goal of a given start)."""
        dist = self.geodesic(self.check_node("node", node), "safe")
        ok = np.argwhere(np.isfinite(dist) & (dist >= min_distance))
        if not len(ok):
            raise ValueError(f"map {self.name!r}: no safe node {min_distance} m from node {tuple(node)} is connected to it")
        return tuple(int(v) for v in ok[rng.integers(len(ok))])

    def sample_start_goal(self, rng: np.random.Generator, min_distance: float = 0.1, tries: int = 200):
        """Random connected safe (start, goal) nodes at least ``min_distance`` apart along the free space."""
        nodes = np.argwhere(self.safe)
        for _ in range(tries):
            g = tuple(nodes[rng.integers(len(nodes))])
            dist = self.geodesic(g, "safe")
            ok = np.argwhere(np.isfinite(dist) & (dist >= min_distance))
            if len(ok):
                return tuple(int(v) for v in ok[rng.integers(len(ok))]), tuple(int(v) for v in g)
        raise ValueError(f"map {self.name!r}: no start/goal pair {min_distance} m apart is connected")


# ------------------------------------------------------------------- procedural maps
def _segments_free(shape, res, segs) -> np.ndarray:
    H, W = shape
    ys = (H - 0.5 - np.arange(H))[:, None] * res
    xs = (np.arange(W) + 0.5)[None, :] * res
    free = np.zeros(shape, dtype=bool)
    for (x0, y0, r0), (x1, y1, r1) in segs:
        dx, dy = x1 - x0, y1 - y0
        L2 = dx * dx + dy * dy
        t = np.clip(((xs - x0) * dx + (ys - y0) * dy) / max(L2, 1e-12), 0, 1)
        d2 = (xs - x0 - t * dx) ** 2 + (ys - y0 - t * dy) ** 2
        free |= d2 < (r0 + t * (r1 - r0)) ** 2
    return free


def procedural_map(seed: int, size: tuple[float, float] = (0.4, 0.4), resolution: float = 0.002,
                   origin: tuple[float, float] | None = None, lattice: float = 0.08,
                   width: tuple[float, float] = (0.04, 0.065), narrowing: float = 0.03, p_narrow: float = 0.3,
                   dead_ends: int = 2, **map_kw) -> Map:
    """An intestine-like map from ``seed``: a winding channel with narrowings and dead ends."""
    if not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an int, got {type(seed).__name__}")
    for name, v in (("size", size), ("width", width)):
        if not (np.shape(v) == (2,) and all(is_finite_real(x) and x > 0 for x in v)):
            raise ValueError(f"{name} must be two finite lengths > 0 (m), got {v!r}")
    for name, v in (("resolution", resolution), ("lattice", lattice), ("narrowing", narrowing)):
        if not (is_finite_real(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0 (m), got {v!r}")
    if not (0 < narrowing <= width[0] <= width[1]):
        raise ValueError(f"need 0 < narrowing <= width[0] <= width[1], got {narrowing}, {width}")
    if not (is_finite_real(p_narrow) and 0 <= p_narrow <= 1):  # 30 (%) narrowed every edge, NaN none
        raise ValueError(f"p_narrow (a probability) must be in [0, 1], got {p_narrow!r}")
    dead_ends = check_integer("dead_ends", dead_ends, lo=0)  # a negative count gave none
    rng = np.random.default_rng(int(seed))
    W, H = size
    nx, ny = max(2, int(W / lattice)), max(2, int(H / lattice))
    mx, my = (W - (nx - 1) * lattice) / 2, (H - (ny - 1) * lattice) / 2
    jit = 0.22 * lattice
    pos = {(i, j): (mx + i * lattice + rng.uniform(-jit, jit), my + j * lattice + rng.uniform(-jit, jit))
           for i in range(nx) for j in range(ny)}
    # randomized depth-first spanning tree
    start = (int(rng.integers(nx)), int(rng.integers(ny)))
    adj = {n: [] for n in pos}
    seen, stack = {start}, [start]
    while stack:
        i, j = stack[-1]
        nbrs = [n for n in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)) if n in pos and n not in seen]
        if not nbrs:
            stack.pop()
            continue
        n = nbrs[rng.integers(len(nbrs))]
        adj[(i, j)].append(n)
        adj[n].append((i, j))
        seen.add(n)
        stack.append(n)

    def farthest(src):
        prev, order = {src: None}, deque([src])
        last = src
        while order:
            last = order.popleft()
            for n in adj[last]:
                if n not in prev:
                    prev[n] = last
                    order.append(n)
        return last, prev

    a, _ = farthest(start)
    b, prev = farthest(a)
    path = [b]
    while prev[path[-1]] is not None:
        path.append(prev[path[-1]])
    keep = set(zip(path[:-1], path[1:]))
    on_path = set(path)
    for _ in range(dead_ends):  # short side branches off the main channel
        node = path[rng.integers(len(path))]
        for _hop in range(int(rng.integers(1, 3))):
            off = [n for n in adj[node] if n not in on_path]
            if not off:
                break
            nxt = off[rng.integers(len(off))]
            keep.add((node, nxt))
            on_path.add(nxt)
            node = nxt
    radius = {n: rng.uniform(*width) / 2 for n in on_path}
    segs = []
    for u, v in keep:
        (x0, y0), (x1, y1), r0, r1 = pos[u], pos[v], radius[u], radius[v]
        if rng.random() < p_narrow:
            xm, ym = (x0 + x1) / 2, (y0 + y1) / 2
            segs += [((x0, y0, r0), (xm, ym, narrowing / 2)), ((xm, ym, narrowing / 2), (x1, y1, r1))]
        else:
            segs.append(((x0, y0, r0), (x1, y1, r1)))
    segs += [((x, y, radius[n]), (x, y, radius[n])) for n in on_path for (x, y) in [pos[n]]]
    shape = (int(round(H / resolution)), int(round(W / resolution)))
    free = _segments_free(shape, resolution, segs)
    tex = rng.normal(0.0, 6.0, shape)
    img = np.where(free, FREE_LEVEL + tex, WALL_LEVEL + tex).clip(0, 255).astype(np.uint8)
    if origin is None:
        origin = (-W / 2, 0.45 - H / 2)
    return Map(img, resolution, origin, name=f"procedural-{seed}", **map_kw)


def load_map(path: str | Path, resolution: float = 0.002, origin: tuple[float, float] | None = None, **map_kw) -> Map:
    """A map from a grayscale (or colour, converted) image file; walls are dark pixels."""
    import cv2
    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if img is None:
        raise ValueError(f"path: cannot read a map image from {str(path)!r} (missing or not an image file)")
    if origin is None:
        W, H = img.shape[1] * resolution, img.shape[0] * resolution
        origin = (-W / 2, 0.45 - H / 2)
    return Map(img, resolution, origin, name=path.stem, **map_kw)
