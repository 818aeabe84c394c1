"""Benchmark: LGVI against PyElastica (PositionVerlet) on the same rod, in the same process.

Problem: the PDMS rod with a tip magnet of Paper I Table I.6 (D 4 mm, L 60.55 mm, E 365.12 kPa,
rho 1101, nu 0.5, 10 elements, tip magnet 9.6e-5 kg as a lumped mass), clamped-free, gravity
perpendicular to the rod, at the printed time step 9e-5 s, float64. PyElastica gets the same
rod, masses, gravity and time step (its tip-node mass is raised by the magnet's mass).

Prints human-readable lines and, last, one JSON line. ``--quick`` keeps it near a minute.
"""
from __future__ import annotations

import argparse
import platform
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

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
    ap.add_argument("--threads", type=int, default=Args.threads)
    ap.add_argument("--batch", type=int, default=Args.batch)
    ap.add_argument("--n-elements", type=int, default=Args.n_elements)
    ap.add_argument("--steps-per-call", type=int, default=Args.steps_per_call)
    ap.add_argument("--no-compile", dest="compile", action="store_false")
    ap.add_argument("--window", type=float, default=None, help="seconds per timing (default 0.5 quick, 2 full)")
    args = Args(**vars(ap.parse_args(argv)))
    if args.quick:  # a small batch, the same on both sides
        args.batch = min(args.batch, 64)
    torch.set_num_threads(args.threads)
    window = args.window or (0.5 if args.quick else 2.0)
    rod = pdms_tip_magnet_rod(args.n_elements)
    n = rod.n_nodes
    out = {"problem": "pdms_tip_magnet (Table I.6)", "n_elements": rod.N, "n_nodes": n, "dt": DT, "dtype": "float64",
           "threads": torch.get_num_threads(), "device": "cpu", "batch": args.batch, "torch": torch.__version__,
           "cpu": platform.processor() or platform.machine()}

    # --- PyElastica, single rod and a batch of rods in one collection
    import elastica

    out["pyelastica"] = getattr(elastica, "__version__", "1.0")
    pe_step, pe_rods = pyelastica_system(rod, 1)
    t_pe = timeit(lambda: pe_step(50), window) / 50
    out["pyelastica_us_per_step"] = t_pe * 1e6
    pe_batch = args.batch  # the same rods on both sides (--quick sets a small batch for both)
    pe_bstep, _ = pyelastica_system(rod, pe_batch)
    t_peb = timeit(lambda: pe_bstep(5), window) / 5
    out["pyelastica_batch_rods"] = pe_batch
    out["pyelastica_node_steps_per_s"] = pe_batch * n / t_peb
    print(f"PyElastica: {t_pe * 1e6:.1f} us/step single rod; {pe_batch} rods: {t_peb * 1e3:.2f} ms/step "
          f"= {pe_batch * n / t_peb:.3e} node-steps/s")

    # --- ours, eager
    sim = LGVI(rod, dt=DT, loads=Loads(gravity=GRAVITY))
    s0 = sim.initial_state()
    state = {"s": s0}

    def eager_step():
        state["s"] = sim.step(state["s"])

    t_eager = timeit(eager_step, window)
    out["single_rod_eager_us_per_step"] = t_eager * 1e6
    print(f"LGVI eager: {t_eager * 1e6:.1f} us/step single rod")
    sb = sim.initial_state(p=s0.p.expand(args.batch, n, 3))
    bstate = {"s": sb}

    def eager_batch():
        bstate["s"] = sim.step(bstate["s"])

    t_beager = timeit(eager_batch, window)
    out["batched_eager_node_steps_per_s"] = args.batch * n / t_beager
    print(f"LGVI eager batch {args.batch}: {t_beager * 1e3:.2f} ms/step = {args.batch * n / t_beager:.3e} node-steps/s")

    t_single, t_batch = t_eager, t_beager
    if args.compile:
        k = args.steps_per_call
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c0 = time.perf_counter()
            sim.compiled_rollout(s0, n_steps=k, steps_per_call=k)
            out["compile_s_single"] = time.perf_counter() - c0
            cs = {"s": s0}

            def comp_step():
                cs["s"], _ = sim.compiled_rollout(cs["s"], n_steps=k * 10, steps_per_call=k)

            t_comp = timeit(comp_step, window) / (k * 10)
            out["single_rod_compiled_us_per_step"] = t_comp * 1e6
            print(f"LGVI compiled ({k} steps/call): {t_comp * 1e6:.1f} us/step single rod "
                  f"(compile {out['compile_s_single']:.1f} s)")
            c0 = time.perf_counter()
            sim.compiled_rollout(sb, n_steps=k, steps_per_call=k)
            out["compile_s_batched"] = time.perf_counter() - c0
            cb = {"s": sb}

            def comp_batch():
                cb["s"], _ = sim.compiled_rollout(cb["s"], n_steps=k, steps_per_call=k)

            t_cb = timeit(comp_batch, window) / k
            out["batched_compiled_node_steps_per_s"] = args.batch * n / t_cb
            print(f"LGVI compiled batch {args.batch}: {t_cb * 1e3:.3f} ms/step = {args.batch * n / t_cb:.3e} node-steps/s")
            # the compiled and eager paths agree
            e1, _ = sim.simulate(s0, n_steps=k * 10, record_every=10**9)
            c1, _ = sim.compiled_rollout(s0, n_steps=k * 10, steps_per_call=k)
            out["compiled_vs_eager_max_abs_m"] = float((e1.p - c1.p).abs().max())
        t_single, t_batch = min(t_eager, t_comp), min(t_beager, t_cb)

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
