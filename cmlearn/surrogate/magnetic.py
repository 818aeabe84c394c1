"""The magnetic-rod surrogate (Paper II, Data-set IV, Table II.1): closed-loop rollout, orientation errors
in degrees and the static Cosserat model as the baseline, against the LGVI.

Orientation error. For a predicted magnet rotation ``R_p`` and the reference ``R_r`` (both from the
block's tracked points, :func:`cmlearn.data.magnetic.magnet_frames`), the error is the rotation vector
``log(R_p R_r^T)`` in world coordinates, in degrees: its x, y, z components are the error angles about
the world axes (where the rod hangs along -z, x and y are the swing, z the turn about the vertical; in
the planar set-up, horizontal along x and steered in the x-z plane, y is the swing, as in the thesis).
Per axis we report the maximum and the mean of the absolute value over the samples, as Table II.1.

Free-running means closed loop: each step's input wrench (the magnets' torque and force) is computed
from the surrogate's own last predicted frame and the coil currents, so the surrogate needs nothing
from the physics but the currents. One-step predictions use the true history and wrench. Where a rollout
passes the rod's snap-throughs (folds of its equilibrium), when the surrogate's rod snaps is decided by
differences as small as float rounding, so one free-running run is one draw: :func:`nudged_free_running`
gives the spread over starts nudged by ~1e-8 m (``scripts/report_free_running_spread.py``).

The Cosserat baseline (:func:`cosserat_orientations`) solves the static rod of
:func:`physics.scenes_cosserat.paper2_magnetic_rod` in the same eMNS at each sample time with that
time's currents, warm-started from the previous sample (quasi-static, as the thesis ran it).
"""
from __future__ import annotations

import math
import time
import weakref
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor

from cmlearn.data.generate import reference_rollout
from cmlearn.data.magnetic import (block_nodes, by_frames, currents_series, equivalent_forces, field_samples,
                                   linearised_field, magnet_frames, rollout, simulate, tracked_points, wrench_inputs)
from cmlearn.data.quasistatic import static_track
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.eval.metrics import axis_errors, rmse_t
from cmlearn.io import save_torch_atomic
from physics.magnetics.field_table import CoilFieldTable

from .evaluate import from_rest, interest_slots, one_step

__all__ = ["MAGNETS", "simulate", "rollout", "orientation_errors", "orientation_stats", "closed_loop", "closed_loop_inputs",
           "closed_loop_wrench", "nudged_free_running", "cosserat_orientations", "base_pose", "evaluate", "run_scene", "short_check", "compare_scene",
           "FIELD_TABLE_RADIUS", "field_table", "closed_loop_step", "closed_loop_program", "check_workspace",
           "closed_loop_latency", "reference_profiles", "profile_start"]

MAGNETS = ("proximal", "distal")  # the rod's magnets in order along it
# m: the ball over which the real-time closed loop tabulates the coil field: the six-coil eMNS's 50 mm workspace
# (the rod's magnets stay within 48.5 mm of its centre, where the rod is clamped) and 10 mm more for a surrogate's
# error, 5 mm short of the coils' faces
FIELD_TABLE_RADIUS = 0.06
_TABLES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # field_table's, per eMNS


def reference_profiles(task, duration: float | None, data_dir: str | Path | None):
    """(label, scene, LGVI points, wrench inputs, whether it is the printed profile) per profile of ``task``: the
    printed one, then the held-out ones, each the LGVI's run (:func:`reference_rollout`, cached in ``data_dir``)."""
    for name in (task.scene, *task.heldout):
        scene = task.scene_by_name(name)
        pts, W, _ = reference_rollout(task, name, duration, data_dir)
        label = f"{name} (last 40 %)" if name == task.scene else name
        yield label, replace(scene, duration=duration or scene.duration), pts.float(), W.float(), name == task.scene


def profile_start(task, pts: Tensor, W: Tensor, eta: int, printed: bool) -> tuple[Tensor, Tensor, int, int]:
    """(points, the modelled nodes' wrench of their steps, start, pad) of a :func:`reference_profiles` case: the
    printed profile from its 60 % cut (:func:`split_ranges`), a held-out one from rest (``eta`` rest frames
    before t = 0, :func:`from_rest`)."""
    Wk = node_wrench(W, task.wrench_nodes, task.modeled)
    if printed:
        return pts, Wk, split_ranges(1, pts.shape[0])["test"][0][1], 0
    return *from_rest(pts, Wk, eta), eta, eta


