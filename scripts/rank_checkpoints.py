"""Rank surrogate checkpoints of one task on fresh variants of its scene: a validation set of its own.

    python scripts/rank_checkpoints.py checkpoints/ellipse.pt runs/ell_h512.pt [--seed 2] [--variants 4]
        [--out FILE.md]

A run's own validation (``val_loss``, ``val_rollout_mm``) scores one trajectory of its data; the
held-out scenes are the test and must not pick a model. This draws ``--variants`` new trajectories
from the task's own variant generator with another seed than any checkpoint or a model it was made from
trained on or was selected by (:func:`~cmlearn.surrogate.evaluate.used_seeds`: the data, ``--val-fresh``,
refinement and blend seeds its metadata records; the same distribution, none of them trained on or selected
by), simulates them with the LGVI (cached in ``--data-dir`` like
a training dataset), rolls every checkpoint out free-running on each from its first frames (as the
held-out scenes are: from rest, or from the start of their load), and ranks the checkpoints by the
mean over the variants of the node of interest's largest error on any axis. Prints a markdown table
and ends with one JSON line. Tasks with their own evaluation (the magnetic rod) are not supported.
"""
from __future__ import annotations

import argparse
import json

import torch

from cmlearn.args import bounded, readable, writable
from cmlearn.data import cached_dataset, get_task
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import load_checkpoint
from cmlearn.surrogate.evaluate import fresh_errors, fresh_score, used_seeds


def variant_info(info) -> object:
    """The generator's description of the fresh variants (variant 0's left out)."""
    return {k: v[1:] for k, v in info.items()} if isinstance(info, dict) else info[1:]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("checkpoints", type=readable(), nargs="+", help="surrogate checkpoints (.pt) of one task")
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=2,
                    help="the fresh variants' seed (not one a checkpoint was trained "
                    "or selected on: train_surrogate's defaults are 0 and, with --val-fresh, 1)")
    ap.add_argument("--variants", type=bounded(int, at_least=1), default=4, help="fresh trajectories to rank on")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data",
                    help="where the fresh variants' LGVI runs are cached")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (0: the scene's own)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=2, help="torch CPU threads")
    ap.add_argument("--out", type=writable(), default="", help="also write the table to this markdown file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    loaded = [(path, *load_checkpoint(path)) for path in a.checkpoints]
    tasks = {meta["task"] for _, _, meta in loaded}
    if len(tasks) != 1:
        ap.error(f"checkpoints: all must be of one task, got {sorted(tasks)}")
    task = get_task(tasks.pop())
    if task.custom:
        ap.error(f"checkpoints: task {task.name!r} has its own evaluation, not supported here")
    for path, _, meta in loaded:
        how = used_seeds(meta).get(a.seed)
        if how:
            ap.error(f"--seed {a.seed} is no fresh seed for {path}: {how}")
    # variant 0 of the generator is the printed scene (trained on): drawn, then left out of the ranking
    data = cached_dataset(task, a.variants + 1, a.seed, a.data_dir, a.duration or None)
    rows = []
    for path, model, meta in loaded:
        errs = fresh_errors(model.eval(), task, data)
        rows.append({"checkpoint": str(path), "score_mm": fresh_score(errs),
                     "max_mm": [[e[ax]["max_mm"] for ax in "xyz"] for e in errs],
                     "mean_mm": [[e[ax]["mean_mm"] for ax in "xyz"] for e in errs]})
    rows.sort(key=lambda r: r["score_mm"])
    info = variant_info(data["meta"]["variants"])
    head = " | ".join(f"variant {v + 1}" for v in range(a.variants))
    lines = [f"Task {task.name}: {a.variants} fresh variants (seed {a.seed}) {json.dumps(info)}, free-running "
             "from their first frames; max, mean absolute error (mm) x / y / z of the node of interest.", "",
             f"| rank | checkpoint | score (mean of max, mm) | {head} |",
             "|---|---|---|" + "---|" * a.variants]
    for i, r in enumerate(rows, 1):
        cells = " | ".join(" / ".join(f"{m:.2f}, {n:.2f}" for m, n in zip(mx, mn))
                           for mx, mn in zip(r["max_mm"], r["mean_mm"]))
        lines.append(f"| {i} | {r['checkpoint']} | {r['score_mm']:.2f} | {cells} |")
    table = "\n".join(lines) + "\n"
    print(table)
    if a.out:
        write_text_atomic(a.out, table)
    res = {"task": task.name, "seed": a.seed, "variants": a.variants, "variant_info": info, "ranking": rows}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
