"""Does a surrogate's free-running error depend on how hard the load pushes? A held-out load, scaled.

    python scripts/report_load_amplitude.py [--checkpoints checkpoints/semicircle.pt ...]
        [--scene semicircle_heldout] [--scales 0.25 0.5 1 1.5] [--duration S] [--out docs/load_amplitude.md]

The scene's own node force (by default the task's first held-out scene) is multiplied by each scale and
the LGVI and every checkpoint (of one task) run the scene from rest. Per scale the report gives the
range the headline node sweeps per axis and each checkpoint's free-running max error per axis, in mm
and as % of that axis's range. An error that keeps its share of the range at every scale is a bias of
the model's response; one that grows with the scale is extrapolation past the training loads. Writes
the markdown atomically and prints one JSON line last.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import torch

from cmlearn.args import bounded, writable
from cmlearn.data.generate import scene_rollout
from cmlearn.eval.metrics import axis_errors
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import Surrogate, SurrogateDivergence
from cmlearn.surrogate.evaluate import interest_slots


def scaled(scene, k: float):
    """The scene with its node force multiplied by ``k``."""
    force = scene.loads.force
    if force is None:
        raise ValueError(f"scene {scene.name!r} has no node force to scale")

    def fn(t):
        f = force(t)
        return None if f is None else k * f
    return replace(scene, loads=replace(scene.loads, force=fn))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/semicircle.pt", "checkpoints/semicircle_fast.pt"])
    ap.add_argument("--scene", default="", help="a scene of the checkpoints' task (default: its first held-out scene)")
    ap.add_argument("--scales", type=bounded(float), nargs="+", default=[0.25, 0.5, 1.0, 1.5])
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0, help="shorter than the scene (tests)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--out", type=writable(), default="")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    engines = {Path(p).name: Surrogate.load(p) for p in a.checkpoints}
    tasks = {e.task.name for e in engines.values()}
    if len(tasks) != 1:
        raise SystemExit(f"--checkpoints: give checkpoints of one task, not {sorted(tasks)}")
    task = next(iter(engines.values())).task
    if task.custom:
        raise SystemExit(f"task {task.name!r} runs its own closed-loop physics; not covered here")
    base = task.scene_by_name(a.scene or task.heldout[0])
    if a.duration:
        base = replace(base, duration=a.duration)
    slot = interest_slots(task, base)[0]
    rows = []
    for k in a.scales:
        scene = scaled(base, k)
        ref, _, wall = scene_rollout(task, scene)
        true = ref[:, slot].double()
        rng = ((true - true[0]).abs().amax(0) * 1e3).tolist()
        row = {"scale": k, "range_mm": rng, "lgvi_wall_s": wall, "errors": {}}
        for name, eng in engines.items():
            try:
                pred, _ = eng.run_scene(scene)
            except SurrogateDivergence as e:
                row["errors"][name] = {"runs_away": str(e)}
                continue
            e = axis_errors(pred[:, slot], true, base.rod.length)
            err = [e[ax]["max_mm"] for ax in "xyz"]
            row["errors"][name] = {"max_mm": err,
                                   "pct_of_range": [100 * e / r if r > 1e-9 else None for e, r in zip(err, rng)]}
        rows.append(row)
        print(f"scale {k:g}: range {' / '.join(f'{r:.1f}' for r in rng)} mm", flush=True)

    def cell(e):
        if "runs_away" in e:
            return "runs away"
        return " / ".join(f"{m:.1f}" + (f" ({p:.0f} %)" if p is not None else "") for m, p in zip(e["max_mm"], e["pct_of_range"]))

    lines = [f"Free-running max error (mm, and % of the node's range on that axis) x / y / z of the "
             f"{base.node_labels[0]} on `{base.name}` with its node force scaled, from rest over "
             f"{base.duration:g} s (`python scripts/report_load_amplitude.py`).", "",
             "| scale | node range x / y / z (mm) | " + " | ".join(engines) + " |",
             "|---:|---|" + "---|" * len(engines)]
    for r in rows:
        lines.append(f"| {r['scale']:g} | " + " / ".join(f"{x:.1f}" for x in r["range_mm"]) + " | "
                     + " | ".join(cell(r["errors"][n]) for n in engines) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        write_text_atomic(Path(a.out), text)
    print(json.dumps({"task": task.name, "scene": base.name, "duration": base.duration, "rows": rows}))


if __name__ == "__main__":
    main()