def orientation_errors(R_pred: Tensor, R_ref: Tensor) -> Tensor:
    """World-frame error angles (..., 3) in degrees: the rotation vector of ``R_pred R_ref^T``."""
    from physics.lie import so3_log
    if R_pred.shape[-2:] != (3, 3) or R_ref.shape[-2:] != (3, 3):
        raise ValueError(f"R_pred {tuple(R_pred.shape)} and R_ref {tuple(R_ref.shape)} must both be (..., 3, 3)")
    torch.broadcast_shapes(R_pred.shape, R_ref.shape)
    return so3_log(R_pred.double() @ R_ref.double().transpose(-1, -2)) * (180.0 / math.pi)


def orientation_stats(err: Tensor) -> dict:
    """Per magnet and axis, max and mean absolute error (deg) of errors (T, K, 3)."""
    a = err.abs()
    return {name: {ax: {"max_deg": float(a[:, k, i].max()), "mean_deg": float(a[:, k, i].mean())}
                   for i, ax in enumerate("xyz")} for k, name in enumerate(MAGNETS)}


@torch.no_grad()
def closed_loop(model, task, rod, emns, hist: Tensor, currents, k0: int, n_steps: int, ref: Tensor) -> Tensor:
    """Free-running frames (B, n_steps, n_tracked, 3) after ``hist`` (B, eta+1, n_tracked, 3) ending at frame
    ``k0``; the step from frame k uses the currents at ``(k + 1/2) delta`` and the wrench of frame k."""
    def wrench_fn(h, frame):
        t = torch.tensor((k0 + h + 0.5) * task.delta, dtype=torch.float64)
        I = torch.as_tensor(currents(t), dtype=torch.float64)
        return node_wrench(wrench_inputs(task, rod, emns, frame.double(), I).float(), task.wrench_nodes, task.modeled)
    return model.rollout(hist.float(), torch.zeros(hist.shape[0], n_steps, 0), ref, wrench_fn=wrench_fn)


@torch.no_grad()
def nudged_free_running(model, task, scene, pos: Tensor, start: int, pad: int = 0, n: int = 16,
                        sigma: float = 1e-8, seed: int = 0, wrench: Tensor | None = None) -> dict:
    """Closed-loop free-running orientation errors from ``n`` copies of the true history at frame ``start`` of
    ``pos`` (T, n_tracked, 3; its first ``pad`` frames before t = 0), each modelled point nudged by N(0, sigma^2)
    m (float32 rounding of these coordinates is ~1e-8 m), run as one batch. Returns, per start, the sum of the
    six mean absolute errors (deg), and per magnet and axis the mean over starts of the mean error and the
    largest maximum: the spread of a free-running figure whose rollout passes the rod's snap-throughs.
    ``wrench``: the modelled nodes' forces (T-1, K, 3) of ``pos``'s steps, as in the data; where given they drive
    the rollout instead of the closed loop (open loop: the wrench of the LGVI's own poses)."""
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n must be a positive number of starts, got {n!r}")
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be a finite distance >= 0 (m), got {sigma!r}")
    W = model.config.eta + 1
    hist = pos[None, start - W + 1:start + 1].float().repeat(n, 1, 1, 1)
    g = torch.Generator().manual_seed(seed)
    idx = model.idx_modeled
    hist[:, :, idx] += sigma * torch.randn(hist[:, :, idx].shape, generator=g)
    rod, H, ref = scene.rod, pos.shape[0] - 1 - start, pos[:1].float().expand(n, -1, -1)
    if wrench is None:
        pred = closed_loop(model, task, rod, scene.loads.field.emns, hist, scene.loads.field.currents, start - pad,
                           H, ref)
    else:
        if wrench.shape[0] != pos.shape[0] - 1:
            raise ValueError(f"wrench must hold one step per interval of pos ({pos.shape[0] - 1}), got {wrench.shape[0]}")
        pred = model.rollout(hist, wrench[None, start:].float().expand(n, -1, -1, -1), ref)
    _, R_ref, _ = magnet_frames(task, rod, pos[start + 1:].double())
    err = orientation_errors(magnet_frames(task, rod, pred.double())[1], R_ref).abs()  # (n, T, K, 3)
    mean, mx = err.mean(1), err.amax(1)  # (n, K, 3)
    return {"n": n, "sigma_m": sigma, "sum_mean_deg": mean.sum((1, 2)).tolist(),
            **{name: {ax: {"mean_deg": float(mean[:, k, i].mean()), "max_deg": float(mx[:, k, i].max())}
                      for i, ax in enumerate("xyz")} for k, name in enumerate(MAGNETS)}}


