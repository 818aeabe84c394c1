"""Input checks shared across the physics modules; each error names the parameter and its valid range."""
from __future__ import annotations

import math
import numbers

import torch

__all__ = ["check_integer", "is_int", "is_finite_real", "as_real", "real", "positive", "check_rotations"]


def check_integer(name: str, v, lo: int = 1) -> int:
    """``v`` as an int; ``ValueError`` naming ``name`` unless it is a whole number >= ``lo`` (not NaN, inf,
    None or a bool; 2.9 is not 2)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or int(v) != v or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)


def is_int(v) -> bool:
    """Whether ``v`` is an integer type (a Python or numpy int, not a bool; 2.0 is not), where a float would fail
    later (``range``, indexing); :func:`check_integer` accepts whole floats."""
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def is_finite_real(v) -> bool:
    """Whether ``v`` is a finite real number (not NaN, inf, a bool, a string or a tensor); for checks that raise
    their own error."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


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


def check_rotations(name: str, R, tol: float | None = None, single: bool = False) -> None:
    """``ValueError`` naming ``name`` unless ``R`` (``(..., 3, 3)``, or ``(3, 3)`` with ``single``; a tensor or
    an array) is finite, orthonormal to ``tol`` and of determinant +1. The default ``tol`` follows ``R``'s dtype:
    1000 eps, 1e-9 at least and 1e-2 at most (1e-9 in float64, 1.2e-4 in float32). Values are read: not for a
    traced hot path. A scaled ``R`` scaled what it moved; a reflection mirrored it."""
    floating = torch.is_tensor(R) and R.is_floating_point()
    Rd = R.detach().to(torch.float64) if torch.is_tensor(R) else torch.as_tensor(R, dtype=torch.float64)
    shape_ok = Rd.shape == (3, 3) if single else Rd.shape[-2:] == (3, 3)
    if not shape_ok or not bool(torch.isfinite(Rd).all()):
        what = "a finite 3x3 rotation matrix" if single else "finite (..., 3, 3) rotation matrices"
        raise ValueError(f"{name} must be {what}, got shape {tuple(Rd.shape)}")
    if not Rd.numel():
        return
    if tol is None:
        tol = min(1e-2, max(1e-9, 1000 * torch.finfo(R.dtype if floating else torch.float64).eps))
    err = float((Rd.transpose(-1, -2) @ Rd - torch.eye(3, dtype=Rd.dtype, device=Rd.device)).abs().max())
    det = float(torch.linalg.det(Rd).min())
    if err > tol or det <= 0:
        what = "a proper rotation matrix" if single else "proper rotation matrices"
        raise ValueError(f"{name} must be {what} (R^T R = I to {tol:.0e}, det R = +1), got "
                         f"|R^T R - I| up to {err:.3g} and det R down to {det:.3g}")
