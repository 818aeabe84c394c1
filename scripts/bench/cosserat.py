"""Benchmark: the static Cosserat shooting solver against a scipy shooting peer, in the same process.

Problem: the Paper II magnetic rod (physics.scenes_cosserat.paper2_magnetic_rod: 50 mm PMC-770 body,
N42 and N45 magnet blocks, 13 nodes = 12 RK4 steps), hanging under gravity in an eMNS-like linear
field B(x) = B0 + G x (B0 = (4, 1.5, 0) mT, G = diag(20, -10, -10) mT/m): the magnets' wrenches
depend on the solved pose. Solved (a) warm-started from the solution at a neighbouring load (B0
1 % weaker), (b) cold (from the unloaded rod), (c) a batch of ``--batch`` different fields (B0 times
1-1.3, random in-plane turn of up to 30 deg), warm-started from their neighbours' solutions and cold.

Peer: the same model (equations, grid, magnets, scaling) as numpy fixed-step RK4 and
``scipy.optimize.least_squares(method='lm')`` (MINPACK, finite-difference Jacobian), written here.

Where the time goes (compiled path, 1 thread, float64; see physics.cosserat_fast). A warm solve is 3 LM
iterations = 4 shots. At batch 1 each LM iteration (the 12 RK4 steps with six tangent lanes, the two
magnet wrenches, the update) is one compiled program: about 180 us of kernel and a few us of call,
plus about 100 us of Python per solve (loads, tables, the loop), i.e. about 0.8 ms a solve. With one
program per step (52 calls of 7-36 us of kernel plus 5-10 us of call each) and the loads rebuilt on
every solve, the same solve took 1.3-1.7 ms. At batch 1024 each step is its own program vectorised
over the problems (a fused shot compiled for more than ten minutes).

Prints human-readable lines and, last, one JSON line. ``--quick`` shortens the timing windows and
the peer's batch check; ``--no-compile`` times the eager path only (a first compile takes about a
minute here, reported as ``compile_s`` and excluded from the steady-state figures).
"""
from __future__ import annotations

import argparse
import math
import platform
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import torch

from cmlearn.args import bounded
from cmlearn.eval.timing import json_line
from physics.cosserat_shooting import CosseratSolver
from physics.scenes_cosserat import LinearField, paper2_magnetic_rod

B0 = (4e-3, 1.5e-3, 0.0)
GRAD = (20e-3, -10e-3, -10e-3)


@dataclass
class Args:
    quick: bool = False
    threads: int = 1
    batch: int = 1024
    compile: bool = True
    dtype: str = "float64"
    window: float | None = None