def closed_loop_inputs(task, data: dict) -> Tensor:
    """For closed-loop training (:class:`~cmlearn.surrogate.training.SurrogateModule` ``wrench_fn``): the field
    samples (V, T-1, K, 15) of a dataset's trajectories (:func:`cmlearn.data.magnetic.field_samples` at frame
    k with the currents at ``(k + 1/2) delta``, the variants' currents regenerated from the task and seed),
    checked against the dataset's stored wrench."""
    meta = data["meta"]
    scene = replace(task.base_scene(), duration=meta["duration"])
    currents = task.variants(scene, meta["n_variants"], meta["seed"])["currents"]
    pos = data["positions"][:, :-1].double()
    I = currents_series(currents, pos.shape[1], task.delta).movedim(0, -2)  # (V, T-1, C)
    samples = by_frames(lambda p, i: field_samples(task, scene.rod, scene.loads.field.emns, p, i), pos, I)
    W = equivalent_forces(task, scene.rod, pos, linearised_field(samples))
    scale = float(data["wrench"].abs().max())
    if not float((W - data["wrench"].double()).abs().max()) <= 1e-4 * scale:
        raise ValueError(f"the regenerated currents of task {task.name!r} (seed {meta['seed']}) do not give the "
                         "dataset's wrench: regenerate the dataset with this version")
    return samples.float()


def closed_loop_wrench(task):
    """``wrench_fn(frame, samples)`` for closed-loop training: the node forces (B, K, 3) of frames (B, n_tracked, 3)
    in the field linearised about :func:`closed_loop_inputs` samples (B, n_magnets, 15)."""
    rod = task.base_scene().rod

    def wrench_fn(frame, samples):
        w = equivalent_forces(task, rod, frame, linearised_field(samples))
        return node_wrench(w, task.wrench_nodes, task.modeled)
    return wrench_fn


def base_pose(scene) -> dict:
    """The clamp of a magnetic-rod scene as keywords of the Cosserat solve (``{}``: hanging from the origin,
    the Cosserat scene's own base)."""
    if "base_rotation" not in scene.chosen:
        return {}
    from physics.lie import matrix_to_quat
    R = torch.tensor(scene.chosen["base_rotation"], dtype=torch.float64)
    return {"base_position": scene.chosen["base_position"], "base_quaternion": matrix_to_quat(R)}


def cosserat_orientations(currents, times, field_model, n_nodes: int = 13, **pose):
    """Magnet rotations (T, 2, 3, 3) of the static Cosserat rod at ``times`` (s) with ``currents(t)``, each
    solve warm-started from the previous one; also the solver wall time (s). ``pose``: the clamp
    (:func:`base_pose`). :func:`cmlearn.data.quasistatic.static_track`'s rotations."""
    track = static_track(currents, field_model, times, n_nodes, **pose)
    return track.R, track.wall_s


def _position_metrics(pred: Tensor, ref: Tensor, slots, length: float) -> dict:
    r = rmse_t(pred[:, slots[0]], ref[:, slots[0]])
    return {"node": axis_errors(pred[:, slots[0]], ref[:, slots[0]], length),
            "all_nodes_max_mm": float((pred[:, slots] - ref[:, slots]).abs().max()) * 1e3,
            "rmse_mean_mm": float(r.mean()) * 1e3, "rmse_max_mm": float(r.max()) * 1e3}


def cached_cosserat(task, scene, times, data_dir: str | Path | None):
    """:func:`cosserat_orientations` of ``scene``'s currents at ``times``, cached in ``data_dir`` (it does not
    depend on any surrogate and takes minutes)."""
    from cmlearn.data.generate import data_hash
    path = None
    if data_dir is not None:
        key = data_hash(torch.tensor(times, dtype=torch.float64))[:8]
        path = Path(data_dir) / f"{task.name}_{scene.name}_cosserat_{len(times)}_{key}.pt"
        if path.exists():
            blob = torch.load(path, weights_only=True)
            return blob["R"], float(blob["wall_s"])
    R, wall = cosserat_orientations(scene.loads.field.currents, times, scene.loads.field.emns, **base_pose(scene))
    if path is not None:
        save_torch_atomic(path, {"R": R, "wall_s": wall})
    return R, wall


