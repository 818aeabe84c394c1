"""Training windows: (history of eta + 1 frames, the next H frames, the node forces over them, the
trajectory's first frame as the reference shape and, where given, per-step inputs of the task's own
wrench model over them), optionally also played backwards.

Time reversal: an undamped rod under forces that depend on time only (no damping, no velocity
dependence) moves on a time-reversible trajectory: the same frames in reverse order, under the same
forces in reverse order, are a motion of the same system. The LGVI keeps that symmetry to round-off
(tests/test_lgvi.py) and the stored forces are interval midpoints, so the reversed window is exact:
its step from frame k + 1 to frame k uses the force of interval k. A step that has learnt to dissipate
(or pump) energy fits the reversed windows badly, so training on both directions penalises that."""
from __future__ import annotations

from torch import Tensor
from torch.utils.data import Dataset

from physics.checks import is_int

__all__ = ["RolloutWindows", "node_wrench", "split_ranges"]


def node_wrench(wrench: Tensor, wrench_nodes, modeled) -> Tensor:
    """Scatter the stored forces (..., T-1, n_wrench, 3) onto the modelled nodes (..., T-1, K, 3)."""
    out = wrench.new_zeros(*wrench.shape[:-2], len(modeled), 3)  # on the wrench's device (closed loop on a GPU)
    slot = {n: i for i, n in enumerate(modeled)}
    for j, n in enumerate(wrench_nodes):
        if n not in slot:
            raise ValueError(f"wrench node {n} is not a modelled node")
        out[..., slot[n], :] = wrench[..., j, :]
    return out


def split_ranges(n_variants: int, n_frames: int, train_fraction: float = 0.6, val_variants: int = 1,
                 val_tail: float = 0.0):
    """Frame ranges per split: variant 0 (the printed scene) trains on its first ``train_fraction`` and
    evaluates on the rest; the last ``val_variants`` (at most ``n_variants`` - 1) variants validate; all others train
    in full (with ``n_variants`` 1, nothing validates and the validation range is the test range).
    ``val_tail`` > 0: the printed scene's last ``val_tail`` of the trajectory before the cut validates
    instead of training (the thesis's one-trajectory protocol, with ``n_variants`` 1)."""
    if not 0.0 < train_fraction < 1.0:
        raise ValueError(f"train_fraction must lie in (0, 1), got {train_fraction!r}")
    if not val_variants >= 0:
        raise ValueError(f"val_variants must be >= 0, got {val_variants!r}")
    if n_variants > 1 and val_variants > n_variants - 1:
        raise ValueError(f"val_variants must be at most n_variants - 1 = {n_variants - 1} (variant 0 is the printed "
                         f"scene, which trains and tests), got {val_variants}")
    if not 0.0 <= val_tail < train_fraction:
        raise ValueError(f"val_tail must lie in [0, {train_fraction}) of the trajectory, got {val_tail}")
    cut = int(round(train_fraction * (n_frames - 1)))
    tail = int(round((train_fraction - val_tail) * (n_frames - 1)))
    train = [(0, 0, tail)] + [(v, 0, n_frames - 1) for v in range(1, n_variants - val_variants)]
    val = [(0, tail, cut)] if val_tail else []
    val += [(v, 0, n_frames - 1) for v in range(max(1, n_variants - val_variants), n_variants)]
    test = [(0, cut, n_frames - 1)]
    return {"train": train, "val": val or test, "test": test}


class RolloutWindows(Dataset):
    """Every ``stride``-th window start inside the given ``ranges`` [(variant, first_frame, last_frame)]. ``inputs``
    (V, T-1, ...), optional: what a closed-loop training rollout computes each step's wrench from (e.g.
    :func:`cmlearn.surrogate.magnetic.closed_loop_inputs`), windowed like ``wrench``. ``time_reversal``:
    every window also played backwards (the second half of the index; see the module's docstring)."""

    def __init__(self, positions: Tensor, wrench: Tensor, ranges, eta: int, horizon: int,
                 inputs: Tensor | None = None, stride: int = 1, time_reversal: bool = False):
        if inputs is not None and inputs.shape[:2] != wrench.shape[:2]:
            raise ValueError(f"inputs {tuple(inputs.shape)} must match wrench {tuple(wrench.shape)} in (V, T-1)")
        if inputs is not None and time_reversal:
            raise ValueError("time_reversal: a closed-loop wrench model's inputs are not reversible windows")
        for name, v, low in (("eta", eta, 0), ("horizon", horizon, 1), ("stride", stride, 1)):
            if not is_int(v) or v < low:  # 2.0 failed in range()
                raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")
        V, T = positions.shape[:2]
        if tuple(wrench.shape[:2]) != (V, T - 1):
            raise ValueError(f"wrench {tuple(wrench.shape)} must hold the T - 1 = {T - 1} intervals of each of the "
                             f"V = {V} trajectories of positions {tuple(positions.shape)}")
        bad = [r for r in ranges if not (0 <= r[0] < V and 0 <= r[1] <= r[2] <= T - 1)]
        if bad:
            raise ValueError(f"ranges {bad} lie outside the data: (variant in [0, {V}), first <= last frame in "
                             f"[0, {T - 1}])")
        self.positions, self.wrench, self.inputs = positions, wrench, inputs
        self.W, self.H = eta + 1, horizon
        self.index = []
        for v, a, b in ranges:
            for t in range(a + self.W - 1, b - horizon + 1, stride):  # t = last history frame
                self.index.append((v, t, False))
        if not self.index:
            raise ValueError(f"no window of {self.W} + {horizon} frames fits the ranges {ranges}")
        if time_reversal:
            self.index += [(v, t, True) for v, t, _ in self.index]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i):
        v, t, backwards = self.index[i]
        p = self.positions[v]
        s = t - self.W + 1  # the window's frames s .. t + H
        frames, wrench = p[s:t + 1 + self.H], self.wrench[v, t:t + self.H]
        if backwards:  # played from t + H down to s, each step under the force of the interval it crosses
            frames, wrench = frames.flip(0), self.wrench[v, s:s + self.H].flip(0)
        out = (frames[:self.W], frames[self.W:], wrench, p[0])
        return out if self.inputs is None else (*out, self.inputs[v, t:t + self.H])
