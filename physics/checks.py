"""Input checks shared across the physics modules; each error names the parameter and its valid range."""
from __future__ import annotations

import math
import numbers

__all__ = ["check_integer"]


def check_integer(name: str, v, lo: int = 1) -> int:
    """``v`` as an int; ``ValueError`` naming ``name`` unless it is a whole number >= ``lo`` (not NaN, inf,
    None or a bool; 2.9 is not 2)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or int(v) != v or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)
