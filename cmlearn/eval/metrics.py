"""Error metrics of Paper II: per-axis maximum and mean absolute errors and RMSE(t) (II.2)."""
from __future__ import annotations

from torch import Tensor

__all__ = ["axis_errors", "rmse_t"]


def axis_errors(pred: Tensor, ref: Tensor, length: float) -> dict:
    """Per-axis max and mean absolute error of positions (..., T, 3) in mm and max as % of ``length``."""
    if pred.shape != ref.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and ref {tuple(ref.shape)} must have the same shape")
    e = (pred.double() - ref.double()).abs().reshape(-1, 3)
    out = {}
    for i, ax in enumerate("xyz"):
        out[ax] = {"max_mm": float(e[:, i].max()) * 1e3, "mean_mm": float(e[:, i].mean()) * 1e3,
                   "max_pct_L": float(e[:, i].max()) / length * 100}
    return out


def rmse_t(pred: Tensor, ref: Tensor) -> Tensor:
    """RMSE(t) = sqrt(mean over the three axes of the squared error), (..., T, 3) -> (..., T)."""
    return (pred.double() - ref.double()).pow(2).mean(-1).sqrt()
