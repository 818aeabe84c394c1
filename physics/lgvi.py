"""Lie group variational integrator for forced Cosserat rods (Paper I), batched and differentiable.

Derivation (from the discrete Lagrangian (I.5)-(I.7) and the discrete Lagrange-d'Alembert
principle (I.8), not transcribed from the printed (I.10)-(I.16)). With node masses ``m_a``,
node inertia ``J_a`` (and ``J_d = tr(J)/2 - J``), ``F^j = R^j^T R^{j+1}`` and the discrete action
``sum_j [ sum_a m_a |p^{j+1}-p^j|^2/(2h) + tr((I - F^j) J_d)/h - h V(q^j) ]`` plus forcing:

* variations of ``p_a^j`` give Stormer-Verlet (the printed ``+2p^j + p^{j-1}`` is a typo):
  ``v^{j+1/2} = v^{j-1/2} + h f^j / m``,  ``p^{j+1} = p^j + h v^{j+1/2}``;
* variations ``R_a^j -> R_a^j exp(eta^)`` give, with ``h pi^j = (J_d F^{j-1} - F^{j-1 T} J_d)^vee``,
  ``(F^j J_d - J_d F^{j T})^vee = h (pi^j + h tau^j) =: h Pi^j``  and  ``pi^{j+1} = F^{j T} Pi^j``,
  solved per node by Newton's method on the Cayley vector ``F = (I + f^)(I - f^)^{-1}``:
  ``G(f) = u + u x f + (u . f) f - 2 J f = 0``, ``u = h Pi`` (T. Lee).

``f^j`` are world-frame forces and ``tau^j`` body-frame torques: elastic (:mod:`physics.elastic`),
gravity, user node wrenches, magnets in a field (:mod:`physics.loads`) and viscous damping
``-c v^{j-1/2}`` and ``-c_r J^{-1} pi^j``. Linear and angular momentum
``sum m v``, ``sum (m p x v + R pi)`` are conserved exactly by the scheme for free rods.
"""
from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from .elastic import elastic_energy, internal_loads, relative_cayley
from .errors import SolverError
from .checks import check_rotations, is_int
from .lie import mtm3, mtv3, mv3
from .loads import Loads, magnet_node_loads, magnet_positions
from .programs import compile_program, tracing
from .rod import Rod, RodParams

__all__ = ["Boundary", "LGVIState", "Trajectory", "LGVI", "solve_cayley"]


class Boundary(str, Enum):
    CLAMPED_FREE = "clamped-free"
    CLAMPED_CLAMPED = "clamped-clamped"
    FREE_FREE = "free-free"
    PRESCRIBED_BASE = "prescribed-base"


class LGVIState(NamedTuple):
    """Positions ``p`` (..., n, 3) at ``t``; half-step velocities ``v = (p^j - p^{j-1})/h``;
    rotations ``R`` (..., n, 3, 3); body angular momenta ``pi`` (..., n, 3); step counter; the time ``t0`` the
    counter started at (``t`` is ``t0 + step * dt``: summed step by step it would drift)."""

    t: float
    p: Tensor
    v: Tensor
    R: Tensor
    pi: Tensor
    step: int = 0
    t0: float = 0.0


class Trajectory(NamedTuple):
    t: Tensor  # (T,)
    p: Tensor  # (..., T, n, 3)
    R: Tensor | None  # (..., T, n, 3, 3)
    energy: Tensor | None  # (..., T)
    newton_iters: Tensor  # (n_steps,) iterations used per step
    newton_residual: float  # largest residual seen


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1, keepdim=True)


def _solve_diag_skew(d: Tensor, u: Tensor, b: Tensor) -> Tensor:
    """Solve ``(diag(d) + u^) x = b`` in closed form:
    ``adj = adj(diag d) + u u^T - (diag(d) u)^``, ``det = d1 d2 d3 + sum_i d_i u_i^2``."""
    d1, d2, d3 = d.unbind(-1)
    adj_d = torch.stack((d2 * d3, d1 * d3, d1 * d2), -1)
    det = (d1 * d2 * d3)[..., None] + _dot(d, u * u)
    return (adj_d * b + u * _dot(u, b) - torch.linalg.cross(d * u, b, dim=-1)) / det


def _cayley_residual(f: Tensor, u: Tensor, J: Tensor) -> Tensor:
    return u + torch.linalg.cross(u, f, dim=-1) + _dot(u, f) * f - 2 * J * f


