"""Benchmark: batch-1 surrogate step latency against the LGVI step on the same scene, same run.

    python scripts/bench/surrogate.py [--quick] [--task semicircle] [--scene NAME] [--checkpoint PATH] [--compile]

Reports the surrogate's steps per second at batch 1 (eager and, with ``--compile``, compiled ahead
of time by :meth:`cmlearn.surrogate.Surrogate.compile`; the compile time separately), the LGVI's steps per second on the task's scene (eager, float64), the
wall time per simulated second of each and their ratio, and the errors of a short free-running
rollout against the LGVI. A mirrored model is timed twice: with every mirror image (any input: the
``surrogate_step_*`` keys) and with the images the scene's own symmetries leave, as ``run_scene`` steps
that scene (the ``*_symmetric`` keys, with ``scene_symmetry_axes``; Simulation III's printed push keeps
one of four). The magnetic rod runs in closed loop (each step also computes the magnets'
wrench from its own last frame and the currents, in the coils' field tabulated over the workspace): its
wall time per simulated second is the closed loop's, the currents' evaluation included
(``surrogate_closed_loop_step_hz``; ``*_latency_us``: a step alone, currents given;
``*_exact_field_step_hz``: in the exact coil field, as the evaluation runs it), and with ``--compile`` its
closed loop is compiled too (``*_compiled``). Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, replace

import torch

from cmlearn.compare import find_checkpoint
from cmlearn.data import get_task, scene_rollout
from cmlearn.surrogate import Surrogate
from cmlearn.surrogate.evaluate import short_check


@dataclass
class Args:
    task: str = "semicircle"
    scene: str = ""
    checkpoint: str = ""
    quick: bool = False
    compile: bool = False
    threads: int = 1


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="semicircle")
    ap.add_argument("--scene", default="", help="one of the task's scenes (default: the printed one)")
    ap.add_argument("--checkpoint", default="")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    a = Args(**vars(ap.parse_args(argv)))
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    engine = Surrogate.load(find_checkpoint(task.name, a.checkpoint or None), task=task.name)
    scene = task.scene_by_name(a.scene or task.scene)
    dur = 0.2 if a.quick else 1.0
    short = replace(scene, duration=dur)
    n = 300 if a.quick else 3000
    mirrored = bool(engine.model.config.reflections) and not task.custom
    axes = engine.scene_symmetry(scene, engine.scene_wrench(scene, int(round(scene.duration / task.delta)))) \
        if mirrored else ()
    step_s = engine.step_latency(n=n)
    res = {"surrogate_step_hz": 1 / step_s, "surrogate_step_us": step_s * 1e6}
    if mirrored:
        step_y = engine.step_latency(n=n, scene=scene)
        res.update({"scene_symmetry_axes": list(axes), "surrogate_step_hz_symmetric": 1 / step_y,
                    "surrogate_step_us_symmetric": step_y * 1e6})
    n_sur = int(round(dur / task.delta))
    if task.custom:
        # the magnetic rod runs in closed loop: each step also computes the magnets' wrench from the model's own
        # last frame and the currents, so a simulated second costs the closed loop's wall time (the currents'
        # evaluation included), not the bare step's; in the tabulated field (the engine's), and in the exact
        # field for comparison (the evaluation's)
        run, latency = task.hook("run_scene"), task.hook("closed_loop_latency")
        t0 = time.perf_counter()
        run(engine, short)  # warm-up, and the field table
        res["closed_loop_first_run_s"] = time.perf_counter() - t0  # the field table built in it
        wall_cl = run(engine, short)[1]
        wall_exact = run(engine, short, exact_field=True)[1]
        lat = latency(engine, short, n=n // 10)
        res.update({"surrogate_closed_loop_step_hz": n_sur / wall_cl,
                    "surrogate_closed_loop_step_us": wall_cl / n_sur * 1e6, "surrogate_closed_loop_latency_us": lat * 1e6,
                    "surrogate_closed_loop_exact_field_step_hz": n_sur / wall_exact})
    if a.compile:
        t0 = time.perf_counter()
        engine.compile()
        engine.step_latency(n=5, warmup=1)
        res["compile_s"] = time.perf_counter() - t0
        step_c = engine.step_latency(n=n)
        res.update({"surrogate_step_hz_compiled": 1 / step_c, "surrogate_step_us_compiled": step_c * 1e6})
        if mirrored:
            engine.step_latency(n=5, warmup=1, scene=scene)  # its own program
            step_yc = engine.step_latency(n=n, scene=scene)
            res.update({"surrogate_step_hz_symmetric_compiled": 1 / step_yc,
                        "surrogate_step_us_symmetric_compiled": step_yc * 1e6})
        if task.custom:
            t0 = time.perf_counter()
            run(engine, short)  # compiles the closed loop's program
            res["closed_loop_compile_s"] = time.perf_counter() - t0
            wall_clc = run(engine, short)[1]
            lat_c = latency(engine, short, n=n)
            res.update({"surrogate_closed_loop_step_hz_compiled": n_sur / wall_clc,
                        "surrogate_closed_loop_step_us_compiled": wall_clc / n_sur * 1e6,
                        "surrogate_closed_loop_latency_us_compiled": lat_c * 1e6})
    _, _, lgvi_wall = scene_rollout(task, short)
    lgvi_steps = int(round(dur / scene.dt))
    sur_per_sim_s = step_s / task.delta
    if task.custom:
        sur_per_sim_s = wall_cl / dur
    lgvi_per_sim_s = lgvi_wall / dur
    if task.custom and a.compile:
        res["speedup_per_simulated_second_compiled"] = lgvi_per_sim_s * dur / wall_clc
    # the compiled ratios: the LGVI's own compiled path (torch.compile, 4 steps a call) on the same rollout, and
    # the compiled step against it; not for a task with a module of its own (the magnetic rod): its coil field
    # reads the time as a Python number, so torch.compile would recompile at every step and time its compiler
    compiled_ratios = a.compile and not task.custom
    if compiled_ratios:
        sim = short.make_integrator()
        cfg = short.initial_configuration()
        st = sim.initial_state(p=cfg["p"], R=cfg.get("R"))
        t0 = time.perf_counter()
        sim.compiled_rollout(st, n_steps=4, steps_per_call=4)
        res["lgvi_compile_s"] = time.perf_counter() - t0
        n_c = lgvi_steps - lgvi_steps % 4
        t0 = time.perf_counter()
        sim.compiled_rollout(st, n_steps=n_c, steps_per_call=4)
        lgvi_c_per_sim_s = (time.perf_counter() - t0) / (n_c * scene.dt)
        res.update({"lgvi_step_hz_compiled": 1 / (lgvi_c_per_sim_s * scene.dt),
                    "speedup_per_simulated_second_both_compiled": lgvi_c_per_sim_s * task.delta / step_c})
        if mirrored:
            res.update({"speedup_per_simulated_second_symmetric_compiled": lgvi_per_sim_s * task.delta / step_yc,
                        "speedup_per_simulated_second_symmetric_both_compiled":
                            lgvi_c_per_sim_s * task.delta / step_yc})
    if mirrored:
        res["speedup_per_simulated_second_symmetric"] = lgvi_per_sim_s * task.delta / step_y
    check = short_check(engine, scene.name, dur)
    res.update({
        "lgvi_step_hz": lgvi_steps / lgvi_wall, "lgvi_wall_per_sim_s": lgvi_per_sim_s,
        "surrogate_wall_per_sim_s": sur_per_sim_s, "speedup_per_simulated_second": lgvi_per_sim_s / sur_per_sim_s,
        **({"speedup_per_simulated_second_compiled": lgvi_per_sim_s * task.delta / step_c}
           if compiled_ratios else {}),
        "quick_rollout_max_err_mm": check["max_err_mm"], "quick_rollout_s": dur, "scene": scene.name,
        "surrogate_delta_s": task.delta, "lgvi_dt_s": scene.dt, "n_tracked": len(task.tracked),
        "n_modeled": len(task.modeled), "lgvi_nodes": scene.rod.n_nodes, "batch": 1, "threads": a.threads,
        "dtype_surrogate": "float32", "dtype_lgvi": "float64", "device": "cpu", "args": asdict(a)})
    print(f"{task.name} ({scene.name}): surrogate {res['surrogate_step_hz']:.0f} steps/s at batch 1 ({step_s * 1e6:.0f} us), "
          f"LGVI {res['lgvi_step_hz']:.0f} steps/s on {scene.rod.n_nodes} nodes")
    if task.custom:
        print(f"  closed loop (step and the magnets' wrench, tabulated field): {res['surrogate_closed_loop_step_hz']:.0f} "
              f"steps/s ({res['surrogate_closed_loop_step_us']:.0f} us; a step alone, currents given, "
              f"{res['surrogate_closed_loop_latency_us']:.0f} us); in the exact field "
              f"{res['surrogate_closed_loop_exact_field_step_hz']:.0f} steps/s")
    print(f"  wall per simulated second: LGVI {lgvi_per_sim_s:.2f} s, surrogate {sur_per_sim_s * 1e3:.2f} ms "
          f"-> {res['speedup_per_simulated_second']:.0f}x")
    if a.compile:
        print(f"  compiled surrogate step: {res['surrogate_step_hz_compiled']:.0f} steps/s ({step_c * 1e6:.0f} us, "
              f"compile {res['compile_s']:.1f} s)" + (
                  f" -> {res['speedup_per_simulated_second_compiled']:.0f}x per simulated second; against the LGVI "
                  f"compiled too ({res['lgvi_step_hz_compiled']:.0f} steps/s): "
                  f"{res['speedup_per_simulated_second_both_compiled']:.0f}x" if compiled_ratios else
                  f"; its closed loop compiled ({res['closed_loop_compile_s']:.1f} s): "
                  f"{res['surrogate_closed_loop_step_hz_compiled']:.0f} steps/s with the currents' evaluation, a step "
                  f"alone {res['surrogate_closed_loop_latency_us_compiled']:.0f} us -> "
                  f"{res['speedup_per_simulated_second_compiled']:.0f}x per simulated second (its LGVI's coil field "
                  "recompiles every step, so the LGVI runs eager)"))
    if mirrored:
        print(f"  with the scene's symmetries (axes {axes}: {engine.model.mirror_sign.shape[0] >> len(axes)} of "
              f"{engine.model.mirror_sign.shape[0]} mirror images): {res['surrogate_step_hz_symmetric']:.0f} steps/s "
              f"-> {res['speedup_per_simulated_second_symmetric']:.0f}x" + (
                  f"; compiled {res['surrogate_step_hz_symmetric_compiled']:.0f} steps/s -> "
                  f"{res['speedup_per_simulated_second_symmetric_compiled']:.0f}x (both compiled: "
                  f"{res['speedup_per_simulated_second_symmetric_both_compiled']:.0f}x)" if a.compile else ""))
    print(f"  free-running error over {dur} s of {scene.name}: {check['max_err_mm']:.2f} mm")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
