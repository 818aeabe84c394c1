"""Static equilibrium of the discrete rod under gravity and a uniform magnetic field.

Used to start scenes at rest in equilibrium (e.g. a rod sagging under gravity in a field before
the field starts to move). Two stages, both over the free nodes' positions and rotations
``R_a exp(w_a^)``:

1. minimise the potential ``V = elastic - sum_a m_a g . p_a - sum_k m_k(R) . B`` with a
   trust-region Newton method (exact Hessian from ``torch.func``), re-centring between rounds;
2. Newton's method on the residual the LGVI itself applies at rest — elastic forces/torques
   (:func:`physics.elastic.internal_loads`), gravity and the magnets' torques as shared between
   nodes by :func:`physics.loads.magnet_node_loads` (for a magnet inside an element that split is
   not exactly the gradient of ``-m . B``, so stage 1 alone leaves a small residual).

A scene started at the result stays at rest up to round-off.
"""
from __future__ import annotations

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

from .checks import check_rotations, is_finite_real, is_int
from .elastic import elastic_energy, internal_loads, relative_cayley
from .errors import SolverError
from .lie import so3_exp
from .loads import UniformField, magnet_node_loads, magnet_poses
from .rod import Rod

__all__ = ["static_equilibrium"]


def _check_inputs(n: int, p0, R0, gravity, field, tol, rounds) -> None:
    """ValueError naming the first argument of :func:`static_equilibrium` that cannot be solved for."""
    def bad(name, msg):
        raise ValueError(f"static_equilibrium: {name} must be {msg}")
    if not torch.is_tensor(p0) or p0.shape != (n, 3) or not bool(torch.isfinite(p0).all()):
        bad("p0", f"finite node positions ({n}, 3) for this rod, got "
                  f"{tuple(p0.shape) if torch.is_tensor(p0) else type(p0).__name__}")
    if not torch.is_tensor(R0) or R0.shape != (n, 3, 3) or not bool(torch.isfinite(R0).all()):
        bad("R0", f"finite node rotations ({n}, 3, 3) for this rod, got "
                  f"{tuple(R0.shape) if torch.is_tensor(R0) else type(R0).__name__}")
    check_rotations("static_equilibrium: R0", R0)
    for name, x, unit in (("gravity", gravity, "m/s^2"), ("field", field, "T")):
        if x is not None:
            x = torch.as_tensor(x, dtype=torch.float64)
            if x.shape != (3,) or not bool(torch.isfinite(x).all()):
                bad(name, f"a finite 3-vector ({unit}), got {x.tolist()}")
    if not (is_finite_real(tol) and tol > 0):
        bad("tol", f"a finite number > 0, got {tol!r}")
    if not is_int(rounds) or rounds < 1:
        bad("rounds", f"an integer >= 1, got {rounds!r}")


