"""Benchmark: batch-1 surrogate step latency against the LGVI step on the same scene, same run, interleaved.

    python scripts/bench/surrogate.py [--quick] [--task semicircle] [--scene NAME] [--checkpoint PATH] [--compile]
                                      [--rounds R]

Reports the surrogate's steps per second at batch 1 (eager and, with ``--compile``, compiled ahead
of time by :meth:`cmlearn.surrogate.Surrogate.compile`; the compile time separately), the LGVI's steps per second on
the task's scene (eager, float64), the wall time per simulated second of each and their ratio, and the errors of a
short free-running rollout against the LGVI. Every figure is timed in ``--rounds`` rounds, each of which times
every surrogate form and the LGVI once in turn: the surrogate a block of steps from the scene's initial shape (its
cost per step does not depend on the state), the LGVI the next share of one rollout of the scene's first 2 s (its
whole duration on Simulation III, whose held-out force acts only in its second half; 0.2 s with ``--quick``),
whose Newton iterations cost more where the rod moves. A ratio is the mean over the rounds of each round's LGVI
block against the surrogate timed beside it (``*_rounds``: min, mean, max), so that a machine whose speed drifts
(these shared CPUs drift by up to 2x over minutes) slows both sides of it alike; a surrogate rate is the median
of its rounds, the LGVI's the mean over the window. The surrogate is timed twice: its step on any input
(:meth:`Surrogate.step`, every mirror image of a mirrored model; the ``surrogate_step_*`` keys) and its rollout
step on the scene as ``run_scene`` steps it (the ``*_rollout`` keys): the LSTM states carried from step to step
(:class:`cmlearn.surrogate.Stepper`), along the scene's own forces, and for a mirrored model with the images the
scene's symmetries leave (``scene_symmetry_axes``; Simulation III's printed push keeps one of four, its held-out
force two). The magnetic rod runs in closed loop (each step also computes the magnets'
wrench from its own last frame and the currents, in the coils' field tabulated over the workspace): its
wall time per simulated second is the closed loop's, the currents' evaluation included
(``surrogate_closed_loop_step_hz``; ``*_latency_us``: a step alone, currents given;
``*_exact_field_step_hz``: in the exact coil field, as the evaluation runs it), and with ``--compile`` its
closed loop is compiled too (``*_compiled``). With ``--compile`` the LGVI is also timed compiled
(:meth:`physics.lgvi.LGVI.compiled_rollout`, 4 steps a call; ``lgvi_step_hz_compiled``, ``*_both_compiled``); on
the magnetic rod the calls within which the coil field's cached maps refresh run eagerly
(``lgvi_compiled_eager_call_share``). Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass, replace
from statistics import mean, median

import torch

from cmlearn.args import bounded, readable
from cmlearn.compare import find_checkpoint
from cmlearn.data import TASKS, get_task
from cmlearn.eval.timing import json_line, lgvi_blocks
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
    rounds: int = 0


def interleaved(timers: dict, rounds: int) -> dict[str, list[float]]:
    """Each timer (a call returning seconds per simulated second) called once per round, in turn."""
    out = {k: [] for k in timers}
    for _ in range(rounds):
        for k, f in timers.items():
            out[k].append(f())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="semicircle", choices=sorted(TASKS))
    ap.add_argument("--scene", default="", help="one of the task's scenes (default: the printed one)")
    ap.add_argument("--checkpoint", type=readable(), default="")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0,
                    help="rounds of interleaved timing (default 9, --quick 3)")
    a = Args(**vars(ap.parse_args(argv)))
    rounds = a.rounds or (3 if a.quick else 9)
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    if a.scene and a.scene not in (task.scene, *task.heldout):  # an unknown name gave a traceback
        ap.error(f"--scene: {a.scene!r} is not a scene of task {task.name!r}; choose from "
                 f"{', '.join((task.scene, *task.heldout))}")
    path = find_checkpoint(task.name, a.checkpoint or None)
    engine = Surrogate.load(path, task=task.name)
    scene = task.scene_by_name(a.scene or task.scene)
    dur = 0.2 if a.quick else 1.0
    short = replace(scene, duration=dur)
    n_block = 30 if a.quick else 300  # timed surrogate steps a round (eager; compiled 4x as many)
    # the LGVI's blocks cover the first `window` s of the scene (its whole duration on Simulation III), a share a round
    window = min(scene.duration, 0.2 if a.quick else 2.0)
    lgvi_steps = max(4, 4 * int(window / scene.dt / rounds / 4 + 1e-9))
    mirrored = bool(engine.model.config.reflections) and not task.custom
    axes = engine.scene_symmetry(scene, engine.scene_wrench(scene, int(round(scene.duration / task.delta)))) \
        if mirrored else ()
    res = {"scene_symmetry_axes": list(axes)} if mirrored else {}
    per_sim = lambda step_s: step_s / task.delta  # noqa: E731 - seconds per simulated second of a step's latency
    sur = {"eager": lambda: per_sim(engine.step_latency(n=n_block, warmup=5))}
    if not task.custom:
        sur["eager_rollout"] = lambda: per_sim(engine.step_latency(n=n_block, warmup=5, scene=scene))
    compiled = None
    if a.compile:
        compiled = Surrogate.load(path, task=task.name)
        t0 = time.perf_counter()
        compiled.compile()
        compiled.step_latency(n=5, warmup=1)
        res["compile_s"] = time.perf_counter() - t0
        sur["compiled"] = lambda: per_sim(compiled.step_latency(n=4 * n_block, warmup=20))
        if not task.custom:
            compiled.step_latency(n=5, warmup=1, scene=scene)  # its own program
            sur["compiled_rollout"] = lambda: per_sim(compiled.step_latency(n=4 * n_block, warmup=20, scene=scene))
    lgvi = {}
    if task.custom:
        # the magnetic rod runs in closed loop: each step also computes the magnets' wrench from the model's own
        # last frame and the currents, so a simulated second costs the closed loop's wall time (the currents'
        # evaluation included), not the bare step's; in the tabulated field (the engine's), and in the exact
        # field for comparison (the evaluation's)
        run, latency = task.hook("run_scene"), task.hook("closed_loop_latency")
        t0 = time.perf_counter()
        run(engine, short)  # warm-up, and the field table
        res["closed_loop_first_run_s"] = time.perf_counter() - t0  # the field table built in it
        sur.update({"closed_loop": lambda: run(engine, short)[1] / dur,
                    "closed_loop_exact_field": lambda: run(engine, short, exact_field=True)[1] / dur})
        if a.compile:
            t0 = time.perf_counter()
            run(compiled, short)  # compiles the closed loop's program
            res["closed_loop_compile_s"] = time.perf_counter() - t0
            sur["closed_loop_compiled"] = lambda: run(compiled, short)[1] / dur
    lgvi["eager"] = lgvi_blocks(scene, lgvi_steps, compiled=False)[0]
    if a.compile:  # the LGVI's own compiled path (LGVI.compiled_rollout, 4 steps a call)
        block, res["lgvi_compile_s"], compiled_sim = lgvi_blocks(scene, lgvi_steps, compiled=True)
        eager_blocks = []

        def counted() -> float:  # the calls replayed eagerly where the coil field's cache refreshed (magnetic rod)
            out = block()
            eager_blocks.append(compiled_sim.eager_blocks)
            return out
        lgvi["compiled"] = counted
    times = interleaved({**{("sur", k): f for k, f in sur.items()}, **{("lgvi", k): f for k, f in lgvi.items()}}, rounds)
    for (side, k), v in times.items():  # rates: the surrogate's median round, the LGVI's mean over the window
        if side == "lgvi":
            res["lgvi_step_hz" + ("" if k == "eager" else "_compiled")] = 1 / (mean(v) * scene.dt)
        elif k.startswith("closed_loop"):
            key = "surrogate_" + k + "_step_hz"
            res[key.replace("_compiled_step_hz", "_step_hz_compiled")] = 1 / (median(v) * task.delta)
        else:
            name = {"eager": "", "eager_rollout": "_rollout", "compiled": "_compiled",
                    "compiled_rollout": "_rollout_compiled"}[k]
            res["surrogate_step_hz" + name] = 1 / (median(v) * task.delta)
            res["surrogate_step_us" + name] = median(v) * task.delta * 1e6

    def ratio(key: str, sur_key: str, lgvi_key: str = "eager"):
        """The LGVI's wall time per simulated second over the surrogate's, each round's LGVI block against the
        surrogate timed beside it, averaged over the rounds (their LGVI blocks cover equal shares of the window)."""
        r = [lg / s for lg, s in zip(times[("lgvi", lgvi_key)], times[("sur", sur_key)])]
        res[key] = mean(r)
        res[key + "_rounds"] = [min(r), mean(r), max(r)]
    base = "closed_loop" if task.custom else "eager"
    ratio("speedup_per_simulated_second", base)
    if not task.custom:
        ratio("speedup_per_simulated_second_rollout", "eager_rollout")
    if a.compile:
        ratio("speedup_per_simulated_second_compiled", "closed_loop_compiled" if task.custom else "compiled")
        ratio("speedup_per_simulated_second_both_compiled", "closed_loop_compiled" if task.custom else "compiled",
              "compiled")
        res["lgvi_compiled_eager_call_share"] = sum(eager_blocks) / (len(eager_blocks) * lgvi_steps / 4)
        if not task.custom:
            ratio("speedup_per_simulated_second_rollout_compiled", "compiled_rollout")
            ratio("speedup_per_simulated_second_rollout_both_compiled", "compiled_rollout", "compiled")
    if task.custom:
        res.update({"surrogate_closed_loop_step_us": 1e6 / res["surrogate_closed_loop_step_hz"],
                    "surrogate_closed_loop_latency_us": latency(engine, short, n=n_block) * 1e6})
        if a.compile:
            res.update({"surrogate_closed_loop_step_us_compiled": 1e6 / res["surrogate_closed_loop_step_hz_compiled"],
                        "surrogate_closed_loop_latency_us_compiled": latency(compiled, short, n=4 * n_block) * 1e6})
    lgvi_per_sim_s, sur_per_sim_s = mean(times[("lgvi", "eager")]), median(times[("sur", base)])
    check = short_check(engine, scene.name, dur)
    res.update({
        "lgvi_wall_per_sim_s": lgvi_per_sim_s, "surrogate_wall_per_sim_s": sur_per_sim_s, "rounds": rounds,
        "lgvi_window_s": lgvi_steps * rounds * scene.dt,
        "quick_rollout_max_err_mm": check["max_err_mm"], "quick_rollout_s": dur, "scene": scene.name,
        "surrogate_delta_s": task.delta, "lgvi_dt_s": scene.dt, "n_tracked": len(task.tracked),
        "n_modeled": len(task.modeled), "lgvi_nodes": scene.rod.n_nodes, "batch": 1, "threads": a.threads,
        "dtype_surrogate": "float32", "dtype_lgvi": "float64", "device": "cpu", "args": asdict(a)})
    span = lambda key: "{:.0f}-{:.0f}x".format(res[key + "_rounds"][0], res[key + "_rounds"][2])  # noqa: E731
    print(f"{task.name} ({scene.name}), {rounds} interleaved rounds (the LGVI over the scene's first "
          f"{res['lgvi_window_s']:g} s): surrogate "
          f"{res['surrogate_step_hz']:.0f} steps/s at batch 1 ({res['surrogate_step_us']:.0f} us), LGVI "
          f"{res['lgvi_step_hz']:.0f} steps/s on {scene.rod.n_nodes} nodes")
    if task.custom:
        print(f"  closed loop (step and the magnets' wrench, tabulated field): {res['surrogate_closed_loop_step_hz']:.0f} "
              f"steps/s ({res['surrogate_closed_loop_step_us']:.0f} us; a step alone, currents given, "
              f"{res['surrogate_closed_loop_latency_us']:.0f} us); in the exact field "
              f"{res['surrogate_closed_loop_exact_field_step_hz']:.0f} steps/s")
    print(f"  wall per simulated second: LGVI {lgvi_per_sim_s:.2f} s, surrogate {sur_per_sim_s * 1e3:.2f} ms "
          f"-> {res['speedup_per_simulated_second']:.0f}x (rounds {span('speedup_per_simulated_second')})")
    if a.compile:
        print(f"  compiled surrogate step: {res['surrogate_step_hz_compiled']:.0f} steps/s "
              f"({res['surrogate_step_us_compiled']:.0f} us, compile {res['compile_s']:.1f} s)" + (
                  f"; its closed loop compiled ({res['closed_loop_compile_s']:.1f} s): "
                  f"{res['surrogate_closed_loop_step_hz_compiled']:.0f} steps/s with the currents' evaluation, a step "
                  f"alone {res['surrogate_closed_loop_latency_us_compiled']:.0f} us -> "
                  f"{res['speedup_per_simulated_second_compiled']:.0f}x per simulated second (rounds "
                  f"{span('speedup_per_simulated_second_compiled')}); against the LGVI compiled too "
                  f"({res['lgvi_step_hz_compiled']:.0f} steps/s, {100 * res['lgvi_compiled_eager_call_share']:.1f} % "
                  "of its calls replayed eagerly where the coil field's cache refreshed): "
                  f"{res['speedup_per_simulated_second_both_compiled']:.0f}x" if task.custom else
                  f" -> {res['speedup_per_simulated_second_compiled']:.0f}x per simulated second (rounds "
                  f"{span('speedup_per_simulated_second_compiled')}); against the LGVI compiled too "
                  f"({res['lgvi_step_hz_compiled']:.0f} steps/s): {res['speedup_per_simulated_second_both_compiled']:.0f}x"))
    if not task.custom:
        images = f" ({engine.model.mirror_sign.shape[0] >> len(axes)} of {engine.model.mirror_sign.shape[0]} mirror " \
            f"images, the scene's symmetry axes {axes})" if mirrored else ""
        print(f"  its rollout step on the scene, the LSTM states carried{images}: {res['surrogate_step_hz_rollout']:.0f} "
              f"steps/s -> {res['speedup_per_simulated_second_rollout']:.0f}x" + (
                  f"; compiled {res['surrogate_step_hz_rollout_compiled']:.0f} steps/s "
                  f"({res['surrogate_step_us_rollout_compiled']:.0f} us) -> "
                  f"{res['speedup_per_simulated_second_rollout_compiled']:.0f}x (rounds "
                  f"{span('speedup_per_simulated_second_rollout_compiled')}; both compiled: "
                  f"{res['speedup_per_simulated_second_rollout_both_compiled']:.0f}x)" if a.compile else ""))
    print(f"  free-running error over {dur} s of {scene.name}: {check['max_err_mm']:.2f} mm")
    print(json_line(res, digits=17))
    return res


if __name__ == "__main__":
    main()
