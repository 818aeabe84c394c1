"""Generate surrogate training data with the LGVI and store it compactly and atomically.

A dataset file (``torch.save``) holds, for V variants of a task's scene sampled every ``delta``:

* ``positions`` (V, T, n_tracked, 3) float32: the tracked nodes (anchors + modelled nodes);
* ``wrench`` (V, T - 1, n_wrench, 3) float32: the world force on each input-wrench node at the
  middle of every interval ``[t_k, t_k + delta)`` (exact for forces switching on the grid);
* ``meta``: task, scene, seed, variant count, delta, dt, node lists, variant descriptions, the
  library version and a sha256 ``data_hash`` of the arrays.

Files are cached under ``data/`` (ignored by git) and regenerated from the physics when missing. So are
the single LGVI runs an evaluation compares a surrogate with (:func:`reference_rollout`).
"""
from __future__ import annotations

import hashlib
import time
from pathlib import Path

import torch

import physics
from physics.checks import is_int
from cmlearn.io import save_torch_atomic

from .tasks import SurrogateTask, get_task

__all__ = ["simulate_task", "generate_dataset", "load_dataset", "cached_dataset", "data_hash", "dataset_path",
           "lgvi_frames", "scene_integrator", "scene_rollout", "reference_rollout"]


def dataset_path(data_dir: str | Path, task: str, variants: int, seed: int, duration: float | None = None) -> Path:
    """The cache file of a dataset: ``<data_dir>/<task>_v<variants>_s<seed>[_d<duration>].pt``."""
    suffix = f"_d{duration:g}" if duration else ""
    return Path(data_dir) / f"{task}_v{variants}_s{seed}{suffix}.pt"


def data_hash(*tensors: torch.Tensor) -> str:
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _midpoint_wrench(force, task: SurrogateTask, times, n_variants: int):
    """(V, T-1, n_wrench, 3) force on the wrench nodes at the interval midpoints."""
    W = torch.zeros(n_variants, len(times) - 1, len(task.wrench_nodes), 3, dtype=torch.float64)
    if force is None or not task.wrench_nodes:
        return W
    idx = list(task.wrench_nodes)
    for k in range(len(times) - 1):
        f = force(torch.tensor(0.5 * (times[k] + times[k + 1]), dtype=torch.float64))
        if f is not None:
            W[:, k] = f[..., idx, :]
    return W


def lgvi_frames(sim, state, n_frames: int, every: int, compile: bool = False, record_R: bool = False):
    """Node positions (..., n_frames, n, 3) of the LGVI ``sim`` every ``every`` steps from ``state`` (the first frame),
    its wall time, and the compile time (0 eagerly); with ``record_R`` the rotations (..., n_frames, n, 3, 3) second.
    With ``compile`` the steps run in :meth:`physics.LGVI.compiled_rollout` (as many a call as divide ``every``, up to
    4), its program built by an untimed first call from ``state``; it equals the eager run to round-off (its fixed
    Newton count; a coil field's maps, which that call leaves evaluated where its steps ended, refresh within the
    field's ``tol`` of the eager run's)."""
    n = (n_frames - 1) * every
    compiled = 0.0
    if compile:
        spc = max(k for k in (1, 2, 4) if every % k == 0)
        t0 = time.perf_counter()
        sim.compiled_rollout(state, n_steps=spc, steps_per_call=spc)
        compiled = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, p, *R = sim.compiled_rollout(state, n_steps=n, steps_per_call=spc, record_every=every // spc,
                                        record_R=record_R)
    else:
        t0 = time.perf_counter()
        traj = sim.simulate(state, n_steps=n, record_every=every, record_R=record_R)[1]
        p, R = traj.p, [traj.R]
    wall = time.perf_counter() - t0
    return (p, R[0], wall, compiled) if record_R else (p, wall, compiled)


def scene_integrator(scene, p0=None, R0=None, force="scene"):
    """``(scene, its LGVI, the initial state)``: the scene with its force replaced by ``force`` (unless ``"scene"``),
    started from its own shape or the batch of initial shapes ``p0``, ``R0``."""
    from dataclasses import replace
    if force != "scene":
        scene = replace(scene, loads=replace(scene.loads, force=force))
    sim = scene.make_integrator()
    cfg = scene.initial_configuration()
    return scene, sim, sim.initial_state(p=cfg["p"] if p0 is None else p0, R=cfg.get("R") if R0 is None else R0)


