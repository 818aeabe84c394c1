"""Error against run time of the quasi-static hybrid's real-time step: the static solve's tolerance.

    python scripts/report_hybrid_tolerance.py [--task magnetic_rod] [--scene NAME] [--tols 1e-10 1e-8 1e-6 1e-4]
        [--duration S] [--eager] [--threads 1] [--data-dir data] [--out docs/hybrid_tolerance.md]

The real-time stepper (:meth:`cmlearn.surrogate.quasistatic.QuasiStaticSurrogate.stepper`, compiled unless
``--eager``) runs the scene (default the task's held-out profile, all of it) from rest once per tolerance of its
static solve (``tol``, the bound on the scaled tip residual; the first one is the reference, the offline track's
1e-10 by default). Per tolerance: the step's median, mean and slowest time, the frames slower than the frame, the
mean Levenberg-Marquardt iterations, the magnets' largest and mean deviation (deg, any axis) from the reference
tolerance's frames, and the hybrid's error against the LGVI (the sum of the six mean absolute orientation errors and
the largest, deg; the LGVI's run cached in ``--data-dir``). Batch 1, CPU. Writes the markdown atomically and prints one
JSON line last.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from statistics import median

import torch

from cmlearn.args import bounded, writable
from cmlearn.compare import find_checkpoint
from cmlearn.data import get_task, reference_rollout
from cmlearn.io import write_text_atomic
from cmlearn.surrogate.magnetic import magnet_frames, orientation_errors
from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate


def run(hybrid: QuasiStaticSurrogate, scene, n: int, tol: float, compile: bool) -> dict:
    """The stepper over the scene's first ``n`` frames at ``tol``: rotations (n, 2, 3, 3), step times and iterations."""
    st = hybrid.stepper(scene, compile=compile, tol=tol)
    currents, d = scene.loads.field.currents, hybrid.task.delta
    R, times, its = [], [], []
    for k in range(1, n + 1):
        I = currents(torch.tensor(k * d, dtype=torch.float64))
        t0 = time.perf_counter()
        R.append(st.step(I)[1])
        times.append(time.perf_counter() - t0)
        its.append(st.iterations)
    return {"R": torch.stack(R).double(), "times": times, "its": its}


def table(res: dict) -> str:
    lines = [f"{res['scene']}: {res['frames']} frames of {res['delta_s'] * 1e3:g} ms from rest, the stepper "
             f"{'compiled' if res['compiled'] else 'eager'}, {res['threads']} thread(s); deviation against tol "
             f"{res['rows'][0]['tol']:g}",
             "",
             "| tol | step median / mean / slowest (ms) | over the frame | LM iterations (mean) | deviation max / mean "
             "(deg) | error vs LGVI: sum of means / max (deg) |",
             "|---|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['tol']:g} | {r['step_median_ms']:.3f} / {r['step_mean_ms']:.3f} / {r['step_max_ms']:.1f} | "
                     f"{r['over_frame']} | {r['mean_iterations']:.2f} | {r['deviation_max_deg']:.1e} / "
                     f"{r['deviation_mean_deg']:.1e} | {r['lgvi_sum_mean_deg']:.3f} / {r['lgvi_max_deg']:.2f} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="magnetic_rod", choices=("magnetic_rod", "magnetic_rod_planar"))
    ap.add_argument("--scene", default="", help="one of the task's scenes (default: its first held-out one)")
    ap.add_argument("--tols", type=bounded(float, above=0), nargs="+", default=[1e-10, 1e-8, 1e-6, 1e-4],
                    help="the static solve's tolerances; the first is the reference")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="seconds of the scene (default all of it)")
    ap.add_argument("--eager", action="store_true", help="the eager stepper (the exact coil model) instead")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--data-dir", type=writable(folder=True), default="data", help="where the LGVI's run is cached")
    ap.add_argument("--out", type=writable(), default="", help="markdown file for the table")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    scene = task.scene_by_name(a.scene or task.heldout[0])
    if a.duration:
        scene = replace(scene, duration=a.duration)
    n = int(round(scene.duration / task.delta))
    hybrid = QuasiStaticSurrogate.load(find_checkpoint(f"{task.name}_quasistatic"), task=task.name)
    pts = reference_rollout(task, scene.name, scene.duration, a.data_dir)[0]
    R_lgvi = magnet_frames(task, scene.rod, pts[1:].double())[1]
    compile_s = 0.0
    if not a.eager:  # the programs (solver and frame) are built by a first step, timed apart
        t0 = time.perf_counter()
        first = scene.loads.field.currents(torch.tensor(task.delta, dtype=torch.float64))
        hybrid.stepper(scene, compile=True).step(first)
        compile_s = time.perf_counter() - t0
    rows, ref = [], None
    for tol in a.tols:
        out = run(hybrid, scene, n, tol, not a.eager)
        ref = out["R"] if ref is None else ref
        dev = orientation_errors(out["R"], ref).abs()
        err = orientation_errors(out["R"], R_lgvi).abs()
        t = out["times"]
        rows.append({"tol": tol, "step_median_ms": median(t) * 1e3, "step_mean_ms": sum(t) / len(t) * 1e3,
                     "step_max_ms": max(t) * 1e3, "over_frame": sum(x > task.delta for x in t),
                     "mean_iterations": sum(out["its"]) / len(out["its"]), "deviation_max_deg": float(dev.max()),
                     "deviation_mean_deg": float(dev.mean()), "lgvi_sum_mean_deg": float(err.mean(0).sum()),
                     "lgvi_max_deg": float(err.max())})
        print(json.dumps(rows[-1]), flush=True)
    res = {"task": task.name, "scene": scene.name, "frames": n, "delta_s": task.delta, "compiled": not a.eager,
           "compile_s": compile_s, "threads": a.threads, "batch": 1, "device": "cpu", "dtype_static": "float64",
           "dtype_correction": "float32", "rows": rows}
    text = table(res)
    print(text)
    if a.out:
        command = " ".join(["python scripts/report_hybrid_tolerance.py", *(sys.argv[1:] if argv is None else argv)])
        write_text_atomic(Path(a.out), "# The quasi-static hybrid's solve tolerance: error against run time\n\n"
                          f"`{command}`\n\n{text}\n")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
