"""Evaluate Sub-controller 2 candidates inside the switching controller (thesis Section 4.1.3).

For each controller (``iqn``: the trained Rainbow-IQN agent of ``--agent`` inside its
:class:`~cmlearn.rl.agent.ActingGuard`, ``iqn_greedy``: the same, plain greedy, ``attractor``, ``errt``,
``memory``: the explored-map planner of :mod:`cmlearn.planning.memory`, ``random``, ``teacher``: the
privileged map-reading teacher of :mod:`cmlearn.rl.teacher`) and each setting (undisturbed /
disturbed x training maps / unseen maps) it runs ``--episodes`` seeded episodes with random
start and goal (the same seeds for every controller) and reports: success rate with its 95 %
Wilson interval, mean decisions (Sub-controller 2 steps) and Sub-controller 1 steps, particle path
length (successful episodes), tracking error |particle - end-effector| per axis (episode mean and
episode maximum, averaged over episodes, as the thesis), compute time per decision, and the
failure reasons. Saves trajectory plots like Figures 4.9-4.13 and a markdown table; prints one
JSON line last. ``--switch-distance`` sets the switching law's threshold (default 5 cm, the
thesis's 10 cm with 0.10; see :mod:`cmlearn.rl.switching`). The ``iqn`` controllers run in the
environment their agent was trained in: with the map-memory waypoint in the goal marker when its
``train_config.waypoint_lookahead`` is > 0 (``--agent-waypoints N`` overrides, 0 = the goal). The
memory of those and of ``memory`` starts from a camera sweep of each training map (maps the robot
has swept before; ``--no-sweep`` starts it empty there too) and empty on the unseen maps.

    python scripts/eval_controllers.py [--quick] [--episodes 200] [--controllers iqn,attractor,errt,memory]
"""
from __future__ import annotations

import argparse
import json
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cmlearn.args import bounded, writable


@dataclass
class Args:
    quick: bool = False
    episodes: int = 200
    controllers: str = "iqn,attractor,errt,memory"
    agent: str = str(Path(__file__).resolve().parents[1] / "checkpoints" / "iqn_agent.pt")
    threads: int = 1
    seed: int = 0
    train_maps: int = 8
    unseen_maps: int = 8
    unseen_offset: int = 0  # unseen maps from procedural seed 10000 + offset (a fresh set: 8, 16, ...)
    disturbance_probability: float = 0.03
    disturbance_min: float = 0.06
    disturbance_max: float = 0.15
    switch_distance: float = 0.05
    plots: int = 2
    out: str = "eval_controllers"
    report: str = ""
    atlas_cache: str = "default"
    agent_waypoints: int = -1  # waypoint_lookahead of the iqn controllers' environment; -1: the agent's own
    no_sweep: bool = False  # memory controllers (iqn with waypoints, memory): no sweep of the training maps either


CONTROLLERS = ("iqn", "iqn_greedy", "attractor", "errt", "memory", "random", "teacher")
#: lower bounds of the number options (at least, above), checked as parsed: they failed hours into a run, or not at all
BOUNDS = {"episodes": (1, None), "threads": (1, None), "seed": (0, None), "train_maps": (1, None),
          "unseen_maps": (1, None), "unseen_offset": (0, None), "plots": (0, None), "agent_waypoints": (-1, None),
          "disturbance_probability": (0, None), "disturbance_min": (None, 0), "disturbance_max": (None, 0),
          "switch_distance": (None, 0)}


