"""Shipped surrogates: checkpoints and the real-time rollout engine (training lives in
:mod:`cmlearn.surrogate.training`, which needs Lightning)."""
from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint, surrogate_checkpoints
from .engine import Stepper, Surrogate, SurrogateDivergence

__all__ = ["CheckpointError", "Stepper", "Surrogate", "SurrogateDivergence", "load_checkpoint", "save_checkpoint", "surrogate_checkpoints"]
