"""Benchmark: generating a surrogate task's training data with the LGVI, eager against its compiled rollout, same run.

    python scripts/bench/dataset.py [--quick] [--task semicircle] [--variants V] [--duration S] [--threads N]

The task's first ``V`` training variants (the printed scene and random ones, as :func:`cmlearn.data.simulate_task`
draws them) as one LGVI batch for ``S`` simulated seconds, float64, CPU: eagerly (``LGVI.simulate``), as the datasets were made, and
compiled (:meth:`physics.LGVI.compiled_rollout`, its program compiled ahead of time in an untimed first call, timed
apart). After an untimed round, each is timed ``--rounds`` times in turn; the ratio is of the medians. Also the
largest difference of the two runs' tracked positions (round-off: the compiled path's fixed Newton count) and whether
the float32 data the datasets store are the same bytes. Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import platform
from dataclasses import replace
from statistics import median

import torch

from cmlearn.args import bounded
from cmlearn.data import TASKS, data_hash
from cmlearn.data.generate import lgvi_frames, scene_integrator
from cmlearn.eval.timing import json_line


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="semicircle", choices=sorted(k for k, t in TASKS.items() if not t.custom))
    ap.add_argument("--variants", type=bounded(int, at_least=0), default=0,
                    help="variants in the batch (default: the shipped model's)")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (default 0.2, --quick 0.02)")
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0,
                    help="timed runs of each (default 2, --quick 1)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)
    variants = a.variants or (3 if a.quick else {"semicircle": 96, "ellipse": 32, "square_tracking": 64}.get(a.task, 32))
    duration = a.duration or (0.02 if a.quick else 0.2)
    rounds = a.rounds or (1 if a.quick else 2)
    task = TASKS[a.task]
    try:  # a duration under one frame leaves no simulated time to divide by
        task.check_duration(duration)
    except ValueError as e:
        ap.error(f"--duration: {e}")
    torch.set_num_threads(a.threads)
    scene = replace(task.base_scene(), duration=duration)
    var = task.variants(scene, variants, 0)  # as simulate_task: one integrator, so the compiled program is built once
    scene, sim, state = scene_integrator(scene, var["p"], var.get("R"),
                                     var["force"] if var["force"] is not None else "scene")
    every, n_frames = task.record_every(scene), int(round(duration / task.delta)) + 1

    runs, first, compile_s = {"eager": [], "compiled": []}, {}, 0.0
    for r in range(rounds + 1):  # round 0 untimed: the compiled program's compile (timed apart), the eager warm-up
        for mode in ("eager", "compiled"):
            p, wall, comp_s = lgvi_frames(sim, state, n_frames, every, mode == "compiled")
            if r == 0:
                first[mode], compile_s = p[..., list(task.tracked), :], max(compile_s, comp_s)
            else:
                runs[mode].append(wall)
    pe, pc = first["eager"], first["compiled"]
    sim_s = (n_frames - 1) * task.delta
    eager, comp = median(runs["eager"]), median(runs["compiled"])
    diff = float((pc - pe).abs().max())
    same = data_hash(pc.float()) == data_hash(pe.float())
    n_nodes = pe.shape[-2]
    print(f"{a.task}: {variants} variants x {sim_s:g} s ({pe.shape[-3]} frames of {n_nodes} tracked nodes), float64, "
          f"{a.threads} thread(s), {platform.machine()}")
    print(f"  eager LGVI:    {eager:.3f} s ({eager / sim_s:.3f} s per simulated second of the batch)")
    print(f"  compiled LGVI: {comp:.3f} s ({comp / sim_s:.3f} s per simulated second; its compile {compile_s:.1f} s "
          f"apart) -> {eager / comp:.2f}x")
    print(f"  compiled vs eager: largest difference {diff:.2e} m; float32 data {'identical' if same else 'differ'}")
    print(json_line({"task": a.task, "variants": variants, "duration_s": sim_s, "tracked_nodes": n_nodes,
                      "threads": a.threads, "dtype": "float64", "rounds": rounds, "eager_s": eager, "compiled_s": comp,
                      "eager_runs_s": runs["eager"], "compiled_runs_s": runs["compiled"], "compile_s": compile_s,
                      "speedup_compiled": eager / comp, "max_diff_m": diff, "float32_identical": same,
                      "torch": torch.__version__, "machine": platform.machine()}, digits=17))


if __name__ == "__main__":
    main()
