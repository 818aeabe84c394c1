"""Is a surrogate's single step biased? Its one-step error, signed, beside the true second difference.

    python scripts/report_one_step_bias.py [--checkpoints checkpoints/semicircle.pt ...] [--window 20]
        [--duration S] [--out docs/one_step_bias.md]

For each checkpoint the LGVI runs the task's printed scene; the surrogate predicts every frame from
the true history (one-step, as in the tables of ``docs/surrogates.md``). Per window of ``--window``
surrogate steps and per axis, at the headline node, the report gives the mean signed one-step error
(the bias) and the mean and mean absolute true second difference ``p(t+1) - 2 p(t) + p(t-1)``, the
quantity the model's output stands for. A bias comparable to the second difference itself grows as
h^2 along a free-running rollout, whatever the rollout's stability. Over the frames after the 60 % cut,
which no model trained on, it also gives the one-step error's RMS and maximum beside the true second
difference's, which is the error of predicting a zero second difference (``p(t+1) = 2 p(t) - p(t-1)``).
Writes the markdown atomically and prints one JSON line last.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import torch

from cmlearn.args import bounded, writable
from cmlearn.data.generate import scene_rollout
from cmlearn.data.windows import split_ranges
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import Surrogate
from cmlearn.surrogate.evaluate import interest_slots, one_step

ROOT = Path(__file__).resolve().parents[1]


def bias_table(path: str, window: int, duration: float | None) -> dict:
    engine = Surrogate.load(path)
    task = engine.task
    if task.custom:
        raise ValueError(f"{path}: task {task.name!r} runs its own closed-loop physics; not covered here")
    scene = task.base_scene()
    if duration:
        scene = replace(scene, duration=duration)
    pos, _, _ = scene_rollout(task, scene)
    pos = pos.double()
    n = pos.shape[0] - 1
    eta = engine.eta
    pred = one_step(engine.model, pos, engine.scene_wrench(scene, n), eta)  # frames eta+1 .. n
    slot = interest_slots(task, scene)[0]
    err = (pred[:, slot].double() - pos[eta + 1:, slot]) * 1e3
    acc = (pos[eta + 1:, slot] - 2 * pos[eta:-1, slot] + pos[eta - 1:-2, slot]) * 1e3
    rows = []
    for a in range(0, err.shape[0], window):
        e, s = err[a:a + window], acc[a:a + window]
        rows.append({"frames": [a + eta + 1, a + eta + len(e)],
                     "t_s": [(a + eta + 1) * task.delta, (a + eta + len(e)) * task.delta],
                     **{ax: {"bias_mm": float(e[:, i].mean()), "mean_abs_err_mm": float(e[:, i].abs().mean()),
                             "d2_mean_mm": float(s[:, i].mean()), "d2_mean_abs_mm": float(s[:, i].abs().mean())}
                        for i, ax in enumerate("xyz")}})
    cut = split_ranges(1, n + 1)["test"][0][1]
    e, s = err[max(cut - eta, 0):], acc[max(cut - eta, 0):]  # frames after the cut, which no model trained on
    unseen = {ax: {"err_rms_mm": float(e[:, i].pow(2).mean().sqrt()), "err_max_mm": float(e[:, i].abs().max()),
                   "d2_rms_mm": float(s[:, i].pow(2).mean().sqrt()), "d2_max_mm": float(s[:, i].abs().max())}
              for i, ax in enumerate("xyz")}
    return {"checkpoint": str(path), "task": task.name, "scene": task.scene, "node": scene.nodes_of_interest[0],
            "delta_s": task.delta, "window": window, "cut_frame": cut, "rows": rows, "after_cut": unseen}


def markdown(results: list[dict]) -> str:
    out = ["# One-step bias of the shipped surrogates (`python scripts/report_one_step_bias.py`)", "",
           "Mean signed one-step error (bias) at the headline node against the true second difference",
           "p(t+1) - 2 p(t) + p(t-1) over the same frames (mean signed, mean absolute), mm, per window of",
           "surrogate steps of the printed scene; frames before the cut trained the model.", ""]
    for r in results:
        out += [f"## {r['task']} (`{r['checkpoint']}`), node {r['node']}, step {r['delta_s'] * 1e3:g} ms, "
                f"cut at frame {r['cut_frame']}", "",
                "After the cut, one-step error RMS / max against a zero second difference's (the true second "
                "difference's RMS / max), mm: " + "; ".join(
                    f"{ax} {u['err_rms_mm']:.3f} / {u['err_max_mm']:.3f} against {u['d2_rms_mm']:.3f} / {u['d2_max_mm']:.3f}"
                    for ax, u in r["after_cut"].items()) + ".", "",
                "| frames | " + " | ".join(f"{ax}: bias / true d2 mean / true abs d2" for ax in "xyz") + " |",
                "|---|" + "---|" * 3]
        for w in r["rows"]:
            out.append(f"| {w['frames'][0]}-{w['frames'][1]} | " + " | ".join(
                f"{w[ax]['bias_mm']:+.3f} / {w[ax]['d2_mean_mm']:+.3f} / {w[ax]['d2_mean_abs_mm']:.3f}"
                for ax in "xyz") + " |")
        out.append("")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/semicircle.pt", "checkpoints/semicircle_fast.pt",
                                                         "checkpoints/square_tracking.pt"])
    ap.add_argument("--window", type=bounded(int, at_least=1), default=20)
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="shorter printed scene (s), for smoke runs")
    ap.add_argument("--out", type=writable(), default="docs/one_step_bias.md")
    a = ap.parse_args(argv)
    if a.window < 1:
        raise ValueError(f"--window must be >= 1, got {a.window}")
    torch.set_num_threads(1)
    results = [bias_table(c if Path(c).exists() else str(ROOT / c), a.window, a.duration or None)
               for c in a.checkpoints]
    write_text_atomic(Path(a.out), markdown(results))
    print(f"wrote {a.out}")
    print(json.dumps({"results": results}))
    return results


if __name__ == "__main__":
    main()
