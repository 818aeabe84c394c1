"""The quasi-static hybrid surrogate of the magnetic rod: the static Cosserat rod solved at each 20 ms step
for the step's currents, plus a learned correction for the rod's dynamics
(:class:`~cmlearn.models.QuasiStaticCorrection`). It needs nothing from the physics but the currents: the
static solve is warm-started from the step before, and the correction runs free on its own deviations.

Checkpoints are their own format (``cmlearn-quasistatic/1``: the correction's weights and configuration and
the metadata, with a JSON copy), written atomically and loaded without Lightning by
:meth:`QuasiStaticSurrogate.load`. Orientation errors are those of :mod:`cmlearn.surrogate.magnetic` (Table
II.1): the printed profile's last 40 % from its 60 % cut (the true deviations before the cut), the held-out
profiles from rest.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor

from cmlearn.data.generate import cached_dataset, dataset_path, reference_rollout
from cmlearn.data.magnetic import check_tracked_points, magnet_frames
from cmlearn.data.quasistatic import (StaticTrack, cached_static_track, compose, deviation, static_state,
                                      static_track, with_fold_clock)
from cmlearn.data.tasks import get_task
from cmlearn.data.windows import split_ranges
from cmlearn.io import CheckpointError, save_sealed
from cmlearn.models.quasistatic import QuasiStaticConfig, QuasiStaticCorrection
from physics.lie import so3_exp

from .checkpoint import plain_meta, read_blob
from .engine import check_scene
from .magnetic import base_pose, orientation_errors, orientation_stats

__all__ = ["FORMAT", "save_quasistatic", "QuasiStaticSurrogate", "rest_rotations", "scene_track", "profile_tracks",
           "rollout_from", "deviation_errors", "profile_scores", "static_tracks", "fresh_scores", "short_check",
           "evaluate_quasistatic"]

FORMAT = "cmlearn-quasistatic/1"


def save_quasistatic(path: str | Path, model: QuasiStaticCorrection, meta: dict) -> Path:
    """Write the checkpoint and its JSON metadata (``<name>.json``) atomically."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    return save_sealed(path, {"format": FORMAT, "config": model.config.to_dict(),
                              "meta": plain_meta({**meta, "format": FORMAT}), "state_dict": state})


def rest_rotations(task) -> Tensor:
    """The static rod's magnet rotations (2, 3, 3) at rest (zero current) in the task's scene."""
    scene = task.base_scene()
    return static_track(lambda t: torch.zeros(scene.loads.field.emns.n_coils, dtype=torch.float64),
                        scene.loads.field.emns, [0.0], **base_pose(scene))[1][0]


def scene_track(task, scene, n_frames: int, cache: str | Path | None = None, currents=None,
                truncate: bool = False) -> StaticTrack:
    """:func:`cached_static_track` of ``scene`` at its first ``n_frames`` frames (k delta), in its eMNS and clamp,
    along its own currents or ``currents`` (``truncate``: as :func:`static_track`'s)."""
    times = [k * task.delta for k in range(n_frames)]
    return cached_static_track(cache, scene.loads.field.currents if currents is None else currents,
                               scene.loads.field.emns, times, truncate=truncate, **base_pose(scene))


def profile_tracks(task, scene, positions: Tensor, R_rest: Tensor, cache: str | Path | None = None,
                   currents=None, truncate: bool = False, track: StaticTrack | None = None):
    """Static states ``s`` (..., T, 13: with the margin) and deviations ``d`` (..., T, 12) of a scene's LGVI runs
    ``positions`` (..., T, n_tracked, 3) at frames k delta, and the :class:`StaticTrack`; the track cached at
    ``cache`` if given.
    ``currents``: a batch of profiles ``currents(t) -> (V, C)`` instead of the scene's own; ``truncate``: a
    profile whose static track ends at a fold is NaN from there (:func:`static_track`) instead of an error;
    ``track``: the track where already solved."""
    if track is None:
        track = scene_track(task, scene, positions.shape[-3], cache, currents, truncate)
    c, Rl, _ = magnet_frames(task, scene.rod, positions.double())
    return static_state(track.P, track.R, R_rest, track.margin), deviation(c, Rl, track.P, track.R), track


