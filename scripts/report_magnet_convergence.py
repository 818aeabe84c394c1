"""Convergence of permanent magnets as dipole grids: error against dipole count, distance and run time.

The 50.8 mm cube (Br 1.3 T, the Paper V block magnet) split into n^3 dipoles is compared with
magpylib's exact cuboid field (its gradient by 4th-order central differences of the exact field)
on 64 random directions at each distance from the centre. Writes docs/magnet_convergence.md
(atomically) and prints one JSON line last.

    python scripts/report_magnet_convergence.py [--quick] [--out docs/magnet_convergence.md]
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from cmlearn.args import bounded, writable
from cmlearn.io import write_text_atomic
from physics.magnetics import CuboidMagnet

EDGE, BR = 0.0508, 1.3


@dataclass
class Args:
    quick: bool = False
    out: str = "docs/magnet_convergence.md"
    threads: int = 1


def fd_gradient(getB, pts: np.ndarray, h: float) -> np.ndarray:
    G = np.zeros(pts.shape + (3,))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        G[..., j] = (-getB(pts + 2 * e) + 8 * getB(pts + e) - 8 * getB(pts - e) + getB(pts - 2 * e)) / (12 * h)
    return G


def study(counts, distances, n_dirs=64, timing_points=10_000):
    import magpylib

    exact = magpylib.magnet.Cuboid(dimension=(EDGE,) * 3, polarization=(0, 0, BR))
    cube = CuboidMagnet(dimensions=(EDGE,) * 3, polarization=(0.0, 0.0, BR))
    g = torch.Generator().manual_seed(0)
    u = torch.randn(n_dirs, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    refs = {}
    for r in distances:
        pts = (r * u).numpy()
        refs[r] = (exact.getB(pts), fd_gradient(exact.getB, pts, 1e-5))
    timing_pts = 0.1 * u.repeat(timing_points // n_dirs + 1, 1)[:timing_points]
    rows = []
    for n in counts:
        model = cube.field_model(n)
        row = {"requested": n, "dipoles": model.dipoles.count, "field_err": {}, "gradient_err": {}}
        for r in distances:
            B, G = model.field_and_gradient(r * u)
            B_ref, G_ref = refs[r]
            row["field_err"][r] = float((np.linalg.norm(B.numpy() - B_ref, axis=-1)
                                         / np.linalg.norm(B_ref, axis=-1)).max())
            row["gradient_err"][r] = float((np.linalg.norm((G.numpy() - G_ref).reshape(-1, 9), axis=-1)
                                            / np.linalg.norm(G_ref.reshape(-1, 9), axis=-1)).max())
        model.field(timing_pts)
        t0 = time.perf_counter()
        model.field(timing_pts)
        row["us_per_point"] = (time.perf_counter() - t0) / timing_points * 1e6
        rows.append(row)
    return rows


def to_markdown(rows, distances, cmd: str) -> str:
    head = " | ".join(f"{r * 1e3:.0f} mm" for r in distances)
    lines = [
        "# Permanent magnets as dipole grids: convergence",
        "",
        "50.8 mm cube, Br 1.3 T, as n^3 point dipoles at the cell centres, against the exact cuboid field",
        "(magpylib; its gradient by 4th-order central differences, h = 10 um). Maximum relative error over 64",
        "random directions at each distance from the centre (the cube's corners are at 44 mm). Time: one",
        "field evaluation per point, float64, 1 thread, 10,000 points.",
        "",
        f"Produced by `{cmd}`.",
        "",
        "## Field |B - B_exact| / |B_exact|",
        "",
        f"| dipoles | {head} | us / point |",
        "|---:|" + "---:|" * len(distances) + "---:|",
    ]
    for row in rows:
        errs = " | ".join(f"{row['field_err'][r]:.2e}" for r in distances)
        lines.append(f"| {row['dipoles']} | {errs} | {row['us_per_point']:.1f} |")
    lines += ["", "## Gradient |dB - dB_exact|_F / |dB_exact|_F", "", f"| dipoles | {head} |",
              "|---:|" + "---:|" * len(distances)]
    for row in rows:
        errs = " | ".join(f"{row['gradient_err'][r]:.2e}" for r in distances)
        lines.append(f"| {row['dipoles']} | {errs} |")
    lines += ["", "Halving the cell size (8x the dipoles) cuts the error about 16x: outside the magnet 1/r is harmonic,",
              "so the cell-centre (midpoint) rule over cubic cells has no h^2 term and converges like (h / r)^4.", ""]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=writable(), default=Args.out)
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    a = Args(**vars(ap.parse_args(argv)))
    torch.set_num_threads(a.threads)
    counts = (8, 125, 1728) if a.quick else (8, 64, 216, 512, 1000, 1728, 2000, 4096, 8000, 13824)
    distances = (0.05, 0.075, 0.15) if a.quick else (0.05, 0.06, 0.075, 0.1, 0.15, 0.25)
    rows = study(counts, distances, timing_points=1000 if a.quick else 10_000)
    cmd = "python scripts/report_magnet_convergence.py" + (" --quick" if a.quick else "")
    write_text_atomic(a.out, to_markdown(rows, distances, cmd))
    at75 = {row["dipoles"]: (row["field_err"][0.075], row["gradient_err"][0.075]) for row in rows}
    print(f"wrote {a.out}")
    for n, (eb, eg) in at75.items():
        print(f"  {n:6d} dipoles: field {eb:.2e}, gradient {eg:.2e} at 75 mm")
    print(json.dumps({"field_err_75mm": {str(n): v[0] for n, v in at75.items()},
                      "gradient_err_75mm": {str(n): v[1] for n, v in at75.items()}, "args": asdict(a)}))


if __name__ == "__main__":
    main()
