"""Benchmark: LGVI against PyElastica (PositionVerlet) on the same rod, in the same process.

Problem: the PDMS rod with a tip magnet of Paper I Table I.6 (D 4 mm, L 60.55 mm, E 365.12 kPa,
rho 1101, nu 0.5, 10 elements, tip magnet 9.6e-5 kg as a lumped mass), clamped-free, gravity
perpendicular to the rod, at the printed time step 9e-5 s, float64. PyElastica gets the same
rod, masses, gravity and time step (its tip-node mass is raised by the magnet's mass).

PyElastica and ours (eager and compiled, single rod and batched) are timed in ``--rounds`` interleaved rounds, each
timing every one of them once in turn, and the medians are reported (the runs of the batched figures too): on a
shared machine one window of the peer's and one of ours could fall on different turns of its load (PyElastica's
batch ranged over 1.0-1.9e6 node-steps/s in single windows on 2026-12-04). Prints human-readable lines and, last, one
JSON line. ``--quick`` keeps it near a minute.
"""
from __future__ import annotations

import argparse
import platform
import time
import warnings
from dataclasses import dataclass
from statistics import median

import numpy as np
import torch

from cmlearn.args import bounded
from cmlearn.eval.timing import json_line
from physics import LGVI, CircularSection, Loads, Magnet, Material, Rod

DT = 9e-5
GRAVITY = (0.0, -9.81, 0.0)


@dataclass
class Args:
    quick: bool = False
    threads: int = 1
    batch: int = 1024
    n_elements: int = 10
    steps_per_call: int = 4
    compile: bool = True
    window: float | None = None
    rounds: int = 0


def pdms_tip_magnet_rod(n_elements: int) -> Rod:
    return Rod(length=0.06055, section=CircularSection(4e-3), material=Material(E=365.12e3, density=1101.0, nu=0.5),
               n_elements=n_elements, magnets=(Magnet(s=0.06055, mass=9.6e-5),))