@torch.no_grad()
def rollout_from(model: QuasiStaticCorrection, s: Tensor, d: Tensor, start: int) -> Tensor:
    """Free-running deviations (..., T-1-start, 12) of frames start+1 .. T-1 from static states ``s`` and the
    true deviations ``d`` (..., T, 12) up to frame ``start`` (float32 inside); a history reaching before frame 0
    repeats frame 0 (from rest). A model that reads the fold clock gets it (:func:`with_fold_clock`) where ``s``
    (..., T, 13) has none, counted from its first frame."""
    c = model.config
    if not 0 <= start < s.shape[-2] - 1:
        raise ValueError(f"start must be a frame 0..{s.shape[-2] - 2} of the {s.shape[-2]} frames, got {start!r}")
    if c.fold_clock and s.shape[-1] == 13:
        s = with_fold_clock(s, c.fold_clock)
    lead = max(c.eta, c.increments - 1)
    batch = s.shape[:-2]
    s, d = s.reshape(-1, *s.shape[-2:]).float(), d.reshape(-1, *d.shape[-2:]).float()
    if start < lead:
        pad = lead - start
        s = torch.cat([s[:, :1].expand(-1, pad, -1), s], 1)
        d = torch.cat([d[:, :1].expand(-1, pad, -1), d], 1)
        start = lead
    dev = model.rollout(d[:, start - c.eta:start + 1], s[:, start + 1 - c.increments:])
    return dev.double().reshape(*batch, *dev.shape[1:])


def deviation_errors(d_pred: Tensor, d_true: Tensor) -> Tensor:
    """Orientation errors (..., 2, 3) deg (:func:`~cmlearn.surrogate.magnetic.orientation_errors`) of magnets at
    deviations ``d_pred`` from the same static rod as the true ``d_true`` (..., 12)."""
    rad = math.pi / 180.0
    R = lambda x: so3_exp(x[..., 6:].unflatten(-1, (2, 3)).double() * rad)  # noqa: E731
    return orientation_errors(R(d_pred), R(d_true))


def profile_scores(model: QuasiStaticCorrection, s: Tensor, d: Tensor) -> Tensor:
    """Per profile the sum of the six mean absolute orientation errors (deg) of the hybrid run from rest (zero
    deviation) along static states ``s`` (V, T, 12), against the true deviations ``d``: a score on profiles no
    model trained on."""
    return _sum_of_means(rollout_from(model, s, torch.zeros_like(d), 0), d[:, 1:])


def _sum_of_means(d_pred: Tensor, d_true: Tensor) -> Tensor:
    """Per profile the sum of the six mean absolute orientation errors (deg) of deviations (V, T, 12)."""
    return deviation_errors(d_pred, d_true).abs().mean(1).sum((1, 2))


def static_tracks(task, dataset: dict, data_dir: str | Path | None, R_rest: Tensor,
                  truncate: bool = False) -> tuple[Tensor, Tensor]:
    """Static states (V, T, 13) and deviations (V, T, 12) of ``dataset``'s profiles (regenerated from its seed,
    the static track cached as ``<dataset>_static.pt`` in ``data_dir``; ``truncate``: as :func:`profile_tracks`')."""
    meta = dataset["meta"]
    scene = task.base_scene()
    cache = None
    if data_dir is not None:
        cache = dataset_path(data_dir, task.name, meta["n_variants"], meta["seed"]).with_suffix("")
        cache = cache.with_name(cache.name + "_static.pt")
    return profile_tracks(task, scene, dataset["positions"], R_rest, cache,
                          task.variants(scene, meta["n_variants"], meta["seed"])["currents"], truncate)[:2]


def fresh_scores(model: QuasiStaticCorrection, task, n_variants: int, seed: int, data_dir: str | Path | None) -> dict:
    """:func:`profile_scores` of the hybrid and of the static rod alone on the random profiles 1..n-1 of a dataset
    of ``seed`` (profile 0 is the printed one): the median, mean and largest sum of six mean errors (deg)."""
    data = cached_dataset(task, n_variants, seed, data_dir)
    s, d = static_tracks(task, data, data_dir, rest_rotations(task))
    out = {"seed": seed, "profiles": n_variants - 1, "data_hash": data["meta"]["data_hash"]}
    for name, sc in (("hybrid", profile_scores(model, s[1:], d[1:])),
                     ("static", _sum_of_means(torch.zeros_like(d[1:, 1:]), d[1:, 1:]))):
        out[name] = {"median": float(sc.median()), "mean": float(sc.mean()), "max": float(sc.max()),
                     "per_profile": [round(float(x), 4) for x in sc]}
    return out


