"""Benchmark: the batched solvers and surrogates on a GPU against the CPU, in the same process.

    python scripts/bench/gpu.py [--quick] [--device cuda] [--threads N] [--batches 1 64 1024 16384]

Three workloads, each timed on the CPU (``--threads`` threads) and on ``--device`` from the same
inputs, with the largest difference between the two results after the timed steps:

- LGVI eager step, the PDMS rod with a tip magnet of Paper I Table I.6 (10 elements, 11 nodes, gravity,
  dt 9e-5 s), float64 and float32, batches of rods: node-steps per second;
- the same rods, float64, with ``LGVI.compiled_rollout`` (four steps a program call and a finiteness and
  Newton-residual check after each; on the CPU the scalar C++ program compiled ahead of time, on the device
  ``torch.compile``): node-steps per second, and the seconds of the first call (the compile; ``--quick``: the
  first batch size only);
- the static Cosserat solve of the Paper II magnetic rod (13 nodes, eMNS-like linear field), float64,
  a batch of fields (B0 times 1-1.3, turned up to 30 deg in plane), cold start: solves per second
  (the first three batch sizes only; ``--quick``: the first);
- the shipped Simulation III surrogate (``checkpoints/semicircle_fast.pt``), float32, a free-running
  rollout of a batch of histories: node-steps per second (modelled nodes x steps x batch);
- its rollout step as a controller calls it (``surrogate_step``; ``Surrogate.stepper``, the LSTM states carried):
  seconds a step, the device synchronised after each, for a batch of the printed push from rest, on the CPU
  eager and compiled (``Surrogate.compile``; the compile not timed; ``--quick``: the first batch size only, with
  library matrix products) and on the device eager and as
  one CUDA-graph replay (``stepper(..., graph=True)``), and the graph's step with the forces coming from and the
  frame going back to the host; then the largest difference between the graph's 200-step rollout and the CPU's
  eager one, and between the graph's and the device's eager one.

Timings synchronise the device before reading the clock. ``--device cpu`` runs both sides on the CPU
(a check of the script where no GPU is seen). Prints human-readable lines and, last, one JSON line.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from cmlearn.args import bounded
from cmlearn.eval.timing import json_line
from physics import LGVI, Loads, UniformField
from physics.cosserat_shooting import CosseratSolver
from physics.scenes_cosserat import LinearField, paper2_magnetic_rod

DT = 9e-5
GRAVITY = (0.0, -9.81, 0.0)
WORKLOADS = ("lgvi", "lgvi_compiled", "cosserat", "surrogate", "surrogate_step")
STEP_ROLLOUT = 200  # steps of the surrogate_step workload's rollouts compared
COMPILED_STEPS = 40  # steps a timed compiled_rollout call (ten program calls of four steps)


@dataclass
class Args:
    quick: bool = False
    device: str = "cuda"
    threads: int = 0  # CPU threads (0: every core)
    workloads: list[str] = field(default_factory=lambda: list(WORKLOADS))
    batches: list[int] = field(default_factory=list)  # empty: 1 and 64 with --quick, else 1, 64, 1024, 16384
    window: float | None = None
    no_cpu_compile: bool = False


def timeit(fn, window: float, sync) -> float:
    """Seconds per call of ``fn`` (one untimed call first; the device synchronised around the clock)."""
    fn()
    sync()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        sync()
        el = time.perf_counter() - t0
        if el >= window:
            return el / n


def sync_for(dev: torch.device):
    return torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short windows and batches up to 64")
    ap.add_argument("--device", default=Args.device)
    ap.add_argument("--threads", type=bounded(int, at_least=0), default=Args.threads,
                    help="CPU threads (0: every core)")
    ap.add_argument("--workloads", nargs="+", default=list(WORKLOADS), choices=WORKLOADS)
    ap.add_argument("--batches", type=bounded(int, at_least=1), nargs="+", default=[])
    ap.add_argument("--window", type=bounded(float, above=0), default=None,
                    help="seconds per timing (default 0.3 quick, 1.5 full)")
    ap.add_argument("--no-cpu-compile", action="store_true",
                    help="surrogate_step: leave out the CPU's compiled step (a run on torch 2.11 crashed with it)")
    a = Args(**vars(ap.parse_args(argv)))
    dev = torch.device(a.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device is seen here (use --device cpu to check the script)")
    torch.set_num_threads(a.threads or os.cpu_count() or 1)
    batches = a.batches or ([1, 64] if a.quick else [1, 64, 1024, 16384])
    window = a.window or (0.3 if a.quick else 1.5)
    sides = {"cpu": torch.device("cpu"), "dev": dev}
    out = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
           "threads": torch.get_num_threads(), "torch": torch.__version__,
           "cpu": platform.processor() or platform.machine(), "lgvi": [], "lgvi_compiled": [], "cosserat": [],
           "surrogate": [], "surrogate_step": []}
    print(f"device {out['device']} against the CPU ({out['threads']} threads), torch {out['torch']}")

    # ---------------------------------------------------------------------- LGVI, PDMS rod + tip magnet
    from physics import CircularSection, Magnet, Material, Rod
    rod = Rod(length=0.06055, section=CircularSection(4e-3), n_elements=10,
              material=Material(E=365.12e3, density=1101.0, nu=0.5),
              magnets=(Magnet(s=0.06055, mass=9.6e-5, moment=(0.0, 0.0, 0.0109)),))
    n = rod.n_nodes

    def rods(dtype, batch, d):
        """The integrator and a batch of the rod at rest, each swung sideways at its own speed."""
        sim = LGVI(rod, dt=DT, dtype=dtype, device=d,
                   loads=Loads(gravity=GRAVITY, field=UniformField(torch.tensor([2e-3, 0.0, 0.0]))))
        s0 = sim.initial_state()
        v = torch.zeros(batch, n, 3, dtype=dtype, device=d)
        v[..., 0] = torch.linspace(-0.05, 0.05, batch, dtype=dtype, device=d)[:, None] * rod.arclength.to(
            d, dtype) / rod.length
        return sim, sim.initial_state(p=s0.p.expand(batch, n, 3), R=s0.R.expand(batch, n, 3, 3), v=v)

    for dtype in (torch.float64, torch.float32) if "lgvi" in a.workloads else ():
        for batch in batches:
            rate, ends = {}, {}
            for side, d in sides.items():
                sim, st0 = rods(dtype, batch, d)
                st = {"s": st0}

                def step():
                    st["s"] = sim.step(st["s"])

                rate[side] = batch * n / timeit(step, window, sync_for(d))
                ends[side], _ = sim.simulate(st0, n_steps=50, record_every=10**9)
            diff = float((ends["dev"].p.cpu().double() - ends["cpu"].p.double()).abs().max())
            row = {"dtype": str(dtype).removeprefix("torch."), "batch": batch, "nodes": n,
                   "cpu_node_steps_per_s": rate["cpu"], "dev_node_steps_per_s": rate["dev"],
                   "ratio_dev_over_cpu": rate["dev"] / rate["cpu"], "max_abs_diff_m_after_50_steps": diff}
            out["lgvi"].append(row)
            print(f"LGVI {row['dtype']} batch {batch:6d}: CPU {rate['cpu']:.3e}, device {rate['dev']:.3e} node-steps/s "
                  f"(x{row['ratio_dev_over_cpu']:.2f}); max |device - CPU| after 50 steps {diff:.1e} m")

    for batch in (batches[:1] if a.quick else batches) if "lgvi_compiled" in a.workloads else ():
        rate, ends, compile_s = {}, {}, {}
        for side, d in sides.items():
            sim, st0 = rods(torch.float64, batch, d)
            t0 = time.perf_counter()
            sim.compiled_rollout(st0, n_steps=4)
            sync_for(d)()
            compile_s[side] = time.perf_counter() - t0
            st = {"s": st0}

            def roll():
                st["s"], _ = sim.compiled_rollout(st["s"], n_steps=COMPILED_STEPS)

            rate[side] = batch * n * COMPILED_STEPS / timeit(roll, window, sync_for(d))
            ends[side], _ = sim.compiled_rollout(st0, n_steps=48)
        diff = float((ends["dev"].p.cpu() - ends["cpu"].p).abs().max())
        row = {"dtype": "float64", "batch": batch, "nodes": n, "steps_per_call": COMPILED_STEPS,
               "cpu_node_steps_per_s": rate["cpu"], "dev_node_steps_per_s": rate["dev"],
               "ratio_dev_over_cpu": rate["dev"] / rate["cpu"], "cpu_compile_s": compile_s["cpu"],
               "dev_compile_s": compile_s["dev"], "max_abs_diff_m_after_48_steps": diff}
        out["lgvi_compiled"].append(row)
        print(f"LGVI compiled float64 batch {batch:6d}: CPU {rate['cpu']:.3e}, device {rate['dev']:.3e} node-steps/s "
              f"(x{row['ratio_dev_over_cpu']:.2f}); compile {compile_s['cpu']:.1f} s / {compile_s['dev']:.1f} s; "
              f"max |device - CPU| after 48 steps {diff:.1e} m")

    # ---------------------------------------------------------------------- static Cosserat, Paper II magnetic rod
    crod = paper2_magnetic_rod()
    for batch in (batches[:3] if not a.quick else batches[:1]) if "cosserat" in a.workloads else ():
        g = torch.Generator().manual_seed(batch)
        scale = 1 + 0.3 * torch.rand(batch, generator=g, dtype=torch.float64)
        turn = math.radians(30) * (2 * torch.rand(batch, generator=g, dtype=torch.float64) - 1)
        b0 = torch.tensor([4e-3, 1.5e-3, 0.0], dtype=torch.float64)
        B0 = torch.stack((b0[0] * turn.cos() - b0[1] * turn.sin(), b0[0] * turn.sin() + b0[1] * turn.cos(),
                          torch.zeros(batch, dtype=torch.float64)), -1) * scale[:, None]
        rate, ys = {}, {}
        for side, d in sides.items():
            solver = CosseratSolver(crod.rod, device=d)
            fld = LinearField(B0[:, None, :].to(d), torch.diag(torch.tensor([20e-3, -10e-3, -10e-3],
                                                                             dtype=torch.float64)).to(d))
            res = {}

            def solve():
                res["s"] = crod.solve(solver, field=fld)

            rate[side] = batch / timeit(solve, window, sync_for(d))
            ys[side] = res["s"].y.cpu()
        diff = float((ys["dev"] - ys["cpu"]).abs().max())
        row = {"dtype": "float64", "batch": batch, "nodes": crod.rod.n_nodes,
               "cpu_solves_per_s": rate["cpu"], "dev_solves_per_s": rate["dev"],
               "ratio_dev_over_cpu": rate["dev"] / rate["cpu"], "max_abs_diff_state": diff}
        out["cosserat"].append(row)
        print(f"Cosserat float64 batch {batch:6d}: CPU {rate['cpu']:.3e}, device {rate['dev']:.3e} solves/s "
              f"(x{row['ratio_dev_over_cpu']:.2f}); max |device - CPU| {diff:.1e}")

    # ---------------------------------------------------------------------- surrogate rollout
    from cmlearn.surrogate import Surrogate
    engine = Surrogate.load(Path(__file__).resolve().parents[2] / "checkpoints" / "semicircle_fast.pt",
                            task="semicircle")
    model, task = engine.model.eval(), engine.task
    W, K, H = engine.eta + 1, len(task.modeled), 20
    ref = task.base_scene().initial_configuration()["p"][list(task.tracked)].float()
    for batch in batches if "surrogate" in a.workloads else ():
        g = torch.Generator().manual_seed(batch)
        hist0 = ref + 1e-4 * torch.randn(batch, W, *ref.shape, generator=g).cumsum(1)
        wrench0 = 0.02 * torch.randn(batch, H, K, 3, generator=g)
        rate, preds = {}, {}
        for side, d in sides.items():
            m = model.to(d)
            hist, wrench, r = hist0.to(d), wrench0.to(d), ref.expand(batch, *ref.shape).to(d)
            res = {}

            @torch.no_grad()
            def roll():
                res["p"] = m.rollout(hist, wrench, r)

            rate[side] = batch * K * H / timeit(roll, window, sync_for(d))
            preds[side] = res["p"].cpu()
        model.cpu()
        diff = float((preds["dev"] - preds["cpu"]).abs().max())
        row = {"dtype": "float32", "batch": batch, "modelled_nodes": K, "steps": H,
               "cpu_node_steps_per_s": rate["cpu"], "dev_node_steps_per_s": rate["dev"],
               "ratio_dev_over_cpu": rate["dev"] / rate["cpu"], "max_abs_diff_m": diff}
        out["surrogate"].append(row)
        print(f"surrogate float32 batch {batch:6d}: CPU {rate['cpu']:.3e}, device {rate['dev']:.3e} node-steps/s "
              f"(x{row['ratio_dev_over_cpu']:.2f}); max |device - CPU| {diff:.1e} m")

    for batch in batches if "surrogate_step" in a.workloads else ():
        compile_cpu = not a.no_cpu_compile and (not a.quick or batch == batches[0])
        out["surrogate_step"].append(surrogate_step(engine, batch, dev, window, compile_cpu,
                                                    gemm_templates=not a.quick))

    print(json_line(out, digits=4))
    return out


def surrogate_step(engine, batch: int, dev: torch.device, window: float, cpu_compile: bool = True,
                   gemm_templates: bool = True) -> dict:
    """The ``surrogate_step`` workload at one batch size (the module's docstring); prints its line. ``gemm_templates``:
    as in :meth:`~cmlearn.surrogate.Surrogate.compile` (False with ``--quick``: a faster compile)."""
    from cmlearn.surrogate import Surrogate
    task, W = engine.task, engine.eta + 1
    scene = task.base_scene()
    wrench = engine.scene_wrench(scene, STEP_ROLLOUT)[:, None].expand(-1, batch, -1, -1).contiguous()
    p0 = scene.initial_configuration()["p"][list(task.tracked)].float().expand(batch, -1, -1)
    hist = p0[:, None].expand(-1, W, -1, -1)

    def stepper(eng, d, graph=False):
        return eng.stepper(hist.to(d), p0.to(d), graph=graph)

    def latency(st, w, host=False):
        k = [0]

        def one():
            x = st.step(w[k[0] % STEP_ROLLOUT])
            if host:
                x.cpu()
            k[0] += 1
        return timeit(one, window, sync_for(w.device))

    def roll(st, w):
        return torch.stack([st.step(w[k]) for k in range(STEP_ROLLOUT)]).cpu()

    cpu = torch.device("cpu")
    row = {"checkpoint": "semicircle_fast.pt", "dtype": "float32", "batch": batch,
           "modelled_nodes": engine.model.idx_modeled.numel(), "s_per_step": {}}
    t = row["s_per_step"]
    with torch.no_grad():
        t["cpu_eager"] = latency(stepper(engine, cpu), wrench)
        ref = roll(stepper(engine, cpu), wrench)
        if not cpu_compile:
            row["cpu_compiled_error"] = "left out (--no-cpu-compile, or --quick past the first batch)"
        else:
            try:
                fast = Surrogate(engine.model, engine.meta).compile(gemm_templates=gemm_templates)
                t0 = time.perf_counter()
                stepper(fast, cpu).step(wrench[0])
                row["cpu_compile_s"] = time.perf_counter() - t0
                t["cpu_compiled"] = latency(stepper(fast, cpu), wrench)
            except Exception as e:  # a torch whose inductor cannot lower the program: say so and go on
                row["cpu_compiled_error"] = f"{type(e).__name__}: {str(e)[:200]}"
        engine.model.to(dev)
        wd = wrench.to(dev)
        t["dev_eager"] = latency(stepper(engine, dev), wd)
        graph = dev.type == "cuda"  # --device cpu: the device's eager step stands in for the graph's
        t0 = time.perf_counter()
        st = stepper(engine, dev, graph=graph)
        sync_for(dev)()
        row["graph_record_s"] = time.perf_counter() - t0
        t["dev_graph"] = latency(st, wd)
        t["dev_graph_host_round_trip"] = latency(stepper(engine, dev, graph=graph), wrench, host=True)
        graphed, eager = roll(stepper(engine, dev, graph=graph), wd), roll(stepper(engine, dev), wd)
        engine.model.cpu()
    row["max_abs_diff_m_graph_vs_cpu"] = float((graphed - ref).abs().max())
    row["max_abs_diff_m_graph_vs_dev_eager"] = float((graphed - eager).abs().max())
    row["swing_m"] = float((ref - p0).abs().max())
    row["steps_per_s"] = {k: 1 / v for k, v in t.items()}
    row["graph_speedup_over"] = {k: v / t["dev_graph"] for k, v in t.items() if k != "dev_graph"}
    print(f"surrogate step batch {batch:6d}: " + ", ".join(f"{k} {v * 1e6:.1f} us" for k, v in t.items())
          + f"; graph - CPU {row['max_abs_diff_m_graph_vs_cpu']:.1e} m, graph - device eager "
          f"{row['max_abs_diff_m_graph_vs_dev_eager']:.1e} m over {STEP_ROLLOUT} steps (swing {row['swing_m']:.3f} m)")
    return row


if __name__ == "__main__":
    main()