def solve_cayley(u: Tensor, J: Tensor, tol: float, max_iter: int = 20, fixed_iters: int | None = None):
    """Solve ``(F J_d - J_d F^T)^vee = u`` for ``F = (I + f^)(I - f^)^{-1}``, per node.

    ``J`` (..., 3) principal inertia. Newton's method on ``G(f) = u + u x f + (u.f) f - 2 J f``,
    whose Jacobian ``u^ + diag(u.f - 2 J) + f u^T`` is inverted in closed form (diagonal plus
    skew, then Sherman-Morrison for the rank-one term): no 3x3 matrices are formed. Returns
    ``(f, iterations, residual)``, ``residual`` (...,) being ``|G(f)| / (2 max J)`` (units of ``f``).
    With ``fixed_iters`` the loop has no data-dependent control flow (for ``torch.compile``).
    """
    f = u / (2 * J)
    n_it = fixed_iters if fixed_iters is not None else max_iter
    it = 0
    for it in range(1, n_it + 1):
        uf = _dot(u, f)
        G = u + torch.linalg.cross(u, f, dim=-1) + uf * f - 2 * J * f
        d = uf - 2 * J
        y = _solve_diag_skew(d, u, -G)
        z = _solve_diag_skew(d, u, f)
        df = y - z * (_dot(u, y) / (1 + _dot(u, z)))
        f = f + df
        if fixed_iters is None and float(df.abs().max()) <= tol:
            break
    res = _cayley_residual(f, u, J).norm(dim=-1) / (2 * J.amax(-1))
    return f, it, res


def _rotate_by_cayley(R: Tensor, Pi: Tensor, f: Tensor):
    """``R F`` and ``F^T Pi`` for ``F = (I + f^)(I - f^)^{-1} = a I + c f^ + c f f^T``
    (``c = 2/(1+|f|^2)``, ``a = 1 - c |f|^2``) without forming F."""
    ff = _dot(f, f)
    c = 2.0 / (1.0 + ff)
    a = 1.0 - c * ff
    Rf = mv3(R, f)
    RF = a[..., None] * R + c[..., None] * (torch.linalg.cross(R, f.unsqueeze(-2).expand_as(R), dim=-1)
                                            + Rf.unsqueeze(-1) * f.unsqueeze(-2))
    FtPi = a * Pi - c * torch.linalg.cross(f, Pi, dim=-1) + c * f * _dot(f, Pi)
    return RF, FtPi


