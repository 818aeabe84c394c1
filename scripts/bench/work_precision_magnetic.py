"""Benchmark: error against run time on the magnetic rod (Paper II Data-set IV), the physics on coarser meshes beside
the shipped surrogates: the work-precision table of :mod:`work_precision` with the magnets' orientations.

    python scripts/bench/work_precision_magnetic.py [--quick] [--eager] [--rounds R] [--out DIR]

For each scene of the task (the printed profile and the held-out one, 24 s each) the reference is the LGVI as the
scene prints it (10 elements, dt 0.08 ms), compiled (:meth:`physics.LGVI.compiled_rollout`: within 4e-11 m of the
eager run, which takes about 250 s a profile). Beside it, from rest, free-running, in the same process and all
compiled (``--eager``: everything eager, the stepper in the exact coil field; for the tests):

- the same LGVI with 2 and 1 elements in each PMC part instead of 4 (:func:`physics.scenes_magnetic_rod.on_mesh`),
  at the printed step and at a longer one (``SWEEP``): the coarser meshes' stability limits are 0.16 and 0.18 ms
  against the printed mesh's 0.11 ms;
- the static Cosserat rod (13 nodes) solved at every frame's currents: the quasi-static hybrid's real-time stepper
  (:meth:`cmlearn.surrogate.quasistatic.QuasiStaticSurrogate.stepper`) without its correction;
- the quasi-static hybrid (``checkpoints/<task>_quasistatic.pt``): that solve plus the learned correction;
- the LSTM surrogate (``checkpoints/<task>.pt``) in closed loop in the tabulated coil field (``Surrogate.run_scene``).

Each row: per magnet, the max and mean absolute orientation error (deg) about x / y / z against the reference over
every 20 ms frame, the sum of the six means, and the wall time per simulated second: the median of ``--rounds``
timed runs after an untimed one (which compiles), the LGVIs each in a block of its own, the other rows in interleaved
rounds (:func:`work_precision.timed_rows`); ``speedup`` is the reference's median over the row's. Batch 1,
``--threads`` threads (default 1), CPU. ``--out DIR`` writes ``work_precision_<task>.md``. Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from statistics import median

import torch
from work_precision import timed_rows

from cmlearn.args import bounded, writable
from cmlearn.compare import find_checkpoint
from cmlearn.data import get_task
from cmlearn.data.generate import lgvi_frames
from cmlearn.data.magnetic import magnet_frames
from cmlearn.eval.timing import json_line
from cmlearn.io import write_text_atomic
from cmlearn.surrogate import Surrogate
from cmlearn.surrogate.magnetic import MAGNETS, orientation_errors
from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate
from physics.elastic import relative_cayley
from physics.loads import magnet_poses
from physics.scenes_magnetic_rod import on_mesh

# (elements in each PMC part, step s) beside the printed (4, 8e-5): 0.49-0.88 of each mesh's stability limit, each
# step a divisor of the 20 ms frame
SWEEP = ((2, 8e-5), (2, 1.25e-4), (1, 8e-5), (1, 1.6e-4))
PRINTED = (4, 8e-5)


def lgvi_runner(scene, delta: float, compiled: bool = True):
    """``run() -> (magnet rotations (T, K, 3, 3) every ``delta`` from rest, wall s)`` of the LGVI on ``scene``
    (compiled: the first run's wall includes its compile)."""
    sim = scene.make_integrator()
    cfg = scene.initial_configuration()
    state = sim.initial_state(p=cfg["p"], R=cfg["R"])
    every, n_frames = int(round(delta / scene.dt)), int(round(scene.duration / delta)) + 1
    prm = scene.rod.params(torch.float64)

    def run():
        p, R, wall, compile_s = lgvi_frames(sim, state, n_frames, every, compiled, record_R=True)
        return magnet_poses(p, R, relative_cayley(R, check=False), prm)[1], wall + compile_s
    return run


def stepper_runner(hybrid: QuasiStaticSurrogate, scene, corrected: bool, compiled: bool = True):
    """``run() -> (magnet rotations (T, K, 3, 3), wall s)`` of the real-time stepper from rest: with its
    correction (the hybrid) or the static rod alone (frame 0 is the rest the stepper starts from)."""
    currents, d = scene.loads.field.currents, hybrid.task.delta
    n = int(round(scene.duration / d))
    Is = [currents(torch.tensor(k * d, dtype=torch.float64)) for k in range(1, n + 1)]
    st = hybrid.stepper(scene, compile=compiled)

    def static():
        return st.solution.R[..., st.nodes, :, :].float()

    def run():
        st.reset()
        out = [static()]
        t0 = time.perf_counter()
        for I in Is:
            if corrected:
                out.append(st.step(I)[1])
            else:
                st.solve(I)
                out.append(static())
        wall = time.perf_counter() - t0
        return torch.stack(out), wall
    return run


def lstm_runner(engine: Surrogate, task, scene):
    def run():
        p, wall = engine.run_scene(scene)
        return magnet_frames(task, scene.rod, p.double())[1], wall
    return run


def errors(R: torch.Tensor, R_ref: torch.Tensor) -> dict:
    """Per magnet ``{max_deg, mean_deg}`` (3 each, x / y / z) over the frames after the first, and the sum of means."""
    a = orientation_errors(R[1:], R_ref[1:]).abs()
    out = {name: {"max_deg": a[:, k].amax(0).tolist(), "mean_deg": a[:, k].mean(0).tolist()}
           for k, name in enumerate(MAGNETS)}
    out["sum_of_means_deg"] = float(a.mean(0).sum())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="magnetic_rod", choices=("magnetic_rod",))
    ap.add_argument("--quick", action="store_true", help="the held-out profile's first 0.3 s, one coarse mesh")
    ap.add_argument("--eager", action="store_true", help="every model eager")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0, help="timing rounds (default 3, --quick 1)")
    ap.add_argument("--out", type=writable(folder=True), default="", help="folder for the table (.md)")
    a = ap.parse_args(argv)
    rounds = a.rounds or (1 if a.quick else 3)
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    hybrid = QuasiStaticSurrogate.load(find_checkpoint(f"{task.name}_quasistatic"), task=task.name)
    lstm = Surrogate.load(find_checkpoint(task.name), task=task.name)
    lstm = lstm if a.eager else lstm.compile()
    results = []
    for name in task.heldout[:1] if a.quick else [task.scene, *task.heldout]:
        scene = task.scene_by_name(name)
        if a.quick:
            scene = replace(scene, duration=0.3)
        blocks = {("LGVI", k, dt): (lambda s=replace(on_mesh(scene, k), dt=dt): lgvi_runner(s, task.delta, not a.eager))
                  for k, dt in (PRINTED, *(SWEEP[:1] if a.quick else SWEEP))}
        rows = {("static Cosserat, 13 nodes", None, None): stepper_runner(hybrid, scene, False, not a.eager),
                ("quasi-static hybrid", None, None): stepper_runner(hybrid, scene, True, not a.eager),
                ("LSTM, closed loop", None, None): lstm_runner(lstm, task, scene)}
        notes = {}
        timed = timed_rows(rows, blocks, rounds, notes)
        R_ref, ref_walls, _ = timed[("LGVI", *PRINTED)]
        out = []
        for (model, per_part, dt), (R, walls, first) in timed.items():
            out.append({"model": model, "per_part": per_part, "dt_s": dt,
                        "n_elements": None if per_part is None else 2 * per_part + 2, **errors(R, R_ref),
                        "wall_per_sim_s": median(walls) / scene.duration, "speedup": median(ref_walls) / median(walls),
                        "compile_s": max(first - median(walls), 0.0)})
        results.append({"scene": name, "duration_s": scene.duration, "printed_dt_s": scene.dt,
                        "mode": "eager" if a.eager else "compiled", "rows": out,
                        "notes": [{"model": str(k), "why": v} for k, v in notes.items()]})
        print(table(results[-1]))
    res = {"task": task.name, "scenes": results, "rounds": rounds, "threads": a.threads, "batch": 1,
           "dtype_lgvi": "float64", "dtype_static": "float64", "dtype_surrogate": "float32", "device": "cpu",
           "surrogate_delta_s": task.delta, "args": vars(a)}
    if a.out:
        write_text_atomic(Path(a.out) / f"work_precision_{task.name}.md", report(res))
    print(json_line(res, digits=17))


