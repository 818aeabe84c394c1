"""Benchmark: the quasi-static hybrid's real-time step against the LGVI and the LSTM surrogate, same run.

    python scripts/bench/quasistatic.py [--quick] [--task magnetic_rod] [--scene NAME] [--rounds R] [--compile]
                                        [--hybrid PATH] [--checkpoint PATH]

One hybrid step (:meth:`cmlearn.surrogate.quasistatic.QuasiStaticSurrogate.latency`, the real-time stepper) is the
static Cosserat solve at the next frame's currents, started from the secant predictor of the last two frames (13
nodes, float64, eager), and the learned correction (float32); with ``--compile`` also with the solver's compiled
path and the correction one program compiled ahead of time (their compile timed apart) against the LGVI compiled
too (:meth:`physics.lgvi.LGVI.compiled_rollout`, 4 steps a call), and that compiled step
started from the last frame's solution alone (no predictor), and the compiled step along the whole scene, whose
slowest steps are the snap-throughs: with the staged solve (:data:`~cmlearn.surrogate.quasistatic_stepper.STAGES`)
and with the solver's own escalation of load steps instead, and the compiled step with its chord steps against LM
alone and with the first stage's solve by a :class:`~physics.cosserat_frames.FrameSolve` against the solver's call,
each two steppers in alternating blocks of frames along the whole scene (:func:`stepper_ab`); the LSTM surrogate's
(``checkpoints/<task>.pt``) is its closed-loop step in the tabulated coil field; the LGVI (float64, eager) runs the
scene's first seconds. In ``--rounds`` rounds each is timed once in turn, along the scene's first steps; the wall
time per simulated second of each, and the LGVI's over the hybrid's as a ratio per round (min, mean, max). Also the
hybrid's and the static rod's orientation errors over the printed profile's first move
(:func:`cmlearn.surrogate.quasistatic.short_check`).
Batch 1, ``--threads`` threads (default 1), CPU. Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from statistics import mean, median

import torch

from cmlearn.args import bounded, readable
from cmlearn.compare import find_checkpoint
from cmlearn.data import get_task
from cmlearn.eval.timing import json_line, lgvi_blocks
from cmlearn.surrogate import Surrogate
from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate, short_check
from cmlearn.surrogate.quasistatic_stepper import STAGES


def stepper_ab(hybrid: QuasiStaticSurrogate, scene, block: int, option: str) -> dict:
    """The compiled step with a stepper ``option`` on (the default) against off: two steppers along the whole scene,
    in alternating blocks of ``block`` frames (which goes first alternates too), so that both see the same frames and
    the same drift of the machine's speed; per block pair the ratio of the two steps' medians, and the largest
    difference of the magnets' rotations between the two (their frames' solves reach the same equilibria)."""
    currents, d = scene.loads.field.currents, hybrid.task.delta
    n = int(round(scene.duration / d))
    sts = {c: hybrid.stepper(scene, compile=True, **{option: c}) for c in (True, False)}
    med, its, ratios, rot = {True: [], False: []}, {True: [], False: []}, [], {True: [], False: []}
    for c in (True, False):  # the first frame compiles
        sts[c].step(currents(torch.tensor(d, dtype=torch.float64)))
    for k0 in range(2, n + 1, block):
        for c in ((True, False) if (k0 // block) % 2 else (False, True)):
            ts = []
            for k in range(k0, min(k0 + block, n + 1)):
                I = currents(torch.tensor(k * d, dtype=torch.float64))
                t0 = time.perf_counter()
                rot[c].append(sts[c].step(I)[1])
                ts.append(time.perf_counter() - t0)
                its[c].append(sts[c].iterations)
            med[c].append(median(ts))
        ratios.append(med[True][-1] / med[False][-1])
    return {"option": option, "block": block, "pairs": len(ratios), "median_ratio": median(ratios),
            "min_ratio": min(ratios), "max_ratio": max(ratios), "pairs_faster": sum(r < 1 for r in ratios),
            "on_ms": median(med[True]) * 1e3, "off_ms": median(med[False]) * 1e3, "on_iterations": mean(its[True]),
            "off_iterations": mean(its[False]),
            "max_rotation_difference": float((torch.stack(rot[True]) - torch.stack(rot[False])).abs().max())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="magnetic_rod", choices=("magnetic_rod", "magnetic_rod_planar"))
    ap.add_argument("--scene", default="", help="one of the task's scenes (default: the held-out one)")
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0,
                    help="rounds of timing (default 5, --quick 2)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--compile", action="store_true", help="also time the hybrid with the solver's compiled path")
    ap.add_argument("--hybrid", type=readable(), default="",
                    help="the quasi-static hybrid (default: checkpoints/<task>_quasistatic.pt)")
    ap.add_argument("--checkpoint", type=readable(), default="",
                    help="the LSTM surrogate (default: checkpoints/<task>.pt)")
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args(argv)
    rounds = a.rounds or (2 if a.quick else 5)
    paths = {}
    for flag, name, given in (("--hybrid", f"{a.task}_quasistatic", a.hybrid), ("--checkpoint", a.task, a.checkpoint)):
        try:  # none shipped for the task (magnetic_rod_planar): the flag that gives one
            paths[flag] = find_checkpoint(name, given or None)
        except FileNotFoundError:
            ap.error(f"{flag}: no checkpoints/{name}.pt here or in the source tree; pass {flag} PATH")
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    scene = task.scene_by_name(a.scene or task.heldout[0])
    hybrid = QuasiStaticSurrogate.load(paths["--hybrid"], task=task.name)
    lstm = Surrogate.load(paths["--checkpoint"], task=task.name)
    n = 10 if a.quick else 50  # hybrid / LSTM steps a round
    lgvi_steps = 24 if a.quick else 248  # LGVI steps a round (its dt is 0.08 ms; a multiple of 4 steps a compiled call)
    latency = task.hook("closed_loop_latency")
    short = replace(scene, duration=0.2)
    step_s = {"hybrid": [], "hybrid_static_solve": [], "hybrid_correction": [], "lstm": [], "lgvi_per_sim": [],
              "hybrid_compiled": [], "hybrid_compiled_solve": [], "hybrid_compiled_correction": [],
              "hybrid_compiled_warm": [], "lgvi_per_sim_compiled": []}
    its = {}
    block = lgvi_blocks(scene, lgvi_steps, compiled=False)[0]
    compile_s = None
    if a.compile:
        t0 = time.perf_counter()
        hybrid.latency(scene, n=1, compile=True)
        compile_s = time.perf_counter() - t0
        block_compiled, lgvi_compile_s, _ = lgvi_blocks(scene, lgvi_steps, compiled=True)
    for _ in range(rounds):
        if a.compile:
            h = hybrid.latency(scene, n=n, compile=True)
            step_s["hybrid_compiled"].append(h["step_s"])
            step_s["hybrid_compiled_solve"].append(h["static_solve_s"])
            step_s["hybrid_compiled_correction"].append(h["correction_s"])
            w = hybrid.latency(scene, n=n, compile=True, predictor=False)
            step_s["hybrid_compiled_warm"].append(w["step_s"])
            its.update(compiled=h["iterations"], compiled_warm=w["iterations"])
            step_s["lgvi_per_sim_compiled"].append(block_compiled())
        h = hybrid.latency(scene, n=n)
        step_s["hybrid"].append(h["step_s"])
        step_s["hybrid_static_solve"].append(h["static_solve_s"])
        step_s["hybrid_correction"].append(h["correction_s"])
        step_s["lstm"].append(latency(lstm, short, n=n))
        step_s["lgvi_per_sim"].append(block())
    whole, ab = {}, {}
    if a.compile:  # every frame of the scene, folds included: the slowest step against the frame
        for label, stages in (("staged", STAGES), ("escalation", ())):
            whole[label] = hybrid.latency(scene, n=None, compile=True, stages=stages)
        ab = {o: stepper_ab(hybrid, scene, 10 if a.quick else 50, o) for o in ("chord", "frame_solve")}
    d = task.delta
    ratios = [lg / (hy / d) for lg, hy in zip(step_s["lgvi_per_sim"], step_s["hybrid"])]
    t0 = time.perf_counter()
    check = short_check(hybrid, duration=1.0 if a.quick else 1.5)  # the printed profile's currents start at 0.6 s
    res = {"task": task.name, "scene": scene.name, "rounds": rounds, "batch": 1, "threads": a.threads,
           "dtype_static": "float64", "dtype_correction": "float32", "dtype_lgvi": "float64", "device": "cpu",
           "surrogate_delta_s": d, "lgvi_dt_s": scene.dt,
           "hybrid_step_hz": 1 / median(step_s["hybrid"]), "hybrid_step_ms": median(step_s["hybrid"]) * 1e3,
           "hybrid_static_solve_ms": median(step_s["hybrid_static_solve"]) * 1e3,
           "hybrid_correction_us": median(step_s["hybrid_correction"]) * 1e6,
           "hybrid_real_time_factor": d / median(step_s["hybrid"]),
           "lstm_closed_loop_step_hz": 1 / median(step_s["lstm"]),
           "lgvi_step_hz": 1 / (mean(step_s["lgvi_per_sim"]) * scene.dt),
           "lgvi_wall_per_sim_s": mean(step_s["lgvi_per_sim"]),
           "hybrid_wall_per_sim_s": median(step_s["hybrid"]) / d,
           "speedup_per_simulated_second": mean(ratios), "speedup_rounds": [min(ratios), mean(ratios), max(ratios)],
           "check": check, "check_wall_s": time.perf_counter() - t0}
    if a.compile:
        res.update({"hybrid_step_ms_compiled": median(step_s["hybrid_compiled"]) * 1e3,
                    "hybrid_step_hz_compiled": 1 / median(step_s["hybrid_compiled"]),
                    "hybrid_static_solve_ms_compiled": median(step_s["hybrid_compiled_solve"]) * 1e3,
                    "hybrid_correction_us_compiled": median(step_s["hybrid_compiled_correction"]) * 1e6,
                    "hybrid_step_ms_compiled_no_predictor": median(step_s["hybrid_compiled_warm"]) * 1e3,
                    "lm_iterations_compiled": its["compiled"],
                    "lm_iterations_compiled_no_predictor": its["compiled_warm"], "chord_ab": ab["chord"],
                    "frame_solve_ab": ab["frame_solve"],
                    "hybrid_real_time_factor_compiled": d / median(step_s["hybrid_compiled"]),
                    "speedup_per_simulated_second_compiled": mean(
                        lg / (hy / d) for lg, hy in zip(step_s["lgvi_per_sim"], step_s["hybrid_compiled"])),
                    "compile_s": compile_s, "scene_steps": whole["staged"]["steps"],
                    "lgvi_step_hz_compiled": 1 / (mean(step_s["lgvi_per_sim_compiled"]) * scene.dt),
                    "lgvi_compile_s": lgvi_compile_s,
                    "speedup_per_simulated_second_both_compiled": mean(
                        lg / (hy / d) for lg, hy in zip(step_s["lgvi_per_sim_compiled"], step_s["hybrid_compiled"]))})
        for label, w in whole.items():
            res.update({f"slowest_step_ms_{label}": w["max_step_s"] * 1e3, f"steps_over_frame_{label}": w["over_frame"],
                        f"max_lm_iterations_{label}": w["max_iterations"],
                        f"lm_iterations_whole_scene_{label}": w["iterations"]})
    print(f"{task.name} ({scene.name}), batch 1, {a.threads} thread(s), {rounds} rounds: hybrid step "
          f"{res['hybrid_step_ms']:.1f} ms ({res['hybrid_step_hz']:.0f} steps/s; static solve "
          f"{res['hybrid_static_solve_ms']:.1f} ms, correction {res['hybrid_correction_us']:.0f} us), "
          f"{res['hybrid_real_time_factor']:.2f}x real time at its {d * 1e3:.0f} ms step")
    if a.compile:
        print(f"  compiled (first step {compile_s:.0f} s): hybrid step "
              f"{res['hybrid_step_ms_compiled']:.2f} ms ({res['hybrid_step_hz_compiled']:.0f} steps/s; static solve "
              f"{res['hybrid_static_solve_ms_compiled']:.2f} ms in {its['compiled']:.2f} iterations (chord and LM), "
              f"correction {res['hybrid_correction_us_compiled']:.0f} us), "
              f"{res['hybrid_real_time_factor_compiled']:.2f}x real time, "
              f"{res['speedup_per_simulated_second_compiled']:.1f}x faster than the LGVI per simulated second, "
              f"{res['speedup_per_simulated_second_both_compiled']:.1f}x than the LGVI compiled "
              f"({res['lgvi_step_hz_compiled']:.0f} steps/s, compile {lgvi_compile_s:.0f} s); "
              f"without the predictor {res['hybrid_step_ms_compiled_no_predictor']:.2f} ms "
              f"({its['compiled_warm']:.2f} iterations)")
        for what, r in (("chord steps", ab["chord"]), ("the first stage by a FrameSolve", ab["frame_solve"])):
            print(f"  {what} on / off, blocks of {r['block']} frames alternating along the whole scene: the step's "
                  f"median {r['median_ratio']:.3f}x (block pairs {r['min_ratio']:.3f}-{r['max_ratio']:.3f}x, "
                  f"{r['pairs_faster']} of {r['pairs']} faster; {r['on_ms']:.3f} / {r['off_ms']:.3f} ms, "
                  f"{r['on_iterations']:.2f} / {r['off_iterations']:.2f} iterations; rotations within "
                  f"{r['max_rotation_difference']:.1e})")
        w, e = whole["staged"], whole["escalation"]
        print(f"  the whole scene compiled ({w['steps']} steps): slowest step {w['max_step_s'] * 1e3:.1f} ms "
              f"({w['max_iterations']} iterations), {w['over_frame']} steps slower than the {d * 1e3:.0f} ms frame; "
              f"with the solver's escalation instead of the stages {e['max_step_s'] * 1e3:.1f} ms "
              f"({e['max_iterations']} iterations), {e['over_frame']} over")
    print(f"  LSTM closed loop {res['lstm_closed_loop_step_hz']:.0f} steps/s; LGVI {res['lgvi_step_hz']:.0f} steps/s "
          f"({res['lgvi_wall_per_sim_s']:.2f} s per simulated second) -> hybrid "
          f"{res['speedup_per_simulated_second']:.1f}x "
          f"faster per simulated second (rounds {min(ratios):.1f}-{max(ratios):.1f})")
    print(f"  orientation errors over the printed profile's first {check['duration']} s: hybrid "
          f"{check['sum_mean_deg']:.3f} deg (sum of six means), static rod {check['static_sum_mean_deg']:.3f}")
    print(json_line(res, digits=17))
    return res


if __name__ == "__main__":
    main()
