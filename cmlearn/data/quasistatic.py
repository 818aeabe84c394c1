"""The static Cosserat rod along a current profile, and the magnets' deviation from it: the data of the
quasi-static hybrid surrogate of the magnetic rod (:mod:`cmlearn.models.quasistatic`).

Static track. At every frame time the static Cosserat rod (:func:`physics.scenes_cosserat.paper2_magnetic_rod`,
13 nodes) is solved in the scene's eMNS with that time's currents, warm-started from the previous frame's
solution (the thesis's quasi-static use of the model); a batch of current profiles (``currents(t) -> (V, C)``)
is solved as one batch. Where the rod snaps over (a fold of its equilibrium) the track jumps within one frame;
the dynamic rod follows in about 0.2 s, with overshoot.

Coordinates (12 per frame, two magnets in :data:`~cmlearn.surrogate.magnetic.MAGNETS` order):

* static state ``s``: the two magnet centres (mm) and the rotation vectors (deg) of the magnets' rotations
  relative to their rotations at rest (the static rod at zero current), and as a 13th column the solution's
  stability margin (:func:`stability_margin`), which tells a snap-through coming, and where a model asks for it
  (``QuasiStaticConfig.fold_clock``) as a 14th column the fold clock (:func:`fold_clock`), which tells how long ago
  the last one began;
* deviation ``d``: the LGVI's block centres minus the static ones (mm) and the rotation vectors (deg) of
  ``R_lgvi R_static^T`` (world frame), so that :func:`compose` rebuilds the LGVI's magnets from ``s`` and ``d``.
"""
from __future__ import annotations

import hashlib
import math
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

import physics
from cmlearn.io import save_torch_atomic
from physics.errors import SolverError
from physics.lie import so3_exp, so3_log

__all__ = ["N_COORDS", "FOLD_JUMP_DEG", "field_hook", "TabulatedField", "StaticTrack", "stability_margin",
           "static_track", "static_state", "fold_clock_step", "fold_clock", "with_fold_clock", "deviation", "compose",
           "cached_static_track"]

N_COORDS = 12
#: A static track whose magnet rotation changes by more than this (deg) within one frame has jumped over a fold
#: (the tracks' snap-throughs jump 45-57 deg a frame; elsewhere at most about 4).
FOLD_JUMP_DEG = 10.0
_DEG = 180.0 / math.pi


#: A trial position farther than this (m) from the coils' origin is a diverging shooting step (the rod is 50 mm long).
FAR = 1e3


def field_hook(emns, I: Tensor):
    """Field hook with fixed currents ``I`` (C,) or (V, C); trial positions that are not finite or farther than
    :data:`FAR` (a diverging shooting step) get a NaN field, so that the solver rejects the step instead of the coil
    model raising."""
    def hook(_t, x):
        ok = (x.abs() <= FAR).all(-1, keepdim=True)  # False where NaN
        B, dB = emns.field_and_gradient(torch.where(ok, x, torch.zeros_like(x)), I)
        return B.masked_fill(~ok, math.nan), dB.masked_fill(~ok[..., None], math.nan)
    return hook


class TabulatedField:
    """Field hook of an eMNS tabulated over its workspace (:class:`~physics.magnetics.field_table.CoilFieldTable`)
    with fixed ``currents`` (C,): a hook whose state is tensors and whose field has no data-dependent branch, so
    that the compiled solver (``CosseratSolver(compile=True)``) runs it on its fast path."""

    def __init__(self, table, currents: Tensor):
        self.table, self.currents = table, currents

    def __call__(self, _t, x):
        return self.table.field_and_gradient(x, self.currents, check=False)


class StaticTrack(NamedTuple):
    """The static rod along a profile: magnet centres ``P`` (..., T, 2, 3), rotations ``R`` (..., T, 2, 3, 3),
    the stability ``margin`` (..., T) and the solver's wall time (s)."""

    P: Tensor
    R: Tensor
    margin: Tensor
    wall_s: float


def stability_margin(sol) -> Tensor:
    """The smallest singular value (...,) of a static solution's scaled shooting Jacobian (``sol``: the solution or
    its Jacobian (..., 6, 6)): it falls towards zero as the loads approach a fold of the equilibrium (where the rod
    snaps over), like the square root of the distance to it, so the last few frames' margins tell when within the
    next frame the branch ends."""
    return torch.linalg.svdvals(sol if isinstance(sol, Tensor) else sol.jacobian)[..., -1]


