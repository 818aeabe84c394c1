"""Reproduction of Figure II.13: time to solve the Cosserat BVP of the Paper II rod versus the
tolerable error E, the number of nodes N and the initial-guess error (0-20 %), beside the thesis's
8.33-50 Hz. Writes docs/cosserat_timing.md and docs/cosserat_timing.png (atomically) and prints one
JSON line last.

Protocol (thesis lines 1912-1916): known magnet torques and forces are assigned (here the magnet
wrenches of the benchmark's linear field at the solved pose, applied as dead loads at the magnet
centres, plus gravity); a valid solution is found; the guess is that solution times (1 - e) for a
guess error e; each case is solved ``--reps`` times (the thesis: 50) and the mean and standard
deviation of the wall time are reported. E is our dimensionless tip residual (``|r|_2`` in units of
E I / L^2 and E I / L); the thesis's E mixed N and N m. The tip error of each N against a 385-node
solution shows what coarser grids cost in accuracy.

    python scripts/report_cosserat_timing.py [--quick] [--no-compile] [--out docs/cosserat_timing.md]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from cmlearn.args import bounded, writable
from physics.scenes_cosserat import LinearField, paper2_magnetic_rod

THESIS_HZ = (8.33, 50.0)


@dataclass
class Args:
    quick: bool = False
    compile: bool = True
    reps: int | None = None
    threads: int = 1
    out: str = "docs/cosserat_timing.md"


def atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def magnet_wrenches(scene, solver):
    """The linear field's wrenches on the magnets at the solved pose (the 'known' tau_m, f_m)."""
    fld = LinearField(torch.tensor([4e-3, 1.5e-3, 0.0], dtype=torch.float64),
                      torch.diag(torch.tensor([20e-3, -10e-3, -10e-3], dtype=torch.float64)))
    sol = scene.solve(solver, field=fld)
    nodes = list(scene.rod.grid.magnet_nodes)
    mom = torch.stack([sol.R[j] @ torch.tensor(m.moment, dtype=torch.float64) for j, m in zip(nodes, scene.rod.magnets)])
    B, dB = fld(0.0, sol.p[nodes])
    return (dB * mom[:, :, None]).sum(-2), torch.linalg.cross(mom, B, dim=-1)


