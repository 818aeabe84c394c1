"""Benchmark: error against run time on the Paper II scenes, the physics on coarser meshes and steps beside the
shipped surrogates (DESIGN 7's work-precision table).

    python scripts/bench/work_precision.py [--quick] [--task semicircle] [--compile] [--rounds R] [--out DIR]

For each scene of the task (the printed one and the held-out ones) the reference is the LGVI as the scene prints it
(its mesh and step: the data every surrogate learns and the thesis's figures are against). Beside it run, from rest,
free-running, in the same process:

- the same LGVI on other meshes and steps (``SWEEPS``; the same rod, loads and headline node, built by the scene's
  mesh-study builder, :func:`physics.scenes_paper2.on_mesh`; a scene without one only on its printed mesh), eager
  and, with ``--compile``, compiled (:meth:`physics.LGVI.compiled_rollout`, its compile time apart); a step above a
  mesh's stability limit is reported as such;
- every shipped surrogate of the task, eager (``Surrogate.run_scene``) and, with ``--compile``, compiled.

Each row: the headline node's per-axis max and mean absolute error (mm) against the reference over the whole run,
and the wall time per simulated second, the median of ``--rounds`` timed runs after an untimed one: the eager rows and
the surrogates in interleaved rounds (each times every row once, in turn, so that the rows of one round share the
machine's state), each compiled LGVI in a block of its own (:func:`timed_rows`); ``speedup`` is the reference's
median over the row's, ``compile_s`` the first run's excess. The finer mesh of a sweep tells how far the printed mesh itself is from
convergence. ``--out DIR`` writes ``work_precision_<task>.md`` (the table) and ``.png`` (log-log, each scene's
largest per-axis maximum against wall time per simulated second, the thesis's largest printed maximum as a line).
Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from statistics import median

import torch

from cmlearn.args import bounded, writable
from cmlearn.data import get_task
from cmlearn.data.generate import lgvi_frames, scene_integrator
from cmlearn.eval.metrics import axis_errors
from cmlearn.eval.timing import json_line
from cmlearn.io import atomic_write, write_text_atomic
from cmlearn.surrogate import Surrogate, surrogate_checkpoints
from cmlearn.surrogate.evaluate import interest_slots, thesis_errors
from physics import SolverError
from physics.scenes_paper2 import on_mesh

ROOT = Path(__file__).resolve().parents[2]

# (elements, step s) run beside each scene's printed LGVI; a step must divide the surrogate's 10 ms
SWEEPS = {
    "semicircle": ((200, 1e-4), (100, 1e-3), (100, 2.5e-3), (50, 1e-3), (50, 2.5e-3), (26, 1e-3), (26, 2.5e-3),
                   (14, 2.5e-3)),
    "square_tracking": ((16, 1e-4), (8, 1.25e-4), (4, 1.25e-4), (2, 1.25e-4)),
    "ellipse": ((116, 5e-4), (58, 2e-3), (30, 1e-3), (30, 2e-3)),
}
QUICK_SWEEP = ((50, 1e-3),)


@dataclass
class Args:
    task: str = "semicircle"
    quick: bool = False
    compile: bool = False
    threads: int = 1
    rounds: int = 0
    out: str = ""


def physics_scene(scene, n_elements: int, dt: float):
    """``scene`` on ``n_elements`` at step ``dt`` (None where the scene has no mesh-study builder)."""
    if n_elements != scene.rod.N:
        scene = on_mesh(scene, n_elements)
    return None if scene is None else replace(scene, dt=dt)


def physics_runner(scene, delta: float, compiled: bool):
    """``run() -> (headline node positions (T, 3) every ``delta``, wall s)`` of the LGVI on ``scene`` from rest
    (:func:`cmlearn.data.generate.lgvi_frames`; the first compiled run's wall includes its compile)."""
    _, sim, start = scene_integrator(scene)
    every = int(round(delta / scene.dt))
    n_frames = int(round(scene.duration / delta)) + 1
    node = scene.nodes_of_interest[0]

    def run():
        p, wall, compile_s = lgvi_frames(sim, start, n_frames, every, compiled)
        return p[..., node, :].double(), wall + compile_s
    return run


def timed_rows(rows: dict, blocks: dict, rounds: int, notes: dict) -> dict:
    """``{key: (positions of the first timed run, walls, the first run's wall)}``. The ``rows`` (runners) run once
    untimed (warm-up; the surrogates' programs are compiled ahead of time), then in ``rounds`` interleaved rounds;
    each of the ``blocks`` (a compiled LGVI: a factory of its runner) compiles its own program (ahead of time on the
    CPU; where it falls back to torch.compile, in a fresh dynamo cache, which caches a function's programs per code
    object, so the sweep's LGVIs would evict one another) and runs its rounds in a row. A run that fails
    (:class:`physics.SolverError`) is noted and its row dropped."""
    out = {}
    for k, run in rows.items():
        t0 = time.perf_counter()
        try:
            p, _ = run()
        except SolverError as e:
            notes[k[:3]] = str(e)
            continue
        out[k] = (p, [], time.perf_counter() - t0)
    for _ in range(rounds):
        for k in out:
            out[k][1].append(rows[k]()[1])
    for k, make in blocks.items():
        torch._dynamo.reset()
        run = make()
        try:
            p, first = run()
            out[k] = (p, [run()[1] for _ in range(rounds)], first)
        except SolverError as e:  # e.g. a step the compiled path's fixed Newton count does not converge in
            notes[k[:3]] = f"compiled: {e}"
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="semicircle", choices=sorted(SWEEPS))
    ap.add_argument("--quick", action="store_true", help="the printed scene's first 0.3 s, one coarse mesh")
    ap.add_argument("--compile", action="store_true", help="also the compiled LGVI and surrogates")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--rounds", type=bounded(int, at_least=0), default=0, help="timing rounds (default 3, --quick 1)")
    ap.add_argument("--out", type=writable(folder=True), default="",
                    help="folder for the table (.md) and the plot (.png)")
    a = Args(**vars(ap.parse_args(argv)))
    rounds = a.rounds or (1 if a.quick else 3)
    torch.set_num_threads(a.threads)
    task = get_task(a.task)
    names = [task.scene] if a.quick else [task.scene, *task.heldout]
    paths = [p for p in surrogate_checkpoints(ROOT / "checkpoints")
             if json.loads(p.with_suffix(".json").read_text())["task"] == task.name]
    engines = {p.stem: Surrogate.load(p, task=task.name) for p in paths}
    compiled = {p.stem: Surrogate.load(p, task=task.name).compile() for p in paths} if a.compile else {}
    results = []
    for name in names:
        scene = task.scene_by_name(name)
        if a.quick:
            scene = replace(scene, duration=0.3)
        slot = interest_slots(task, scene)[0]
        rows, blocks, notes = {}, {}, {}
        configs = [(scene.rod.N, scene.dt)] + list(QUICK_SWEEP if a.quick else SWEEPS[task.name])
        for i, (n, dt) in enumerate(configs):
            s = physics_scene(scene, n, dt)
            if s is None:
                continue
            key = ("LGVI, printed" if i == 0 else "LGVI", n, dt)
            try:
                rows[(*key, "eager")] = physics_runner(s, task.delta, False)
            except ValueError as e:  # above the mesh's stability limit
                notes[key] = str(e).split(" of the")[0]
                continue
            if a.compile:
                blocks[(*key, "compiled")] = lambda s=s: physics_runner(s, task.delta, True)
        for stem, eng in engines.items():  # run_scene: (tracked positions, wall s)
            rows[(stem, None, task.delta, "eager")] = lambda eng=eng: eng.run_scene(scene)
            if stem in compiled:
                rows[(stem, None, task.delta, "compiled")] = lambda eng=compiled[stem]: eng.run_scene(scene)
        timed = timed_rows(rows, blocks, rounds, notes)
        p_ref, ref_walls, _ = timed[next(iter(rows))]  # the printed LGVI, eager: the reference
        out = []
        for k, (p, w, first) in timed.items():
            e = axis_errors(p[:, slot] if k[1] is None else p, p_ref, scene.rod.length)
            out.append({"model": k[0], "n_elements": k[1], "dt_s": k[2], "mode": k[3],
                        "max_mm": [e[x]["max_mm"] for x in "xyz"], "mean_mm": [e[x]["mean_mm"] for x in "xyz"],
                        "wall_per_sim_s": median(w) / scene.duration, "speedup": median(ref_walls) / median(w),
                        **({"compile_s": first - median(w)} if k[3] == "compiled" else {})})
        thesis = thesis_errors(task.name, "seen_last40" if name == task.scene else name)
        results.append({"scene": name, "node": scene.node_labels[0], "duration_s": scene.duration,
                        "printed_n_elements": scene.rod.N, "printed_dt_s": scene.dt, "rows": out,
                        "thesis_max_mm": [m for m, _ in thesis] if thesis else None,
                        "notes": [{"model": k[0], "n_elements": k[1], "dt_s": k[2], "why": v} for k, v in notes.items()]})
        print(table(results[-1]))
    res = {"task": task.name, "scenes": results, "rounds": rounds, "threads": a.threads, "batch": 1,
           "dtype_lgvi": "float64", "dtype_surrogate": "float32", "device": "cpu", "surrogate_delta_s": task.delta,
           "args": asdict(a)}
    if a.out:
        folder = Path(a.out)
        write_text_atomic(folder / f"work_precision_{task.name}.md", report(res))
        plot(res, folder / f"work_precision_{task.name}.png")
    print(json_line(res, digits=17))


