"""Table of the shipped surrogates' errors next to the thesis's (Paper II), from the checkpoints' metadata.

    python scripts/report_surrogates.py [--out docs/surrogates.md]

Each checkpoint stores the errors measured when it was trained (scripts/train_surrogate.py): the
printed scene's unseen last 40 % (history from the LGVI at the cut) and the held-out scenes from
rest, each one-step (true history) and free-running (own predictions). Prints one JSON line last.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from cmlearn.io import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]

# Paper II, max / mean absolute errors (mm) per axis
THESIS = {
    "ellipse": ((1.57, 0.27), (2.27, 0.46), (0.23, 0.06)),
    "ellipse_horizontal": ((26.33, 3.37), (21.71, 3.70), (4.92, 4.22)),
    "square_tracking": ((3.58, 1.70), (1.80, 0.69), (2.73, 1.41)),
    "square_tracking_heldout": ((10.49, 2.61), (5.54, 1.05), (5.97, 2.83)),
    "semicircle": ((1.36, 0.78), (0.23, 0.13), (2.22, 0.81)),
    "semicircle_heldout": ((3.73, 1.25), (2.0, 0.2), (8.1, 1.2)),
}


def fmt(e) -> str:
    return " / ".join(f"{e[a]['max_mm']:.2f}, {e[a]['mean_mm']:.2f}" for a in "xyz")


def thesis_for(task: str, case: str):
    if case == "seen_last40":
        return THESIS.get(task)
    return THESIS.get(case) or THESIS.get(f"{task}_heldout")


def rows(checkpoints):
    out = []
    for path in checkpoints:
        meta = json.loads(path.with_suffix(".json").read_text())
        for case, m in meta["metrics"].items():
            th = thesis_for(meta["task"], case)
            out.append({"task": meta["task"], "case": case if case != "seen_last40" else f"{meta['scene']} (last 40 %)",
                        "thesis": " / ".join(f"{a}, {b}" for a, b in th) if th else "",
                        "one_step": fmt(m["one_step"]["node"]), "free_running": fmt(m["free_running"]["node"]),
                        "free_rmse_max_mm": m["free_running"]["rmse_max_mm"],
                        "step_ms": meta["delta"] * 1e3, "command": meta["command"]})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/surrogates.md")
    ap.add_argument("--checkpoints", default=str(ROOT / "checkpoints"))
    a = ap.parse_args(argv)
    cks = sorted(Path(a.checkpoints).glob("*.pt"))
    table = rows(cks)
    lines = ["# Shipped LSTM node surrogates against the LGVI (Paper II)", "",
             "Max, mean absolute error (mm) per axis x / y / z of the scene's node of interest (node 30 of 59, the",
             "tip, node 51 of 101). One-step: each prediction from the true history; free-running: the surrogate on",
             "its own predictions (from the true history at the 60 % cut on the printed scene, from rest on the",
             "held-out scenes). Thesis: Paper II's figures for the same cases.", "",
             "| scene | surrogate step | thesis | ours, one-step | ours, free-running |", "|---|---:|---|---|---|"]
    for r in table:
        lines.append(f"| {r['case']} | {r['step_ms']:.0f} ms | {r['thesis']} | {r['one_step']} | {r['free_running']} |")
    lines += ["", "Training commands:", ""]
    lines += [f"- `{json.loads(c.with_suffix('.json').read_text())['command']}`" for c in cks]
    write_text_atomic(a.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(json.dumps({"rows": table}))


if __name__ == "__main__":
    main()