def _case(model, task, scene, pos: Tensor, wr: Tensor, start: int, pad: int = 0, cosserat: bool = True,
          data_dir: str | Path | None = None, nudged: int = 16) -> dict:
    """Both surrogate modes (and the Cosserat model) on frames start+1 .. T-1 of ``pos`` (T, n_tracked, 3),
    whose first ``pad`` frames are copies of the rest frame before t = 0 (frame k is at (k - pad) delta); with
    ``nudged`` > 0 also the free-running spread over that many nudged starts (:func:`nudged_free_running`)."""
    rod, emns, cur = scene.rod, scene.loads.field.emns, scene.loads.field.currents
    W = model.config.eta + 1
    ref = pos[start + 1:].double()
    preds = {"one_step": one_step(model, pos, wr, start).double(),
             "free_running": closed_loop(model, task, rod, emns, pos[None, start - W + 1:start + 1], cur, start - pad,
                                         pos.shape[0] - 1 - start, pos[:1].float())[0].double()}
    _, R_ref, _ = magnet_frames(task, rod, ref)
    slots = interest_slots(task, scene)
    out = {mode: _position_metrics(p, ref, slots, rod.length) for mode, p in preds.items()}
    out["orientation_deg"] = {mode: orientation_stats(orientation_errors(magnet_frames(task, rod, p)[1], R_ref))
                              for mode, p in preds.items()}
    if cosserat:
        times = [(k - pad) * task.delta for k in range(start + 1, pos.shape[0])]
        R_cos, wall = cached_cosserat(task, scene, times, data_dir)
        out["orientation_deg"]["cosserat"] = orientation_stats(orientation_errors(R_cos, R_ref))
        out["cosserat_wall_s"] = wall
    if nudged:
        out["free_running_nudged"] = nudged_free_running(model, task, scene, pos, start, pad, n=nudged)
    return out


def evaluate(model, task, data: dict, args) -> dict:
    """Metrics stored with a checkpoint: the printed scene's last 40 % (true history at the cut) and the
    held-out scenes from rest, surrogate one-step and free-running (closed loop), the free-running spread over
    16 nudged starts (``free_running_nudged``) and the Cosserat model."""
    meta = data["meta"]
    scene = task.base_scene()
    duration = getattr(args, "duration", 0.0) or None
    if duration:
        scene = replace(scene, duration=duration)
    pos = data["positions"][0]
    wr = node_wrench(data["wrench"][0], meta["wrench_nodes"], meta["modeled"])
    cut = split_ranges(meta["n_variants"], pos.shape[0])["test"][0][1]
    data_dir = getattr(args, "data_dir", "data")
    metrics = {"seen_last40": _case(model, task, scene, pos, wr, cut, data_dir=data_dir)}
    eta = model.config.eta
    for name in task.heldout:
        held = task.scene_by_name(name)
        p, W, wall = reference_rollout(task, name, duration, getattr(args, "data_dir", "data"))
        p, W = p.float(), W.float()
        Wk = node_wrench(W, task.wrench_nodes, task.modeled)
        p_hist, W_hist = from_rest(p, Wk, eta)
        metrics[name] = _case(model, task, replace(held, duration=duration or held.duration), p_hist, W_hist, eta,
                              pad=eta, data_dir=data_dir)
        metrics[name]["lgvi_wall_s"] = wall
    return metrics


def initial_points(task, scene) -> Tensor:
    cfg = scene.initial_configuration()
    return tracked_points(task, scene.rod, cfg["p"], cfg["R"]).float()


def field_table(emns) -> CoilFieldTable:
    """``emns``'s field tabulated over the ball of :data:`FIELD_TABLE_RADIUS` (a 1 mm grid, interpolated at order
    6: for the default eMNS within 2.6e-9 of the exact superposition and 1.5e-8 of its gradient over the
    workspace, 8e-8 and 1.2e-6 at the ball's edge, relative), built once per eMNS (0.3-0.6 s), for the
    real-time closed loop."""
    table = _TABLES.get(emns)
    if table is None:
        table = _TABLES[emns] = CoilFieldTable.from_emns(emns, radius=FIELD_TABLE_RADIUS, spacing=1e-3, order=6)
    return table


