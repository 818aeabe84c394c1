"""The end-effector camera: pybullet (TinyRenderer, DIRECT mode) renders the map lying on the table.

The camera looks straight down from the end-effector (``height`` above the table, its image
centre on the tool point) with a square field of view covering ``extent`` metres of table
(default 12 cm at 10.5 cm: a 59.5 degree pinhole). The map is a textured quad at its place on
the table; around it a dark table (intensity ``table_level`` <= 50, i.e. an obstacle) bounds the
workspace, like the boundary obstacles of the thesis's Figure 4.11. Lighting is ambient only, so
a rendered pixel is the map's gray level. The RGB image is converted to gray with ITU-R 601
weights. Rows run from +y (top) to -y, columns from -x to +x, as the map image.

One 84x84 render costs about 2-4 ms; :mod:`cmlearn.rl.atlas` renders each 1 cm grid node once.
"""
from __future__ import annotations

import math
import numbers
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from physics.checks import is_finite_real

from .maps import Map

__all__ = ["CameraSpec", "PybulletCamera"]

NEAR, FAR = 0.01, 1.0  # the clipping planes of the camera's projection (m)


@dataclass(frozen=True)
class CameraSpec:
    """The camera: ``size`` x ``size`` pixels, ``height`` (m) above the table, seeing ``extent`` (m) of it; the table
    must lie between the renderer's clipping planes (``NEAR``, ``FAR``), or the view is blank."""
    size: int = 84
    height: float = 0.105
    extent: float = 0.12
    table_level: int = 25

    def __post_init__(self):
        if not (isinstance(self.size, int) and self.size >= 16):
            raise ValueError(f"size must be an int >= 16 pixels, got {self.size!r}")
        for name in ("height", "extent"):
            v = getattr(self, name)
            if not (is_finite_real(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0 (m), got {v!r}")
        if not NEAR < self.height < FAR - 0.01:  # outside, the table was clipped: a blank (white) view, no walls
            raise ValueError(f"height must be in ({NEAR}, {FAR - 0.01}) m (the table between the camera's clipping "
                             f"planes), got {self.height}")
        if not (isinstance(self.table_level, numbers.Real) and 0 <= self.table_level <= 255):
            raise ValueError(f"table_level must be in [0, 255], got {self.table_level!r}")

    @property
    def fov_deg(self) -> float:
        return 2 * math.degrees(math.atan(self.extent / 2 / self.height))

    @property
    def metres_per_pixel(self) -> float:
        return self.extent / self.size


class PybulletCamera:
    """Renders the view of ``spec`` at world (x, y) over ``map_`` (a pybullet DIRECT client of its own)."""

    def __init__(self, map_: Map, spec: CameraSpec = CameraSpec()):
        import cv2
        import pybullet as p
        self.p, self.map, self.spec = p, map_, spec
        self._tmp = tempfile.TemporaryDirectory(prefix="cmlearn-cam-")
        tmp = Path(self._tmp.name)
        cv2.imwrite(str(tmp / "map.png"), cv2.cvtColor(map_.image, cv2.COLOR_GRAY2BGR))
        W, H = map_.size
        (tmp / "quad.obj").write_text(
            f"v 0 0 0\nv {W} 0 0\nv {W} {H} 0\nv 0 {H} 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
            "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n")
        self.cid = cid = p.connect(p.DIRECT)
        g = spec.table_level / 255
        table = p.createVisualShape(p.GEOM_BOX, halfExtents=[5, 5, 0.001], rgbaColor=[g, g, g, 1], physicsClientId=cid)
        p.createMultiBody(baseVisualShapeIndex=table, basePosition=[0, 0, -0.002], physicsClientId=cid)
        quad = p.createVisualShape(p.GEOM_MESH, fileName=str(tmp / "quad.obj"), physicsClientId=cid)
        body = p.createMultiBody(baseVisualShapeIndex=quad, basePosition=[*map_.origin, 0.0], physicsClientId=cid)
        tex = p.loadTexture(str(tmp / "map.png"), physicsClientId=cid)
        p.changeVisualShape(body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=cid)
        self._proj = p.computeProjectionMatrixFOV(fov=spec.fov_deg, aspect=1.0, nearVal=NEAR, farVal=FAR)

    def render(self, x: float, y: float) -> np.ndarray:
        """Grayscale (size, size) uint8 view from the end-effector at (x, y)."""
        if not all(is_finite_real(v) for v in (x, y)):  # NaN gave a white view
            raise ValueError(f"x and y must be finite numbers (m), got {x!r}, {y!r}")
        p, s = self.p, self.spec
        view = p.computeViewMatrix([x, y, s.height], [x, y, 0.0], [0, 1, 0])
        rgba = p.getCameraImage(s.size, s.size, view, self._proj, renderer=p.ER_TINY_RENDERER, shadow=0,
                                lightAmbientCoeff=1.0, lightDiffuseCoeff=0.0, lightSpecularCoeff=0.0,
                                physicsClientId=self.cid)[2]
        rgb = np.asarray(rgba, dtype=np.float32).reshape(s.size, s.size, 4)[..., :3]
        return (rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32) + 0.5).clip(0, 255).astype(np.uint8)

    def close(self):
        if self.cid is not None:
            self.p.disconnect(self.cid)
            self.cid = None
            self._tmp.cleanup()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
