"""Inverse problems on the static Cosserat rod, by gradient-based optimisation through the implicit
gradients of :class:`~physics.cosserat_shooting.CosseratSolver`.

Example: the uniform field that turns a tip-magnet rod's tip to a target angle::

    rod = CosseratRod.uniform(0.05, CircularSection(1e-3), Material(E=2e6, density=1100.0, nu=0.5),
                              magnets=(MagnetDipole(0.05, (0.0, 0.0, 5e-3)),))
    fit = fit_uniform_field(CosseratSolver(rod), math.radians(45))
    fit.field, math.degrees(fit.tip_angle)   # |B| ~ E I theta / (L |mu|) across the tip; 45.0
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .checks import check_integer, is_int, positive, real
from .cosserat_shooting import CosseratSolver, StaticSolution
from .loads import UniformField

__all__ = ["FieldFit", "fit_uniform_field", "tip_angle"]


def tip_angle(sol: StaticSolution, plane: tuple[int, int] = (0, 2)) -> Tensor:
    """Angle (rad) of the tip tangent (body E3 of the tip) in the world plane ``plane`` = (a, b),
    measured from axis b towards axis a (default: in the x-z plane from +z towards +x)."""
    axes = isinstance(plane, (tuple, list)) and len(plane) == 2 and all(
        is_int(a) and -3 <= a <= 2 for a in plane)
    if not (axes and plane[0] % 3 != plane[1] % 3):  # (0, 0) gave 45 deg whatever the shape, (0, 3) an IndexError
        raise ValueError(f"plane must be two different world axes (a, b) out of 0, 1, 2 (x, y, z), got {plane!r}")
    t = sol.R[..., -1, :, 2]
    return torch.atan2(t[..., plane[0]], t[..., plane[1]])


class FieldFit(NamedTuple):
    """Result of :func:`fit_uniform_field`: the field (3,) T, the tip angle reached (rad), the final
    solution, the number of solves, the final loss, and whether the target was reached (the angle within the
    fit's ``angle_tol``, its final solve converged)."""

    field: Tensor
    tip_angle: float
    solution: StaticSolution
    evaluations: int
    loss: float
    reached: bool


def fit_uniform_field(solver: CosseratSolver, target_angle: float, *, magnitude: float | None = None,
                      field_angle: float | None = None, reg: float = 1e-4, max_evals: int = 40,
                      angle_tol: float = math.radians(0.5), **solve_kw) -> FieldFit:
    """Find a uniform field ``B = b (sin phi, 0, cos phi)`` (in the x-z plane) that turns the tip of
    ``solver``'s rod (base along +z) to ``target_angle`` (rad, from +z towards +x), by L-BFGS on
    ``((theta - target)/1 deg)^2 + reg (b/b_ref)^2`` with implicit gradients (module docstring). The
    small penalty picks, among the fields that reach the angle, nearly the weakest one (for a single
    tip magnet: across the tip, ``b = E I theta / (L |mu|)``). ``magnitude`` (T) is ``b_ref`` and the
    start (default that estimate from the tip-most magnet), ``field_angle`` the start's ``phi``
    (default ``target + 90 deg``); ``solve_kw`` go to :meth:`CosseratSolver.solve` (gravity, loads,
    ...). Each evaluation is warm-started from the previous solution. ``reached`` says whether the returned field
    turns the tip to within ``angle_tol`` (rad) of the target: a fit can end elsewhere (a target beyond what the
    rod's branch from its start reaches) and then says so rather than raise."""
    if not isinstance(solver, CosseratSolver):
        raise TypeError(f"solver must be a CosseratSolver, got {type(solver).__name__}")
    rod = solver.rod
    if not rod.magnets:
        raise ValueError("fit_uniform_field: the rod has no magnets")
    if not math.isfinite(target_angle) or abs(target_angle) >= math.pi:
        raise ValueError(f"target_angle must be finite and in (-pi, pi), got {target_angle!r}")
    if magnitude is not None and not (math.isfinite(magnitude) and magnitude > 0):
        raise ValueError(f"magnitude (the start's field strength, T) must be finite and > 0, got {magnitude!r}")
    check_integer("max_evals", max_evals)
    # a negative reg rewarded a stronger field (loss -1), a NaN angle_tol reached nothing
    if real("reg", reg) < 0:
        raise ValueError(f"reg must be finite and >= 0, got {reg!r}")
    positive("angle_tol", angle_tol)
    if field_angle is not None:
        real("field_angle", field_angle)
    kw = dict(dtype=solver.dtype, device=solver.device)
    if magnitude is None:  # the estimate from the tip-most magnet (the magnets need not be listed base to tip)
        mu = math.sqrt(sum(c * c for c in max(reversed(rod.magnets), key=lambda m: m.s).moment))
        if mu == 0:
            raise ValueError("fit_uniform_field: the rod's tip-most magnet has a zero moment, so there is no estimate "
                             "of the field strength: give magnitude= (the start's field strength, T)")
    b_ref = magnitude if magnitude is not None else max(rod.bending_scale * abs(target_angle) / (rod.length * mu), 1e-6)
    sgn = 1.0 if target_angle >= 0 else -1.0
    phi0 = target_angle + sgn * math.pi / 2 if field_angle is None else float(field_angle)
    u = torch.tensor([1.0, phi0], **kw, requires_grad=True)
    state = {"init": solve_kw.pop("init", None), "n": 0, "sol": None}
    deg = math.radians(1.0)

    def field_of(u):
        return b_ref * u[0] * torch.stack((torch.sin(u[1]), torch.zeros_like(u[1]), torch.cos(u[1])))

    def closure():
        opt.zero_grad()
        sol = solver.solve(field=UniformField(field_of(u)), init=state["init"], differentiable=True, **solve_kw)
        if sol.residual.numel() != 1:  # (the loss below is one number; a batch failed in backward())
            raise ValueError(f"fit_uniform_field fits one problem, but the loads, parameters or init of solve_kw "
                             f"make a batch of shape {tuple(sol.residual.shape)}")
        state["init"], state["sol"], state["n"] = sol, sol, state["n"] + 1
        loss = ((tip_angle(sol) - target_angle) / deg) ** 2 + reg * u[0] ** 2
        loss.backward()
        return loss

    opt = torch.optim.LBFGS([u], lr=1.0, max_iter=max_evals, max_eval=max_evals, tolerance_grad=1e-9,
                            tolerance_change=1e-12, line_search_fn="strong_wolfe")
    opt.step(closure)
    with torch.no_grad():
        B = field_of(u).detach()
        sol = solver.solve(field=UniformField(B), init=state["init"], **solve_kw)
        th = float(tip_angle(sol))
        loss = ((th - target_angle) / deg) ** 2 + reg * float(u[0]) ** 2
    reached = abs(th - target_angle) <= angle_tol and bool(sol.converged.all())
    return FieldFit(B, th, sol, state["n"] + 1, loss, reached)