def scene_rollout(task: SurrogateTask, scene, p0=None, R0=None, force="scene", duration=None, compile: bool = False):
    """Run the LGVI on ``scene`` (or a batch of initial shapes / a batched force) and return the
    tracked-node positions (..., T, n_tracked, 3) every ``delta``, the wrench inputs and the wall time. A task
    with a module of its own (the magnetic rod: tracked points rebuilt from the magnets' frames, wrench inputs
    from the coil field) runs the scene as that module does, from the scene's own shape and loads. ``compile``:
    the LGVI's compiled rollout (:func:`lgvi_frames`; the wall time leaves its compile out)."""
    if task.custom:
        if p0 is not None or R0 is not None or force != "scene":
            raise ValueError(f"scene_rollout: task {task.name!r} runs its scenes from their own shape and loads "
                             "(p0, R0 and force are not accepted)")
        return task.hook("rollout")(task, scene, duration=duration, compile=compile)
    scene, sim, state = scene_integrator(scene, p0, R0, force)
    every = task.record_every(scene)
    n_frames = int(round((duration or scene.duration) / task.delta)) + 1
    p, wall, _ = lgvi_frames(sim, state, n_frames, every, compile)
    pos = p[..., list(task.tracked), :]
    times = [k * task.delta for k in range(n_frames)]
    n_var = pos.shape[0] if pos.dim() == 4 else 1
    W = _midpoint_wrench(scene.loads.force, task, times, n_var)
    if pos.dim() == 3:
        W = W[0]
    return pos, W, wall


def reference_rollout(task: SurrogateTask, name: str, duration: float | None = None,
                      data_dir: str | Path | None = None) -> tuple[torch.Tensor, torch.Tensor, float]:
    """:func:`scene_rollout` of the task's scene ``name`` (the printed or a held-out one) for ``duration`` s (the
    scene's own where None): tracked positions, wrench inputs and the LGVI's wall time. With ``data_dir`` the run
    is cached there as ``<task>_<name>_<duration>s_ref.pt`` and read back (wall time included: the one measured
    when it was made) while it fits the task's step and node sets, this library version and its hash (as with
    datasets, a scene whose definition changed needs its file removed); evaluations of held-out scenes repeat these
    runs, which take minutes at full length."""
    from dataclasses import replace
    scene = task.scene_by_name(name)
    d = float(duration or scene.duration)
    want = {"task": task.name, "scene": name, "duration": d, "delta": task.delta, "tracked": list(task.tracked),
            "wrench_nodes": list(task.wrench_nodes), "physics_version": physics.__version__}
    path = Path(data_dir) / f"{task.name}_{name}_{d:g}s_ref.pt" if data_dir is not None else None
    if path is not None and path.exists():
        try:
            blob = torch.load(path, weights_only=True)
            fits = blob["meta"] == want and data_hash(blob["positions"], blob["wrench"]) == blob["hash"]
        except Exception:  # noqa: BLE001 - an unreadable or older cache file is made again
            fits = False
        if fits:
            return blob["positions"], blob["wrench"], blob["lgvi_wall_s"]
    pos, W, wall = scene_rollout(task, replace(scene, duration=d))
    if path is not None:
        save_torch_atomic(path, {"positions": pos, "wrench": W, "lgvi_wall_s": wall, "hash": data_hash(pos, W),
                                 "meta": want})
    return pos, W, wall


def simulate_task(task: SurrogateTask | str, n_variants: int, seed: int = 0, duration: float | None = None,
                  compile: bool = False):
    """Simulate ``n_variants`` of the task's scene (variant 0 the printed scene) as one batch, for the
    scene's duration or a shorter ``duration`` (tests); ``compile``: the LGVI's compiled rollout
    (:func:`lgvi_frames`), not for a task with a module of its own."""
    from dataclasses import replace
    task = get_task(task) if isinstance(task, str) else task
    if not (is_int(n_variants) and n_variants >= 1):
        raise ValueError(f"n_variants must be an integer >= 1 (the printed scene and random variants), got "
                         f"{n_variants!r}")
    if not (is_int(seed) and seed >= 0):
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    task.check_duration(duration)
    if task.custom:
        if compile:
            raise ValueError(f"simulate_task: task {task.name!r} runs its own LGVI, eagerly (compile is not accepted)")
        return task.hook("simulate")(task, n_variants, seed, duration)
    scene = task.base_scene()
    if duration is not None:
        scene = replace(scene, duration=duration)
    var = task.variants(scene, n_variants, seed)
    force = var["force"] if var["force"] is not None else "scene"
    pos, W, wall = scene_rollout(task, scene, var["p"], var.get("R"), force=force, compile=compile)
    return pos, W, var["info"], wall


