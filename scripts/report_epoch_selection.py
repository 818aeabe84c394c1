"""Free-running errors of every saved epoch of a surrogate training run, beside its validation metrics.

    python scripts/report_epoch_selection.py runs/ell_sel06.pt [--threads 1] [--out FILE.md]

Takes the checkpoint ``scripts/train_surrogate.py`` wrote (its metadata names the task, the data file
and the log folder; run it with ``--keep-top-k -1`` to keep every epoch), loads each Lightning
checkpoint of that run into the same architecture and rolls it out free-running on the printed
scene's unseen last 40 % (from the true history at the cut) and on the held-out scenes (from rest,
the LGVI run once). Prints a markdown table, one row per epoch, with ``val_loss`` (the validation
windows' rollout loss) and ``val_rollout_mm`` (the whole validation trajectory free-running) from the
run's ``metrics.csv``, marking the epoch each would select: does the selection metric rank the epochs
as the headline errors do? Ends with one JSON line. Tasks with their own evaluation (the magnetic rod) are not supported.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import re
from pathlib import Path

import torch

from cmlearn.args import bounded, readable, writable
from cmlearn.data import dataset_path, get_task, load_dataset
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.eval.metrics import axis_errors
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import load_checkpoint
from cmlearn.surrogate.evaluate import free_running, heldout_case, interest_slots


def epoch_metrics(version_dir: Path) -> dict[int, dict]:
    out: dict[int, dict] = {}
    for row in csv.DictReader((version_dir / "metrics.csv").open()):
        for key in ("val_loss", "val_rollout_mm"):
            if row.get(key):
                out.setdefault(int(row["epoch"]), {})[key] = float(row[key])
    return out


def cases(task, meta: dict, data_dir: str):
    """(name, positions, wrench, start) of the seen scene's last 40 % and of each held-out scene."""
    args = meta["args"]
    data = load_dataset(dataset_path(data_dir, task.name, args["variants"], args["seed"], args["duration"]),
                        task=task.name)
    if data["meta"]["data_hash"] != meta["data_hash"]:
        raise SystemExit(f"data file hash {data['meta']['data_hash']} is not the run's {meta['data_hash']}")
    dm = data["meta"]
    pos = data["positions"][0]
    cut = split_ranges(dm["n_variants"], pos.shape[0])["test"][0][1]
    out = [("seen_last40", pos, node_wrench(data["wrench"][0], dm["wrench_nodes"], dm["modeled"]), cut)]
    eta = meta["architecture"]["eta"]
    for name in task.heldout:
        out.append((name, *heldout_case(task, name, eta, args["duration"], data_dir)[:2], eta))
    return out


def errors(model, positions, wrench, start, slot, length) -> list[float] | None:
    """Max absolute error (mm) per axis of the free-running rollout; None where it runs away."""
    pred = free_running(model, positions, wrench, start)[:, slot].double()
    if not torch.isfinite(pred).all():
        return None
    e = axis_errors(pred, positions[start + 1:, slot].double(), length)
    return [e[ax]["max_mm"] for ax in "xyz"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=readable(),
                    help="the checkpoint train_surrogate.py wrote (its .json names the log folder)")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--out", type=writable(), default="", help="also write the table to this markdown file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    model, meta = load_checkpoint(a.run)
    task = get_task(meta["task"])
    if task.custom:
        raise SystemExit(f"task {task.name!r} has its own evaluation; this report covers the position tasks")
    versions = sorted(Path(meta["args"]["log_dir"], task.name).glob("version_*/ckpt"))
    if not versions:
        raise SystemExit(f"no Lightning checkpoints under {meta['args']['log_dir']}/{task.name}/version_*/ckpt")
    scene = task.base_scene()
    slot, length = interest_slots(task, scene)[0], scene.rod.length
    runs = cases(task, meta, a.data_dir)
    rows, vals = [], {}
    for ckpt_dir in versions:
        vals.update(epoch_metrics(ckpt_dir.parent))
        for path in sorted(ckpt_dir.glob("epoch=*.ckpt"), key=lambda p: int(re.match(r"epoch=(\d+)", p.name)[1])):
            state = torch.load(path, map_location="cpu", weights_only=False)
            model.load_state_dict({k[len("model."):]: v for k, v in state["state_dict"].items() if k.startswith("model.")})
            model.float().eval()
            rows.append((state["epoch"], [errors(model, p, w, s, slot, length) for _, p, w, s in runs]))
    best = {k: min((e for e in vals if k in vals[e]), key=lambda e: vals[e][k], default=None)
            for k in ("val_loss", "val_rollout_mm")}
    lines = [f"Free-running max error (mm) x / y / z of the {scene.node_labels[0]}, `{meta['command']}`; "
             "* marks the epoch val_loss selects, + the one val_rollout_mm selects.", "",
             "| epoch | val_loss | val_rollout_mm | " + " | ".join(name for name, *_ in runs) + " |",
             "|---:|---:|---:|" + "---|" * len(runs)]
    for epoch, errs in rows:
        v = vals.get(epoch, {})
        mark = ("*" if best["val_loss"] == epoch else "") + ("+" if best["val_rollout_mm"] == epoch else "")
        cells = [f"{v[k]:.1f}" if k in v and math.isfinite(v[k]) else "" for k in ("val_loss", "val_rollout_mm")]
        cells += ["runs away" if e is None else " / ".join(f"{x:.1f}" for x in e) for e in errs]
        lines.append(f"| {epoch}{mark} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        write_text_atomic(Path(a.out), text)
    print(json.dumps({"run": a.run, "cases": [name for name, *_ in runs], "selected": best,
                      "epochs": [{"epoch": e, **vals.get(e, {}), "free_running_max_mm": errs} for e, errs in rows]}))


if __name__ == "__main__":
    main()