def static_equilibrium(rod: Rod, p0: Tensor, R0: Tensor, *, fixed=(0,), gravity=None, field=None,
                       tol: float = 1e-10, rounds: int = 4) -> tuple[Tensor, Tensor]:
    """Equilibrium configuration near ``(p0, R0)`` (float64 (n, 3), (n, 3, 3)).

    ``fixed`` node indices (negative ones from the tip) keep their pose; ``gravity`` (3,) m/s^2;
    ``field`` a uniform field (3,) in tesla acting on the rod's magnets. ``tol`` bounds the residual node forces and torques,
    relative to ``E I / (L l_min)`` and ``E I / L`` (``l_min`` the shortest element: a node's force
    grows with its elements' length). Raises :class:`~physics.errors.SolverError` if it
    does not converge.
    """
    prm = rod.params(torch.float64)
    n = rod.n_nodes
    _check_inputs(n, p0, R0, gravity, field, tol, rounds)
    fixed = tuple(fixed)
    if not all(is_int(i) or torch.is_tensor(i) and i.numel() == 1
               and not i.is_floating_point() and i.dtype != torch.bool for i in fixed):  # 1.7 fixed node 1, silently
        raise ValueError(f"static_equilibrium: fixed must hold integer node indices, got {fixed}")
    fixed = tuple(int(i) for i in fixed)
    if not all(-n <= i < n for i in fixed):
        raise ValueError(f"static_equilibrium: fixed node indices must lie in [-{n}, {n - 1}], got {fixed}")
    fixed = {i % n for i in fixed}  # negative indices count from the tip, as in Python
    if len(fixed) == n:
        raise ValueError(f"static_equilibrium: fixed holds every node of this {n}-node rod: no free node to solve for")
    if not fixed and gravity is not None and any(float(x) != 0 for x in gravity):
        raise ValueError("static_equilibrium: a rod with no fixed node under gravity has no equilibrium (it falls); "
                         "fix a node, e.g. fixed=(0,)")
    free = torch.tensor([i for i in range(n) if i not in fixed], dtype=torch.long)
    k = len(free)
    lchar, L = min(rod.lengths), rod.length
    EI = min(rod.C2[:2])
    scale = EI / L  # energy / torque scale
    g = None if gravity is None else torch.as_tensor(gravity, dtype=torch.float64)
    B = None if field is None else torch.as_tensor(field, dtype=torch.float64)
    use_field = B is not None and len(rod.magnets) > 0
    uniform = UniformField(B) if use_field else None
    state = {"p": p0.to(torch.float64).clone(), "R": R0.to(torch.float64).clone()}

    def pose(x: Tensor):
        p_c, R_c = state["p"], state["R"]
        p = p_c.index_add(0, free, lchar * x[: 3 * k].reshape(k, 3))
        R = R_c.index_copy(0, free, R_c[free] @ so3_exp(x[3 * k:].reshape(k, 3)))
        return p, R

    def recentre(x: Tensor):
        state["p"], state["R"] = pose(x)

    def potential(x: Tensor) -> Tensor:
        p, R = pose(x)
        V = elastic_energy(p, R, prm)
        if g is not None:
            V = V - (prm.mass[:, None] * g * p).sum()
        if use_field:
            _, _, mom = magnet_poses(p, R, relative_cayley(R, check=False), prm)
            V = V - (mom * B).sum()
        return V / scale

    def residual(x: Tensor) -> Tensor:
        """Scaled node forces (world) and torques (body) on the free nodes, as the LGVI applies them."""
        p, R = pose(x)
        psi = relative_cayley(R, check=False)
        f, tau = internal_loads(p, R, prm, psi)
        if g is not None:
            f = f + prm.mass[:, None] * g
        if use_field:
            fm, tm = magnet_node_loads(uniform, 0.0, p, R, psi, prm)
            f, tau = f + fm, tau + tm
        return torch.cat(((f[free] * (L * lchar / EI)).reshape(-1), (tau[free] / scale).reshape(-1)))

    zero_t = torch.zeros(6 * k, dtype=torch.float64)
    zero = zero_t.numpy()
    grad_fn, hess_fn = torch.func.grad(potential), torch.func.hessian(potential)
    jac_fn = torch.func.jacfwd(residual)

    def fun(x):
        return float(potential(torch.from_numpy(x)))

    def jac(x):
        return grad_fn(torch.from_numpy(x)).numpy()

    def hess(x):
        return hess_fn(torch.from_numpy(x)).numpy()

    rnorm = np.inf
    for _ in range(rounds):
        res = scipy.optimize.minimize(fun, zero, jac=jac, hess=hess, method="trust-exact",
                                      options={"gtol": tol, "maxiter": 200})
        recentre(torch.from_numpy(res.x))
        for _ in range(10):  # Newton on the LGVI residual; keeps converging after V hits round-off
            r = residual(zero_t)
            rnorm = float(r.abs().max())
            if rnorm <= tol:
                return state["p"], state["R"]
            step = torch.linalg.solve(jac_fn(zero_t), -r)
            if float(step.abs().max()) > 0.1:  # not in the Newton basin: back to the trust region
                break
            recentre(step)
    raise SolverError(f"static_equilibrium did not converge (max residual {rnorm:.2e} > {tol:.1e} in units "
                      f"of E I / (L l_min) and E I / L)")
