"""Free-running errors of surrogate checkpoints on the trajectories they were trained on, beside unseen ones:
does a model fit its training data and fail to generalise, or not fit it at all?

    python scripts/report_training_fit.py checkpoints/semicircle.pt checkpoints/semicircle_fast.pt \
        [--starts 40 120] [--steps 80] [--out docs/training_fit.md] [--variants N --duration S]

Each checkpoint is run on its own dataset (read from ``--data-dir`` or made by the LGVI as a training run makes
it; a hash other than the checkpoint's is noted; ``--variants`` and ``--duration`` make a smaller one instead).
Every trajectory is cut into free-running windows of ``--steps`` steps from the true history ending at each of
the ``--starts`` frames, where such a window lies inside the part of the trajectory the run trained on (the
training split of :func:`cmlearn.data.windows.split_ranges`) or inside a validation trajectory; the printed
scene's test part (its last 40 %, from the cut) is the third group, as in the README's tables. For each group
the node of interest's largest error on any axis (max over the window) is summarised over its windows (median,
mean, largest), with the mean of the node's swing in those windows (its largest distance from its mean
position) for scale. Position tasks only. Prints a markdown table and ends with one JSON line.
"""
from __future__ import annotations

import argparse
import json

import torch
from torch import Tensor

from cmlearn.args import bounded, readable, writable
from cmlearn.data import cached_dataset, get_task
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import load_checkpoint
from cmlearn.surrogate.evaluate import interest_slots


def windows(ranges, starts, steps: int, eta: int) -> list[tuple[int, int]]:
    """(variant, start) of every window of ``steps`` steps from a start in ``starts`` inside a range."""
    return [(v, s) for v, a, b in ranges for s in starts if s >= a + eta and s + steps <= b]


@torch.no_grad()
def window_errors(model, data: dict, wins, steps: int, slot: int) -> tuple[Tensor, Tensor]:
    """The node's largest axis error (mm) and its swing (mm) over each free-running window, batched."""
    meta, W = data["meta"], model.config.eta + 1
    pos = data["positions"].float()
    wr = node_wrench(data["wrench"], meta["wrench_nodes"], meta["modeled"]).float()
    hist = torch.stack([pos[v, s - W + 1:s + 1] for v, s in wins])
    truth = torch.stack([pos[v, s + 1:s + 1 + steps] for v, s in wins])
    pred = model.rollout(hist, torch.stack([wr[v, s:s + steps] for v, s in wins]), pos[[v for v, _ in wins], 0],
                         anchors=truth)
    node_true = truth[:, :, slot].double()
    err = (pred[:, :, slot].double() - node_true).abs().amax(1).amax(-1) * 1e3
    swing = (node_true - node_true.mean(1, keepdim=True)).norm(dim=-1).amax(1) * 1e3
    return err, swing


def summary(err, swing) -> dict:
    return {"windows": int(err.numel()), "median_mm": float(err.median()), "mean_mm": float(err.mean()),
            "max_mm": float(err.max()), "swing_mm": float(swing.mean())}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("checkpoints", type=readable(), nargs="+", help="surrogate checkpoints (.pt) of position tasks")
    ap.add_argument("--starts", type=bounded(int, at_least=0), nargs="+", default=[40, 120],
                    help="window starts (frames)")
    ap.add_argument("--steps", type=bounded(int, at_least=1), default=80,
                    help="free-running steps per window (the printed scene's "
                    "test part of Simulation III has 80)")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data",
                    help="where the checkpoints' datasets are read or made")
    ap.add_argument("--variants", type=bounded(int, at_least=0), default=0,
                    help="trajectories of the dataset (0: the checkpoint's own; "
                    "another number makes another dataset, for quick checks)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (0: the checkpoint's own)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1, help="torch CPU threads")
    ap.add_argument("--out", type=writable(), default="", help="also write the table to this markdown file")
    a = ap.parse_args(argv)
    if a.variants == 1:
        ap.error("--variants must be 0 or >= 2, got 1")
    torch.set_num_threads(a.threads)
    rows, out, notes = [], {}, []
    for path in a.checkpoints:
        model, meta = load_checkpoint(path)
        task = get_task(meta["task"])
        if task.custom:
            ap.error(f"checkpoints: {path} is of task {task.name!r}, which has its own evaluation")
        args = meta.get("args", {})
        n_variants = a.variants or meta["n_variants"]
        duration = a.duration or args.get("duration") or None
        data = cached_dataset(task, n_variants, meta["data_seed"], a.data_dir, duration)
        if not (a.variants or a.duration) and data["meta"]["data_hash"] != meta["data_hash"]:
            notes.append(f"`{path}` was trained on data {meta['data_hash']}, these hash {data['meta']['data_hash']}.")
            print("note:", notes[-1])
        split = split_ranges(n_variants, data["positions"].shape[1],
                             val_variants=0 if args.get("val_fresh") else 1, val_tail=args.get("val_tail", 0.0))
        slot = interest_slots(task, task.base_scene())[0]
        eta = model.config.eta
        (_, cut, last), = split["test"]
        groups = {"trained on": (windows(split["train"], a.starts, a.steps, eta), a.steps),
                  "validation": ([] if args.get("val_fresh") else windows(split["val"], a.starts, a.steps, eta),
                                 a.steps),
                  "printed, test part": ([(0, cut)], last - cut)}
        res = {}
        for name, (wins, steps) in groups.items():
            if not wins:
                continue
            res[name] = summary(*window_errors(model, data, wins, steps, slot))
            r = res[name]
            rows.append(f"| `{path}` | {name} | {r['windows']} | {r['median_mm']:.2f} | {r['mean_mm']:.2f} | "
                        f"{r['max_mm']:.2f} | {r['swing_mm']:.1f} |")
        out[str(path)] = res
    head = ["| checkpoint | trajectories | windows | median | mean | largest | node's swing |",
            "|---|---|---|---|---|---|---|"]
    table = "\n".join(head + rows)
    print(table)
    if a.out:
        write_text_atomic(a.out, f"Node of interest, largest free-running error on any axis over a window of "
                                 f"{a.steps} steps (the printed test part: to the end), mm; starts {a.starts}.\n\n"
                                 + table + "\n" + "".join(f"\n{n}" for n in notes) + ("\n" if notes else ""))
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