def time_case(solver, scene, F, T, init_scale, reps):
    """Mean and std (s) of solving from the valid solution times ``init_scale``; the LM iterations."""
    ref = scene.solve(solver, point_forces=F, point_torques=T)
    init = ref.base_wrench * init_scale
    times, sol = [], None
    scene.solve(solver, point_forces=F, point_torques=T, init=init)  # untimed
    for _ in range(reps):
        t0 = time.perf_counter()
        sol = scene.solve(solver, point_forces=F, point_torques=T, init=init)
        times.append(time.perf_counter() - t0)
    return statistics.mean(times), (statistics.stdev(times) if reps > 1 else 0.0), int(sol.iterations), ref


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases and repetitions (smoke test)")
    ap.add_argument("--no-compile", dest="compile", action="store_false")
    ap.add_argument("--reps", type=bounded(int, at_least=1), default=None)
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=Args.threads)
    ap.add_argument("--out", type=writable(), default=Args.out)
    args = Args(**vars(ap.parse_args(argv)))
    torch.set_num_threads(args.threads)
    reps = args.reps or (2 if args.quick else 20)
    nodes = (7, 13, 25) if args.quick else (7, 9, 13, 17, 25, 33, 49)
    tols = (1e-2, 1e-6, 1e-10) if args.quick else (1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
    errs = (0.0, 0.1, 0.2) if args.quick else (0.0, 0.02, 0.05, 0.1, 0.15, 0.2)
    warnings.simplefilter("ignore")
    base = paper2_magnetic_rod()
    with torch.no_grad():
        F, T = magnet_wrenches(base, base.solver())
        fine = paper2_magnetic_rod(385).solve(point_forces=F, point_torques=T)
        t_compile = 0.0
        by_tol, by_n, acc = {}, {}, {}
        for n in nodes:
            sc = paper2_magnetic_rod(n)
            t0 = time.perf_counter()
            solver = sc.solver(compile=args.compile, tol=1e-10)
            sc.solve(solver, point_forces=F, point_torques=T)
            t_compile = max(t_compile, time.perf_counter() - t0)
            for e in errs:
                by_n[(n, e)] = time_case(solver, sc, F, T, 1 - e, reps)[:3]
            ref = sc.solve(solver, point_forces=F, point_torques=T)
            acc[n] = float((ref.tip_position - fine.tip_position).norm()) / sc.rod.length
            if n == 13:
                for tol in tols:
                    s_tol = sc.solver(compile=args.compile, tol=tol)
                    for e in errs:
                        by_tol[(tol, e)] = time_case(s_tol, sc, F, T, 1 - e, reps)[:3]
    # ------------------------------------------------------------------ plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    band = dict(color="tab:orange", alpha=0.15, label="thesis 8.33-50 Hz (20-120 ms)")
    for ax, data, xs, xlabel in ((axes[0], by_tol, tols, "tolerable error E (scaled tip residual)"),
                                 (axes[1], by_n, nodes, "number of nodes N")):
        ax.axhspan(1e3 / THESIS_HZ[1], 1e3 / THESIS_HZ[0], **band)
        for e in errs:
            m = [data[(x, e)][0] * 1e3 for x in xs]
            s = [data[(x, e)][1] * 1e3 for x in xs]
            ax.errorbar(xs, m, yerr=s, marker="o", ms=3, capsize=2, label=f"guess error {e * 100:.0f} %")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("solve time (ms)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].invert_xaxis()
    axes[0].set_title(f"(A) N = 13, {'compiled' if args.compile else 'eager'} torch, {torch.get_num_threads()} "
                      f"thread(s)")
    axes[1].set_title("(B) E = 1e-10")
    axes[1].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    out = Path(args.out)
    png = out.with_suffix(".png")
    tmp_png = png.with_name(png.name + ".tmp.png")
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(tmp_png, dpi=110)
    os.replace(tmp_png, png)
    plt.close(fig)
    # ------------------------------------------------------------------ report
    mode = "compiled (inductor programs of physics.cosserat_fast, first compile excluded)" if args.compile else "eager"
    lines = [
        "# Cosserat BVP solve time (Figure II.13 reproduction)",
        "",
        f"Generated by `scripts/report_cosserat_timing.py{' --quick' if args.quick else ''}"
        f"{'' if args.compile else ' --no-compile'}{f' --reps {args.reps}' if args.reps else ''}"
        f"{f' --threads {args.threads}' if args.threads != Args.threads else ''}`: Paper II rod (`physics.scenes_cosserat`), known magnet "
        f"wrenches and gravity, CPU, {torch.get_num_threads()} thread(s), float64, {mode}; mean +- std of {reps} solves "
        f"per case (the thesis: 50). Thesis: 8.33-50 Hz (20-120 ms per solve). Longest first solve "
        f"{t_compile:.1f} s (compiling, or loading inductor's on-disk cache; a cold compile costs about 15 s per grid "
        f"step here, see `physics/cosserat_fast.py`).",
        "",
        f"![Figure II.13 reproduction]({png.name})",
        "",
        "## (A) Time versus tolerable error E (N = 13)",
        "",
        "| E | " + " | ".join(f"guess err {e * 100:.0f} %" for e in errs) + " |",
        "|---|" + "---|" * len(errs),
    ]
    for tol in tols:
        lines.append(f"| {tol:.0e} | " + " | ".join(
            f"{by_tol[(tol, e)][0] * 1e3:.2f} ms ({1 / by_tol[(tol, e)][0]:.0f} Hz, {by_tol[(tol, e)][2]} it)"
            for e in errs) + " |")
    lines += ["", "## (B) Time versus number of nodes N (E = 1e-10)", "",
              "| N | tip error vs 385 nodes (% L) | " + " | ".join(f"guess err {e * 100:.0f} %" for e in errs) + " |",
              "|---|---|" + "---|" * len(errs)]
    for n in nodes:
        lines.append(f"| {n} | {acc[n] * 100:.2e} | " + " | ".join(
            f"{by_n[(n, e)][0] * 1e3:.2f} ms ({1 / by_n[(n, e)][0]:.0f} Hz, {by_n[(n, e)][2]} it)" for e in errs) + " |")
    hz13 = [1 / by_n[(13, e)][0] for e in errs]
    lines += ["", f"At the thesis's 13 nodes: {min(hz13):.0f}-{max(hz13):.0f} Hz over guess errors 0-"
                  f"{errs[-1] * 100:.0f} % (thesis: 8.33-50 Hz over its nodes and tolerances).", ""]
    atomic_write(out, "\n".join(lines).encode())
    res = {"out": str(out), "png": str(png), "compiled": args.compile, "reps": reps, "threads": torch.get_num_threads(),
           "hz_13_nodes": [round(h, 2) for h in hz13], "thesis_hz": list(THESIS_HZ),
           "tip_error_pct_L": {str(n): float(f"{acc[n] * 100:.3g}") for n in nodes},
           "compile_s": round(t_compile, 2)}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