def closed_loop_step(model, task, rod, field: CoilFieldTable, program: bool = False):
    """The real-time closed loop's step ``(hist (B, eta+1, n_tracked, 3), currents (B, C), ref (B, n_tracked,
    3)[, rest]) -> (the history moved on by one frame, that frame (B, n_tracked, 3))``: the magnets' node
    forces from the last frame in the tabulated ``field`` (its ball unchecked, so that the step compiles:
    :func:`run_scene` checks it afterwards), then the model's step (``program``: its compiled form); anchors
    stay put. Tracks no gradients (inference)."""
    idx = model.idx_modeled
    block_nodes(rod)  # computed with tensors: cached here, outside a trace

    @torch.no_grad()
    def step(hist: Tensor, I: Tensor, ref: Tensor, *rest: Tensor) -> tuple[Tensor, Tensor]:
        last = hist[:, -1]
        f = equivalent_forces(task, rod, last.double(), lambda c: field.field_and_gradient(c, I, check=False))
        w = node_wrench(f.float(), task.wrench_nodes, task.modeled)
        nxt = last.index_copy(1, idx, model(hist, w, ref, program=program, rest=rest[0] if rest else None))
        return torch.cat([hist[:, 1:], nxt[:, None]], 1), nxt
    return step


def check_workspace(task, rod, field: CoilFieldTable, points: Tensor) -> None:
    """Raise :class:`~.engine.SurrogateDivergence`, naming the step, its time and the magnet, where a rollout's
    points (T, n_tracked, 3) put a magnet outside ``field``'s tabulated ball (beyond the eMNS's workspace)."""
    from .engine import SurrogateDivergence
    c = magnet_frames(task, rod, points.double())[0]
    bad = field.outside(c) | ~torch.isfinite(c).all(-1)
    if bool(bad.any()):
        k, j = (int(x) for x in bad.nonzero()[0])
        raise SurrogateDivergence(
            f"the {task.name!r} surrogate left the eMNS's workspace at step {k} (t = {k * task.delta:.3f} s): the "
            f"{MAGNETS[j]} magnet is {float((c[k, j] - field.centre).norm()):.4g} m from its centre, beyond the "
            f"{field.radius:g} m where its field is tabulated")


@torch.no_grad()
def run_scene(engine, scene, duration: float | None = None, exact_field: bool = False) -> tuple[Tensor, float]:
    """Closed-loop surrogate on ``scene`` from rest, in the tabulated field (:func:`field_table`,
    :func:`closed_loop_step`; compiled after ``engine.compile()``), or with ``exact_field`` in the coils' exact
    field, eager, as the evaluation runs it (:func:`closed_loop`): tracked points (T, n_tracked, 3) and the wall
    time, the currents' evaluation included."""
    from .engine import check_scene
    task = engine.task
    check_scene(task, scene)
    task.check_duration(duration or scene.duration)
    n = int(round((duration or scene.duration) / task.delta))
    if exact_field:
        ref = initial_points(task, scene)[None]
        t0 = time.perf_counter()
        fr = closed_loop(engine.model, task, scene.rod, scene.loads.field.emns,
                         ref[:, None].expand(-1, engine.eta + 1, -1, -1), scene.loads.field.currents, 0, n, ref)
        return torch.cat([ref, fr[0]]), time.perf_counter() - t0
    step, args = closed_loop_program(engine, scene)
    hist, ref = args[0], args[2]
    t0 = time.perf_counter()
    currents = currents_series(scene.loads.field.currents, n, task.delta).split(1)  # n of (1, C)
    out = [ref]
    for I in currents:
        hist, nxt = step(hist, I, *args[2:])
        out.append(nxt)
    wall = time.perf_counter() - t0
    out = torch.cat(out)
    check_workspace(task, scene.rod, field_table(scene.loads.field.emns), out)
    return out, wall


