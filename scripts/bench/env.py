"""Benchmark: steps per second of the magnetic-particle environment (single process, random actions).

The camera atlas of the map is rendered (or loaded from the cache) first and timed separately;
then the gymnasium env made by ``gymnasium.make`` steps with uniformly random actions, resetting
when an episode ends (resets are included). Also measured: one pybullet render of the camera,
i.e. the bound on an env that rendered every step. Prints readable lines and, last, one JSON line.

    python scripts/bench/env.py [--quick] [--seconds 5] [--seed 0]
"""
from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from dataclasses import asdict, dataclass

import numpy as np

from cmlearn.args import bounded
from cmlearn.eval.timing import json_line


@dataclass
class Args:
    quick: bool = False
    seconds: float = 5.0
    seed: int = 0
    map_seed: int = 0
    atlas_cache: str = "default"


def parse(argv=None) -> Args:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1.5 s of stepping")
    ap.add_argument("--seconds", type=bounded(float, above=0), default=5.0)
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=0)
    ap.add_argument("--map-seed", dest="map_seed", type=bounded(int, at_least=0), default=0)
    ap.add_argument("--atlas-cache", dest="atlas_cache", default="default",
                    help="folder of cached atlases ('default': $CMLEARN_CACHE or ~/.cache/cmlearn; 'tmp': a temp dir)")
    a = Args(**vars(ap.parse_args(argv)))
    if a.quick:
        a.seconds = min(a.seconds, 1.5)
    return a


def main(argv=None):
    args = parse(argv)
    import gymnasium as gym
    import torch

    import cmlearn.rl as rl
    cache = tempfile.mkdtemp(prefix="cmlearn-atlas-") if args.atlas_cache == "tmp" else args.atlas_cache
    t0 = time.perf_counter()
    env = gym.make(rl.ENV_ID, map_seeds=(args.map_seed,), atlas_cache=cache)
    env.reset(seed=args.seed)
    build_s = time.perf_counter() - t0
    base = env.unwrapped
    t0 = time.perf_counter()
    base.atlas.precompute()
    atlas_s = time.perf_counter() - t0
    cam = base.atlas.camera()
    cam.render(0.0, 0.45)
    t0 = time.perf_counter()
    for k in range(20):
        cam.render(0.001 * k, 0.45)
    render_ms = (time.perf_counter() - t0) / 20 * 1e3
    rng = np.random.default_rng(args.seed)
    steps = episodes = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < args.seconds:
        _, _, term, trunc, _ = env.step(int(rng.integers(4)))
        steps += 1
        if term or trunc:
            episodes += 1
            env.reset()
    wall = time.perf_counter() - t0
    res = {
        "env_steps_per_s": round(steps / wall, 1), "steps": steps, "episodes": episodes,
        "mean_episode_steps": round(steps / max(episodes, 1), 1), "render_ms_per_image": round(render_ms, 3),
        "render_every_step_bound_steps_per_s": round(1e3 / render_ms, 1), "atlas_build_s": round(atlas_s, 3),
        "atlas_nodes": int(base.map.nx * base.map.ny), "env_build_s": round(build_s, 3), "device": "cpu",
        "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(), "processes": 1,
        "python": platform.python_version(), "args": asdict(args),
    }
    print(f"env: {res['env_steps_per_s']} steps/s over {steps} steps ({episodes} episodes, random actions)")
    print(f"atlas: {res['atlas_nodes']} views in {atlas_s:.2f} s; one pybullet render {render_ms:.2f} ms "
          f"(rendering every step would cap at {res['render_every_step_bound_steps_per_s']} steps/s)")
    env.close()
    print(json_line(res, digits=17))
    return res


if __name__ == "__main__":
    main()
