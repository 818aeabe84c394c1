"""What does a surrogate's one-step error measure? Checkpoints of one task against step baselines.

    python scripts/report_step_baselines.py [--checkpoints checkpoints/magnetic_rod.pt ...] [--variants N]
        [--seed S] [--eta N] [--ridge 1e-6] [--duration S] [--out docs/step_baselines.md]

Each checkpoint beside the baselines of :mod:`cmlearn.surrogate.baselines`: the constant-velocity step (the
Verlet-form surrogate with a zero network output) and least-squares linear steps fitted on the training
trajectories (``--variants``, ``--seed``: the dataset, by default the first checkpoint's own, made by the LGVI
where ``--data-dir`` lacks it; every trajectory's frames but the printed one's last 40 %), local (each node from
its own and its neighbours' last frames and its force, what a node model sees) and global (every node from all
tracked points and forces), with the checkpoint's nodes and history (``--eta``: a longer one). Two modes: one-step
(true history and wrench) and free-running, on the printed scene from its 60 % cut and the held-out scenes from
rest.

* A magnetic-rod task: the sum of the six mean absolute orientation errors (deg, distal and proximal magnet
  about x, y, z); free-running open loop (each step's wrench the LGVI's own, :func:`nudged_free_running` with one
  unnudged start), the checkpoints also closed loop. A run that left the rod reads "lost".
* Any other task: the node of interest's max and mean absolute error per axis (mm, as
  :func:`cmlearn.surrogate.evaluate.evaluate`), beside the thesis's. A rollout that left every shape of the rod
  (an error beyond twice its length) reads "lost".

Writes the markdown atomically and prints one JSON line last.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from cmlearn.args import bounded, writable
from cmlearn.data import cached_dataset
from cmlearn.data.magnetic import magnet_frames
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.io import write_text_atomic
from cmlearn.models import NodeLSTMConfig
from cmlearn.surrogate.baselines import LinearStep
from cmlearn.surrogate.engine import load_checkpoints
from cmlearn.surrogate.evaluate import evaluate_scenes, one_step, thesis_errors
from cmlearn.surrogate.magnetic import nudged_free_running, orientation_errors, profile_start, reference_profiles


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


def magnetic_rows(models: dict, engines: dict, task, a) -> list[dict]:
    """Per reference profile, each model's orientation sums one-step, open loop and (checkpoints) closed loop."""
    rows = []
    for label, scene, pts, W, printed in reference_profiles(task, a.duration or None, a.data_dir):
        row = {"case": label, "models": {}}
        for name, model in models.items():
            p, wk, s, pad = profile_start(task, pts, W, model.config.eta, printed)
            r = {"one_step": one_step_sum(model, task, scene, p, wk, s),
                 "open_loop": free_sum(model, task, scene, p, wk, s, pad, True)}
            if name in engines:
                r["closed_loop"] = free_sum(model, task, scene, p, wk, s, pad, False)
            row["models"][name] = r
        rows.append(row)
        print(f"{label}: done", flush=True)
    return rows


def position_rows(models: dict, task, data: dict, a) -> list[dict]:
    """Per scene (the printed one's last 40 %, each held-out one from rest: :func:`evaluate_scenes`), each model's
    node-of-interest errors (:func:`_node_errors`) and the thesis's."""
    L = task.base_scene().rod.length
    results = {name: evaluate_scenes(model, task, data, a.duration or None, a.data_dir) for name, model in models.items()}
    rows = []
    for case in next(iter(results.values())):
        rows.append({"case": f"{task.scene} (last 40 %)" if case == "seen_last40" else case,
                     "thesis": thesis_errors(task.name, case),
                     "models": {name: _node_errors(r[case], L) for name, r in results.items()}})
        print(f"{rows[-1]['case']}: done", flush=True)
    return rows


def _node_errors(result: dict, length: float) -> dict:
    """The node entry of :func:`evaluate` per mode, max and mean mm per axis; ``None`` for a rollout that left every
    shape of the rod (an error beyond twice its length, or not finite)."""
    out = {}
    for mode in ("one_step", "free_running"):
        e = {ax: {k: v[k] for k in ("max_mm", "mean_mm")} for ax, v in result[mode]["node"].items()}
        ok = all(math.isfinite(v) and v <= 2e3 * length for d in e.values() for v in d.values())
        out[mode] = e if ok else None
    return out


