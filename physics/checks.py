"""Input checks shared across the physics modules; each error names the parameter and its valid range."""
from __future__ import annotations

import math
import numbers

import torch

__all__ = ["check_integer", "as_real", "real", "positive"]


def check_integer(name: str, v, lo: int = 1) -> int:
    """``v`` as an int; ``ValueError`` naming ``name`` unless it is a whole number >= ``lo`` (not NaN, inf,
    None or a bool; 2.9 is not 2)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or int(v) != v or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)


def as_real(name: str, v) -> float:
    """``v`` as a float; ``TypeError`` naming ``name`` unless it is a real number or a one-element tensor (not a
    string, None or a bool: a string such as YAML's ``1e6`` passed ``float()`` and failed later in arithmetic)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) and not (torch.is_tensor(v) and v.numel() == 1):
        raise TypeError(f"{name} must be a real number, got {type(v).__name__} {v!r}")
    return float(v)


def real(name: str, v, positive: bool = False) -> float:
    """``v`` as a float; also a ``ValueError`` unless it is finite (and > 0 with ``positive``)."""
    x = as_real(name, v)
    if not math.isfinite(x) or (positive and x <= 0):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}, got {x!r}")
    return x


def positive(name: str, v) -> float:
    return real(name, v, positive=True)