class QuasiStaticSurrogate:
    """A loaded hybrid: ``run(scene, ...)`` gives its magnets along a scene's currents; ``latency()`` times one
    real-time step (the warm static solve and the correction) at batch 1."""

    def __init__(self, model: QuasiStaticCorrection, meta: dict):
        self.model, self.meta = model.eval(), meta
        self.task = get_task(meta["task"])
        self._rest, self._programs = None, {}

    @classmethod
    def load(cls, path: str | Path, task: str | None = None) -> "QuasiStaticSurrogate":
        blob, meta = read_blob(path, FORMAT, task)
        try:
            model = QuasiStaticCorrection(QuasiStaticConfig(**blob["config"]))
            model.load_state_dict(blob["state_dict"])
        except (TypeError, ValueError, RuntimeError, KeyError) as e:
            raise CheckpointError(f"{path}: weights do not match the stored configuration ({str(e)[:200]})") from None
        return cls(model, meta)

    @property
    def rest(self) -> Tensor:
        if self._rest is None:
            self._rest = rest_rotations(self.task)
        return self._rest

    @torch.no_grad()
    def run(self, scene, positions: Tensor | None = None, start: int = 0, cache=None, track=None):
        """Magnet centres (H, 2, 3) and rotations (H, 2, 3, 3) of frames start+1 .. T-1 of ``scene`` (T frames
        of its duration), and the static track's. From rest where ``start`` is 0 (deviations zero before t = 0);
        from frame ``start`` of the LGVI's ``positions`` (its true deviations before) otherwise. ``track``: the
        scene's :class:`~cmlearn.data.quasistatic.StaticTrack` at its T frames where already solved."""
        self._check_scene(scene)
        self.task.check_duration(scene.duration)
        T = int(round(scene.duration / self.task.delta)) + 1
        if positions is not None:
            check_tracked_points(self.task, scene.rod, positions)
            if positions.dim() != 3 or positions.shape[0] != T:
                raise ValueError(f"positions must hold the scene's {T} frames (T, n_tracked, 3), got "
                                 f"{tuple(positions.shape)}")
        elif start:
            raise ValueError("a start after rest needs the LGVI's positions for its history")
        if track is not None and not (isinstance(track, StaticTrack) and track.P.shape[:2] == (T, 2)):
            raise ValueError(f"track must be the scene's StaticTrack at its {T} frames (P ({T}, 2, 3)), got "
                             f"{tuple(track.P.shape) if isinstance(track, StaticTrack) else type(track).__name__}")
        if positions is None:
            track = scene_track(self.task, scene, T, cache) if track is None else track
            s, d = static_state(track.P, track.R, self.rest, track.margin), torch.zeros(T, 12, dtype=torch.float64)
        else:
            s, d, track = profile_tracks(self.task, scene, positions, self.rest, cache, track=track)
        P, R = track.P, track.R
        dev = rollout_from(self.model, s, d, start)
        cp, Rp = compose(dev, P[start + 1:], R[start + 1:])
        return cp, Rp, P[start + 1:], R[start + 1:]

    def _check_scene(self, scene) -> None:
        """:func:`~cmlearn.surrogate.engine.check_scene` (the task's rod and clamp), and a ValueError unless the
        scene's rod hangs in a coil field, whose currents the hybrid solves for."""
        check_scene(self.task, scene)
        if not hasattr(getattr(scene.loads, "field", None), "currents"):
            raise ValueError(f"scene {scene.name!r} has no coil field (loads.field with currents), which the "
                             "quasi-static hybrid solves in")

    def stepper(self, scene, compile: bool = False, predictor: bool = True, **kw):
        """The real-time hybrid in ``scene``'s coils and clamp, at rest at zero current
        (:class:`~cmlearn.surrogate.quasistatic_stepper.QuasiStaticStepper`: ``step(currents)`` -> the next frame's
        magnets; keywords go to it). ``compile``: the solver's compiled path in the coils' field tabulated over the
        workspace and the rest of the step one program compiled ahead of time; the first solve compiles (about three
        minutes here, seconds from inductor's cache)."""
        from .quasistatic_stepper import QuasiStaticStepper
        self._check_scene(scene)
        return QuasiStaticStepper(self.model, self.rest, scene.loads.field.emns, base_pose(scene), self.task.delta,
                                  compile=compile, predictor=predictor, programs=self._programs, **kw)

    def latency(self, scene, n: int | None = 50, compile: bool = False, predictor: bool = True, **kw) -> dict:
        """Seconds of one real-time step of :meth:`stepper` (keywords go to it) at batch 1 along ``scene``'s first
        ``n`` frames (``None``: all of them): the medians of the static solve at the next frame's currents and of
        the correction (the first step, which compiles where ``compile``, is not timed), the slowest step, the
        steps slower than the frame and the mean LM iterations of a solve."""
        n = int(round(scene.duration / self.task.delta)) if n is None else n
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"n must be an integer >= 1 (steps timed) or None, got {n!r}")
        st = self.stepper(scene, compile=compile, predictor=predictor, **kw)
        currents = scene.loads.field.currents
        t_solve, t_net, its = [], [], []
        for k in range(1, n + 2):
            I = currents(torch.tensor(k * self.task.delta, dtype=torch.float64))
            t0 = time.perf_counter()
            st.solve(I)
            t1 = time.perf_counter()
            st.correct()
            t2 = time.perf_counter()
            if k > 1:
                t_solve.append(t1 - t0)
                t_net.append(t2 - t1)
                its.append(st.iterations)
        med = lambda x: sorted(x)[len(x) // 2]  # noqa: E731
        steps = [a + b for a, b in zip(t_solve, t_net)]
        return {"static_solve_s": med(t_solve), "correction_s": med(t_net), "step_s": med(t_solve) + med(t_net),
                "max_step_s": max(steps), "over_frame": sum(x > self.task.delta for x in steps), "steps": len(steps),
                "iterations": sum(its) / len(its), "max_iterations": max(its)}


def short_check(engine: QuasiStaticSurrogate, duration: float = 1.5, data_dir: str | Path | None = None) -> dict:
    """The hybrid from rest against the LGVI over the printed profile's first ``duration`` s (its first move):
    what a checkpoint records and a test reproduces."""
    task = engine.task
    scene = replace(task.base_scene(), duration=duration)
    pts = reference_rollout(task, task.scene, duration, data_dir)[0]
    _, Rp, _, Rs = engine.run(scene)
    R_ref = magnet_frames(task, scene.rod, pts[1:].double())[1]
    e, es = orientation_errors(Rp, R_ref).abs(), orientation_errors(Rs, R_ref).abs()
    return {"scene": task.scene, "duration": duration, "sum_mean_deg": float(e.mean(0).sum()),
            "max_deg": float(e.max()), "static_sum_mean_deg": float(es.mean(0).sum())}


def evaluate_quasistatic(engine: QuasiStaticSurrogate, data_dir: str | Path | None = None) -> dict:
    """Orientation errors (deg) of the hybrid and of the static rod alone, per profile of the task (the printed
    one's last 40 % from the cut, the held-out ones from rest), with the sums of the six means, and the run's
    ``wall_s``: the static solves' time within it unless ``static_track_cached`` (read from ``data_dir``)."""
    task = engine.task
    out = {}
    for name in (task.scene, *task.heldout):
        scene = task.scene_by_name(name)
        pts = reference_rollout(task, name, data_dir=data_dir)[0]
        cache = None if data_dir is None else Path(data_dir) / f"{task.name}_{name}_static_{pts.shape[0]}.pt"
        printed = name == task.scene
        start = split_ranges(1, pts.shape[0])["test"][0][1] if printed else 0
        cached = cache is not None and cache.exists()
        t0 = time.perf_counter()
        _, Rp, _, Rs = engine.run(scene, pts if printed else None, start, cache)
        wall = time.perf_counter() - t0
        R_ref = magnet_frames(task, scene.rod, pts[start + 1:].double())[1]
        res = {}
        for model, R in (("hybrid", Rp), ("static", Rs)):
            e = orientation_errors(R, R_ref)
            res[model] = {**orientation_stats(e), "sum_mean_deg": float(e.abs().mean(0).sum())}
        res["wall_s"], res["static_track_cached"] = wall, cached
        out[f"{name} (last 40 %)" if printed else name] = res
    return out