def _label(r: dict) -> str:
    if r["n_elements"] is None:
        return f"`{r['model']}.pt` ({r['mode']})"
    return f"{r['model']}, {r['n_elements']} elements, dt {r['dt_s']:g} s ({r['mode']})"


def table(s: dict) -> str:
    lines = [f"{s['scene']} ({s['node']}, {s['duration_s']:g} s from rest; reference: the LGVI on "
             f"{s['printed_n_elements']} elements at dt {s['printed_dt_s']:g} s)",
             "| model | max x / y / z (mm) | mean x / y / z (mm) | wall / simulated s | speed-up | compile |",
             "|---|---|---|---:|---:|---:|"]
    for r in sorted(s["rows"], key=lambda r: -r["wall_per_sim_s"]):
        lines.append(f"| {_label(r)} | " + " / ".join(f"{v:.3g}" for v in r["max_mm"]) + " | "
                     + " / ".join(f"{v:.3g}" for v in r["mean_mm"]) + f" | {r['wall_per_sim_s']:.3g} s | "
                     f"{r['speedup']:.3g}x | " + (f"{max(r['compile_s'], 0):.0f} s |" if "compile_s" in r else "|"))
    if s["thesis_max_mm"]:
        lines.append("| thesis (RNN, max) | " + " / ".join(f"{v:.3g}" for v in s["thesis_max_mm"]) + " | | | | |")
    lines += [f"- {n['model']}, {n['n_elements']} elements, dt {n['dt_s']:g} s: {n['why']}" for n in s["notes"]]
    return "\n".join(lines)