def static_track(currents, emns, times, n_nodes: int = 13, truncate: bool = False, **pose) -> StaticTrack:
    """The static Cosserat rod at ``times`` (s) with ``currents(t) -> (C,)`` or ``(V, C)`` A (then ``...`` = V),
    each solve warm-started from the one before (:class:`StaticTrack`). ``pose``: the clamp
    (:func:`cmlearn.surrogate.magnetic.base_pose`). Where no equilibrium is found (:func:`_warm_step`) a
    :class:`SolverError` names the time and the profile; with ``truncate`` (a batch of profiles) that profile's
    track ends there instead, with a warning: its frames from then on are NaN, and the batch goes on."""
    from physics.scenes_cosserat import paper2_magnetic_rod
    if len(times) == 0:
        raise ValueError("times must hold at least one time")
    sc = paper2_magnetic_rod(n_nodes)
    solver = sc.solver()
    nodes = list(sc.rod.grid.magnet_nodes)
    live, ended = None, {}  # a profile whose track ended is solved at zero currents, so that the batch converges

    def driven(t):
        I = _currents_at(currents, t)
        return I if live is None else I * live[:, None]
    P, R, margin, sol = [], [], [], None
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        while True:
            try:
                sol = (sc.solve(solver, field=field_hook(emns, driven(t)), load_steps=4, **pose) if sol is None else
                       _warm_step(sc, solver, lambda I: field_hook(emns, I), driven, pose, sol, float(times[k - 1]),
                                  float(t), _HALVINGS))
                break
            except SolverError as e:
                shape = _currents_at(currents, t).shape
                if not truncate or len(shape) != 2 or e.node is None or e.node in ended:
                    raise
                warnings.warn(f"static track: profile {e.node} has no equilibrium at t = {float(t):.6g} s; its track "
                              f"ends there ({e})", stacklevel=2)
                ended[e.node] = k
                live = torch.ones(shape[0], dtype=torch.float64)
                live[list(ended)] = 0.0
        P.append(sol.p[..., nodes, :])
        R.append(sol.R[..., nodes, :, :])
        margin.append(stability_margin(sol))
    out = StaticTrack(torch.stack(P, -3), torch.stack(R, -4), torch.stack(margin, -1), time.perf_counter() - t0)
    for j, k in ended.items():
        out.P[j, k:], out.R[j, k:], out.margin[j, k:] = math.nan, math.nan, math.nan
    return out


_HALVINGS = 4


def _currents_at(currents, t: float) -> Tensor:
    return torch.as_tensor(currents(torch.tensor(float(t), dtype=torch.float64)), dtype=torch.float64)


def _warm_step(sc, solver, field_of, currents, pose, sol, t_prev: float, t: float, halvings: int):
    """The static rod at ``t`` warm-started from ``sol`` (the solution at ``t_prev``). Where the currents move too
    far in one frame for the warm start and the solver's own load stepping, the step is split in two halves, each
    warm-started from the one before, up to ``halvings`` times. A problem that fails even then has passed a fold
    (its branch ended): it alone is solved again from the unloaded rod with load stepping, which lands on a branch
    that still exists; where that fails too, a :class:`SolverError` names the time and the problem. ``field_of(I)``:
    the field hook of currents ``I`` (e.g. :func:`field_hook` of the eMNS)."""
    field = field_of(_currents_at(currents, t))
    out = sc.solve(solver, field=field, init=sol, raise_on_failure=False, **pose)
    if bool(out.converged.all()):
        return out
    if halvings > 0:
        mid = 0.5 * (t_prev + t)
        half = _warm_step(sc, solver, field_of, currents, pose, sol, t_prev, mid, halvings - 1)
        # the problems that converged in one step keep that solution: each problem of a batch is solved as alone
        return _where(out.converged, out, _warm_step(sc, solver, field_of, currents, pose, half, mid, t, halvings - 1))
    out = _where(out.converged, out, sc.solve(solver, field=field, load_steps=4, raise_on_failure=False, **pose))
    if not bool(out.converged.all()):
        bad = int((~out.converged).flatten().nonzero()[0])
        raise SolverError(f"static track: no equilibrium reached from t = {t_prev:.6g} s in {2 ** _HALVINGS} "
                          f"warm-started sub-steps nor from the unloaded rod (scaled tip residual "
                          f"{float(out.residual.flatten()[bad]):.3e})", time=t, node=bad)
    return out


def _where(mask: Tensor, a, b):
    """The static solution ``a`` where ``mask`` (...,) holds and ``b`` elsewhere (problem by problem)."""
    pick = lambda x, y: torch.where(mask.reshape(mask.shape + (1,) * (x.dim() - mask.dim())), x, y)  # noqa: E731
    return type(a)(a.s, *(pick(x, y) for x, y in zip(a[1:], b[1:])))


def static_state(P: Tensor, R: Tensor, R_rest: Tensor, margin: Tensor | None = None) -> Tensor:
    """``s`` (..., 12) of static magnet centres ``P`` (..., 2, 3) m and rotations ``R`` (..., 2, 3, 3) against
    the rotations at rest ``R_rest`` (2, 3, 3); with the stability ``margin`` (...) as a 13th column."""
    rot = so3_log(R @ R_rest.to(R).transpose(-1, -2)) * _DEG
    cols = [(P * 1e3).flatten(-2), rot.flatten(-2)] + ([] if margin is None else [margin[..., None].to(P)])
    return torch.cat(cols, -1)


