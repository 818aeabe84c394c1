"""Evaluation: error metrics as in the thesis."""
from .metrics import axis_errors, rmse_t

__all__ = ["axis_errors", "rmse_t"]