def _label(r: dict) -> str:
    if r["per_part"] is None:
        return r["model"]
    printed = ", printed (the reference)" if (r["per_part"], r["dt_s"]) == PRINTED else ""
    return f"LGVI{printed}, {r['n_elements']} elements ({r['per_part']} a PMC part), dt {r['dt_s']:g} s"


def table(s: dict) -> str:
    fmt = lambda v: " / ".join(f"{x:.3g}" for x in v)  # noqa: E731
    lines = [f"{s['scene']} ({s['duration_s']:g} s from rest; reference: the {s['mode']} LGVI on the printed 10 "
             f"elements at dt {s['printed_dt_s']:g} s)",
             f"| model ({s['mode']}) | distal max x / y / z | distal mean | proximal max | proximal mean | sum of means "
             "| wall / simulated s | speed-up | compile |",
             "|---|---|---|---|---|---:|---:|---:|---:|"]
    for r in sorted(s["rows"], key=lambda r: -r["wall_per_sim_s"]):
        d, p = r["distal"], r["proximal"]
        lines.append(f"| {_label(r)} | {fmt(d['max_deg'])} | {fmt(d['mean_deg'])} | {fmt(p['max_deg'])} | "
                     f"{fmt(p['mean_deg'])} | {r['sum_of_means_deg']:.3g} | {r['wall_per_sim_s']:.3g} s | "
                     f"{r['speedup']:.3g}x | {r['compile_s']:.0f} s |")
    lines += [f"- {n['model']}: {n['why']}" for n in s["notes"]]
    return "\n".join(lines)


def report(res: dict) -> str:
    head = (f"# Error against run time: {res['task']}\n\nGenerated by `python scripts/bench/work_precision_magnetic.py"
            f"{' --quick' if res['args']['quick'] else ''}{' --eager' if res['args']['eager'] else ''}"
            f"{' --rounds %d' % res['rounds'] if res['args']['rounds'] else ''} --out docs` (the median of "
            f"{res['rounds']} timed run{'s' if res['rounds'] > 1 else ''} after an untimed one; {res['threads']} "
            "thread, batch 1, CPU; the LGVI and the static rod in float64, the networks in float32). Every model runs "
            "from rest, free-running; errors (deg) are the magnets' orientations about the world axes "
            "against the reference at every 20 ms frame; compile times are apart. For scale, Table II.1's means "
            "(against the experiment) sum to 3.11 deg for the thesis's RNN and 13.93 for its static Cosserat model.\n")
    return head + "\n" + "\n\n".join(table(s) for s in res["scenes"]) + "\n"


if __name__ == "__main__":
    main()