def timeit(fn, min_time: float) -> float:
    """Seconds per call of ``fn`` (repeated until ``min_time`` has passed)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        el = time.perf_counter() - t0
        if el >= min_time:
            return el / n


def pyelastica_system(rod: Rod, n_rods: int):
    import elastica as ea

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing):
        pass

    sim = Sim()
    rods = []
    for _ in range(n_rods):
        r = ea.CosseratRod.straight_rod(
            rod.N, np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), rod.length,
            rod.section.diameter / 2, rod.material.density, youngs_modulus=rod.material.E,
            shear_modulus=rod.material.shear_modulus)
        r.mass[-1] += sum(m.mass for m in rod.magnets)
        sim.append(r)
        sim.constrain(r).using(ea.OneEndFixedBC, constrained_position_idx=(0,), constrained_director_idx=(0,))
        sim.add_forcing_to(r).using(ea.GravityForces, acc_gravity=np.array(GRAVITY))
        rods.append(r)
    sim.finalize()
    stepper = ea.PositionVerlet()
    state = {"t": 0.0}

    def step(k=1):
        for _ in range(k):
            state["t"] = stepper.step(sim, state["t"], DT)

    return step, rods


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short timing windows, a batch of at most 64 rods")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=Args.threads)
    ap.add_argument("--batch", type=bounded(int, at_least=1), default=Args.batch)
    ap.add_argument("--n-elements", type=bounded(int, at_least=1), default=Args.n_elements)
    ap.add_argument("--steps-per-call", type=bounded(int, at_least=1), default=Args.steps_per_call)
    ap.add_argument("--no-compile", dest="compile", action="store_false")
    ap.add_argument("--window", type=bounded(float, above=0), default=None,
                    help="seconds per timing (default 0.5 quick, 2 full)")
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0,
                    help="interleaved timing rounds (default 1 quick, 3 full)")
    args = Args(**vars(ap.parse_args(argv)))
    if args.quick:  # a small batch, the same on both sides
        args.batch = min(args.batch, 64)
    torch.set_num_threads(args.threads)
    window = args.window or (0.5 if args.quick else 2.0)
    args.rounds = args.rounds or (1 if args.quick else 3)
    rod = pdms_tip_magnet_rod(args.n_elements)
    n = rod.n_nodes
    out = {"problem": "pdms_tip_magnet (Table I.6)", "n_elements": rod.N, "n_nodes": n, "dt": DT, "dtype": "float64",
           "threads": torch.get_num_threads(), "device": "cpu", "batch": args.batch, "torch": torch.__version__,
           "cpu": platform.processor() or platform.machine()}

    # --- PyElastica, single rod and a batch of rods in one collection
    import elastica

    out["pyelastica"] = getattr(elastica, "__version__", "1.0")
    pe_step, _ = pyelastica_system(rod, 1)
    pe_batch = args.batch  # the same rods on both sides (--quick sets a small batch for both)
    pe_bstep, _ = pyelastica_system(rod, pe_batch)
    out["pyelastica_batch_rods"] = pe_batch

    # --- ours: eager and (once compiled, untimed) compiled, single rod and batched
    sim = LGVI(rod, dt=DT, loads=Loads(gravity=GRAVITY))
    s0 = sim.initial_state()
    sb = sim.initial_state(p=s0.p.expand(args.batch, n, 3))
    st = {"s": s0, "b": sb, "cs": s0, "cb": sb}
    k = args.steps_per_call

    def eager_step():
        st["s"] = sim.step(st["s"])

    def eager_batch():
        st["b"] = sim.step(st["b"])

    def comp_step():
        st["cs"], _ = sim.compiled_rollout(st["cs"], n_steps=k * 10, steps_per_call=k)

    def comp_batch():
        st["cb"], _ = sim.compiled_rollout(st["cb"], n_steps=k, steps_per_call=k)

    # seconds per step of each, timed in interleaved rounds (each round times every one once, in turn), so that
    # the peer and ours see the same turns of a shared machine; the medians are reported
    timed = {"pe": (lambda: pe_step(50), 50), "pe_batch": (lambda: pe_bstep(5), 5), "eager": (eager_step, 1),
             "eager_batch": (eager_batch, 1)}
    if args.compile:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for key, state in (("single", s0), ("batched", sb)):
                c0 = time.perf_counter()
                sim.compiled_rollout(state, n_steps=k, steps_per_call=k)
                out[f"compile_s_{key}"] = time.perf_counter() - c0
        timed.update(compiled=(comp_step, k * 10), compiled_batch=(comp_batch, k))
    runs = {key: [] for key in timed}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(args.rounds):
            for key, (fn, steps) in timed.items():
                runs[key].append(timeit(fn, window) / steps)
    t = {key: median(v) for key, v in runs.items()}
    out["rounds"] = args.rounds
    t_pe, t_peb, t_eager, t_beager = t["pe"], t["pe_batch"], t["eager"], t["eager_batch"]
    out["pyelastica_us_per_step"] = t_pe * 1e6
    out["pyelastica_node_steps_per_s"] = pe_batch * n / t_peb
    out["pyelastica_node_steps_per_s_runs"] = [pe_batch * n / x for x in runs["pe_batch"]]
    print(f"PyElastica: {t_pe * 1e6:.1f} us/step single rod; {pe_batch} rods: {t_peb * 1e3:.2f} ms/step "
          f"= {pe_batch * n / t_peb:.3e} node-steps/s")
    out["single_rod_eager_us_per_step"] = t_eager * 1e6
    out["batched_eager_node_steps_per_s"] = args.batch * n / t_beager
    print(f"LGVI eager: {t_eager * 1e6:.1f} us/step single rod; batch {args.batch}: {t_beager * 1e3:.2f} ms/step = "
          f"{args.batch * n / t_beager:.3e} node-steps/s")

    t_single, t_batch = t_eager, t_beager
    if args.compile:
        t_comp, t_cb = t["compiled"], t["compiled_batch"]
        out["single_rod_compiled_us_per_step"] = t_comp * 1e6
        out["batched_compiled_node_steps_per_s"] = args.batch * n / t_cb
        out["batched_compiled_node_steps_per_s_runs"] = [args.batch * n / x for x in runs["compiled_batch"]]
        print(f"LGVI compiled ({k} steps/call): {t_comp * 1e6:.1f} us/step single rod (compile "
              f"{out['compile_s_single']:.1f} s); batch {args.batch}: {t_cb * 1e3:.3f} ms/step = "
              f"{args.batch * n / t_cb:.3e} node-steps/s (compile {out['compile_s_batched']:.1f} s)")
        # the compiled and eager paths agree
        e1, _ = sim.simulate(s0, n_steps=k * 10, record_every=10**9)
        c1, _ = sim.compiled_rollout(s0, n_steps=k * 10, steps_per_call=k)
        out["compiled_vs_eager_max_abs_m"] = float((e1.p - c1.p).abs().max())
        t_single, t_batch = min(t_eager, t_comp), min(t_beager, t_cb)
    print(f"(medians of {args.rounds} interleaved rounds of {window} s each)")

    # --- agreement with PyElastica over 0.1 s (same discretisation size; both converge to the continuum)
    steps = int(round(0.1 / DT))
    s_end, _ = sim.simulate(s0, n_steps=steps, record_every=10**9)
    pe_step_chk, pe_chk = pyelastica_system(rod, 1)
    pe_step_chk(steps)
    tip_pe = pe_chk[0].position_collection[:, -1]
    out["tip_diff_vs_pyelastica_at_0.1s_pct_L"] = float(np.linalg.norm(s_end.p[-1].numpy() - tip_pe)) / rod.length * 100

    out["single_rod_us_per_step"] = t_single * 1e6
    out["single_time_ratio_vs_pyelastica"] = t_single / t_pe
    out["batched_node_steps_per_s"] = args.batch * n / t_batch
    out["batched_speedup_vs_pyelastica"] = out["batched_node_steps_per_s"] / out["pyelastica_node_steps_per_s"]
    out["rtf_pdms_tip_magnet"] = DT / t_single
    out["rtf_pdms_tip_magnet_eager"] = DT / t_eager
    out["stability_dt_max"] = rod.stable_time_step().dt_max
    print(f"single-rod time ratio ours/PyElastica = {out['single_time_ratio_vs_pyelastica']:.2f}; batched speed-up = "
          f"{out['batched_speedup_vs_pyelastica']:.1f}x; real-time factor = {out['rtf_pdms_tip_magnet']:.2f} "
          f"(eager {out['rtf_pdms_tip_magnet_eager']:.2f})")
    print(json_line(out))
    return out


if __name__ == "__main__":
    main()
