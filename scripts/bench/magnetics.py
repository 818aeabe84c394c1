"""Benchmark: field of the 50.8 mm cube magnet (Br 1.3 T) as a dipole grid against magpylib.

Same points, same run: ours (torch, the cube as ~2000 point dipoles) versus magpylib's exact
cuboid and magpylib's collection of the same dipoles; then the force and torque on a dipole at
every point. Prints readable lines and, last, one JSON line.

    python scripts/bench/magnetics.py [--quick] [--threads 1] [--points 10000] [--dipoles 2000]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from cmlearn.args import bounded
from cmlearn.eval.timing import json_line
from physics.magnetics import CuboidMagnet

EDGE, BR = 0.0508, 1.3


@dataclass
class Args:
    quick: bool = False
    threads: int = 1
    points: int = 10_000
    dipoles: int = 2000
    dtype: str = "float64"
    seed: int = 0


def parse(argv=None) -> Args:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1000 points, fewer repeats (about 10 s)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    ap.add_argument("--points", type=bounded(int, at_least=1), default=10_000)
    ap.add_argument("--dipoles", type=bounded(int, at_least=1), default=2000,
                    help="requested count; the grid is the nearest n^3")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=0)
    a = Args(**vars(ap.parse_args(argv)))
    if a.quick:
        a.points = min(a.points, 1000)
    return a


def best_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    import magpylib

    a = parse(argv)
    torch.set_num_threads(a.threads)
    dtype = getattr(torch, a.dtype)
    g = torch.Generator().manual_seed(a.seed)
    u = torch.randn(a.points, 3, generator=g, dtype=torch.float64)
    r = 0.06 + 0.09 * torch.rand(a.points, 1, generator=g, dtype=torch.float64)  # 60-150 mm from the centre
    pts64 = r * u / u.norm(dim=-1, keepdim=True)
    pts = pts64.to(dtype)
    cube = CuboidMagnet(dimensions=(EDGE,) * 3, polarization=(0.0, 0.0, BR))
    model = cube.field_model(a.dipoles, dtype=dtype)
    S = model.dipoles.count
    repeats = 3 if a.quick else 5

    t_ours = best_time(lambda: model.field(pts), repeats)
    moments = torch.zeros_like(pts)
    moments[:, 2] = 0.0109  # the Paper I tip magnet at every point
    t_force = best_time(lambda: model.force_torque(pts, moments), repeats)

    exact = magpylib.magnet.Cuboid(dimension=(EDGE,) * 3, polarization=(0, 0, BR))
    t_cuboid = best_time(lambda: exact.getB(pts64.numpy()), repeats)
    dp = model.dipoles.positions.double().numpy()
    dm = model.dipoles.moments.double().numpy()
    collection = magpylib.Collection([magpylib.misc.Dipole(position=p, moment=m) for p, m in zip(dp, dm)])
    # magpylib evaluates all (source, point) pairs at once; keep its temporaries bounded with chunks of points
    chunk = max(1, 2_000_000 // S)

    def mp_dipoles():
        return np.concatenate([collection.getB(pts64[i:i + chunk].numpy()) for i in range(0, a.points, chunk)])

    t_mp_dip = best_time(mp_dipoles, repeats)

    B = model.field(pts).double().numpy()
    B_exact = exact.getB(pts64.numpy())
    B_mp_dip = mp_dipoles()
    on75 = 0.075 * u[:200] / u[:200].norm(dim=-1, keepdim=True)
    B75 = model.field(on75.to(dtype)).double().numpy()
    B75_exact = exact.getB(on75.numpy())
    err75 = float((np.linalg.norm(B75 - B75_exact, axis=-1) / np.linalg.norm(B75_exact, axis=-1)).max())
    same_dipoles = float(np.abs(B - B_mp_dip).max() / np.abs(B_mp_dip).max())
    vs_exact = float((np.linalg.norm(B - B_exact, axis=-1) / np.linalg.norm(B_exact, axis=-1)).max())

    res = {
        "field_points_per_s": a.points / t_ours,
        "magpylib_cuboid_points_per_s": a.points / t_cuboid,
        "magpylib_dipoles_points_per_s": a.points / t_mp_dip,
        "speedup_vs_magpylib_dipoles": t_mp_dip / t_ours,
        "ratio_vs_magpylib_cuboid": t_cuboid / t_ours,
        "force_points_per_s": a.points / t_force,
        "cube_dipole_rel_err_75mm": err75,
        "max_rel_err_vs_exact_60_150mm": vs_exact,
        "max_rel_diff_vs_magpylib_dipoles": same_dipoles,
        "n_dipoles": S, "n_points": a.points, "dtype": a.dtype, "threads": a.threads, "device": "cpu",
        "torch": torch.__version__, "magpylib": magpylib.__version__, "args": asdict(a),
    }
    print(f"cube {EDGE * 1e3:.1f} mm, Br {BR} T as {S} dipoles; {a.points} points at 60-150 mm; "
          f"{a.dtype}, {a.threads} thread(s)")
    print(f"  ours field          {res['field_points_per_s']:12.4g} points/s")
    print(f"  magpylib dipoles    {res['magpylib_dipoles_points_per_s']:12.4g} points/s   "
          f"ours is {res['speedup_vs_magpylib_dipoles']:.1f}x (same dipoles, max rel diff {same_dipoles:.1e})")
    print(f"  magpylib cuboid     {res['magpylib_cuboid_points_per_s']:12.4g} points/s   "
          f"ours is {res['ratio_vs_magpylib_cuboid']:.2f}x (exact field; our max rel err {vs_exact:.1e})")
    print(f"  ours force+torque   {res['force_points_per_s']:12.4g} points/s")
    print(f"  dipole-grid rel err at 75 mm: {err75:.2e}")
    print(json_line(res, digits=17))
    return res


if __name__ == "__main__":
    main()