def magnetic_table(rows: list[dict], a) -> list[str]:
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
    return lines


def position_table(rows: list[dict], task, config, a) -> list[str]:
    def cell(e):
        return "lost" if e is None else " / ".join(f"{e[ax]['max_mm']:.2f}, {e[ax]['mean_mm']:.2f}" for ax in "xyz")

    lines = [f"One-step and free-running error of {task.name} surrogates beside step baselines: the node of "
             f"interest's max, mean absolute error (mm) about x / y / z; linear steps fitted on {a.variants} "
             f"trajectories (seed {a.seed}, ridge {a.ridge:g}, history eta = {config.eta}) "
             f"(`python scripts/report_step_baselines.py`).",
             "", "| case | model | one-step | free-running |", "|---|---|---|---|"]
    for r in rows:
        if r["thesis"]:
            th = " / ".join(f"{mx}, {mn}" for mx, mn in r["thesis"])
            lines.append(f"| {r['case']} | thesis (Paper II) | {th} | {th} |")
        for name, m in r["models"].items():
            lines.append(f"| {r['case']} | {name} | {cell(m['one_step'])} | {cell(m['free_running'])} |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/magnetic_rod.pt"])
    ap.add_argument("--variants", type=bounded(int, at_least=0), default=0,
                    help="trajectories the linear steps are fitted on (0: the first checkpoint's training set)")
    ap.add_argument("--seed", type=bounded(int, at_least=-1), default=-1,
                    help="their dataset's seed (-1: the first checkpoint's)")
    ap.add_argument("--eta", type=bounded(int, at_least=0), default=0,
                    help="the linear steps' history length (0: the checkpoint's)")
    ap.add_argument("--ridge", type=bounded(float, at_least=0), default=1e-6,
                    help="the linear fits' ridge (standardised features)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0, help="shorter trajectories (tests)")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data",
                    help="where datasets and LGVI reference runs are cached")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--out", type=writable(), default="")
    a = ap.parse_args(argv)
    if a.variants == 1:
        ap.error(f"--variants must be >= 2 (the printed trajectory and others) or 0, got {a.variants}")
    if a.eta == 1:
        ap.error(f"--eta must be >= 2 or 0 (the checkpoint's), got {a.eta}")
    torch.set_num_threads(a.threads)
    try:
        engines, task = load_checkpoints(a.checkpoints)
    except ValueError as e:
        raise SystemExit(f"--checkpoints: {e}") from None
    first = next(iter(engines.values()))
    a.variants = a.variants or first.meta["n_variants"]
    a.seed = first.meta["data_seed"] if a.seed < 0 else a.seed
    c = first.model.config
    config = NodeLSTMConfig(n_tracked=c.n_tracked, modeled=c.modeled, left=c.left, right=c.right, eta=a.eta or c.eta)
    data = cached_dataset(task, a.variants, a.seed, a.data_dir, a.duration or None)
    P = data["positions"]
    Wk = node_wrench(data["wrench"], task.wrench_nodes, task.modeled)
    ranges = split_ranges(a.variants, P.shape[1], val_variants=0)["train"]
    models = {**{n: e.model for n, e in engines.items()},
              "constant velocity": LinearStep(config),
              "linear, local": LinearStep(config).fit(P, Wk, ranges, a.ridge),
              "linear, global": LinearStep(config, local=False).fit(P, Wk, ranges, a.ridge)}
    if task.custom:
        rows = magnetic_rows(models, engines, task, a)
        lines = magnetic_table(rows, a)
    else:
        rows = position_rows(models, task, data, a)
        lines = position_table(rows, task, config, a)
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        write_text_atomic(Path(a.out), text)
    print(json.dumps({"task": task.name, "variants": a.variants, "seed": a.seed, "eta": config.eta,
                      "ridge": a.ridge, "rows": rows}))


if __name__ == "__main__":
    main()
