"""Image atlas: the end-effector camera view rendered once per node of the map's 1 cm grid.

The thesis swept the real environment with the end-effector camera on a 1 cm grid and trained
on those images; the atlas does the same with :class:`~cmlearn.rl.camera.PybulletCamera`.
A view is looked up at the grid node nearest the end-effector (so off-grid positions, e.g. under
Sub-controller 1, see the image up to 7 mm away; the discrete actions move 1 cm, so Sub-controller
2 stays on nodes). Views render lazily on first use (saved once all are rendered); :meth:`Atlas.precompute` renders all.

On disk (``cache_dir``), an atlas is one ``.npz`` named by the SHA-256 of the map's pixels,
resolution, origin and grid step, the camera spec and ``ATLAS_VERSION``; it is written atomically
and only when complete, and rejected with a clear error if its shape does not match.
"""
from __future__ import annotations

import hashlib
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..io import atomic_write, check_writable
from .camera import CameraSpec, PybulletCamera
from .maps import Map

__all__ = ["Atlas", "atlas_key", "default_cache_dir", "ATLAS_VERSION"]

ATLAS_VERSION = 1


def default_cache_dir() -> Path:
    return Path(os.environ.get("CMLEARN_CACHE", Path.home() / ".cache" / "cmlearn")) / "atlas"


def atlas_key(map_: Map, spec: CameraSpec) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(map_.image).tobytes())
    h.update(repr((map_.image.shape, map_.resolution, map_.origin, map_.step, spec, ATLAS_VERSION)).encode())
    return h.hexdigest()[:24]


class Atlas:
    """Camera views of ``map_`` on its grid; ``view(x, y)`` returns the (size, size) uint8 image."""

    def __init__(self, map_: Map, spec: CameraSpec = CameraSpec(), cache_dir: str | Path | None = None):
        self.map, self.spec = map_, spec
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.key = atlas_key(map_, spec)
        self.images = np.zeros((map_.nx, map_.ny, spec.size, spec.size), dtype=np.uint8)
        self.filled = np.zeros((map_.nx, map_.ny), dtype=bool)
        self._filled = self.filled.tolist()
        self._camera = None
        self.renders = self._count = 0
        if self.cache_dir is not None:
            if self.path.exists():
                self._load()
            else:  # a file or an unwritable folder failed only at the save, after every view was rendered
                check_writable(self.cache_dir, folder=True)

    @property
    def path(self) -> Path | None:
        return None if self.cache_dir is None else self.cache_dir / f"atlas_{self.key}.npz"

    def _load(self):
        try:
            with np.load(self.path) as z:
                imgs = z["images"]
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile, zlib.error) as e:  # numpy's words
            raise ValueError(f"atlas file {self.path}: unreadable or not an atlas ({type(e).__name__}: {e}); delete "
                             "the file to rebuild it") from None
        if imgs.shape != self.images.shape or imgs.dtype != np.uint8:
            raise ValueError(f"atlas file {self.path}: images {imgs.dtype}{imgs.shape} do not match the map grid and "
                             f"camera {self.images.shape}; delete the file to rebuild it")
        self.images[:] = imgs
        self.filled[:] = True
        self._filled = self.filled.tolist()
        self._count = self.filled.size

    def camera(self) -> PybulletCamera:
        if self._camera is None:
            self._camera = PybulletCamera(self.map, self.spec)
        return self._camera

    def node_view(self, i: int, j: int) -> np.ndarray:
        """The view at grid node (i, j); ValueError outside the grid (a negative index rendered a view off the map
        into the slot of a node at the other side, which the saved atlas kept)."""
        self.map.check_node("(i, j)", (i, j))
        return self._node_view(i, j)

    def _node_view(self, i: int, j: int) -> np.ndarray:
        if not self._filled[i][j]:
            self.images[i, j] = self.camera().render(*self.map.node_xy(i, j))
            self.filled[i, j] = self._filled[i][j] = True
            self.renders += 1
            self._count += 1
            if self._count == self.filled.size:
                self.save()  # the lazy fill just completed
        return self.images[i, j]

    def view(self, x: float, y: float) -> np.ndarray:
        return self._node_view(*self.map.nearest_node(x, y))  # always a node of the grid

    def precompute(self, save: bool = True) -> "Atlas":
        for i in range(self.map.nx):
            for j in range(self.map.ny):
                self._node_view(i, j)
        if save and self.path is not None and not self.path.exists():
            self.save()
        return self

    def save(self) -> Path | None:
        """Write the atlas atomically (only a complete one) into ``cache_dir``."""
        if self.path is None or not self.filled.all():
            return None
        return atomic_write(self.path, lambda f: np.savez_compressed(f, images=self.images))

    def close(self):
        if self._camera is not None:
            self._camera.close()
            self._camera = None
