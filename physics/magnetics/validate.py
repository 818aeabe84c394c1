"""Input checks shared by the magnetics specs: each error names the parameter and the valid range."""
from __future__ import annotations

import torch
from torch import Tensor

from ..checks import check_integer as integer, check_rotations, positive, real

__all__ = ["real", "positive", "integer", "vec3", "rotation"]


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
    check_rotations(name, value, tol=1e-9, single=True)
    return tuple(tuple(row) for row in torch.as_tensor(value, dtype=torch.float64).tolist())
