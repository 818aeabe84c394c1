"""Static equilibrium of the discrete rod under conservative loads, by energy minimisation.

Used to start scenes from rest in equilibrium (e.g. a rod sagging under gravity in a magnetic
field before the field starts to move). The total potential of the discrete model,

    V(p, R) = elastic_energy(p, R) - sum_a m_a g . p_a - sum_k m_k(R) . B,

(uniform field ``B``: the magnets' force vanishes and their torque ``m x B`` derives from
``-m . B``) is minimised over the free nodes' positions and rotations ``R_a exp(w_a^)`` with a
trust-region Newton method (exact Hessian from ``torch.func``), re-centring the rotations between
rounds. The result is an equilibrium of exactly the forces the LGVI applies, so a scene started
there stays at rest up to the solver tolerance.
"""
from __future__ import annotations

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

from .elastic import elastic_energy, relative_cayley
from .errors import SolverError
from .lie import so3_exp
from .loads import magnet_poses
from .rod import Rod

__all__ = ["static_equilibrium"]


def static_equilibrium(rod: Rod, p0: Tensor, R0: Tensor, *, fixed=(0,), gravity=None, field=None,
                       gtol: float = 1e-9, rounds: int = 4) -> tuple[Tensor, Tensor]:
    """Minimum-potential configuration near ``(p0, R0)`` (float64 (n, 3), (n, 3, 3)).

    ``fixed`` node indices keep their pose; ``gravity`` (3,) m/s^2; ``field`` a uniform field (3,)
    in tesla acting on the rod's magnets. ``gtol`` bounds the gradient, relative to the rod's
    bending scale ``E I / L``. Raises :class:`~physics.errors.SolverError` if it does not converge.
    """
    prm = rod.params(torch.float64)
    n = rod.n_nodes
    free = torch.tensor([i for i in range(n) if i not in set(fixed)], dtype=torch.long)
    k = len(free)
    lchar = min(rod.lengths)
    scale = min(rod.C2) / rod.length  # energy scale (J per rad^2)
    g = None if gravity is None else torch.as_tensor(gravity, dtype=torch.float64)
    B = None if field is None else torch.as_tensor(field, dtype=torch.float64)
    use_field = B is not None and len(rod.magnets) > 0
    p_c, R_c = p0.to(torch.float64).clone(), R0.to(torch.float64).clone()

    def potential(x: Tensor) -> Tensor:
        dp, w = x[: 3 * k].reshape(k, 3), x[3 * k:].reshape(k, 3)
        p = p_c.index_add(0, free, lchar * dp)
        Rf = R_c[free] @ so3_exp(w)
        R = R_c.index_copy(0, free, Rf)
        V = elastic_energy(p, R, prm)
        if g is not None:
            V = V - (prm.mass[:, None] * g * p).sum()
        if use_field:
            _, _, mom = magnet_poses(p, R, relative_cayley(R, check=False), prm)
            V = V - (mom * B).sum()
        return V / scale

    grad_fn = torch.func.grad(potential)
    hess_fn = torch.func.hessian(potential)

    def fun(x):
        return float(potential(torch.from_numpy(x)))

    def jac(x):
        return grad_fn(torch.from_numpy(x)).numpy()

    def hess(x):
        return hess_fn(torch.from_numpy(x)).numpy()

    def recentre(x: Tensor):
        nonlocal p_c, R_c
        p_c = p_c.index_add(0, free, lchar * x[: 3 * k].reshape(k, 3))
        R_c = R_c.index_copy(0, free, R_c[free] @ so3_exp(x[3 * k:].reshape(k, 3)))

    zero = np.zeros(6 * k)
    gnorm = np.inf
    for _ in range(rounds):
        # globalised Newton (trust region) to get close, then plain Newton steps on the gradient,
        # which keep converging after the energy itself has hit round-off
        res = scipy.optimize.minimize(fun, zero, jac=jac, hess=hess, method="trust-exact",
                                      options={"gtol": gtol, "maxiter": 200})
        recentre(torch.from_numpy(res.x))
        for _ in range(8):
            gr = jac(zero)
            gnorm = float(np.abs(gr).max())
            if gnorm <= gtol:
                return p_c, R_c
            step = np.linalg.solve(hess(zero), -gr)
            if np.abs(step).max() > 0.1:  # not in the Newton basin yet: back to the trust region
                break
            recentre(torch.from_numpy(step))
    raise SolverError(f"static_equilibrium did not converge (max |gradient| {gnorm:.2e} > {gtol:.1e} "
                      f"in units of E I / L)")
