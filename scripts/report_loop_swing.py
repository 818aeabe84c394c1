"""How Simulation I surrogates swing: mean shape, swing range and phase of node 30 against the LGVI.

    python scripts/report_loop_swing.py [CK.pt ...] [--variants 32] [--duration 0] [--after 10]
        [--threads 1] [--out docs/loop_swing.md]

Every Simulation I loop rests as the one circle its rod closes (``SurrogateTask.equilibrium``), so a loop
released from an ellipse swings about it. For each checkpoint (default: the shipped ``ellipse.pt``) this
reports:

* from the circle at rest: how far node 30 moves in y over the run (the LGVI: not at all), i.e. whether
  the model knows the equilibrium;
* on the training loops (the task's dataset, seed 0, ``--variants`` of them) and on the held-out loop,
  each free-running from rest as the held-out scenes are evaluated: node 30's y minimum, maximum and mean
  after the first ``--after`` seconds, its largest error, and the times at which y crosses its mean
  upwards (the swing's phase), beside the LGVI's.

Prints markdown and ends with one JSON line. Figures in ``docs/surrogates.md`` ("Simulation I anchored at its
equilibrium", "Windows as long as the loop's swing") come from it.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from cmlearn.args import bounded, readable, writable
from cmlearn.data import cached_dataset, get_task
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import load_checkpoint
from cmlearn.surrogate.evaluate import heldout_case

ROOT = Path(__file__).resolve().parents[1]
NODE = 29  # node 30 of 59


def swing(y: torch.Tensor, delta: float, after: float) -> dict:
    """Range, mean (mm) of ``y`` (metres, one per step of ``delta``) after ``after`` seconds, and the times of its
    upward crossings of that mean."""
    tail = y[int(round(after / delta)):]
    mean = float(tail.mean())
    s = torch.sign(y - mean)
    up = [round((int(i) + 1) * delta, 2) for i in torch.nonzero((s[:-1] < 0) & (s[1:] > 0)).flatten()]
    return {"min_mm": float(tail.min()) * 1e3, "max_mm": float(tail.max()) * 1e3, "mean_mm": mean * 1e3,
            "up_crossings_s": up}


@torch.no_grad()
def circle_drift(model, task, steps: int) -> float:
    """Node 30's y range (mm) over ``steps`` free-running steps from the circle at rest, the printed loop as the
    reference shape."""
    tr = list(task.tracked)
    circle = task.equilibrium(task.base_scene())[tr].float()
    ref = task.base_scene().initial_configuration()["p"][tr].float()
    W = model.config.eta + 1
    out = model.rollout(circle[None, None].expand(1, W, -1, -1), torch.zeros(1, steps, len(task.modeled), 3), ref[None])
    y = out[0, :, tr.index(NODE), 1]
    return float(y.max() - y.min()) * 1e3


@torch.no_grad()
def loop_rows(models: dict, loops: torch.Tensor, delta: float, after: float, slot: int) -> list[dict]:
    """LGVI and each model's swing on loops (V, T, n_tracked, 3), all from rest (each model's history: copies
    of the first frame) and unloaded, as one batch."""
    pos = loops.float()
    truth = pos[:, 1:, slot, 1]
    rows = [{"lgvi": swing(t.double(), delta, after)} for t in truth]
    for name, m in models.items():
        hist = pos[:, :1].expand(-1, m.config.eta + 1, -1, -1)
        W = torch.zeros(pos.shape[0], pos.shape[1] - 1, m.idx_modeled.numel(), 3)
        y = m.rollout(hist, W, pos[:, 0], anchors=pos[:, 1:])[:, :, slot, 1]
        for r, yv, tv in zip(rows, y, truth):
            r[name] = swing(yv.double(), delta, after) | {"err_max_mm": float((yv - tv).abs().max()) * 1e3}
    return rows


def fmt(s: dict) -> str:
    return f"{s['min_mm']:.0f}, {s['max_mm']:.0f}, {s['mean_mm']:.0f}"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("checkpoints", type=readable(), nargs="*", default=[str(ROOT / "checkpoints" / "ellipse.pt")])
    ap.add_argument("--variants", type=bounded(int, at_least=1), default=32,
                    help="training loops (the dataset of seed 0 with this many)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (0: the scene's 50 s)")
    ap.add_argument("--after", type=bounded(float, at_least=0), default=10.0,
                    help="seconds left out before the range and mean")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data", help="where the LGVI runs are cached")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1, help="torch CPU threads")
    ap.add_argument("--out", type=writable(), default="", help="also write the tables to this markdown file")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    task = get_task("ellipse")
    models = {}
    for path in a.checkpoints:
        m, _ = load_checkpoint(path, task="ellipse")
        models[Path(path).name] = m.eval()
    slot = list(task.tracked).index(NODE)
    data = cached_dataset(task, a.variants, 0, a.data_dir, a.duration or None)
    n_steps = data["positions"].shape[1] - 1
    if a.after >= n_steps * task.delta:
        ap.error(f"--after {a.after} s leaves nothing of the {n_steps * task.delta:g} s run")
    aspects = data["meta"]["variants"]["aspect_h_over_w"]
    labels = [f"{'printed' if v == 0 else 'training'}, h/w {aspects[v]:.2f}" for v in range(a.variants)]
    held, _, _ = heldout_case(task, task.heldout[0], 0, a.duration or None, a.data_dir)
    rows = loop_rows(models, data["positions"], task.delta, a.after, slot)
    rows += loop_rows(models, held[None], task.delta, a.after, slot)
    res = {"circle_drift_mm": {n: circle_drift(m, task, n_steps) for n, m in models.items()},
           "loops": [{"loop": lab, **r} for lab, r in zip(labels + [f"held out ({task.heldout[0]})"], rows)]}
    names = list(models)
    lines = ["# Simulation I: how the loop models swing (`python scripts/report_loop_swing.py`)", "",
             f"Node 30 of Simulation I, y, free-running from rest for {n_steps * task.delta:g} s (min, max, mean mm after "
             f"{a.after:g} s; the largest error). From the circle at rest node 30 moves (y range, mm): "
             + ", ".join(f"{n} {d:.1f}" for n, d in res["circle_drift_mm"].items()) + "; the LGVI 0.", "",
             "| loop | LGVI | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for r in res["loops"]:
        cells = [f"{fmt(r[n])}; {r[n]['err_max_mm']:.0f}" for n in names]
        lines.append(f"| {r['loop']} | {fmt(r['lgvi'])} | " + " | ".join(cells) + " |")
    last = res["loops"][-1]
    lines += ["", "Upward crossings of the mean on the held-out loop (s): LGVI "
              + ", ".join(map(str, last["lgvi"]["up_crossings_s"])) + "; "
              + "; ".join(f"{n} " + ", ".join(map(str, last[n]["up_crossings_s"])) for n in names)]
    table = "\n".join(lines) + "\n"
    print(table)
    if a.out:
        write_text_atomic(a.out, table)
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
