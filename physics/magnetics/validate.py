"""Input checks shared by the magnetics specs: each error names the parameter and the valid range."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from ..checks import check_integer as integer

__all__ = ["real", "positive", "integer", "vec3", "rotation"]


def real(name, v, positive=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) and not (isinstance(v, Tensor) and v.numel() == 1):
        raise TypeError(f"{name} must be a real number, got {type(v).__name__}")
    v = float(v)
    if not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}, got {v!r}")
    return v


def positive(name, v) -> float:
    return real(name, v, positive=True)


def vec3(name, v, nonzero=False) -> tuple:
    t = torch.as_tensor(v, dtype=torch.float64) if not isinstance(v, Tensor) else v.detach().double().cpu()
    if t.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be finite, got {t.tolist()}")
    if nonzero:
        if float(t.norm()) == 0:
            raise ValueError(f"{name} must be a non-zero vector")
        t = t / t.norm()
    return tuple(t.tolist())


def rotation(value, name: str = "orientation") -> tuple[tuple[float, ...], ...]:
    R = torch.as_tensor(value, dtype=torch.float64)
    if R.shape != (3, 3) or not bool(torch.isfinite(R).all()):
        raise ValueError(f"{name} must be a finite 3x3 rotation matrix, got shape {tuple(R.shape)}")
    if float((R.T @ R - torch.eye(3, dtype=R.dtype)).abs().max()) > 1e-9 or float(torch.linalg.det(R)) < 0:
        raise ValueError(f"{name} must be a proper rotation matrix (R^T R = I, det R = +1)")
    return tuple(tuple(row) for row in R.tolist())