@dataclass
class LGVI:
    """Integrator for one rod spec (or explicit batched ``params``) with fixed step ``dt``.

    ``stability``: 'raise' refuses ``dt`` above ``rod.stable_time_step().dt_max``, 'warn' warns,
    'off' skips the check. ``check_every``: steps between NaN/inf and Newton-residual checks (a
    failing interval is replayed step by step to report the exact step, time and node).
    ``newton_iters``: a fixed Newton count (compile-friendly) instead of the adaptive loop.
    ``base_motion(t) -> (p0, R0)`` drives node 0 for ``bc='prescribed-base'``.
    """

    rod: Rod | None
    dt: float
    bc: Boundary | str = Boundary.CLAMPED_FREE
    loads: Loads = field(default_factory=Loads)
    params: RodParams | None = None
    base_motion: Callable[[float], tuple[Tensor, Tensor]] | None = None
    dtype: torch.dtype = torch.float64
    device: torch.device | str | None = None
    stability: str = "raise"
    newton_tol: float | None = None
    newton_max_iter: int = 25
    newton_iters: int | None = None
    check_every: int = 1

    def __post_init__(self):
        try:
            self.bc = Boundary(self.bc)
        except ValueError:
            raise ValueError(f"LGVI.bc must be one of {[b.value for b in Boundary]}, got {self.bc!r}") from None
        if not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"LGVI.dt must be a finite positive time step (s), got {self.dt!r}")
        if self.stability not in ("raise", "warn", "off"):
            raise ValueError(f"LGVI.stability must be 'raise', 'warn' or 'off', got {self.stability!r}")
        if self.params is None:
            if self.rod is None:
                raise ValueError("LGVI: give a Rod spec or explicit params")
            self.params = self.rod.params(self.dtype, self.device)
        else:
            self.params = self.params.to(self.dtype, self.device)
        if self.bc is Boundary.PRESCRIBED_BASE and self.base_motion is None:
            raise ValueError("LGVI: bc='prescribed-base' needs base_motion(t) -> (p0, R0)")
        if self.newton_tol is None:
            self.newton_tol = 1e-13 if self.dtype == torch.float64 else 1e-6
        if int(self.check_every) < 1:
            raise ValueError("LGVI.check_every must be >= 1")
        for name in ("newton_max_iter", "newton_iters"):
            n = getattr(self, name)
            if n is not None and not (is_int(n) and n >= 1):
                raise ValueError(f"LGVI.{name} (Newton iterations of the rotation update) must be an integer >= 1, "
                                 f"got {n!r}")
        self.stability_estimate = None
        if self.rod is not None and self.stability != "off":
            est = self.rod.stable_time_step()
            self.stability_estimate = est
            if self.dt > est.dt_max:
                msg = (f"LGVI.dt={self.dt:.4g} s exceeds the stability limit dt_max={est.dt_max:.4g} s "
                       f"of the linearised explicit update (fastest mode {est.omega_max:.4g} rad/s; "
                       f"closed-form limits: axial {est.dt_axial:.3g}, shear {est.dt_shear:.3g}, "
                       f"bending {est.dt_bending:.3g}, shear-rotation {est.dt_shear_rotation:.3g} s)")
                if self.stability == "raise":
                    raise ValueError(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
        if self.stability != "off":  # the damping is explicit: a velocity or spin decays by (1 - c dt / m) a step
            prm = self.params
            damped = max(float((prm.damping * self.dt / prm.mass[..., None]).max()),
                         float((prm.rot_damping * self.dt / prm.inertia).max()))
            if damped >= 2.0:
                msg = (f"LGVI.dt={self.dt:.4g} s with this damping makes its explicit update unstable: "
                       f"damping dt / mass (or rot_damping dt / inertia) is {damped:.3g}, and must stay below 2")
                if self.stability == "raise":
                    raise ValueError(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
        n = self.params.n_nodes
        fixed = {Boundary.CLAMPED_FREE: [0], Boundary.CLAMPED_CLAMPED: [0, n - 1],
                 Boundary.FREE_FREE: [], Boundary.PRESCRIBED_BASE: [0]}[self.bc]
        free = torch.ones(n, dtype=self.dtype, device=self.device)
        free[fixed] = 0.0
        self._free = free[:, None]
        g = self.loads.gravity
        self._gravity = None if g is None else torch.as_tensor(g, dtype=self.dtype, device=self.device)
        if self._gravity is not None and (self._gravity.shape[-1:] != (3,) or not bool(self._gravity.isfinite().all())):
            raise ValueError(f"Loads.gravity must be a finite 3-vector (m/s^2), got {self.loads.gravity!r}")
        if self.loads.field is not None and self.params.magnet_elem.numel() == 0:
            raise ValueError("Loads.field: this rod has no magnets for the field to act on (it would be ignored)")
        self._has_magnets = self.loads.field is not None  # a rod with magnets (checked above)
        for name in ("force", "torque"):
            if torch.is_tensor(getattr(self.loads, name)):
                self._check_node_load(name, getattr(self.loads, name))
        self._compiled = {}
        self.eager_blocks = 0  # compiled_rollout: blocks of its last call stepped eagerly (a field cache refresh)

    # ------------------------------------------------------------------ states
    def initial_state(self, p: Tensor | None = None, R: Tensor | None = None, v: Tensor | None = None,
                      omega: Tensor | None = None, t: float = 0.0) -> LGVIState:
        """State from node positions/rotations (default: straight along +E3 from the origin),
        velocities ``v`` (world) and body angular velocities ``omega``."""
        prm = self.params
        n = prm.n_nodes
        kw = dict(dtype=self.dtype, device=self.device)
        if p is None:
            s = torch.cat((torch.zeros_like(prm.l[..., :1]), prm.l.cumsum(-1)), -1)
            p = torch.zeros(*s.shape, 3, **kw)
            p[..., 2] = s
        p = torch.as_tensor(p, **kw)
        if R is None:
            R = torch.eye(3, **kw).expand(*p.shape[:-1], 3, 3).clone()
        R = torch.as_tensor(R, **kw)
        if p.shape[-2:] != (n, 3):
            raise ValueError(f"initial_state: p must be (..., {n}, 3), got {tuple(p.shape)}")
        if R.shape[-3:] != (n, 3, 3):
            raise ValueError(f"initial_state: R must be (..., {n}, 3, 3), got {tuple(R.shape)}")
        if not (torch.isfinite(p).all() and torch.isfinite(R).all()):
            raise ValueError("initial_state: p and R must be finite")
        check_rotations("initial_state: R", R)
        p = torch.broadcast_tensors(p[..., None], R)[0][..., 0]
        for name, x in (("v", v), ("omega", omega)):
            if x is not None and not bool(torch.isfinite(torch.as_tensor(x, **kw)).all()):
                raise ValueError(f"initial_state: {name} must be finite")
        v = torch.zeros_like(p) if v is None else torch.as_tensor(v, **kw).expand_as(p).clone()
        pi = torch.zeros_like(p) if omega is None else prm.inertia * torch.as_tensor(omega, **kw).expand_as(p)
        self._check_loads_at(float(t))  # the half kick below applies them
        # the state holds v^{-1/2} and the momentum before the first torque kick: step back half a
        # kick from the given velocities (velocity-Verlet start, keeps the scheme second order)
        state = LGVIState(float(t), p.contiguous(), (v * self._free).contiguous(), R.contiguous(),
                          (pi * self._free).contiguous(), 0, float(t))
        return self._half_kick(state, -0.5)

    def _half_kick(self, state: LGVIState, frac: float) -> LGVIState:
        """Velocities and momenta advanced by ``frac * dt`` of the current loads."""
        prm, h = self.params, self.dt
        psi = relative_cayley(state.R)
        fi, ti = internal_loads(state.p, state.R, prm, psi)
        fe, te = self.external_loads(self._tensor_time(state.t), state.p, state.v, state.R, state.pi, psi)
        v = (state.v + frac * h * (fi + fe) / prm.mass[..., None]) * self._free
        pi = (state.pi + frac * h * (ti + te)) * self._free
        return state._replace(v=v, pi=pi)

    # ------------------------------------------------------------------ loads
    def external_loads(self, t: Tensor, p: Tensor, v: Tensor, R: Tensor, pi: Tensor, psi: Tensor):
        """World forces and body torques (..., n, 3) from gravity, user wrenches, magnets and
        damping at time ``t`` (a 0-d tensor, also what time-dependent load callables receive)."""
        prm = self.params
        force = -prm.damping * v
        torque = -prm.rot_damping * (pi / prm.inertia)
        if self._gravity is not None:
            force = force + prm.mass[..., None] * self._gravity
        fu = self.loads.evaluate_force(t)
        if fu is not None:
            force = force + torch.as_tensor(fu, dtype=self.dtype, device=self.device)
        tu = self.loads.evaluate_torque(t)
        if tu is not None:
            tu = torch.as_tensor(tu, dtype=self.dtype, device=self.device)
            torque = torque + mtv3(R, tu)
        if self._has_magnets:
            fm, tm = magnet_node_loads(self.loads.field, t, p, R, psi, prm)
            force, torque = force + fm, torque + tm
        return force, torque

    # ------------------------------------------------------------------ stepping
    def _advance(self, t: Tensor, p: Tensor, v: Tensor, R: Tensor, pi: Tensor, fixed_iters: int | None,
                 check: bool = True):
        """The pure update (eager and compiled paths share it)."""
        prm, h = self.params, self.dt
        psi = relative_cayley(R, check=check)
        fi, ti = internal_loads(p, R, prm, psi)
        fe, te = self.external_loads(t, p, v, R, pi, psi)
        free = self._free
        v1 = (v + (h / prm.mass[..., None]) * (fi + fe)) * free
        p1 = p + h * v1
        Pi = (pi + h * (ti + te)) * free
        f, iters, res = solve_cayley(h * Pi, prm.inertia, self.newton_tol, self.newton_max_iter, fixed_iters)
        R1, pi1 = _rotate_by_cayley(R, Pi, f)
        t1 = t + h
        if self.bc is Boundary.PRESCRIBED_BASE:
            p1, v1, R1, pi1 = self._apply_base(p, R, p1, v1, R1, pi1, t1)
        return t1, p1, v1, R1, pi1, iters, res

    def _tensor_time(self, t: float) -> Tensor:
        return torch.tensor(t, dtype=self.dtype, device=self.device)

    def _time_after(self, state: LGVIState, steps: int) -> float:
        """The time ``steps`` steps after ``state``: its counter's start time plus a whole number of steps (summing
        ``dt`` step by step drifts: 5,000 steps of 1e-4 s ended at 0.49999999999996 s, inside a load window that ends
        at 0.5 s)."""
        return state.t0 + (state.step + steps) * self.dt

    def step(self, state: LGVIState, *, _return_info: bool = False):
        """One step ``t -> t + dt`` (pure: inputs are not modified)."""
        _, p, v, R, pi, iters, res = self._advance(self._tensor_time(state.t), state.p, state.v, state.R,
                                                   state.pi, self.newton_iters)
        new = LGVIState(self._time_after(state, 1), p, v, R, pi, state.step + 1, state.t0)
        return (new, (iters, res)) if _return_info else new

    def _apply_base(self, p_old, R_old, p, v, R, pi, t):
        p0, R0 = self.base_motion(t)
        kw = dict(dtype=self.dtype, device=self.device)
        p0 = torch.as_tensor(p0, **kw).expand_as(p[..., 0, :])
        R0 = torch.as_tensor(R0, **kw).expand_as(R[..., 0, :, :])
        F0 = mtm3(R_old[..., 0, :, :], R0)
        A = F0 * self.params.inertia_d[..., 0, None, :]
        W = A - A.transpose(-1, -2)  # F J_d - J_d F^T
        Pi0 = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), -1) / self.dt
        pi0 = mtv3(F0, Pi0)
        v0 = (p0 - p_old[..., 0, :]) / self.dt

        def put(x, x0):  # replace node 0
            return torch.cat((x0.unsqueeze(-2), x[..., 1:, :]), -2)

        R = torch.cat((R0.unsqueeze(-3), R[..., 1:, :, :]), -3)
        return put(p, p0), put(v, v0), R, put(pi, pi0)

    # ------------------------------------------------------------------ compiled fused steps
    def compiled_rollout(self, state: LGVIState, n_steps: int, steps_per_call: int = 4,
                         newton_iters: int = 2, record_every: int | None = None, record_R: bool = False):
        """Advance with ``steps_per_call`` steps fused into one compiled program (fixed Newton count: from the
        start ``u / 2J`` two iterations reach round-off for rotations below ~1e-3 rad per step). Finiteness and the
        Newton residual are checked after each call; a failing call is replayed eagerly to report the exact step.
        Returns ``(state, positions (..., T, n, 3))`` with positions recorded every ``record_every`` calls' worth
        of steps (None: final only), and with ``record_R`` the rotations (..., T, n, 3, 3) at the same frames third.
        The first call for a batch shape compiles (seconds); time it separately.

        On the CPU the program is compiled ahead of time for the state's shapes (``make_fx`` and inductor,
        :func:`physics.programs.compile_program`: a call costs a few microseconds and one allocation, where a
        ``torch.compile``'d call costs tens and allocates every intermediate buffer); on another device, or where
        the loads cannot be traced into a program of fixed shapes (a branch on the data), ``torch.compile`` (with
        a warning naming why). The loads are traced with :func:`physics.programs.is_tracing` True: time-dependent
        loads take their tensor forms.

        A field hook that keeps a cache between evaluations (``block_ready``, ``drift``, ``tol``, ``block_done``,
        ``cache`` and ``cached``, as :class:`physics.coil_currents.CoilField`) runs traced on its cache, an input
        of each call: a call is kept only if the hook was ready before it and its drift stayed within ``tol`` at
        every step, else the block is replayed eagerly (where the hook refreshes its cache), so the cache is
        refreshed at the same steps as in the eager rollout. ``self.eager_blocks`` counts the blocks so replayed in
        the last call.
        """
        if not all(is_int(n) and n >= 1 for n in (steps_per_call, newton_iters)):
            raise ValueError(f"compiled_rollout: steps_per_call and newton_iters must be integers >= 1, got "
                             f"{steps_per_call!r} and {newton_iters!r}")
        if n_steps % steps_per_call:
            raise ValueError(f"compiled_rollout: n_steps={n_steps} must be a multiple of steps_per_call={steps_per_call}")
        self.check_state(state, "compiled_rollout", finite=False)
        field = self.loads.field if self._has_magnets and hasattr(self.loads.field, "drift") else None
        t = self._tensor_time(state.t)
        p, v, R, pi = state.p, state.v, state.R, state.pi
        rec = [p] if record_every else None
        rec_R = [R] if record_every and record_R else None
        tol = self._residual_limit()
        self.eager_blocks = 0
        fn = None
        for c in range(n_steps // steps_per_call):
            good = LGVIState(self._time_after(state, c * steps_per_call), p, v, R, pi, state.step + c * steps_per_call,
                             state.t0)
            t = self._tensor_time(good.t)
            until = good.step + steps_per_call
            if field is not None and not field.block_ready(good.t, p):
                out = None
            else:
                if fn is None:  # built once the field's cache exists (an input of the program)
                    fn = self._fused_program((t, p, v, R, pi), steps_per_call, newton_iters, field)
                out = fn(t, p, v, R, pi)
                if field is not None and float(out[6]) > field.tol:
                    out = None
            if out is None:  # the hook would refresh its cache within the block: step it eagerly
                new = self._replay(good, until)
                t, p, v, R, pi = self._tensor_time(new.t), new.p, new.v, new.R, new.pi
                self.eager_blocks += 1
            else:
                t, p, v, R, pi, res, _ = out
                if not (bool(torch.isfinite(p).all()) and float(res) <= tol):
                    self._replay(good, until)
                    raise SolverError("compiled rollout failed but the eager replay did not",
                                      step=good.step, time=good.t)
                if field is not None:
                    field.block_done(good.t + (steps_per_call - 1) * self.dt)
            if record_every and (c + 1) % record_every == 0:
                rec.append(p)
                if rec_R is not None:
                    rec_R.append(R)
        out = LGVIState(self._time_after(state, n_steps), p, v, R, pi, state.step + n_steps, state.t0)
        frames = torch.stack(rec, -3) if record_every else None
        if record_R:
            return out, frames, (torch.stack(rec_R, -4) if record_every else None)
        return out, frames

    def _fused_program(self, inputs: tuple[Tensor, ...], steps: int, newton_iters: int, field):
        """``fn(t, p, v, R, pi) -> (t, p, v, R, pi, largest Newton residual, largest field drift)`` after ``steps``
        steps, compiled for the shapes, dtype and device of ``inputs`` (these five; kept per key, and only while the
        integrator's step, parameters and loads are the objects it was traced with: they are its constants)."""
        p = inputs[1]
        key = (steps, newton_iters, tuple(p.shape), p.dtype, p.device, self.dt)
        kept = self._compiled.get(key)
        if kept is not None and kept[1] is self.params and kept[2] is self.loads:
            return kept[0]

        def fused(t, p, v, R, pi):
            res_max = torch.zeros((), dtype=p.dtype, device=p.device)
            drift = torch.zeros((), dtype=p.dtype, device=p.device)
            t0 = t
            for k in range(steps):  # each step's time from the block's start (no drift, as the eager steps)
                if field is not None:  # where this step evaluates the field
                    drift = torch.maximum(drift, field.drift(magnet_positions(p, self.params)))
                t, p, v, R, pi, _, res = self._advance(t0 + k * self.dt, p, v, R, pi, newton_iters, check=False)
                res_max = torch.maximum(res_max, res.amax())
            return t, p, v, R, pi, res_max, drift
        fn = None
        if p.device.type == "cpu":
            def traced(t, p, v, R, pi, *cache):
                with field.cached(cache) if field is not None else contextlib.nullcontext():
                    return fused(t, p, v, R, pi)
            cache = (lambda: field.cache()) if field is not None else (lambda: ())  # noqa: E731
            try:
                with tracing():
                    prog = compile_program(traced, (*(x.contiguous() for x in inputs), *cache()), direct=True,
                                          vectorize=False)
                fn = lambda *s: prog(*(x.contiguous() for x in s), *cache())  # noqa: E731
            except Exception as err:  # noqa: BLE001 - a load that cannot be traced for fixed shapes
                warnings.warn(f"compiled_rollout: the loads could not be traced into a program ({type(err).__name__}: "
                              f"{str(err).splitlines()[0] if str(err) else ''}); using torch.compile",
                              RuntimeWarning, stacklevel=3)
        if fn is None:
            fn = torch.compile(fused, dynamic=False, fullgraph=False)
        self._compiled[key] = (fn, self.params, self.loads)
        return fn

    def _check_node_load(self, name: str, value, t: float | None = None) -> None:
        """ValueError unless a node force / torque is (..., n, 3) (a (3,) vector would act on every node) and
        finite (a NaN load would be reported as a non-finite state), naming the node."""
        n = self.params.n_nodes
        value = torch.as_tensor(value)
        shape = tuple(value.shape)
        at = "" if t is None else f" (the value of its function at t={t:.6g} s)"
        if shape[-2:] != (n, 3):
            raise ValueError(f"Loads.{name}{at} must be (..., {n}, 3): one world-frame vector per node of this rod "
                             f"(zero where none acts), got shape {shape}")
        bad = ~torch.isfinite(value).all(-1)
        if bool(bad.any()):
            raise ValueError(f"Loads.{name}{at} is not finite at node {int(bad.nonzero()[0, -1])}")

    def _check_loads_at(self, t: float) -> None:
        """:meth:`_check_node_load` on each load given as a function of time, at time ``t``."""
        for name in ("force", "torque"):
            load = getattr(self.loads, name)
            value = load(self._tensor_time(t)) if callable(load) else None
            if value is not None:  # a function may give None: no load at that time
                self._check_node_load(name, value, t)

    def check_state(self, state: LGVIState, where: str = "simulate", finite: bool = True) -> None:
        """ValueError naming the first field of ``state`` that is not this integrator's: shapes (..., n, 3) and
        (..., n, 3, 3) with one batch shape, its dtype and device (a state made by another LGVI: another rod, dtype
        or device), or (``finite``) non-finite values, and the node."""
        n = self.params.n_nodes
        if not isinstance(state, LGVIState):
            raise TypeError(f"{where}: state must be an LGVIState (from initial_state), got {type(state).__name__}")
        batch = state.p.shape[:-2]
        for name, tail in (("p", (n, 3)), ("v", (n, 3)), ("R", (n, 3, 3)), ("pi", (n, 3))):
            x = getattr(state, name)
            if not torch.is_tensor(x) or tuple(x.shape) != (*batch, *tail):
                got = tuple(x.shape) if torch.is_tensor(x) else type(x).__name__
                like = "" if name == "p" else f" with the batch shape of state.p {tuple(batch)}"
                raise ValueError(f"{where}: state.{name} must be (..., {', '.join(map(str, tail))}){like} for this "
                                 f"rod of {n} nodes, got {got}")
            if x.dtype != self.dtype or x.device != self.params.mass.device:
                raise ValueError(f"{where}: state.{name} is {x.dtype} on {x.device}, but this LGVI runs {self.dtype} "
                                 f"on {self.params.mass.device} (make the state with this LGVI's initial_state)")
            if finite:
                bad = ~torch.isfinite(x).flatten(-len(tail) + 1).all(-1)
                if bool(bad.any()):
                    raise ValueError(f"{where}: state.{name} is not finite at node {int(bad.nonzero()[0, -1])}")

    def _check_start(self, state: LGVIState) -> None:
        """:meth:`simulate`'s :meth:`check_state`, and the shape of each load given as a function of time at the
        state's time. (A compiled rollout's call checks only the state's shapes and types, a few us; the values
        would cost it about a tenth of a call of 40 steps: a non-finite start fails its first block, replayed
        eagerly to name the step and node.)"""
        self.check_state(state)
        self._check_loads_at(state.t)

    def _residual_limit(self) -> float:
        """Largest Newton residual accepted before a step counts as not converged."""
        return max(1e3 * self.newton_tol, 1e-10 if self.dtype == torch.float64 else 1e-4)

    def _check(self, state: LGVIState, res: Tensor | None, label: str = ""):
        bad = ~(torch.isfinite(state.p).all(-1) & torch.isfinite(state.R).flatten(-2).all(-1))
        if bool(bad.any()):
            node = int(bad.nonzero()[0, -1])
            raise SolverError("non-finite state (the step is probably above the stability limit "
                              "or the load is too large)", step=state.step, time=state.t, node=node)
        if res is not None and float(res.max()) > self._residual_limit():
            node = int((res == res.max()).nonzero()[0, -1])
            raise SolverError(f"rotation Newton iteration did not converge (residual {float(res.max()):.3e} "
                              f"after {self.newton_max_iter if self.newton_iters is None else self.newton_iters} iterations)",
                              step=state.step, time=state.t, node=node)

    def simulate(self, state: LGVIState, n_steps: int | None = None, duration: float | None = None,
                 record_every: int = 1, record_R: bool = False, record_energy: bool = False,
                 callback: Callable[[LGVIState], None] | None = None):
        """Advance ``n_steps`` (or ``duration`` seconds) and return ``(final_state, Trajectory)``."""
        if (n_steps is None) == (duration is None):
            raise ValueError("simulate: give exactly one of n_steps or duration")
        if n_steps is None:
            if not (math.isfinite(float(duration)) and float(duration) >= 0):
                raise ValueError(f"simulate: duration must be a finite time >= 0 (s), got {duration!r}")
            n_steps = int(round(float(duration) / self.dt))
        if n_steps < 0:
            raise ValueError(f"simulate: n_steps must be >= 0, got {n_steps!r}")
        if record_every < 1:
            raise ValueError(f"simulate: record_every must be >= 1, got {record_every!r}")
        self._check_start(state)
        ts, ps, Rs, Es = [state.t], [state.p], [state.R] if record_R else None, []
        if record_energy:
            Es.append(self.energy(state))
        iters = torch.zeros(n_steps, dtype=torch.int32)
        worst = 0.0
        last_good = state
        res_max = None  # the largest Newton residual since the last check (every step's counts, not the last's)
        for k in range(n_steps):
            state, (it, res) = self.step(state, _return_info=True)
            iters[k] = it
            res_max = res if res_max is None else torch.maximum(res_max, res)
            if (k + 1) % self.check_every == 0 or k + 1 == n_steps:
                res, res_max = res_max, None
                try:
                    self._check(state, res)
                except SolverError:
                    if self.check_every > 1:
                        self._replay(last_good, state.step)
                    raise
                worst = max(worst, float(res.max()))
                last_good = state
            if (k + 1) % record_every == 0:
                ts.append(state.t)
                ps.append(state.p)
                if record_R:
                    Rs.append(state.R)
                if record_energy:
                    Es.append(self.energy(state))
            if callback is not None:
                callback(state)
        traj = Trajectory(
            t=torch.tensor(ts, dtype=self.dtype),
            p=torch.stack(ps, -3),
            R=torch.stack(Rs, -4) if record_R else None,
            energy=torch.stack(Es, -1) if record_energy else None,
            newton_iters=iters,
            newton_residual=worst,
        )
        return state, traj

    def _replay(self, state: LGVIState, until: int) -> LGVIState:
        while state.step < until:
            state, (_, res) = self.step(state, _return_info=True)
            self._check(state, res)
        return state

    # ------------------------------------------------------------------ diagnostics
    def potential_energy(self, state: LGVIState) -> Tensor:
        V = elastic_energy(state.p, state.R, self.params)
        if self._gravity is not None:
            V = V - (self.params.mass[..., None] * self._gravity * state.p).sum((-1, -2))
        return V

    def energy(self, state: LGVIState) -> Tensor:
        """Total energy (...,): kinetic with velocities and momenta advanced half a step to
        ``t`` (velocity-Verlet form, O(h^2) accurate, no drift) plus elastic and gravity."""
        prm = self.params
        kicked = self._half_kick(state, 0.5)
        v, pi = kicked.v, kicked.pi
        T = 0.5 * (prm.mass[..., None] * v * v).sum((-1, -2)) + 0.5 * (pi * pi / prm.inertia).sum((-1, -2))
        return T + self.potential_energy(state)

    def momentum(self, state: LGVIState) -> tuple[Tensor, Tensor]:
        """Linear ``sum m v`` and angular ``sum (m p x v + R pi)`` momentum about the origin."""
        m = self.params.mass[..., None]
        P = (m * state.v).sum(-2)
        L = (m * torch.linalg.cross(state.p, state.v, dim=-1)).sum(-2) + (state.R @ state.pi[..., None])[..., 0].sum(-2)
        return P, L

    @staticmethod
    def orthogonality_error(state: LGVIState) -> Tensor:
        """max |R^T R - I| over nodes (...,)."""
        R = state.R
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        return (R.transpose(-1, -2) @ R - eye).abs().flatten(-3).amax(-1)
