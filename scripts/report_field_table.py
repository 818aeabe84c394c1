"""The tabulated coil field against the exact one: error against grid, interpolation order and distance, and
the cost of each.

The default six-coil eMNS (:func:`physics.magnetics.emns.six_coil_emns`) tabulated over a ball
(:class:`physics.magnetics.field_table.CoilFieldTable`) is compared with the exact superposition of its loops
(:meth:`physics.magnetics.emns.EMNS.unit_field_and_gradient`) on spheres of random directions about the
centre, per coil (the worst relative error of the unit-current field and of its gradient), with the build
time and the eager time of a two-point field-and-gradient evaluation (the magnetic rod's closed loop) of
both. Writes docs/field_table.md (atomically) and prints one JSON line last.

    python scripts/report_field_table.py [--quick] [--out docs/field_table.md]
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass

import torch

from cmlearn.args import bounded, writable
from cmlearn.io import write_text_atomic
from physics.magnetics import CoilFieldTable, six_coil_emns


@dataclass
class Args:
    quick: bool = False
    out: str = "docs/field_table.md"
    threads: int = 1


def _per_call(fn, n: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def study(configs, radii, n_dirs: int, n_calls: int):
    emns = six_coil_emns()
    g = torch.Generator().manual_seed(0)
    u = torch.randn(n_dirs, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    refs = {r: emns.unit_field_and_gradient(r * u) for r in radii}
    I = torch.linspace(-3.0, 3.0, emns.n_coils, dtype=torch.float64)
    two = 0.02 * u[:2]
    exact_us = _per_call(lambda: emns.field_and_gradient(two, I), n_calls) * 1e6
    rows = []
    for radius, spacing, order in configs:
        t0 = time.perf_counter()
        table = CoilFieldTable.from_emns(emns, radius=radius, spacing=spacing, order=order)
        row = {"radius_m": radius, "spacing_m": spacing, "order": order, "build_s": time.perf_counter() - t0,
               "nodes": list(table.tables.shape[1:3]), "field_err": {}, "gradient_err": {}}
        for r in radii:
            if r > radius:
                continue
            B, dB = refs[r]
            Bt, dBt = table.unit_field_and_gradient(r * u)
            row["field_err"][r] = float(((Bt - B).norm(dim=-1) / B.norm(dim=-1)).max())
            row["gradient_err"][r] = float(((dBt - dB).flatten(-2).norm(dim=-1) / dB.flatten(-2).norm(dim=-1)).max())
        row["us_two_points"] = _per_call(lambda: table.field_and_gradient(two, I), n_calls) * 1e6
        rows.append(row)
    return rows, exact_us


def to_markdown(rows, radii, exact_us: float, n_dirs: int, cmd: str) -> str:
    head = " | ".join(f"{r * 1e3:g} mm" for r in radii)
    lines = [
        "# The coil field tabulated: error and cost",
        "",
        "The default six-coil eMNS's unit-current field and gradient, tabulated per coil in its (z, rho) plane",
        "(`physics.magnetics.field_table.CoilFieldTable`) and interpolated by tensor-product Lagrange polynomials,",
        f"against the exact superposition of its 144 loops at {n_dirs} random directions on each sphere about the",
        "workspace's centre (the coils' faces are 65 mm away): the worst relative error over directions and",
        "coils, field / gradient. Eager time of one field-and-gradient evaluation at two points for given",
        f"currents (the magnetic rod's closed loop): exact {exact_us:.0f} us.",
        "",
        f"| ball, grid, order | build | nodes (z x rho) | {head} | two points |",
        "|---|---|---|" + "---|" * len(radii) + "---|",
    ]
    for row in rows:
        errs = " | ".join(f"{row['field_err'][r]:.1e} / {row['gradient_err'][r]:.1e}" if r in row["field_err"]
                          else "" for r in radii)
        lines.append(f"| {row['radius_m'] * 1e3:g} mm, {row['spacing_m'] * 1e3:g} mm, {row['order']} | "
                     f"{row['build_s']:.2f} s | {row['nodes'][0]} x {row['nodes'][1]} | {errs} | "
                     f"{row['us_two_points']:.0f} us |")
    lines += ["", "The magnetic rod's real-time closed loop uses 60 mm, 1 mm, order 6"
              " (`cmlearn.surrogate.magnetic.field_table`).", "", f"`{cmd}`", ""]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=writable(), default="docs/field_table.md")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1)
    a = Args(**vars(ap.parse_args(argv)))
    torch.set_num_threads(a.threads)
    if a.quick:
        configs, radii, n_dirs, n_calls = [(0.06, 2e-3, 4), (0.06, 2e-3, 6)], (0.03, 0.06), 200, 5
    else:
        configs = [(0.05, 1e-3, 4), (0.05, 1e-3, 6), (0.06, 1e-3, 6), (0.06, 5e-4, 6)]
        radii, n_dirs, n_calls = (0.03, 0.05, 0.055, 0.06), 20_000, 200
    rows, exact_us = study(configs, radii, n_dirs, n_calls)
    cmd = "python scripts/report_field_table.py" + (" --quick" if a.quick else "")
    write_text_atomic(a.out, to_markdown(rows, radii, exact_us, n_dirs, cmd))
    res = {"rows": rows, "exact_us_two_points": exact_us, "n_dirs": n_dirs, "out": a.out, "args": asdict(a)}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
