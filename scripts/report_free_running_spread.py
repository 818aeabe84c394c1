"""How much of a magnetic-rod surrogate's free-running error is the luck of its rollout? Starts nudged by ~1e-8 m.

    python scripts/report_free_running_spread.py [--checkpoints checkpoints/magnetic_rod.pt ...] [--starts 16]
        [--sigmas 1e-8 1e-6] [--lgvi-eps 1e-6 1e-3] [--duration S] [--out docs/free_running_spread.md]

The magnetic rod snaps over several times in each profile (a fold of its equilibrium): the magnets turn by
tens of degrees within 0.1 s. A closed-loop surrogate that reaches a fold a step early or late errs by that
much until the next one. Each checkpoint runs free in closed loop on the printed profile from its 60 % cut
and on the held-out profiles from rest, from ``--starts`` copies of the true history with every modelled
point nudged by N(0, sigma^2) per coordinate (``--sigmas`` in m; 1e-8 m is the float32 rounding of these
coordinates), as one batch, and the report gives the spread of the sum of the six mean orientation errors
(deg) over the starts beside the single unnudged run that a checkpoint's metrics record. The same starts (the
first sigma) are also run open loop, fed the wrench of the LGVI's own poses instead of their own, which
separates what the closed loop adds from the network's response to the true forcing. ``--lgvi-eps`` asks
the same of the physics: the LGVI's own run of each profile with every coil current scaled by 1 + eps,
against the unscaled run, as the same sum (its maximum too). Writes the markdown atomically and prints one
JSON line last.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from cmlearn.args import bounded, writable
from cmlearn.data.magnetic import magnet_frames, rollout
from cmlearn.io import write_text_atomic
from cmlearn.surrogate.engine import load_checkpoints
from cmlearn.surrogate.magnetic import (nudged_free_running, orientation_errors, orientation_stats, profile_start,
                                        reference_profiles)


def six_sum(stats: dict) -> float:
    return sum(stats[m][ax]["mean_deg"] for m in ("distal", "proximal") for ax in "xyz")


def lgvi_spread(task, scene, pts, eps: list[float]) -> dict:
    """The LGVI run of ``scene`` with its currents scaled by 1 + eps (one batch) against ``pts``."""
    cur = scene.loads.field.currents
    k = 1.0 + torch.tensor(eps, dtype=torch.float64)
    run, _, wall = rollout(task, scene, currents=lambda t: k[:, None] * torch.as_tensor(cur(t))[None])
    _, R_ref, _ = magnet_frames(task, scene.rod, pts.double())
    out = {}
    for i, e in enumerate(eps):
        st = orientation_stats(orientation_errors(magnet_frames(task, scene.rod, run[i].double())[1], R_ref))
        out[f"{e:g}"] = {"sum_mean_deg": six_sum(st), "max_deg": max(st[m][ax]["max_deg"] for m in st for ax in "xyz")}
    return {"runs": out, "wall_s": wall}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/magnetic_rod.pt"])
    ap.add_argument("--starts", type=bounded(int, at_least=1), default=16)
    ap.add_argument("--sigmas", type=bounded(float, at_least=0), nargs="+", default=[1e-8, 1e-6])
    ap.add_argument("--lgvi-eps", type=bounded(float, at_least=0), nargs="*", default=[1e-6, 1e-3],
                    help="relative current changes for the LGVI's own spread (none: skip it)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="shorter than the profiles (tests)")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data",
                    help="where the LGVI reference runs are cached")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--out", type=writable(), default="")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    try:
        engines, task = load_checkpoints(a.checkpoints, magnetic=True)
    except ValueError as e:
        raise SystemExit(f"--checkpoints: {e}") from None
    rows = []
    for label, scene, pts, W, printed in reference_profiles(task, a.duration or None, a.data_dir):
        row = {"case": label, "models": {}}
        for name, eng in engines.items():
            model = eng.model
            p, Wk, s, pad = profile_start(task, pts, W, model.config.eta, printed)
            one = nudged_free_running(model, task, scene, p, s, pad, n=1, sigma=0.0)["sum_mean_deg"][0]
            row["models"][name] = {"single": one, "nudged": {
                f"{sig:g}": nudged_free_running(model, task, scene, p, s, pad, n=a.starts, sigma=sig) for sig in a.sigmas},
                "open_loop": nudged_free_running(model, task, scene, p, s, pad, n=a.starts, sigma=a.sigmas[0], wrench=Wk)}
        if a.lgvi_eps:
            row["lgvi"] = lgvi_spread(task, scene, pts, a.lgvi_eps)
        rows.append(row)
        print(f"{label}: done", flush=True)

    def spread(v):
        return f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})"

    lines = [f"Closed-loop free-running orientation error of the magnetic rod's surrogates: the sum of the six mean "
             f"absolute errors (deg, distal and proximal magnet about x, y, z) of one run from the true history, "
             f"and its median (min-max) over {a.starts} starts with every modelled point nudged by N(0, sigma^2); "
             f"the last column runs the same starts open loop, each step's magnet wrench that of the LGVI's own poses "
             f"instead of the model's (`python scripts/report_free_running_spread.py`).", "",
             "| case | checkpoint | one run | " + " | ".join(f"sigma {s:g} m" for s in a.sigmas)
             + f" | open loop (the LGVI's wrench), sigma {a.sigmas[0]:g} m |",
             "|---|---|---:|" + "---|" * (len(a.sigmas) + 1)]
    for r in rows:
        for name, m in r["models"].items():
            lines.append(f"| {r['case']} | {name} | {m['single']:.2f} | "
                         + " | ".join(spread(m["nudged"][f"{s:g}"]["sum_mean_deg"]) for s in a.sigmas)
                         + f" | {spread(m['open_loop']['sum_mean_deg'])} |")
    if a.lgvi_eps:
        lines += ["", "The LGVI against itself, every coil current scaled by 1 + eps: the same sum (deg) and the "
                  "largest error about any axis.", "",
                  "| case | " + " | ".join(f"eps {e:g}" for e in a.lgvi_eps) + " |", "|---|" + "---|" * len(a.lgvi_eps)]
        for r in rows:
            lines.append(f"| {r['case']} | " + " | ".join(
                f"{v['sum_mean_deg']:.3f} (max {v['max_deg']:.2f})" for v in r["lgvi"]["runs"].values()) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        write_text_atomic(Path(a.out), text)
    print(json.dumps({"task": task.name, "starts": a.starts, "sigmas": a.sigmas, "rows": rows}))


if __name__ == "__main__":
    main()
