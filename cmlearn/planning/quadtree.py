"""Quadtree decomposition of a grayscale image into obstacle rectangles (Finkel & Bentley 1974),
the obstacle processor of the thesis's ERRT baseline (Figure 4.7).

Pixels with intensity ``<= threshold`` (50) are obstacles. A region that is all obstacle becomes
one rectangle, an obstacle-free region is dropped, a mixed region is split in four while both
halves of each side stay at least ``min_size`` pixels; a mixed region that can no longer be
split becomes a rectangle (conservative). So every obstacle pixel is covered and no rectangle is
smaller than ``min_size`` on a side (unless the image itself is). Afterwards, rectangles sharing
a whole edge are merged, which lowers the count. Counting uses a summed-area table (O(1) per test).

Rectangles are ``(row0, col0, row1, col1)`` pixel index ranges, half-open.
"""
from __future__ import annotations

import numpy as np

__all__ = ["quadtree_rectangles", "merge_rectangles", "covered_mask"]


def quadtree_rectangles(gray: np.ndarray, threshold: int = 50, min_size: int = 4, merge: bool = True) -> list[tuple]:
    """Obstacle rectangles covering every pixel ``<= threshold`` of ``gray`` (2-D array)."""
    g = np.asarray(gray)
    if g.ndim != 2 or g.size == 0:
        raise ValueError(f"gray must be a non-empty 2-D image, got shape {g.shape}")
    if not (isinstance(min_size, (int, np.integer)) and min_size >= 1):
        raise ValueError(f"min_size must be an int >= 1 (pixels), got {min_size!r}")
    from .controllers import _check_settings
    _check_settings(grey={"threshold": threshold})  # a NaN threshold found no obstacle at all
    if g.dtype.kind == "f" and not np.isfinite(g).all():  # a NaN pixel was free space
        raise ValueError("gray must be finite: it has NaN or infinite pixels")
    occ = (g <= threshold).astype(np.int64)
    sat = np.zeros((g.shape[0] + 1, g.shape[1] + 1), dtype=np.int64)
    sat[1:, 1:] = occ.cumsum(0).cumsum(1)

    def count(r0, c0, r1, c1):
        return sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]

    out, stack = [], [(0, 0, g.shape[0], g.shape[1])]
    while stack:
        r0, c0, r1, c1 = stack.pop()
        n = count(r0, c0, r1, c1)
        if n == 0:
            continue
        h, w = r1 - r0, c1 - c0
        if n == h * w:
            out.append((r0, c0, r1, c1))
            continue
        split_r, split_c = h >= 2 * min_size, w >= 2 * min_size
        if not (split_r or split_c):
            out.append((r0, c0, r1, c1))  # mixed but at the minimum size: keep it whole
            continue
        rm = r0 + h // 2 if split_r else r1
        cm = c0 + w // 2 if split_c else c1
        for a, b, c, d in ((r0, c0, rm, cm), (r0, cm, rm, c1), (rm, c0, r1, cm), (rm, cm, r1, c1)):
            if a < c and b < d:
                stack.append((a, b, c, d))
    return merge_rectangles(out) if merge else out


def merge_rectangles(rects: list[tuple]) -> list[tuple]:
    """Merge rectangles that share a whole edge until none do."""
    rects = sorted(set(rects))
    changed = True
    while changed:
        changed = False
        for axis in (0, 1):  # 0: vertically stacked (same columns), 1: side by side (same rows)
            index = {}
            for r in rects:
                key = (r[1], r[3], r[0]) if axis == 0 else (r[0], r[2], r[1])
                index[key] = r
            used, merged = set(), []
            for r in sorted(rects):
                if r in used:
                    continue
                cur = r
                while True:
                    key = (cur[1], cur[3], cur[2]) if axis == 0 else (cur[0], cur[2], cur[3])
                    nxt = index.get(key)
                    if nxt is None or nxt in used or nxt == cur:
                        break
                    used.add(nxt)
                    cur = (cur[0], cur[1], nxt[2], cur[3]) if axis == 0 else (cur[0], cur[1], cur[2], nxt[3])
                    changed = True
                used.add(r)
                merged.append(cur)
            rects = sorted(set(merged))
    return rects


def covered_mask(shape, rects) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    for r0, c0, r1, c1 in rects:
        m[r0:r1, c0:c1] = True
    return m