def timeit(fn, min_time: float, min_reps: int = 3) -> float:
    """Seconds per call of ``fn`` (after one untimed call)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        el = time.perf_counter() - t0
        if el >= min_time and n >= min_reps:
            return el / n


class ScipyShooting:
    """The peer: the same discrete model in numpy (RK4 on the rod's grid, quaternion renormalisation,
    magnet wrenches of the linear field at the node poses, gravity), LM from scipy."""

    def __init__(self, scene, B, G):
        rod, self.grid = scene.rod, scene.rod.grid
        prm = rod.params(torch.float64)
        self.ks, self.kb = prm.ks_inv.numpy(), prm.kb_inv.numpy()
        self.vh, self.uh, self.rho = prm.v_hat.numpy(), prm.u_hat.numpy(), prm.line_density.numpy()
        self.g, self.q0 = np.array(scene.gravity), np.array(scene.base_quaternion)
        self.B, self.G = np.asarray(B, float), np.asarray(G, float)
        self.mags = {j: (np.array(m.moment), m.mass) for j, m in zip(self.grid.magnet_nodes, rod.magnets)}
        L, EI = rod.length, rod.bending_scale
        self.sc = np.array([EI / L**2] * 3 + [EI / L] * 3)
        self.shots = 0

    @staticmethod
    def _R(q):
        w, x, y, z = q
        return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])

    def _rhs(self, y, k, f):
        q, n, m = y[3:7], y[7:10], y[10:13]
        R = self._R(q)
        v = self.ks[k] * (R.T @ n) + self.vh[k]
        u = self.kb[k] * (R.T @ m) + self.uh[k]
        p = R @ v
        w, x, yq, z = q
        dq = 0.5 * np.array([-(x * u[0] + yq * u[1] + z * u[2]), w * u[0] + yq * u[2] - z * u[1],
                             w * u[1] + z * u[0] - x * u[2], w * u[2] + x * u[1] - yq * u[0]])
        dm = -np.array([p[1] * n[2] - p[2] * n[1], p[2] * n[0] - p[0] * n[2], p[0] * n[1] - p[1] * n[0]])
        return np.concatenate((p, dq, -f, dm))

    def _jump(self, y, node):
        if node in self.mags:
            mub, mass = self.mags[node]
            mu = self._R(y[3:7]) @ mub
            Bp = self.B + self.G @ y[:3]
            F = self.G.T @ mu + mass * self.g
            T = np.array([mu[1] * Bp[2] - mu[2] * Bp[1], mu[2] * Bp[0] - mu[0] * Bp[2], mu[0] * Bp[1] - mu[1] * Bp[0]])
            y = y.copy()
            y[7:10] -= F
            y[10:13] -= T
        return y

    def shoot(self, x, record=False):
        self.shots += 1
        y = np.concatenate((np.zeros(3), self.q0, x * self.sc))
        ys = [y]
        for k, h in enumerate(self.grid.h):
            f = self.rho[k] * self.g
            k1 = self._rhs(y, k, f)
            k2 = self._rhs(y + h / 2 * k1, k, f)
            k3 = self._rhs(y + h / 2 * k2, k, f)
            k4 = self._rhs(y + h * k3, k, f)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            y[3:7] /= np.linalg.norm(y[3:7])
            y = self._jump(y, k + 1)
            ys.append(y)
        return np.array(ys) if record else y[7:13] / self.sc

    def solve(self, x0, tol: float):
        """LM from ``x0`` until the scaled tip residual's norm is at most ``tol`` (our solver's stopping rule; MINPACK's
        own tests, on relative changes, would go on for another Jacobian and trial steps); returns the solution and the
        number of shots (finite-difference Jacobian included)."""
        n0 = self.shots

        def residual(x):
            r = self.shoot(x)
            if np.linalg.norm(r) <= tol:
                raise _Converged(x.copy())
            return r
        try:
            x = scipy.optimize.least_squares(residual, x0, method="lm", xtol=1e-13, ftol=1e-13, gtol=1e-13).x
        except _Converged as done:
            x = done.args[0]
        return x, self.shots - n0


class _Converged(Exception):
    """Raised from inside MINPACK's loop with the first point that meets the tolerance."""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short timing windows")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=Args.threads)
    ap.add_argument("--batch", type=bounded(int, at_least=1), default=Args.batch)
    ap.add_argument("--no-compile", dest="compile", action="store_false")
    ap.add_argument("--dtype", choices=("float64", "float32"), default=Args.dtype)
    ap.add_argument("--window", type=bounded(float, above=0), default=None,
                    help="seconds per timing (default 0.5 quick, 2 full)")
    args = Args(**vars(ap.parse_args(argv)))
    torch.set_num_threads(args.threads)
    window = args.window or (0.5 if args.quick else 2.0)
    dtype = getattr(torch, args.dtype)
    sc = paper2_magnetic_rod()
    kw = dict(dtype=dtype)
    G = torch.diag(torch.tensor(GRAD, **kw))
    Bv = torch.tensor(B0, **kw)
    out = {"problem": "paper2_magnetic_rod in a linear field", "n_nodes": len(sc.rod.grid.s), "rk4_steps": len(sc.rod.grid.h),
           "dtype": args.dtype, "threads": torch.get_num_threads(), "device": "cpu", "batch": args.batch,
           "torch": torch.__version__, "cpu": platform.processor() or platform.machine()}
    gen = torch.Generator().manual_seed(0)
    scale = 1 + 0.3 * torch.rand(args.batch, 1, generator=gen, dtype=dtype)
    turn = math.radians(30) * (2 * torch.rand(args.batch, generator=gen, dtype=dtype) - 1)
    Bb = torch.stack((Bv[0] * torch.cos(turn) - Bv[1] * torch.sin(turn),
                      Bv[0] * torch.sin(turn) + Bv[1] * torch.cos(turn), torch.zeros_like(turn)), -1) * scale
    fields = {"near": LinearField(Bv * 0.99, G), "target": LinearField(Bv, G),
              "b_near": LinearField(Bb * 0.99, G), "b_target": LinearField(Bb, G)}

    def solvers(compile_: bool):
        s = CosseratSolver(sc.rod, dtype=dtype, compile=compile_)
        near = sc.solve(s, field=fields["near"])
        b_near = sc.solve(s, field=fields["b_near"])
        return s, near, b_near

    def measure(tag: str, compile_: bool):
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c0 = time.perf_counter()
            s, near, b_near = solvers(compile_)
            setup = time.perf_counter() - c0
            warm = sc.solve(s, field=fields["target"], init=near)
            cold = sc.solve(s, field=fields["target"])
            t_warm = timeit(lambda: sc.solve(s, field=fields["target"], init=near), window)
            t_cold = timeit(lambda: sc.solve(s, field=fields["target"]), window)
            bw = sc.solve(s, field=fields["b_target"], init=b_near)
            t_bw = timeit(lambda: sc.solve(s, field=fields["b_target"], init=b_near), window, 1)
            t_bc = timeit(lambda: sc.solve(s, field=fields["b_target"]), window, 1)
        res = {f"single_warm_hz{tag}": 1 / t_warm, f"single_cold_hz{tag}": 1 / t_cold,
               f"batched_solves_per_s{tag}": args.batch / t_bw, f"batched_cold_solves_per_s{tag}": args.batch / t_bc,
               f"setup_s{tag}": setup}
        print(f"torch{tag or ' compiled'}: warm {t_warm * 1e3:.2f} ms ({1 / t_warm:.0f} Hz, {int(warm.iterations)} LM it), "
              f"cold {t_cold * 1e3:.2f} ms ({1 / t_cold:.0f} Hz, {int(cold.iterations)} it); batch {args.batch}: warm "
              f"{args.batch / t_bw:.0f} solves/s (max {int(bw.iterations.max())} it), cold {args.batch / t_bc:.0f} solves/s; "
              f"setup (incl. compile) {setup:.1f} s")
        return res, warm, cold, bw

    eager, warm_e, cold_e, bw_e = measure("_eager", False)
    out.update(eager)
    out["iterations_warm"], out["iterations_cold"] = int(warm_e.iterations), int(cold_e.iterations)
    warm, bw = warm_e, bw_e
    if args.compile:
        comp, warm, cold, bw = measure("", True)
        out["compile_s"] = comp.pop("setup_s") - eager["setup_s_eager"]
        out.update(comp)
        out["compiled_vs_eager_max_abs_m"] = float((warm.p - warm_e.p).abs().max())
    else:
        out.update({k.replace("_eager", ""): v for k, v in eager.items() if not k.startswith("setup")})
    out["compiled"] = bool(args.compile)
    out["tol"] = tol = CosseratSolver(sc.rod, dtype=dtype).tol
    out["scipy_dtype"] = "float64"  # the peer in float64 whatever --dtype, stopped at our tolerance

    # --- the scipy peer on the same problems
    np.seterr(over="ignore", invalid="ignore")  # LM's trial steps may overflow; MINPACK rejects them
    peer = ScipyShooting(sc, B0, np.diag(GRAD))
    peer_near = ScipyShooting(sc, np.array(B0) * 0.99, np.diag(GRAD))
    x_near, _ = peer_near.solve(np.zeros(6), tol)
    x_w, nfev_w = peer.solve(x_near, tol)
    x_c, nfev_c = peer.solve(np.zeros(6), tol)
    t_sw = timeit(lambda: peer.solve(x_near, tol), window, 2)
    t_sc = timeit(lambda: peer.solve(np.zeros(6), tol), window, 2)
    out["scipy_warm_hz"], out["scipy_cold_hz"] = 1 / t_sw, 1 / t_sc
    out["scipy_shots_warm"], out["scipy_shots_cold"] = int(nfev_w), int(nfev_c)
    tips = [np.abs(peer.shoot(x_w, True)[-1, :3] - warm.tip_position.double().numpy()).max(),
            np.abs(peer.shoot(x_c, True)[-1, :3] - warm.tip_position.double().numpy()).max()]
    n_chk = 4 if args.quick else 16
    for i in range(min(n_chk, args.batch)):
        pi = ScipyShooting(sc, Bb[i].double().numpy(), np.diag(GRAD))
        xi, _ = pi.solve(np.zeros(6), tol)
        tips.append(np.abs(pi.shoot(xi, True)[-1, :3] - bw.tip_position[i].double().numpy()).max())
    out["max_tip_diff_vs_scipy_m"] = float(max(tips))
    out["speedup_vs_scipy_warm"] = out["single_warm_hz"] / out["scipy_warm_hz"]
    out["speedup_vs_scipy_cold"] = out["single_cold_hz"] / out["scipy_cold_hz"]
    out["batched_speedup_vs_scipy_warm"] = out["batched_solves_per_s"] / out["scipy_warm_hz"]
    print(f"scipy peer (numpy RK4 + least_squares lm): warm {t_sw * 1e3:.1f} ms ({1 / t_sw:.1f} Hz, {nfev_w} shots), "
          f"cold {t_sc * 1e3:.1f} ms ({1 / t_sc:.1f} Hz, {nfev_c} shots)")
    print(f"speed-up vs scipy: warm {out['speedup_vs_scipy_warm']:.1f}x, cold {out['speedup_vs_scipy_cold']:.1f}x, "
          f"batched {out['batched_speedup_vs_scipy_warm']:.0f}x; tips agree to {out['max_tip_diff_vs_scipy_m']:.1e} m "
          f"({1 + min(n_chk, args.batch)} problems); thesis (Fig. II.13): 8.33-50 Hz")
    print(json_line(out))
    return out


if __name__ == "__main__":
    main()
