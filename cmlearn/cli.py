"""The ``cmlearn`` command line.

``cmlearn scenes``
    list the named scenes of :mod:`physics.scenes` with one-line descriptions.
``cmlearn simulate [--scene NAME] [--duration S] [--out DIR] [--dtype float64|float32] [--record-every K]``
    run a scene with the LGVI and report wall time, real-time factor (simulated seconds per wall
    second), energy drift, Newton iteration statistics and the position range of the scene's first
    node of interest (the tip for cantilevers); write ``tip_trajectory.png``, ``shapes.png`` and
    ``summary.json`` into ``--out`` (default ``./out/simulate_<scene>``), each written to a
    temporary file and renamed into place.

``cmlearn compare [--scene NAME] [--checkpoint PATH] [--duration S] [--out DIR] [--compile]``
    run the LGVI and the shipped LSTM surrogate on a scene (default the held-out semicircle) and
    report per-axis errors, RMSE(t), wall times and the speed-up (:mod:`cmlearn.compare`).

Heavy modules (torch, matplotlib, the physics package) are imported only by the command that
needs them, so ``cmlearn --help`` is quick.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

from .args import bounded, writable
from .io import atomic_write

__all__ = ["main", "build_parser", "run_scene"]

DEFAULT_SCENE = "pdms_tip_magnet"  # 2 s simulated in roughly 10-20 s of wall time on 2 CPU cores
_FRAMES = 1000  # default number of recorded frames


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cmlearn", description="Modeling, learning and control of magnetically actuated continuum rods.")
    parser.add_argument("--version", action="version", version="%(prog)s " + _version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    p_sc = sub.add_parser("scenes", help="list the named simulation scenes")
    p_sc.set_defaults(func=_cmd_scenes)
    p_sim = sub.add_parser("simulate", help="simulate a named scene with the LGVI and plot it",
                           description="Simulate a named scene (see 'cmlearn scenes') with the Lie group "
                                       "variational integrator, print run-time and accuracy diagnostics and "
                                       "write plots and a JSON summary.")
    p_sim.add_argument("--scene", default=DEFAULT_SCENE, help=f"scene name (default {DEFAULT_SCENE})")
    p_sim.add_argument("--duration", type=bounded(float, above=0), default=None,
                       help="simulated seconds (default: the scene's duration)")
    p_sim.add_argument("--out", type=writable(folder=True, kind=Path), default=None,
                       help="output folder (default ./out/simulate_<scene>)")
    p_sim.add_argument("--dtype", choices=("float64", "float32"), default="float64", help="floating-point type")
    p_sim.add_argument("--record-every", type=bounded(int, at_least=1), default=None,
                       help=f"record every K-th step (default: about {_FRAMES} frames)")
    p_sim.set_defaults(func=_cmd_simulate)
    from .compare import DEFAULT_COMPARE_SCENE
    p_cmp = sub.add_parser("compare", help="run the physics and the shipped surrogate on a scene and compare",
                           description="Run the LGVI and the shipped LSTM node surrogate on the same scene; print "
                                       "per-axis errors, RMSE(t), wall times and the speed-up; write plots.")
    p_cmp.add_argument("--scene", default=DEFAULT_COMPARE_SCENE, help=f"scene (default {DEFAULT_COMPARE_SCENE})")
    p_cmp.add_argument("--checkpoint", default=None, help="surrogate checkpoint (default checkpoints/<task>.pt)")
    p_cmp.add_argument("--duration", type=bounded(float, above=0), default=None, help="simulated seconds")
    p_cmp.add_argument("--out", type=writable(folder=True, kind=Path), default=None,
                       help="output folder (default ./out/compare_<scene>)")
    p_cmp.add_argument("--compile", action="store_true",
                       help="compile the surrogate's step and the LGVI ahead of time (tens of seconds each, timed "
                            "apart) and time their compiled rollouts")
    p_cmp.set_defaults(func=_cmd_compare)
    return parser


def _version() -> str:
    from . import __version__

    return __version__


def main(argv: list[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        # torch's forward-mode AD (used by torch.func.hessian) emits this from its own internals
        warnings.filterwarnings("ignore", message=".*torch.jit.script.* is deprecated", category=FutureWarning)
        return int(args.func(args) or 0)


# ------------------------------------------------------------------------------ scenes
def _cmd_scenes(args) -> int:
    from physics.scenes import SCENES

    width = max(len(n) for n in SCENES)
    for name, scene in SCENES.items():
        print(f"{name:<{width}}  {scene.summary}")
    return 0


# ------------------------------------------------------------------------------ simulate
def run_scene(scene, duration: float | None = None, dtype: str = "float64", record_every: int | None = None) -> dict:
    """Simulate ``scene`` and return the summary dict plus the recorded arrays
    (``_t`` (T,), ``_p`` (T, n, 3) as numpy, for plotting)."""
    import torch

    from physics.lgvi import LGVIState

    duration = scene.duration if duration is None else duration
    n_steps = max(1, int(round(duration / scene.dt)))
    every = record_every or max(1, n_steps // _FRAMES)
    t0 = time.perf_counter()
    integ = scene.make_integrator(dtype=getattr(torch, dtype))
    state = integ.initial_state(**scene.initial_configuration())
    t1 = time.perf_counter()
    final, traj = integ.simulate(state, n_steps=n_steps, record_every=every, record_R=True, record_energy=True)
    wall = time.perf_counter() - t1
    simulated = n_steps * scene.dt

    E = traj.energy.double()
    zero = torch.zeros_like(traj.p[0])
    V = torch.stack([integ.potential_energy(LGVIState(0.0, traj.p[k], zero, traj.R[k], zero))
                     for k in range(traj.p.shape[0])]).double()
    kinetic = E - V
    scale = max(abs(float(E[0])), float(kinetic.max()), 1e-300)
    drift = float((E - E[0]).abs().max()) / scale
    iters = traj.newton_iters.double()
    node = scene.nodes_of_interest[0]
    tip = traj.p[:, node, :].double().numpy() * 1e3
    summary = {
        "scene": scene.name, "description": scene.summary, "dtype": dtype, "dt": scene.dt,
        "n_steps": n_steps, "simulated_s": simulated, "record_every": every, "frames": int(traj.p.shape[0]),
        "threads": torch.get_num_threads(), "setup_s": t1 - t0, "wall_s": wall,
        "real_time_factor": simulated / wall if wall > 0 else float("inf"),
        "energy": {"conserved": scene.energy_conserved, "E0": float(E[0]), "E_end": float(E[-1]),
                   "relative_drift": drift, "scale": scale,
                   "definition": "max_t |E(t) - E(0)| / max(|E(0)|, max_t kinetic(t)) over recorded states"},
        "newton": {"mean_iterations": float(iters.mean()), "max_iterations": int(iters.max()),
                   "max_residual": float(traj.newton_residual)},
        "node": {"index": node, "label": scene.node_labels[0],
                 "min_mm": tip.min(0).tolist(), "max_mm": tip.max(0).tolist(), "mean_mm": tip.mean(0).tolist()},
        "orthogonality_error": float(integ.orthogonality_error(final).max()),
    }
    summary["_t"] = traj.t.double().numpy()
    summary["_p"] = traj.p.double().numpy()
    return summary


def _plots(scene, summary: dict, out: Path) -> list[Path]:
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: a library call leaves the caller's backend alone

    t, p = summary["_t"], summary["_p"] * 1e3
    paths = [out / "tip_trajectory.png", out / "shapes.png"]

    fig = Figure(figsize=(7, 6.5))
    axes = fig.subplots(3, 1, sharex=True)
    for node, label in zip(scene.nodes_of_interest, scene.node_labels):
        for k, ax in enumerate(axes):
            ax.plot(t, p[:, node, k], label=f"{label} (node {node})")
    for k, ax in enumerate(axes):
        ax.set_ylabel(f"{'xyz'[k]} (mm)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    axes[0].set_title(f"{scene.name}: positions of the nodes of interest")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    atomic_write(paths[0], lambda f: fig.savefig(f, format="png", dpi=110))

    span = p.reshape(-1, 3).max(0) - p.reshape(-1, 3).min(0)
    order = np.argsort(span)[::-1].tolist()  # axes by decreasing extent
    views = [tuple(sorted(order[:2])), tuple(sorted((order[0], order[2])))]  # main plane, then the third axis
    fig = Figure(figsize=(12, 5.8))
    axes = fig.subplots(1, 2)
    picks = np.unique(np.linspace(0, len(t) - 1, min(9, len(t))).round().astype(int))
    cmap = matplotlib.colormaps["viridis"]
    node = scene.nodes_of_interest[0]
    for ax, (i, j) in zip(axes, views):
        for c, k in enumerate(picks):
            color = cmap(c / max(1, len(picks) - 1))
            ax.plot(p[k, :, i], p[k, :, j], "-o", ms=2.5, lw=1.2, color=color, label=f"t = {t[k]:.3g} s")
            ax.plot(p[k, node, i], p[k, node, j], "s", color=color, ms=5)
        ax.plot(p[:, node, i], p[:, node, j], ":", color="0.4", lw=0.8)
        ax.set_xlabel(f"{'xyz'[i]} (mm)")
        ax.set_ylabel(f"{'xyz'[j]} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{scene.name}: shape snapshots (squares and dotted path: {scene.node_labels[0]})")
    fig.tight_layout()
    atomic_write(paths[1], lambda f: fig.savefig(f, format="png", dpi=110))
    return paths


def _report(scene, s: dict) -> None:
    e, nw, nd = s["energy"], s["newton"], s["node"]
    print(f"scene {scene.name}: {scene.summary}")
    print(f"steps {s['n_steps']} x dt {s['dt']:g} s = {s['simulated_s']:.4g} s simulated "
          f"({s['dtype']}, {s['threads']} threads, {s['frames']} frames recorded)")
    print(f"wall time {s['wall_s']:.3f} s (setup {s['setup_s']:.3f} s); real-time factor "
          f"{s['real_time_factor']:.4g} (simulated s per wall s, recording every {s['record_every']} steps' positions, "
          "rotations and energy included; scripts/bench/lgvi.py times the steps alone)")
    if e["conserved"]:
        print(f"energy: relative drift {e['relative_drift']:.3e} (max |E - E0| / max(|E0|, max kinetic); "
              f"E0 = {e['E0']:.6g} J)")
    else:
        print(f"energy: not conserved (driven and/or damped scene): E0 = {e['E0']:.6g} J, "
              f"E_end = {e['E_end']:.6g} J, relative change {e['relative_drift']:.3e}")
    print(f"Newton: mean {nw['mean_iterations']:.2f} iterations per step, max {nw['max_iterations']}, "
          f"max residual {nw['max_residual']:.2e}; max |R^T R - I| {s['orthogonality_error']:.1e}")
    print(f"{nd['label']} (node {nd['index']}) position (mm):   min        max        mean")
    for k in range(3):
        print(f"  {'xyz'[k]}  {nd['min_mm'][k]:14.4f} {nd['max_mm'][k]:10.4f} {nd['mean_mm'][k]:10.4f}")


def _cmd_compare(args) -> int:
    from .compare import run_compare
    from .surrogate import SurrogateDivergence

    try:
        run_compare(args.scene, args.checkpoint, args.duration, args.out, compile=args.compile)
    except (KeyError, ValueError, FileNotFoundError) as e:  # CheckpointError is a ValueError; str(KeyError) quotes
        print(f"cmlearn compare: {e.args[0] if isinstance(e, KeyError) and e.args else e}", file=sys.stderr)
        return 2
    except SurrogateDivergence as e:
        print(f"cmlearn compare: {e}", file=sys.stderr)
        return 1
    return 0


def _cmd_simulate(args) -> int:
    from physics.errors import SolverError
    from physics.scenes import UnknownSceneError, get_scene

    try:
        scene = get_scene(args.scene)
    except UnknownSceneError as exc:
        print(f"cmlearn simulate: error: {exc}", file=sys.stderr)
        return 2
    out = args.out if args.out is not None else Path("out") / f"simulate_{scene.name}"
    try:
        summary = run_scene(scene, args.duration, args.dtype, args.record_every)
    except SolverError as exc:
        print(f"cmlearn simulate: solver failed: {exc}", file=sys.stderr)
        return 1
    _report(scene, summary)
    out.mkdir(parents=True, exist_ok=True)
    files = _plots(scene, summary, out)
    record = {k: v for k, v in summary.items() if not k.startswith("_")}
    record["files"] = [p.name for p in files]
    js = out / "summary.json"
    atomic_write(js, lambda f: f.write(json.dumps(record, indent=2).encode()))
    print("wrote " + ", ".join(str(p) for p in [*files, js]))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
