"""What does a magnetic-rod surrogate's one-step error measure? The checkpoint against step baselines.

    python scripts/report_step_baselines.py [--checkpoints checkpoints/magnetic_rod.pt ...] [--variants 32]
        [--seed 0] [--ridge 1e-6] [--duration S] [--out docs/step_baselines.md]

On the printed profile from its 60 % cut and the held-out profiles from rest, the sum of the six mean absolute
orientation errors (deg, distal and proximal magnet about x, y, z) of each checkpoint and of the baselines of
:mod:`cmlearn.surrogate.baselines`: the constant-velocity step (the Verlet-form surrogate with a zero network
output) and least-squares linear steps fitted on the checkpoint's own training profiles (``--variants``,
``--seed``: the dataset, made by the LGVI where ``--data-dir`` lacks it; every profile's frames but the printed
one's last 40 %), local (each node from its own and its neighbours' last frames and its force, what a node model
sees) and global (every node from all tracked points and forces). Two modes: one-step (true history and
wrench) and free-running open loop (each step's wrench the LGVI's own, :func:`nudged_free_running` with one
unnudged start); the checkpoints also closed loop. A run that left the rod reads "lost". Writes the markdown
atomically and prints one JSON line last.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from cmlearn.data import cached_dataset
from cmlearn.data.magnetic import magnet_frames
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.io import write_text_atomic
from cmlearn.surrogate.baselines import LinearStep
from cmlearn.surrogate.evaluate import one_step
from cmlearn.surrogate.magnetic import (load_checkpoints, nudged_free_running, orientation_errors, profile_start,
                                        reference_profiles)


def one_step_sum(model, task, scene, p, Wk, s) -> float:
    """Sum of the six mean one-step orientation errors (deg) over frames s+1 .. T-1."""
    _, R_ref, _ = magnet_frames(task, scene.rod, p[s + 1:].double())
    pred = one_step(model, p, Wk, s).double()
    return float(orientation_errors(magnet_frames(task, scene.rod, pred)[1], R_ref).abs().mean(0).sum())


def free_sum(model, task, scene, p, Wk, s, pad, open_loop: bool) -> float | None:
    """The same sum free-running from frame s (None: the rollout left the rod)."""
    v = nudged_free_running(model, task, scene, p, s, pad, n=1, sigma=0.0, wrench=Wk if open_loop else None)
    v = v["sum_mean_deg"][0]
    return v if math.isfinite(v) else None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/magnetic_rod.pt"])
    ap.add_argument("--variants", type=int, default=32, help="profiles the linear steps are fitted on")
    ap.add_argument("--seed", type=int, default=0, help="their dataset's seed")
    ap.add_argument("--ridge", type=float, default=1e-6, help="the linear fits' ridge (standardised features)")
    ap.add_argument("--duration", type=float, default=0.0, help="shorter profiles (tests)")
    ap.add_argument("--data-dir", default="data", help="where datasets and LGVI reference runs are cached")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    if a.variants < 2:
        ap.error(f"--variants must be >= 2 (the printed profile and others), got {a.variants}")
    if not a.ridge >= 0:
        ap.error(f"--ridge must be >= 0, got {a.ridge}")
    torch.set_num_threads(a.threads)
    try:
        engines, task = load_checkpoints(a.checkpoints)
    except ValueError as e:
        raise SystemExit(f"--checkpoints: {e}") from None
    config = next(iter(engines.values())).model.config
    data = cached_dataset(task, a.variants, a.seed, a.data_dir, a.duration or None)
    P = data["positions"]
    Wk = node_wrench(data["wrench"], task.wrench_nodes, task.modeled)
    ranges = split_ranges(a.variants, P.shape[1], val_variants=0)["train"]
    baselines = {"constant velocity": LinearStep(config),
                 "linear, local": LinearStep(config).fit(P, Wk, ranges, a.ridge),
                 "linear, global": LinearStep(config, local=False).fit(P, Wk, ranges, a.ridge)}
    rows = []
    for label, scene, pts, W, printed in reference_profiles(task, a.duration or None, a.data_dir):
        row = {"case": label, "models": {}}
        for name, model in [*((n, e.model) for n, e in engines.items()), *baselines.items()]:
            p, wk, s, pad = profile_start(task, pts, W, model.config.eta, printed)
            r = {"one_step": one_step_sum(model, task, scene, p, wk, s),
                 "open_loop": free_sum(model, task, scene, p, wk, s, pad, True)}
            if name in engines:
                r["closed_loop"] = free_sum(model, task, scene, p, wk, s, pad, False)
            row["models"][name] = r
        rows.append(row)
        print(f"{label}: done", flush=True)

    def cell(v):
        return "lost" if v is None else f"{v:.2f}"

    lines = [f"One-step and free-running orientation error of magnetic-rod surrogates beside step baselines: the sum "
             f"of the six mean absolute errors (deg, distal and proximal magnet about x, y, z); linear steps fitted on "
             f"{a.variants} profiles (seed {a.seed}, ridge {a.ridge:g}) (`python scripts/report_step_baselines.py`).",
             "", "| case | model | one-step | free-running, open loop (the LGVI's wrench) | free-running, closed loop |",
             "|---|---|---:|---:|---:|"]
    for r in rows:
        for name, m in r["models"].items():
            lines.append(f"| {r['case']} | {name} | {m['one_step']:.2f} | {cell(m['open_loop'])} | "
                         f"{cell(m['closed_loop']) if 'closed_loop' in m else ''} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        write_text_atomic(Path(a.out), text)
    print(json.dumps({"task": task.name, "variants": a.variants, "seed": a.seed, "ridge": a.ridge, "rows": rows}))


if __name__ == "__main__":
    main()
