"""``cmlearn compare``: the physics (LGVI) and a shipped surrogate on the same scene.

Runs both from the scene's initial state, prints per-axis maximum/mean absolute errors of the
nodes of interest (mm and % of rod length), an RMSE(t) summary, the wall time of each and the
speed-up, and writes ``positions.png``, ``rmse.png``, ``shapes.png`` and ``summary.json``. With ``compile``
(``--compile``) the surrogate's step is compiled ahead of time (:meth:`cmlearn.surrogate.Surrogate.compile`) in a
first rollout, timed apart, and the second rollout is the one timed and compared; the LGVI also runs compiled
(:meth:`physics.LGVI.compiled_rollout`, its compile apart), and the speed-up over it is
printed beside the one over the eager LGVI (the errors stay against the eager run). On the
magnetic rod (``magnetic_rod``, ``magnetic_rod_heldout``) it also prints the magnets' orientation errors
in degrees of the surrogate (closed loop), of the static Cosserat model and of the quasi-static hybrid (where
``checkpoints/<task>_quasistatic.pt`` is shipped), and their wall times.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from .io import atomic_write

__all__ = ["DEFAULT_COMPARE_SCENE", "task_for_scene", "find_checkpoint", "surrogate_rollout", "compare_scene",
           "run_compare"]

DEFAULT_COMPARE_SCENE = "semicircle_heldout"


def task_for_scene(name: str):
    """The surrogate task whose printed or held-out scene is ``name``."""
    from .data.tasks import TASKS
    for task in TASKS.values():
        if name == task.scene or name in task.heldout:
            return task
    shipped, unshipped = [], []
    for task in TASKS.values():
        try:
            find_checkpoint(task.name)
            shipped += [task.scene, *task.heldout]
        except FileNotFoundError:
            unshipped += [task.scene, *task.heldout]
    raise KeyError(f"no surrogate task covers scene {name!r}; scenes with a shipped checkpoint: {sorted(shipped)}; "
                   f"without one (train it and pass --checkpoint PATH): {sorted(unshipped)}")


def find_checkpoint(task_name: str, explicit: str | Path | None = None) -> Path:
    if explicit:
        return Path(explicit)
    for root in (Path.cwd(), Path(__file__).resolve().parents[1]):
        p = root / "checkpoints" / f"{task_name}.pt"
        if p.is_file():
            return p
    raise FileNotFoundError(f"no checkpoint for task {task_name!r} in ./checkpoints or the source tree; "
                            "pass --checkpoint PATH")


def surrogate_rollout(engine, scene, compile: bool = False) -> tuple:
    """``(positions, wall seconds, facts)`` of ``engine.run_scene(scene)``; with ``compile`` the engine is compiled and
    the scene run twice, the first run compiling its programs (``facts``: that run's time less the second's, as
    ``surrogate_compile_s``), the second timed."""
    if not compile:
        return (*engine.run_scene(scene), {"surrogate_compiled": False})
    engine.compile()
    t0 = time.perf_counter()
    engine.run_scene(scene)
    first = time.perf_counter() - t0
    p, wall = engine.run_scene(scene)
    return p, wall, {"surrogate_compiled": True, "surrogate_compile_s": first - wall}


def node_errors(task, scene, p_sur, p_ref) -> tuple[dict, list, list]:
    """Per node of interest: per-axis max/mean absolute errors and the RMSE(t) summary (mm) over the predicted
    frames (the first, the initial state both runs start from, left out, as in the checkpoints' recorded metrics);
    with the nodes' slots in the surrogate's output and their labels."""
    from .eval.metrics import axis_errors, rmse_t
    from .surrogate.evaluate import interest_slots
    labels = [lab for n, lab in zip(scene.nodes_of_interest, scene.node_labels) if n in task.tracked]
    slots = interest_slots(task, scene)
    nodes = {}
    for slot, label in zip(slots, labels):
        sur, ref = p_sur[1:, slot], p_ref[1:, slot]
        r = rmse_t(sur, ref)
        nodes[label] = {"errors": axis_errors(sur, ref, scene.rod.length),
                        "rmse_mm": {"mean": float(r.mean()) * 1e3, "max": float(r.max()) * 1e3,
                                    "final": float(r[-1]) * 1e3}}
    return nodes, slots, labels


def compiled_lgvi_facts(task, scene, p_ref, wall_sur: float) -> dict:
    """The LGVI compiled too (:func:`cmlearn.data.generate.scene_rollout` with ``compile``): its wall time and compile
    time apart, how far its tracked points end up from the eager reference ``p_ref`` (mm), and the speed-up of the
    surrogate (``wall_sur`` s) over it."""
    from .data.generate import scene_rollout
    t0 = time.perf_counter()
    p_cmp, _, wall_cmp = scene_rollout(task, scene, compile=True)
    return {"lgvi_compiled_wall_s": wall_cmp, "lgvi_compile_s": time.perf_counter() - t0 - wall_cmp,
            "lgvi_compiled_diff_mm": float((p_cmp - p_ref).abs().max()) * 1e3,
            "speedup_vs_compiled_lgvi": wall_cmp / wall_sur}


def compare_scene(scene_name: str, checkpoint: str | Path | None = None, duration: float | None = None,
                  compile: bool = False) -> dict:
    import torch

    from .data.generate import scene_rollout
    from .surrogate import Surrogate

    task = task_for_scene(scene_name)
    scene = task.scene_by_name(scene_name)
    task.check_duration(duration)
    if duration is not None:
        from dataclasses import replace
        scene = replace(scene, duration=duration)
    engine = Surrogate.load(find_checkpoint(task.name, checkpoint), task=task.name)
    p_ref, _, wall_ref = scene_rollout(task, scene)
    p_sur, wall_sur, facts = surrogate_rollout(engine, scene, compile)
    if compile:
        facts.update(compiled_lgvi_facts(task, scene, p_ref, wall_sur))
    L = scene.rod.length
    t = torch.arange(p_ref.shape[0]) * task.delta
    nodes, slots, labels = node_errors(task, scene, p_sur, p_ref)
    res = {"scene": scene.name, "task": task.name, "duration_s": float(t[-1]), "surrogate_step_s": task.delta,
           "rod_length_m": L, "lgvi_wall_s": wall_ref, "surrogate_wall_s": wall_sur,
           "speedup": wall_ref / wall_sur, **facts, "nodes": nodes, "checkpoint_metrics": engine.meta.get("metrics", {}),
           "_series": {"t": t, "ref": p_ref, "sur": p_sur, "slots": slots, "labels": labels}}
    if task.custom:  # e.g. the magnetic rod (adds magnet orientation errors in degrees)
        res.update(task.hook("compare_scene")(task, scene, p_ref, p_sur, t))
    return res


def _plots(res: dict, out: Path) -> list[Path]:
    from matplotlib.figure import Figure  # no pyplot: a library call leaves the caller's backend alone

    from .eval.metrics import rmse_t

    s = res["_series"]
    t, ref, sur, slot = s["t"].numpy(), s["ref"], s["sur"], s["slots"][0]
    paths = [out / "positions.png", out / "rmse.png", out / "shapes.png"]
    fig = Figure(figsize=(7, 6))
    axes = fig.subplots(3, 1, sharex=True)
    for i, ax in enumerate(axes):
        ax.plot(t, ref[:, slot, i].numpy() * 1e3, "k-", label="LGVI (physics)")
        ax.plot(t, sur[:, slot, i].numpy() * 1e3, "r--", label="LSTM surrogate")
        ax.set_ylabel(f"{'xyz'[i]} (mm)")
    axes[0].set_title(f"{res['scene']}: {s['labels'][0]}")
    axes[0].legend(loc="best")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    atomic_write(paths[0], lambda f: fig.savefig(f, format="png", dpi=110))
    fig = Figure(figsize=(7, 3))
    ax = fig.subplots()
    for j, lab in zip(s["slots"], s["labels"]):
        ax.plot(t, rmse_t(sur[:, j], ref[:, j]).numpy() * 1e3, label=lab)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("RMSE(t) (mm)")
    ax.legend(loc="best")
    fig.tight_layout()
    atomic_write(paths[1], lambda f: fig.savefig(f, format="png", dpi=110))
    fig = Figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    for k in range(0, len(t), max(1, len(t) // 5)):
        ax.plot(*ref[k].T.numpy(), "k-", lw=1)
        ax.plot(*sur[k].T.numpy(), "r--", lw=1)
    ax.set_title("tracked nodes: LGVI (black) and surrogate (red)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    atomic_write(paths[2], lambda f: fig.savefig(f, format="png", dpi=110))
    return paths


def run_compare(scene: str, checkpoint=None, duration=None, out: Path | None = None, compile: bool = False) -> dict:
    import torch

    torch.set_num_threads(1)  # batch-1 stepping: one thread is fastest and timings are comparable
    t0 = time.perf_counter()
    res = compare_scene(scene, checkpoint, duration, compile)
    out = Path(out or f"out/compare_{res['scene']}")
    print(f"{res['scene']}: {res['duration_s']:.2f} s simulated, surrogate step {res['surrogate_step_s'] * 1e3:.0f} ms, "
          f"rod length {res['rod_length_m'] * 1e3:.0f} mm")
    for label, node in res["nodes"].items():
        e = node["errors"]
        print(f"  {label}: " + "  ".join(f"{ax} max {e[ax]['max_mm']:.2f} mm ({e[ax]['max_pct_L']:.2f} % L), "
                                        f"mean {e[ax]['mean_mm']:.2f} mm" for ax in "xyz"))
        r = node["rmse_mm"]
        print(f"    RMSE(t): mean {r['mean']:.2f} mm, max {r['max']:.2f} mm, final {r['final']:.2f} mm")
    for who, per_magnet in res.get("orientation_deg", {}).items():
        for magnet, e in per_magnet.items():
            print(f"  {who} {magnet} magnet orientation: " + "  ".join(
                f"about {ax} max {e[ax]['max_deg']:.2f} deg, mean {e[ax]['mean_deg']:.2f} deg" for ax in "xyz"))
    compiled = f" (compiled; its compile {res['surrogate_compile_s']:.1f} s apart)" if res["surrogate_compiled"] else ""
    print(f"  wall time: LGVI {res['lgvi_wall_s']:.2f} s, surrogate {res['surrogate_wall_s']:.3f} s{compiled}, "
          f"speed-up {res['speedup']:.0f}x" + (f"; static Cosserat {res['cosserat_wall_s']:.2f} s"
                                               if "cosserat_wall_s" in res else "") +
          (f"; quasi-static hybrid {res['hybrid_wall_s']:.2f} s" if "hybrid_wall_s" in res else ""))
    if "lgvi_compiled_wall_s" in res:
        print(f"  LGVI compiled: {res['lgvi_compiled_wall_s']:.3f} s (its compile {res['lgvi_compile_s']:.1f} s apart; "
              f"within {res['lgvi_compiled_diff_mm']:.1e} mm of the eager LGVI), speed-up of the surrogate over it "
              f"{res['speedup_vs_compiled_lgvi']:.0f}x")
    paths = _plots(res, out)
    summary = {k: v for k, v in res.items() if not k.startswith("_")}
    summary["timing"] = {"threads": torch.get_num_threads(), "device": "cpu", "batch": 1, "dtype_lgvi": "float64",
                         "dtype_surrogate": "float32", "note": "one run of each side, not paired (scripts/bench/ "
                                                                 "surrogate.py pairs the step in interleaved rounds)"}
    js = out / "summary.json"
    atomic_write(js, lambda f: f.write(json.dumps(summary, indent=2).encode()))
    print(f"  wrote {', '.join(str(p) for p in paths + [js])} ({time.perf_counter() - t0:.1f} s)")
    return summary
