"""Where a surrogate's free-running error comes from: the node of interest alone on its own predictions.

    python scripts/report_node_recursion.py checkpoints/semicircle.pt [more.pt ...] [--duration S] [--out FILE.md]

For each checkpoint, on its task's printed scene (from the 60 % cut) and held-out scenes (from rest), all
simulated by the LGVI, the node of interest's max, mean absolute error (mm) per axis x / y / z

* one-step: every prediction from the true history;
* node alone: only the node of interest runs on its own predictions, every other tracked node follows the
  LGVI (Paper II's per-node models see their neighbours' measured poses); what the node's own step
  accumulates with exact neighbours;
* free-running: every modelled node on the surrogate's predictions;

and, for the free-running rollout, the largest error (mm) of the chords between consecutive tracked nodes
against the LGVI's, beside the largest change of those chords in the LGVI run itself (how much the rod's
own lengths move). Prints a markdown table and ends with one JSON line. Tasks with their own evaluation
(the magnetic rod) are not supported.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace

import torch

from cmlearn.args import bounded, readable, writable
from cmlearn.data import get_task, scene_rollout
from cmlearn.data.windows import node_wrench, split_ranges
from cmlearn.eval.metrics import axis_errors
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import load_checkpoint
from cmlearn.surrogate.evaluate import free_running, heldout_case, interest_slots, node_recursive, one_step


def chords(p):
    return (p[..., 1:, :] - p[..., :-1, :]).norm(dim=-1)


def cases(task, eta: int, duration: float):
    """(name, tracked positions, node wrench, start, scene) of the printed scene and the held-out scenes."""
    scene = task.base_scene()
    p, w, _ = scene_rollout(task, replace(scene, duration=duration) if duration else scene)
    yield task.scene + " (last 40 %)", p, node_wrench(w.float(), task.wrench_nodes, task.modeled), \
        split_ranges(1, p.shape[0])["test"][0][1], scene
    for name in task.heldout:
        p, w, _ = heldout_case(task, name, eta, duration or None)
        yield name, p, w, eta, task.scene_by_name(name)


def report(model, task, duration: float) -> list[dict]:
    rows, length = [], float(task.base_scene().rod.length)
    for name, p, w, start, scene in cases(task, model.config.eta, duration):
        slot = interest_slots(task, scene)[0]
        ref = p[start + 1:, slot].double()
        free = free_running(model, p, w, start).double()
        row = {"case": name, "node": task.tracked[slot]}
        for mode, pred in (("one_step", one_step(model, p, w, start)[:, slot]),
                           ("node_alone", node_recursive(model, p, w, start, slot)), ("free_running", free[:, slot])):
            row[mode] = axis_errors(pred.double(), ref, length)
        true = chords(p[start + 1:].double())
        row["chord_error_mm"] = float((chords(free) - true).abs().max()) * 1e3
        row["lgvi_chord_change_mm"] = float((true - chords(p[:1].double())).abs().max()) * 1e3
        rows.append(row)
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("checkpoints", type=readable(), nargs="+", help="surrogate checkpoints (.pt)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds of every scene (0: their own)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1, help="torch CPU threads")
    ap.add_argument("--out", type=writable(), default="", help="also write the table to this markdown file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    lines = ["Node of interest, max, mean absolute error (mm) x / y / z; chords: the free-running rollout's largest "
             "chord error against the LGVI's largest chord change (mm).", "",
             "| checkpoint | case (node, 1-based) | one-step | node alone (others from the LGVI) | free-running | chords |",
             "|---|---|---|---|---|---|"]
    out = {}
    for path in a.checkpoints:
        model, meta = load_checkpoint(path)
        task = get_task(meta["task"])
        if task.custom:
            ap.error(f"checkpoints: {path} is of task {task.name!r}, which has its own evaluation")
        out[path] = rows = report(model.eval(), task, a.duration)
        for r in rows:
            cells = [" / ".join(f"{r[m][ax]['max_mm']:.2f}, {r[m][ax]['mean_mm']:.2f}" for ax in "xyz")
                     for m in ("one_step", "node_alone", "free_running")]
            lines.append(f"| {path} | {r['case']} (node {r['node'] + 1}) | " + " | ".join(cells)
                         + f" | {r['chord_error_mm']:.2f} against {r['lgvi_chord_change_mm']:.2f} |")
    table = "\n".join(lines) + "\n"
    print(table)
    if a.out:
        write_text_atomic(a.out, table)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