def generate_dataset(task: SurrogateTask | str, n_variants: int, seed: int, out: str | Path,
                     duration: float | None = None, compile: bool = False) -> dict:
    """Simulate (:func:`simulate_task`) and save the dataset at ``out``; returns its ``meta`` (``lgvi_compiled``: whether
    ``compile`` ran the LGVI's compiled rollout, ``lgvi_wall_s`` without its compile)."""
    task = get_task(task) if isinstance(task, str) else task
    pos, W, info, wall = simulate_task(task, n_variants, seed, duration, compile)
    positions, wrench = pos.float(), W.float()
    scene = task.base_scene()
    meta = {"task": task.name, "scene": task.scene, "seed": seed, "duration": duration or scene.duration, "n_variants": n_variants, "delta": task.delta,
            "dt": scene.dt, "tracked": list(task.tracked), "modeled": list(task.modeled),
            "anchors": list(task.anchors), "wrench_nodes": list(task.wrench_nodes), "rod_length": scene.rod.length,
            "variants": info, "physics_version": physics.__version__, "lgvi_wall_s": wall, "lgvi_compiled": compile,
            "data_hash": data_hash(positions, wrench)}
    save_torch_atomic(out, {"positions": positions, "wrench": wrench, "meta": meta})
    return meta


def cached_dataset(task: SurrogateTask | str, n_variants: int, seed: int, data_dir: str | Path,
                   duration: float | None = None, compile: bool = False) -> dict:
    """The dataset of ``task`` at :func:`dataset_path` in ``data_dir``, generated by the LGVI the first time (with
    ``compile``, its compiled rollout)."""
    task = get_task(task) if isinstance(task, str) else task
    path = dataset_path(data_dir, task.name, n_variants, seed, duration)
    if path.exists():
        data = load_dataset(path, task=task.name)
        stale = _stale(data["meta"], task, duration)
        if not stale:
            return data
        why = f"it was {stale}"
    else:
        why = "missing"
    print(f"generating {path} with the LGVI ({n_variants} variants; {why}) ...", flush=True)
    generate_dataset(task, n_variants, seed, path, duration=duration, compile=compile)
    return load_dataset(path, task=task.name)


def _stale(meta: dict, task: SurrogateTask, duration: float | None = None) -> str:
    """Why a cached dataset no longer fits its task ('' where it does): another scene, LGVI step, duration, rod length,
    surrogate step or node set, or made by another version of the physics (a change within a scene's or the variant
    generator's definition that keeps all of these is not seen: bump ``physics.__version__`` with it)."""
    scene = task.base_scene()
    for key, want in (("scene", task.scene), ("dt", scene.dt), ("duration", duration or scene.duration),
                      ("rod_length", scene.rod.length), ("delta", task.delta), ("tracked", list(task.tracked)),
                      ("wrench_nodes", list(task.wrench_nodes))):
        if meta.get(key) != want:
            return f"sampled with {key} = {meta.get(key)}, and the task now has {want}"
    if meta.get("physics_version") != physics.__version__:
        return f"made by physics {meta.get('physics_version')}, and this is {physics.__version__}"
    return ""


def load_dataset(path: str | Path, task: str | None = None) -> dict:
    """Load and validate a dataset file (clear errors for a corrupt file, a wrong task or a bad hash)."""
    path = Path(path)
    try:
        d = torch.load(path, weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means a corrupt file
        raise ValueError(f"{path}: not a readable cmlearn dataset ({type(e).__name__}: {e})") from None
    if not isinstance(d, dict) or not {"positions", "wrench", "meta"} <= set(d):
        raise ValueError(f"{path}: not a cmlearn dataset (missing positions/wrench/meta)")
    keys = {"task", "data_hash", "duration", "delta", "n_variants", "tracked", "wrench_nodes"}
    if not isinstance(d["meta"], dict) or not keys <= set(d["meta"]):  # a KeyError or TypeError came out of the checks
        raise ValueError(f"{path}: not a cmlearn dataset (its meta lacks "
                         f"{sorted(keys - set(d['meta'])) if isinstance(d['meta'], dict) else 'everything'})")
    if task is not None and d["meta"].get("task") != task:
        raise ValueError(f"{path}: dataset is for task {d['meta'].get('task')!r}, not {task!r}")
    if data_hash(d["positions"], d["wrench"]) != d["meta"]["data_hash"]:
        raise ValueError(f"{path}: data hash mismatch (file modified or corrupt)")
    m = d["meta"]  # the hash covers the arrays' bytes, not their shapes: those must fit the metadata
    T = round(m["duration"] / m["delta"]) + 1
    for name, want in (("positions", (m["n_variants"], T, len(m["tracked"]), 3)),
                       ("wrench", (m["n_variants"], T - 1, len(m["wrench_nodes"]), 3))):
        if tuple(d[name].shape) != want:
            raise ValueError(f"{path}: {name} has shape {tuple(d[name].shape)}, and its metadata (variants, duration / "
                             f"delta, node lists) ask for {want} (file modified or corrupt)")
    return d