def parse(argv=None) -> Args:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for f in Args.__dataclass_fields__.values():
        flag = "--" + f.name.replace("_", "-")
        if f.type == "bool":
            ap.add_argument(flag, dest=f.name, action="store_true")
        else:
            kind = {"int": int, "float": float}.get(f.type)
            kind = bounded(kind, *BOUNDS[f.name]) if kind else str
            if f.name in ("out", "report"):  # the results' folder, the table's copy
                kind = writable(folder=f.name == "out")
            ap.add_argument(flag, dest=f.name, type=kind, default=f.default)
    a = Args(**vars(ap.parse_args(argv)))
    if a.quick:
        a.episodes, a.train_maps, a.unseen_maps, a.plots = min(a.episodes, 4), min(a.train_maps, 2), \
            min(a.unseen_maps, 2), min(a.plots, 1)
    import cmlearn.rl as rl
    try:  # the disturbed settings' and the switching law's checks, before the undisturbed settings' episodes
        rl.DisturbanceConfig(probability=a.disturbance_probability, magnitude=(a.disturbance_min, a.disturbance_max))
        rl.SwitchingConfig(switch_distance=a.switch_distance)
    except ValueError as e:
        ap.error(f"--disturbance-probability, --disturbance-min/max or --switch-distance: {e}")
    names = [c.strip() for c in a.controllers.split(",") if c.strip()]
    for name in names:  # checked before the first controller's hours of episodes, not when its turn comes
        if name not in CONTROLLERS:
            raise SystemExit(f"--controllers: unknown controller {name!r} ({', '.join(CONTROLLERS)})")
    if {"iqn", "iqn_greedy"} & set(names):
        from cmlearn.rl.agent import CheckpointError, load_agent
        try:
            load_agent(a.agent)
        except CheckpointError as e:
            raise SystemExit(f"--agent: {e}") from None
    return a


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k / n."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def make_controller(name: str, env, seed: int, agent: str = "", sweep: bool = False):
    from cmlearn.planning import AttractorController, ERRTController
    from cmlearn.rl import RandomPolicy
    mpp = env.unwrapped.config.camera.metres_per_pixel
    if name in ("iqn", "iqn_greedy"):  # with / without the obstacle mask and revisit tie-break
        from cmlearn.rl.agent import ActingGuard, IQNAgent
        return IQNAgent.load(agent, guard=ActingGuard() if name == "iqn" else None)
    if name == "attractor":
        return AttractorController(mpp)
    if name == "errt":
        return ERRTController(mpp, seed=seed)
    if name == "memory":  # with the sweep of the map as prior where the agent gets it too
        from cmlearn.planning.memory import MemoryPlannerController
        return MemoryPlannerController(mpp, prior=env.unwrapped.sweep_memory if sweep else None)
    if name == "random":
        return RandomPolicy(seed)
    if name == "teacher":  # privileged (reads the map): a reference, not a robot controller
        from cmlearn.rl.teacher import GeodesicTeacher
        return GeodesicTeacher(env)
    raise SystemExit(f"--controllers: unknown controller {name!r} ({', '.join(CONTROLLERS)})")


def plot_episode(res, map_, path: Path, title: str):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cmlearn.io import atomic_write
    tr = res.trajectory
    W, H = map_.size
    ext = (map_.origin[0], map_.origin[0] + W, map_.origin[1], map_.origin[1] + H)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 5.4), gridspec_kw={"width_ratios": [1, 1.2]})
    ax.imshow(map_.image, cmap="gray", extent=ext, vmin=0, vmax=255)
    ax.plot(tr[:, 0], tr[:, 1], "-", color="tab:blue", lw=1.2, label="end-effector")
    ax.plot(tr[:, 2], tr[:, 3], "-", color="tab:red", lw=1.2, label="particle")
    dist = tr[tr[:, 4] == 0]
    ax.plot(dist[:, 2], dist[:, 3], "x", color="orange", ms=9, mew=2, label="disturbance")
    ax.plot(*res.start, "o", color="tab:blue", ms=7, label="start")
    ax.plot(*res.goal, "*", color="tab:green", ms=14, label="goal")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    k = np.arange(len(tr))
    err = tr[:, 2:4] - tr[:, 0:2]
    bx.plot(k, err[:, 0], label="T.E. x")
    bx.plot(k, err[:, 1], label="T.E. y")
    bx.axhline(np.abs(err[:, 0]).mean(), color="tab:blue", ls="--", lw=0.8, label="mean |T.E. x|")
    bx.axhline(np.abs(err[:, 1]).mean(), color="tab:orange", ls="--", lw=0.8, label="mean |T.E. y|")
    sc1 = tr[:, 4] == 1
    if sc1.any():
        bx.fill_between(k, err.min(), err.max(), where=sc1, color="0.85", label="Sub-controller 1")
    bx.set(xlabel="control period", ylabel="particle - end-effector (m)", title=f"{res.reason}, {res.steps} steps")
    bx.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3)
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def summarize(results) -> dict:
    n = len(results)
    k = sum(r.success for r in results)
    lo, hi = wilson(k, n)
    ok = [r for r in results if r.success]
    te_mean = np.array([r.tracking_error_mean for r in results])
    te_max = np.array([r.tracking_error_max for r in results])
    return {
        "episodes": n, "successes": k, "success_rate": round(k / n, 4), "ci95": [round(lo, 4), round(hi, 4)],
        "mean_steps": round(float(np.mean([r.steps for r in results])), 2),
        "mean_steps_success": round(float(np.mean([r.steps for r in ok])), 2) if ok else None,
        "mean_sc1_steps": round(float(np.mean([r.sc1_steps for r in results])), 2),
        "mean_disturbances": round(float(np.mean([r.disturbances for r in results])), 3),
        "path_length_m_success": round(float(np.mean([r.path_length for r in ok])), 4) if ok else None,
        "tracking_error_mean_m": [round(float(v), 4) for v in te_mean.mean(0)],
        "tracking_error_max_m": [round(float(v), 4) for v in te_max.mean(0)],
        "decision_ms": round(1e3 * float(np.mean([r.decision_time_s for r in results])), 3),
        "reasons": dict(Counter(r.reason for r in results)),
    }