def report(res: dict) -> str:
    head = (f"# Error against run time: {res['task']}\n\nGenerated by `python scripts/bench/work_precision.py "
            f"--task {res['task']}{' --quick' if res['args']['quick'] else ''}{' --compile' if res['args']['compile'] else ''}"
            f"{' --rounds %d' % res['rounds'] if res['args']['rounds'] else ''} --out docs` (the median of "
            f"{res['rounds']} timed run{'s' if res['rounds'] > 1 else ''} after an untimed one; {res['threads']} thread, batch 1, the LGVI in float64, the surrogates in float32, "
            "CPU). Every model runs from rest, free-running; errors are the headline node's against the reference "
            "over the whole run; compile times are apart. The thesis's row is Paper II's RNN's maxima, for scale (on a "
            "printed scene over its last 40 % from the true state at the 60 % cut, on a held-out one from rest).\n")
    return head + "\n" + "\n\n".join(table(s) for s in res["scenes"]) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scenes = res["scenes"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.2), squeeze=False)
    for ax, s in zip(axes[0], scenes):
        for r in s["rows"]:
            err = max(r["max_mm"])
            if r["model"] == "LGVI, printed":  # the reference (its compiled run differs by round-off)
                ax.axvline(r["wall_per_sim_s"], color="tab:gray", ls="-" if r["mode"] == "compiled" else ":", lw=0.8,
                           label=f"printed LGVI, {r['mode']}")
                continue
            sur = r["n_elements"] is None
            ax.loglog(r["wall_per_sim_s"], err, ("s" if sur else "o"), mfc="none" if r["mode"] == "eager" else None,
                      color="tab:red" if sur else "tab:blue")
            ax.annotate(r["model"] if sur else f"{r['n_elements']}, {r['dt_s']:g}", (r["wall_per_sim_s"], err),
                        fontsize=7, xytext=(3, 3), textcoords="offset points")
        if s["thesis_max_mm"]:
            ax.axhline(max(s["thesis_max_mm"]), color="k", ls="--", lw=0.8, label="thesis RNN, largest max")
        ax.legend(fontsize=7)
        ax.set_title(s["scene"], fontsize=9)
        ax.set_xlabel("wall time per simulated second (s)")
        ax.set_ylabel("largest per-axis max error (mm)")
    fig.suptitle("LGVI meshes x steps (blue: elements, dt s) and surrogates (red); open: eager, filled: compiled",
                 fontsize=9)
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


if __name__ == "__main__":
    main()