def fold_clock_step(tau: Tensor, prev: Tensor, s: Tensor, margin_before: Tensor, cap: float) -> Tensor:
    """The fold clock (...,) of a frame with static state ``s`` (..., 13) after a frame with ``prev`` (..., 13) and
    clock ``tau``; ``margin_before``: the stability margin of the frame before ``prev``. Where the track jumps over a
    fold between the two frames (a magnet turns by more than :data:`FOLD_JUMP_DEG`), the clock restarts at the time
    since the fold, which lies where the squared margin, linear in the load near a fold, extrapolates from the two
    frames before to zero (halfway where they do not fall); otherwise it counts on by one frame, up to ``cap``."""
    jump = (s[..., 6:12] - prev[..., 6:12]).abs().amax(-1) > FOLD_JUMP_DEG  # (NaN, a track that ended: no jump)
    a, b = margin_before.square(), prev[..., 12].square()
    frac = torch.where(a > b, (b / (a - b).clamp(min=1e-30)).clamp(max=1.0), torch.full_like(a, 0.5))
    return torch.where(jump, 1.0 - frac, (tau + 1.0).clamp(max=cap))


def fold_clock(s: Tensor, cap: float) -> Tensor:
    """Frames (..., T) since the static track ``s`` (..., T, 13) last jumped over a fold, counted from the fold's
    estimated time within its frame (:func:`fold_clock_step`), at most ``cap`` (also before the first fold)."""
    if not cap > 0:
        raise ValueError(f"cap must be a positive number of frames, got {cap}")
    tau = [s.new_full(s.shape[:-2], float(cap))]
    for j in range(1, s.shape[-2]):
        tau.append(fold_clock_step(tau[-1], s[..., j - 1, :], s[..., j, :], s[..., max(j - 2, 0), 12], cap))
    return torch.stack(tau, -1)


def with_fold_clock(s: Tensor, cap: float) -> Tensor:
    """Static states ``s`` (..., T, 13) with :func:`fold_clock` as a 14th column."""
    return torch.cat([s, fold_clock(s, cap)[..., None]], -1)


def deviation(c: Tensor, R: Tensor, P: Tensor, Rs: Tensor) -> Tensor:
    """``d`` (..., 12) of magnets at ``c`` (..., 2, 3), ``R`` (..., 2, 3, 3) from the static ``P``, ``Rs``."""
    rot = so3_log(R @ Rs.transpose(-1, -2)) * _DEG
    return torch.cat([((c - P) * 1e3).flatten(-2), rot.flatten(-2)], -1)


def compose(d: Tensor, P: Tensor, Rs: Tensor) -> tuple[Tensor, Tensor]:
    """Magnet centres (..., 2, 3) and rotations (..., 2, 3, 3) at deviation ``d`` (..., 12) from the static
    ``P``, ``Rs`` (the inverse of :func:`deviation`)."""
    d = d.to(P.dtype)
    dc = d[..., :6].unflatten(-1, (2, 3)) * 1e-3
    dth = d[..., 6:].unflatten(-1, (2, 3)) / _DEG
    return P + dc, so3_exp(dth) @ Rs


def _drive_digest(currents, emns, times) -> str:
    """SHA-256 of the currents at ``times`` and of the coils (their specs' repr): what else a track depends on."""
    h = hashlib.sha256(repr(emns).encode())
    if currents is not None:
        for t in times:
            h.update(_currents_at(currents, t).contiguous().numpy().tobytes())
    return h.hexdigest()


def cached_static_track(path: str | Path | None, currents, emns, times, **kw) -> StaticTrack:
    """:func:`static_track`, read from ``path`` where it holds the same ``times``, keywords ``kw`` (clamp, nodes,
    ``truncate``), physics version, coils and currents at ``times`` (and written there, atomically, where it does
    not); ``None``: no cache."""
    times = [float(t) for t in times]
    key = {"times": times, "physics_version": physics.__version__,
           "kw": {k: v.tolist() if isinstance(v, Tensor) else v for k, v in sorted(kw.items())},
           "drive": _drive_digest(currents, emns, times)}
    if path is not None and Path(path).exists():
        blob = torch.load(path, weights_only=True)
        if blob.get("key") == key and "margin" in blob:
            return StaticTrack(blob["P"], blob["R"], blob["margin"], float(blob["wall_s"]))
    track = static_track(currents, emns, times, **kw)
    if path is not None:
        save_torch_atomic(path, {**track._asdict(), "key": key})
    return track