def main(argv=None):
    args = parse(argv)
    import gymnasium as gym
    import torch
    torch.set_num_threads(args.threads)  # time per decision on one CPU core

    import cmlearn.rl as rl
    from cmlearn.io import write_text_atomic
    out = Path(args.out)
    settings = [(f"{d}/{m}", d == "disturbed", m) for d in ("undisturbed", "disturbed") for m in ("train", "unseen")]
    table, t_start = {}, time.perf_counter()
    for name in [c.strip() for c in args.controllers.split(",") if c.strip()]:
        table[name] = {}
        lookahead = 0
        if name in ("iqn", "iqn_greedy"):  # the observation the agent was trained on (cmlearn.rl.env waypoints)
            from cmlearn.rl.agent import load_agent
            lookahead = args.agent_waypoints if args.agent_waypoints >= 0 else int(
                load_agent(args.agent)[1].get("train_config", {}).get("waypoint_lookahead", 0))
        for label, disturbed, split in settings:
            seeds = rl.map_seeds(split, args.train_maps if split == "train" else args.unseen_maps)
            if split == "unseen":
                seeds = tuple(s + args.unseen_offset for s in seeds)
            dist = rl.DisturbanceConfig(probability=args.disturbance_probability if disturbed else 0.0,
                                        magnitude=(args.disturbance_min, args.disturbance_max))
            sweep = (name == "memory" or lookahead > 0) and split == "train" and not args.no_sweep
            env = gym.make(rl.ENV_ID, map_seeds=seeds, disturbance=dist, atlas_cache=args.atlas_cache,
                           switching=rl.SwitchingConfig(switch_distance=args.switch_distance),
                           waypoint_lookahead=lookahead, waypoint_prior=sweep and lookahead > 0)
            ctrl = make_controller(name, env, args.seed, args.agent, sweep)
            t0 = time.perf_counter()
            results = [rl.run_episode(env, ctrl, seed=args.seed * 1_000_003 + ep) for ep in range(args.episodes)]
            summ = summarize(results)
            summ["wall_s"] = round(time.perf_counter() - t0, 2)
            table[name][label] = summ
            print(f"{name:9s} {label:19s} success {summ['success_rate']:.3f} CI95 {summ['ci95']} "
                  f"steps {summ['mean_steps']} T.E. mean {summ['tracking_error_mean_m']} "
                  f"max {summ['tracking_error_max_m']} {summ['decision_ms']} ms/decision {summ['reasons']}",
                  flush=True)
            shown = sorted(results, key=lambda r: (not r.success, -r.disturbances))[:args.plots]
            for i, r in enumerate(shown):
                m = next(env.unwrapped.get_map(j) for j in range(env.unwrapped.map_count())
                         if env.unwrapped.get_map(j).name == r.map_name)
                plot_episode(r, m, out / f"{name}_{label.replace('/', '_')}_{i}.png", f"{name}: {label}")
            env.close()
    lines = ["| controller | setting | success (95 % CI) | mean steps | T.E. mean x/y (m) | T.E. max x/y (m) | "
             "ms/decision | failures |", "|---|---|---|---|---|---|---|---|"]
    for name, rows in table.items():
        for label, s in rows.items():
            fails = {k: v for k, v in s["reasons"].items() if k != "success"}
            lines.append(f"| {name} | {label} | {100 * s['success_rate']:.1f} % ({100 * s['ci95'][0]:.1f}-"
                         f"{100 * s['ci95'][1]:.1f}) | {s['mean_steps']} | {s['tracking_error_mean_m']} | "
                         f"{s['tracking_error_max_m']} | {s['decision_ms']} | {fails} |")
    md = "\n".join(lines) + "\n"
    write_text_atomic(out / "results.md", md)
    if args.report:
        write_text_atomic(args.report, md)
    print(md)
    print(json.dumps({"results": table, "args": asdict(args), "wall_s": round(time.perf_counter() - t_start, 1)}))
    return table


if __name__ == "__main__":
    main()