def closed_loop_program(engine, scene) -> tuple:
    """A controller's closed loop on ``scene``: ``step`` (:func:`closed_loop_step` in the tabulated field, eager,
    or compiled after ``engine.compile()``) and its arguments ``[hist, currents, ref(, rest)]`` at rest in the
    scene's initial shape (currents zero, (1, C) A); call ``hist, frame = step(hist, currents, *args[2:])``."""
    from .engine import check_scene
    check_scene(engine.task, scene)
    field = field_table(scene.loads.field.emns)
    ref = initial_points(engine.task, scene)[None]
    rest = engine.rest_accel(ref)
    hist = ref[:, None].expand(-1, engine.eta + 1, -1, -1).contiguous()
    args = [hist, torch.zeros(1, scene.loads.field.emns.n_coils, dtype=torch.float64), ref] \
        + ([] if rest is None else [rest])
    step = engine.program(("closed_loop", scene.rod, field),
                          lambda program: closed_loop_step(engine.model, engine.task, scene.rod, field, program), args)
    return step, args


@torch.no_grad()
def closed_loop_latency(engine, scene, n: int = 500, warmup: int = 20) -> float:
    """Seconds per batch-1 closed-loop step (:func:`closed_loop_step`, compiled after ``engine.compile()``; the
    median of ``n`` timed steps from the scene's initial shape, with its currents given), the field and the
    wrench included: what a controller that sets the currents waits for."""
    from .engine import median_latency
    if not (isinstance(n, int) and n >= 1 and isinstance(warmup, int) and warmup >= 0):
        raise ValueError(f"n must be an integer >= 1 and warmup one >= 0, got n={n!r}, warmup={warmup!r}")
    step, args = closed_loop_program(engine, scene)
    args[1] = currents_series(scene.loads.field.currents, 1, engine.task.delta)
    return median_latency(lambda: step(*args), n, warmup)


def short_check(engine, scene_name: str, duration: float, data_dir=None) -> dict:
    """Closed-loop surrogate against the LGVI for the first ``duration`` s: the tip's maximum position
    error (mm) and the largest magnet orientation error (deg). The LGVI's run is cached in ``data_dir`` if given."""
    task = engine.task
    scene = replace(task.scene_by_name(scene_name), duration=duration)
    ref = reference_rollout(task, scene_name, duration, data_dir)[0]
    pred, _ = engine.run_scene(scene)
    slot = interest_slots(task, scene)[0]
    err = orientation_errors(magnet_frames(task, scene.rod, pred.double())[1],
                             magnet_frames(task, scene.rod, ref.double())[1])
    return {"scene": scene_name, "duration": duration,
            "max_err_mm": float((pred[:, slot].double() - ref[:, slot].double()).abs().max()) * 1e3,
            "max_orientation_err_deg": float(err.abs().max())}


def compare_scene(task, scene, p_ref: torch.Tensor, p_sur: torch.Tensor, t: torch.Tensor) -> dict:
    """:func:`cmlearn.compare.compare_scene`'s part for the magnetic rod, from the LGVI's and the surrogate's tracked
    points ``p_ref``, ``p_sur`` at times ``t``: the magnets' orientation errors (deg) of the surrogate (closed loop)
    and of the static Cosserat model, and, where ``checkpoints/<task>_quasistatic.pt`` is shipped, of the
    quasi-static hybrid (:mod:`cmlearn.surrogate.quasistatic`) on the same static track, with the wall times of
    the last two."""
    from cmlearn.compare import find_checkpoint
    rod = scene.rod
    R_ref = magnet_frames(task, rod, p_ref[1:].double())[1]
    orient = {"surrogate": orientation_stats(orientation_errors(magnet_frames(task, rod, p_sur[1:].double())[1], R_ref))}
    track = static_track(scene.loads.field.currents, scene.loads.field.emns, t.tolist(), **base_pose(scene))
    wall_cos = track.wall_s
    orient["cosserat"] = orientation_stats(orientation_errors(track.R[1:], R_ref))
    hybrid = {}
    try:
        path = find_checkpoint(f"{task.name}_quasistatic")
    except FileNotFoundError:  # no quasi-static hybrid shipped for this task
        path = None
    if path is not None:  # the hybrid on the same static track: its correction's time on top of the solves'
        from .quasistatic import QuasiStaticSurrogate
        hyb = QuasiStaticSurrogate.load(path, task=task.name)
        t0 = time.perf_counter()
        R_hyb = hyb.run(scene, track=track)[1]
        hybrid = {"hybrid_wall_s": wall_cos + time.perf_counter() - t0}
        orient["hybrid"] = orientation_stats(orientation_errors(R_hyb, R_ref))
    return {"cosserat_wall_s": wall_cos, **hybrid, "orientation_deg": orient}
