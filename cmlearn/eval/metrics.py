"""Error metrics of Paper II: per-axis maximum and mean absolute errors and RMSE(t) (II.2)."""
from __future__ import annotations

import torch
from torch import Tensor

from physics.checks import positive

__all__ = ["axis_errors", "rmse_t"]


def _check_pair(pred, ref) -> tuple[Tensor, Tensor]:
    """``pred`` and ``ref`` as tensors (numpy arrays are taken); ValueError unless they are positions of one shape
    (..., 3) with at least one point (a transposed (3, T) pair, or a (T, 6) pair, was read as points of 3
    coordinates; a shorter ``ref`` broadcast)."""
    pred, ref = torch.as_tensor(pred), torch.as_tensor(ref)
    if pred.shape != ref.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and ref {tuple(ref.shape)} must have the same shape")
    if pred.ndim < 1 or pred.shape[-1] != 3 or pred.numel() == 0:
        raise ValueError(f"pred and ref must be positions (..., 3) (x, y, z last) with at least one point, got "
                         f"shape {tuple(pred.shape)}")
    return pred, ref


def axis_errors(pred: Tensor, ref: Tensor, length: float) -> dict:
    """Per-axis max and mean absolute error of positions (..., T, 3) in mm and max as % of ``length``."""
    pred, ref = _check_pair(pred, ref)
    length = positive("length", length)
    e = (pred.double() - ref.double()).abs().reshape(-1, 3)
    out = {}
    for i, ax in enumerate("xyz"):
        out[ax] = {"max_mm": float(e[:, i].max()) * 1e3, "mean_mm": float(e[:, i].mean()) * 1e3,
                   "max_pct_L": float(e[:, i].max()) / length * 100}
    return out


def rmse_t(pred: Tensor, ref: Tensor) -> Tensor:
    """RMSE(t) = sqrt(mean over the three axes of the squared error), (..., T, 3) -> (..., T)."""
    pred, ref = _check_pair(pred, ref)
    return (pred.double() - ref.double()).pow(2).mean(-1).sqrt()
