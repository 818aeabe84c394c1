"""Shooting for the static Cosserat rod (:mod:`physics.cosserat`): batched Levenberg-Marquardt,
warm starts, load-stepping continuation and implicit gradients.

Unknowns. The base wrench ``xi = [n(0), m(0)]`` in the scaled units ``F_s = E I / L^2`` and
``M_s = E I / L`` (``E I`` the softest segment's bending stiffness); the residual is the free tip,
``r = [n(L+)/F_s, m(L+)/M_s]`` after the tip loads, and a problem has converged when
``|r|_2 <= tol`` (the thesis's tolerable error E, made dimensionless).

Jacobian. ``jacobian='forward'`` (default) propagates the six tangent directions ``dy/dxi`` through
every RK4 stage beside the state (the variational equation, written out by hand), which is exact
for the discrete map; position derivatives of a non-uniform field's gradient are central
differences. ``jacobian='jacfwd'`` gets the same matrix from ``torch.func``: a ``vmap`` over the six
basis directions of ``jvp`` (``jacfwd`` exploiting that problems are independent); the field must
then be ``torch.func``-compatible.

Levenberg-Marquardt. Each iteration solves ``(J^T J + lambda diag(J^T J)) d = -J^T r`` per problem,
evaluates the residual and Jacobian at ``xi + d`` in one pass, and accepts the step where ``|r|``
decreased, else rejects it. ``lambda`` starts at 1e-3 from a cold start and near Gauss-Newton (1e-6)
from a warm start or a previous load step, and follows the gain ratio ``rho`` (actual over predicted
decrease of ``|r|^2``): divided by 10 for ``rho > 0.75``, doubled for ``rho < 0.25``, and at least
1e-3 and ten times larger after a rejected step. Problems that have converged stop moving; each
keeps its iteration count and residual. A problem that exhausts ``max_iter`` (or whose
``lambda`` blows up) is not converged: :class:`~physics.errors.SolverError` by default, or the
``converged`` flag with ``raise_on_failure=False``; never a silent answer. Problems that fail are
solved again from the start with load stepping (4, 16, ... load steps, up to ``max_load_steps``).

Chord iterations. A solve warm-started near its solution (a control loop's next frame) may pass ``chord``, the
scaled Jacobian of a nearby solution (``StaticSolution.jacobian``, e.g. the last frame's): Newton steps
``xi <- xi - J^{-1} r`` with that Jacobian, updated by Broyden's secant after each step, each needing only the
residual, a shot without tangents (about a seventh of an LM iteration's arithmetic). At most :data:`CHORD_MAX`
and ``max_iter`` of them; a problem stops stepping once its residual is within ``tol``, where the contraction
predicts the next point within it, or where the residual shrinks by less than :data:`CHORD_RATE` a step. The
residuals are evaluated in blocks of ``chord_block`` (default :data:`CHORD_BLOCK` = 3; on the compiled path one
program a block), and the iterations end after the block in which no problem stepped on unpredicted (a problem
that has stopped keeps its point; one whose predicted point turned out not within ``tol`` may step on). LM then
starts from the best point reached (or the predicted one), so that its first evaluation, with the tangents, checks
convergence and gives the solution's Jacobian. Each chord step counts as an iteration. On the magnetic rod's
real-time frames the chord steps shrink the residual about a hundredfold each (the Jacobian changes by about 5 % a
frame).

Which equilibrium. Shooting finds *an* equilibrium, not necessarily a stable one: a strong field
nearly opposite to a magnet's moment can give the unstable, anti-aligned solution. Load stepping
(``load_steps``) and warm starts follow the branch that starts at the unloaded rod.

Gradients (implicit function theorem). The loop runs without autograd. When a load, a parameter or
a field tensor requires grad, one more differentiable shot ``Y(xi*, theta)``, ``r(xi*, theta)`` is
taken at the solution and corrected by one Newton step with the detached Jacobian:
``Y + (dY/dxi)(-J^{-1} r)``. Its value is the solution's (``r`` is at tolerance) and its derivative
``dY/dtheta - (dY/dxi) J^{-1} dr/dtheta`` is exactly the implicit-function derivative of the
converged shape, whatever path the iterations took. Only first derivatives are exact.
An inverse problem solved with these gradients: :func:`physics.cosserat_inverse.fit_uniform_field`.
"""
from __future__ import annotations

import contextlib
import math
from typing import NamedTuple

import torch
from torch import Tensor

from .checks import check_integer, is_finite_real
from .cosserat import CosseratParams, CosseratRod, StaticLoads, broadcast_shape
from .cosserat_ode import quat_matrix, shoot
from .cosserat_fast import fast_chord, fast_lm, flatten_field
from .cosserat_lanes import lane_chunk, lane_step, lane_tables, shoot_lanes, step_table
from .errors import SolverError
from .loads import UniformField

__all__ = ["StaticSolution", "CosseratSolver", "solve_static"]

_LAM_COLD, _LAM_WARM, _LAM_MAX = 1e-3, 1e-6, 1e16
#: Chord iterations: at most this many steps, each needing the residual to shrink at least by this factor; the
#: residuals are evaluated in blocks of ``CHORD_BLOCK`` (the default of ``CosseratSolver.chord_block``).
CHORD_MAX, CHORD_RATE, CHORD_BLOCK = 8, 0.25, 3


class StaticSolution(NamedTuple):
    """Solved shape: node arclengths ``s`` (n,), node states ``y`` (..., n, 13) (``n``, ``m`` just
    distal of each node's point loads), the base wrench ``[n(0), m(0)]`` (..., 6) in SI, per-problem
    ``converged`` (...,) bool, ``iterations`` (...,) (LM steps, all load steps together) and scaled
    ``residual`` (...,), and the scaled shooting Jacobian (..., 6, 6) at the solution."""

    s: Tensor
    y: Tensor
    base_wrench: Tensor
    converged: Tensor
    iterations: Tensor
    residual: Tensor
    jacobian: Tensor

    @property
    def p(self) -> Tensor:
        return self.y[..., 0:3]

    @property
    def q(self) -> Tensor:
        return self.y[..., 3:7]

    @property
    def n(self) -> Tensor:
        return self.y[..., 7:10]

    @property
    def m(self) -> Tensor:
        return self.y[..., 10:13]

    @property
    def R(self) -> Tensor:
        q = self.q
        return quat_matrix(q / q.norm(dim=-1, keepdim=True))

    @property
    def tip_position(self) -> Tensor:
        return self.y[..., -1, 0:3]


def _vec(name: str, v, dtype, device, trailing: tuple[int, ...]) -> Tensor:
    if not isinstance(v, Tensor):
        try:
            v = torch.as_tensor(v, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{name} must be a tensor or a sequence of numbers, got {type(v).__name__}") from None
    v = v.to(dtype=dtype, device=device)
    if tuple(v.shape[v.dim() - len(trailing):]) != trailing or v.dim() < len(trailing):
        raise ValueError(f"{name} must have shape (..., {', '.join(map(str, trailing))}), got {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name} must be finite")
    return v


def _unit_norm(name: str, q: Tensor) -> Tensor:
    """``|q|`` of a base quaternion ``q`` (..., 4), or a ValueError naming ``name`` where it is off 1 by over 1e-6."""
    qn = q.norm(dim=-1)
    off = (qn - 1).abs()
    if bool((off > 1e-6).any()):
        raise ValueError(f"{name} must be a unit quaternion (w, x, y, z) (|q| = 1 within 1e-6), "
                         f"got |q| = {float(qn.flatten()[off.flatten().argmax()]):.6g}")
    return qn


def _needs_grad(*objs, _depth: int = 0) -> bool:
    """Whether any tensor in ``objs`` requires a gradient, looked for in tuples, lists, dicts and objects' attributes
    down to a few levels (a field model's sum keeps its parts' tensors in a list of models)."""
    if not torch.is_grad_enabled():
        return False
    for o in objs:
        if isinstance(o, Tensor):
            if o.requires_grad:
                return True
        elif o is None or isinstance(o, (str, int, float, bool)) or _depth > 6:
            continue
        elif isinstance(o, (tuple, list)):
            if _needs_grad(*o, _depth=_depth + 1):
                return True
        elif isinstance(o, dict):
            if _needs_grad(*o.values(), _depth=_depth + 1):
                return True
        elif hasattr(o, "__dict__") and _needs_grad(*vars(o).values(), _depth=_depth + 1):
            return True
    return False


def tensor_versions(*groups) -> tuple:
    """The in-place version counters of the tensors in ``groups`` (tuples of tensors, e.g. parameters or loads): a
    cache keyed on those objects also compares these, so that values changed in place are not served stale."""
    return tuple(t._version for g in groups for t in g if isinstance(t, Tensor))


class CosseratSolver:
    """Shooting solver for one :class:`~physics.cosserat.CosseratRod` (see the module docstring).

    ``tol`` (default 1e-10 in float64, 1e-4 in float32) bounds the scaled tip residual;
    ``compile=True`` runs the solve through :mod:`physics.cosserat_fast`: per batch shape, a compiled
    program per LM iteration (the shot with its tangents and the update; batches of 8 or more run
    one program per RK4 step in a component-major layout vectorised over the problems, smaller
    ones the whole iteration on six lanes), called through a thin wrapper (a few us a call). The
    first solve per batch shape, dtype and field kind compiles (a few minutes here, ten or more for
    a batch; inductor caches it on disk). A field hook that cannot be traced (a plain function, a time
    function inside) takes the older path of :mod:`physics.cosserat_lanes` (``torch.compile`` d step
    per grid step), as does ``steps_per_call > 1`` (that many steps fused per call). ``chord_block``: the chord
    iterations' residual evaluations per block (module docstring). A real-time loop's repeated solve:
    :class:`physics.cosserat_frames.FrameSolve`.
    """

    def __init__(self, rod: CosseratRod, *, dtype: torch.dtype = torch.float64, device=None,
                 params: CosseratParams | None = None, tol: float | None = None, max_iter: int = 50,
                 jacobian: str = "forward", compile: bool = False, steps_per_call: int = 1,
                 fd_step: float | None = None, chord_block: int = CHORD_BLOCK):
        if not isinstance(rod, CosseratRod):
            raise TypeError(f"rod must be a CosseratRod, got {type(rod).__name__}")
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if jacobian not in ("forward", "jacfwd"):
            raise ValueError(f"jacobian must be 'forward' or 'jacfwd', got {jacobian!r}")
        tol = (1e-10 if dtype == torch.float64 else 1e-4) if tol is None else tol
        if not (is_finite_real(tol) and tol > 0):
            raise ValueError(f"tol must be a finite positive number, got {tol!r}")
        self.rod, self.dtype, self.device = rod, dtype, device
        self.tol, self.max_iter, self.jacobian = float(tol), check_integer("max_iter", max_iter), jacobian
        self.params = rod.params(dtype, device) if params is None else self._check_params(params)
        L, EI = rod.length, rod.bending_scale
        self.scales = (EI / L**2, EI / L)
        if fd_step is not None and not (math.isfinite(fd_step) and fd_step > 0):
            raise ValueError(f"fd_step (the central-difference step of the field's position derivatives, m) must be "
                             f"finite and > 0, got {fd_step!r}")
        self.fd_step = fd_step if fd_step is not None else L * torch.finfo(dtype).eps ** (1 / 3)
        self._s = torch.tensor(rod.grid.s, dtype=dtype, device=device)
        self._sc = torch.tensor([EI / L**2] * 3 + [EI / L] * 3, dtype=dtype, device=device)
        self.compile = bool(compile)
        if self.compile and jacobian != "forward":
            raise ValueError("compile=True needs jacobian='forward'")
        self._step_key, self._step_ver, self._step_tab = None, None, None
        self.steps_per_call = check_integer("steps_per_call", steps_per_call)
        if self.steps_per_call > 1 and not self.compile:  # (it was ignored: the eager shot takes no steps per call)
            raise ValueError(f"steps_per_call={self.steps_per_call} (grid steps fused per compiled call) needs "
                             f"compile=True")
        self._math, step1, chunk = _compiled() if compile else (_lm_math, lane_step, lane_chunk)
        self._lane_step = step1 if self.steps_per_call == 1 else chunk
        self._loads_cache: dict = {}
        self._field_shapes: dict = {}
        self.chord_block = check_integer("chord_block", chord_block)

    def _check_params(self, prm) -> CosseratParams:
        """``prm`` unless it does not fit the solver: not :class:`~physics.cosserat.CosseratParams`, another dtype,
        or made for another grid or number of magnets (another rod or ``n_nodes``)."""
        if not isinstance(prm, CosseratParams):
            raise TypeError(f"params must be CosseratParams (CosseratRod.params), got {type(prm).__name__}")
        for nm, v in zip(prm._fields, prm):
            if v.dtype != self.dtype:
                raise TypeError(f"params.{nm} has dtype {v.dtype}, the solver's is {self.dtype} "
                                f"(make them with rod.params({self.dtype}))")
        S, K = len(self.rod.grid.h), len(self.rod.magnets)
        if prm.ks_inv.shape[-2:] != (S, 3) or prm.magnet_moment.shape[-2:] != (K, 3):
            raise ValueError(f"params are for {prm.ks_inv.shape[-2]} RK4 steps and {prm.magnet_moment.shape[-2]} "
                             f"magnets, the solver's rod has {S} steps (n_nodes - 1) and {K} magnets "
                             f"(make them with this rod's params())")
        return prm

    def _check_loads(self, loads) -> StaticLoads:
        """``loads=`` unless it does not fit the solver (:meth:`make_loads` checks its keywords the same way): not
        :class:`~physics.cosserat.StaticLoads`, another dtype or device, a trailing shape other than the rod's (its
        ``load_points`` then the tip for the point loads), a non-finite value or a base quaternion that is not unit
        (each used to give a wrong shape, or a SolverError after a minute of load stepping, without an error)."""
        if not isinstance(loads, StaticLoads):
            raise TypeError(f"loads must be StaticLoads (make_loads), got {type(loads).__name__}")
        P = len(self.rod.load_points) + 1
        trailing = {"point_force": (P, 3), "point_torque": (P, 3), "field_scale": (), "base_quaternion": (4,)}
        for nm, v in zip(loads._fields, loads):
            want = trailing.get(nm, (3,))
            if not isinstance(v, Tensor) or v.dtype != self.dtype:
                raise TypeError(f"loads.{nm} must be a {self.dtype} tensor (the solver's dtype; make_loads makes one), "
                                f"got {v.dtype if isinstance(v, Tensor) else type(v).__name__}")
            if v.device != self._s.device:
                raise ValueError(f"loads.{nm} is on {v.device}, the solver on {self._s.device}")
            if v.dim() < len(want) or tuple(v.shape[v.dim() - len(want):]) != want:
                raise ValueError(f"loads.{nm} must have shape (..., {', '.join(map(str, want))}) (the rod's "
                                 f"{P - 1} load_points, then the tip, for the point loads), got {tuple(v.shape)}")
            if not bool(torch.isfinite(v).all()):
                raise ValueError(f"loads.{nm} must be finite")
        _unit_norm("loads.base_quaternion", loads.base_quaternion)
        return loads

    # ------------------------------------------------------------------ inputs
    def make_loads(self, *, gravity=None, point_forces=None, point_torques=None, tip_force=None, tip_moment=None,
                   line_force=None, line_torque=None, base_position=None, base_quaternion=None) -> StaticLoads:
        """Validated :class:`~physics.cosserat.StaticLoads` (any leading batch dims; world frame, SI)."""
        kw = dict(dtype=self.dtype, device=self.device)
        z3 = torch.zeros(3, **kw)
        P0 = len(self.rod.load_points)

        def v3(name, v):
            return z3 if v is None else _vec(name, v, self.dtype, self.device, (3,))

        def pts(name, v):
            if v is None:
                return torch.zeros(P0, 3, **kw)
            if P0 == 0:
                raise ValueError(f"{name}: the rod has no load_points (give them in CosseratRod.load_points, "
                                 f"or use tip_force/tip_moment)")
            return _vec(name, v, self.dtype, self.device, (P0, 3))

        pf, pt = pts("point_forces", point_forces), pts("point_torques", point_torques)
        tf, tm = v3("tip_force", tip_force), v3("tip_moment", tip_moment)
        pf = torch.cat(_cat_tip(pf, tf), -2)
        pt = torch.cat(_cat_tip(pt, tm), -2)
        q0 = torch.tensor([1.0, 0, 0, 0], **kw) if base_quaternion is None else \
            _vec("base_quaternion", base_quaternion, self.dtype, self.device, (4,))
        qn = _unit_norm("base_quaternion", q0)
        return StaticLoads(v3("gravity", gravity), v3("line_force", line_force), v3("line_torque", line_torque),
                           pf, pt, torch.ones((), **kw), v3("base_position", base_position), q0 / qn.unsqueeze(-1))

    # ------------------------------------------------------------------ one LM iteration
    def _evaluate(self, x, prm, loads, field, t):
        if self.jacobian == "forward":
            res = shoot(x, prm, self.rod.grid, loads, self.scales, field, t, tangent=True, fd_step=self.fd_step)
            return res.r, res.J, res.Y

        def r_of(xx):
            res = shoot(xx, prm, self.rod.grid, loads, self.scales, field, t, tangent=False, fd_step=self.fd_step)
            return res.r, (res.r, res.Y)

        basis = torch.eye(6, dtype=x.dtype, device=x.device).reshape(6, *([1] * (x.dim() - 1)), 6).expand(6, *x.shape)
        cols, (r, Y) = torch.func.vmap(lambda v: torch.func.jvp(r_of, (x,), (v,), has_aux=True)[1:])(basis)
        return r[0], cols.movedim(0, -1), Y[0]

    def _lm(self, x, prm, loads, field, t, its, lam0, live, flat=None, max_iter=None):
        """LM from ``x`` (batch-shaped), at most ``max_iter`` iterations (default the solver's); returns x, r, J,
        Y, rn and the updated iteration counts."""
        max_iter = self.max_iter if max_iter is None else max_iter
        evaluate = self._evaluate
        if self.compile:
            self._table(prm)
            if self.steps_per_call == 1:
                out = fast_lm(self, x, prm, loads, field, t, its, lam0, live, self._step_tab, flat=flat,
                              max_iter=max_iter)
                if out is not None:
                    return out
            tabs = lane_tables(prm, self.rod.grid, loads, self._step_tab)

            def lanes(xx, prm, loads, field, t):
                return shoot_lanes(self._lane_step, xx, prm, tabs, loads, self.scales, field, t, self.fd_step,
                                   self.steps_per_call)
            evaluate = lanes
        shp, kw = x.shape[:-1], dict(dtype=x.dtype, device=x.device)
        rt, Jt, Yt = evaluate(x, prm, loads, field, t)
        rt, Jt, Yt = rt.contiguous(), Jt.contiguous(), Yt.contiguous()
        r, J, Y = torch.zeros_like(rt), torch.eye(6, **kw).expand_as(Jt).contiguous(), torch.zeros_like(Yt)
        rn = torch.full(shp, math.inf, **kw)
        lam = torch.full(shp, lam0, **kw)
        act = live.clone()
        budget = its + max_iter
        tol = torch.tensor(self.tol, **kw)
        first, xt = True, None
        while True:
            x, r, J, Y, rn, lam, its, act, xt = self._math(x, r, J, Y, rn, lam, act, x.clone() if first else xt,
                                                           rt, Jt, Yt, its, budget, tol, live)
            if first:  # the evaluation at the start point is not an iteration
                its, first = its - live.to(its.dtype), False
            if not bool(act.any()):
                return x, r, J, Y, rn, its
            rt, Jt, Yt = (v.contiguous() for v in evaluate(xt, prm, loads, field, t))

    def _table(self, prm):
        ver = tensor_versions(prm)
        if self._step_key is not prm or self._step_ver != ver:  # reused while the params are unchanged
            self._step_key, self._step_ver, self._step_tab = prm, ver, step_table(prm, self.rod.grid)

    def _chord(self, x, J, prm, loads, field, t, its, live, flat=None, max_steps: int = CHORD_MAX):
        """At most ``max_steps`` chord iterations from ``x`` with the Jacobian ``J`` frozen (see the module
        docstring), evaluated in blocks of :attr:`chord_block`: the point LM starts from and the updated iteration
        counts (a singular ``J``: no steps)."""
        Jinv, info = torch.linalg.inv_ex(J)
        if bool((info != 0).any()):
            return x, its
        Jinv = Jinv.expand(*x.shape[:-1], 6, 6)
        budget, block = its + max_steps, self.chord_block
        if self.compile and self.steps_per_call == 1:
            self._table(prm)
            out = fast_chord(self, x, Jinv, prm, loads, field, t, its, budget, live, self._step_tab, max_steps,
                             block, flat=flat)
            if out is not None:
                return out
        inf = torch.full(x.shape[:-1], math.inf, dtype=x.dtype, device=x.device)
        best, best_rn, prev, tol = x, inf, inf, torch.tensor(self.tol, dtype=x.dtype, device=x.device)
        xp, rp = x, torch.zeros_like(x)
        for k in range(_chord_evaluations(max_steps, block)):
            r = shoot(x, prm, self.rod.grid, loads, self.scales, field, t, record=False, fd_step=self.fd_step).r
            x, Jinv, xp, rp, best, best_rn, prev, its, start, go = _chord_math(x, r, Jinv, xp, rp, best, best_rn,
                                                                              prev, its, budget, live, tol)
            if (k + 1) % block == 0 and not bool(go):
                break
        return start, its

    # ------------------------------------------------------------------ solve
    def solve(self, *, field=None, t: float = 0.0, init=None, load_steps: int = 1, max_load_steps: int = 64,
              params: CosseratParams | None = None, raise_on_failure: bool = True, differentiable: bool | None = None,
              max_iter: int | None = None, chord: Tensor | None = None, **load_kw) -> StaticSolution:
        """Solve for the loads given as keywords of :meth:`make_loads` (or ``loads=StaticLoads``), the
        magnet ``field`` hook and ``params`` (default the rod's). ``init``: a previous
        :class:`StaticSolution` or base wrench (..., 6) in SI (warm start; default the unloaded 0).
        ``load_steps`` > 1 solves at ``k/load_steps`` of every load in turn (continuation); problems
        that still fail are solved again from ``init`` with four times as many load steps, up to
        ``max_load_steps`` (set it to ``load_steps`` to switch that off). ``max_iter``: the LM iterations
        allowed per load step in this call (default the solver's). ``chord``: the scaled Jacobian (..., 6, 6) of a
        nearby solution (its ``jacobian``) for chord iterations before LM (module docstring; one load step
        only). ``differentiable`` (default:
        whenever an input requires grad) adds the implicit-function correction that makes the result
        differentiable."""
        loads = load_kw.pop("loads", None)
        if loads is not None and load_kw:
            raise ValueError(f"give the loads either as loads= or as keywords, not both (got loads= and "
                             f"{', '.join(sorted(load_kw))}=)")
        loads = self._loads(load_kw) if loads is None else self._check_loads(loads)
        if field is not None and not callable(field) and not hasattr(field, "wrench"):
            raise TypeError("field must be callable as field(t, positions) -> B | (B, dB) or have "
                            "wrench(t, positions, moments)")
        if field is not None and not self.rod.magnets:
            raise ValueError("field: this rod has no magnets for the field to act on (it would be ignored)")
        max_iter = self.max_iter if max_iter is None else max_iter
        for nm, v in (("load_steps", load_steps), ("max_load_steps", max_load_steps), ("max_iter", max_iter)):
            check_integer(nm, v)
        if chord is not None:
            if load_steps != 1:
                raise ValueError(f"chord iterations need load_steps=1, got load_steps={load_steps}")
            if not isinstance(chord, Tensor) or chord.shape[-2:] != (6, 6) or not bool(torch.isfinite(chord).all()):
                raise ValueError("chord must be a finite scaled Jacobian (..., 6, 6) (a StaticSolution's jacobian), "
                                 f"got {chord.shape if isinstance(chord, Tensor) else type(chord).__name__}")
        prm = self.params if params is None else self._check_params(params)
        kw = dict(dtype=self.dtype, device=self.device)
        sc = self._sc
        if init is None:
            x0 = torch.zeros(6, **kw)
        elif isinstance(init, StaticSolution):
            x0 = init.base_wrench.detach().to(**kw) / sc
        else:
            x0 = _vec("init", init, self.dtype, self.device, (6,)) / sc
        flat = flatten_field(field) if self.compile else None
        shp = self._batch_shape(loads, prm, x0, field, t, flat)
        if chord is not None and not _broadcasts_to(chord.shape[:-2], shp):
            raise ValueError(f"chord: its batch shape {tuple(chord.shape[:-2])} does not broadcast to the problems' "
                             f"{tuple(shp)}")
        x0 = x0.detach().expand(*shp, 6).clone()
        its = torch.zeros(shp, dtype=torch.long, device=self.device)
        grad = differentiable if differentiable is not None else _needs_grad(tuple(loads), tuple(prm), field)
        prm_d, loads_d = _detach(prm), _detach(loads)

        def continuation(steps, live, its, x=x0):
            for k in range(1, steps + 1):
                lk = loads_d if k == steps else loads_d.scaled(k / steps)
                x, r, J, Y, rn, its = self._lm(x, prm_d, lk, field, t, its,
                                               _LAM_COLD if (init is None and k == 1) else _LAM_WARM, live, flat,
                                               max_iter)
            return x, r, J, Y, rn, its

        with torch.no_grad():
            live = torch.ones(shp, dtype=torch.bool, device=self.device)
            xc = x0
            if chord is not None:
                xc, its = self._chord(x0, chord.detach().to(**kw), prm_d, loads_d, field, t, its, live, flat,
                                      min(CHORD_MAX, max_iter))
            x, r, J, Y, rn, its = continuation(load_steps, live, its, xc)
            if raise_on_failure:  # (otherwise such problems end unconverged, with the others solved)
                self._check_start(x0, prm_d, loads_d, max_load_steps, field, t, rn)
            steps = load_steps
            while steps < max_load_steps and not bool((rn <= self.tol).all()):
                steps = min(4 * steps, max_load_steps)
                live = ~(rn <= self.tol)
                new = continuation(steps, live, its)
                x, r, J, Y, rn = (torch.where(live.reshape(tuple(shp) + (1,) * (a.dim() - live.dim())), a, b)
                                  for a, b in zip(new[:5], (x, r, J, Y, rn)))
                its = new[5]
        converged = rn <= self.tol
        if raise_on_failure and not bool(converged.all()):
            bad = (~converged).flatten().nonzero().flatten()
            i = int(bad[0])
            raise SolverError(f"Cosserat shooting did not converge for {bad.numel()} of {converged.numel()} problem(s): "
                              f"scaled tip residual {float(rn.flatten()[i]):.3e} > tol {self.tol:.1e} after "
                              f"{int(its.flatten()[i])} Levenberg-Marquardt iterations with up to {steps} load steps "
                              f"(try a warm start, more nodes, a larger max_iter or max_load_steps)",
                              step=int(its.flatten()[i]), node=i)
        if grad:
            Y, x = self._implicit(x, J, prm, loads, field, t)
        return StaticSolution(self._s, Y, x * sc, converged, its, rn, J)

    def _check_start(self, x0, prm, loads, n_steps, field, t, rn):
        """A :class:`SolverError` at once for a problem that found no finite residual and whose tip residual is not
        finite even at its start point under the smallest load step (``loads`` over ``n_steps``): a NaN or infinite
        field, load or parameter. Load stepping cannot mend that and used to spend about a minute finding out."""
        lost = ~torch.isfinite(rn)
        if not bool(lost.any()):
            return
        r0 = shoot(x0, prm, self.rod.grid, loads.scaled(1 / n_steps), self.scales, field, t, record=False,
                   fd_step=self.fd_step).r
        bad = (lost & ~torch.isfinite(r0).all(-1)).flatten().nonzero().flatten()
        if bad.numel():
            raise SolverError(f"Cosserat shooting: the tip residual of {bad.numel()} of {lost.numel()} problem(s) is "
                              f"not finite at the start point (the unloaded or warm-start base wrench under "
                              f"1/{n_steps} of the loads): the field hook, a load or a parameter "
                              f"gives NaN or infinity", step=0, node=int(bad[0]))

    def _batch_shape(self, loads: StaticLoads, prm: CosseratParams, x0: Tensor, field, t: float, flat=None):
        """The problems' batch shape: that of the loads, the parameters, the start ``x0`` (..., 6) and the field's
        output broadcast together."""
        shapes = [t_.shape[:-1] for t_ in (loads.gravity, loads.line_force, loads.line_torque,
                                           loads.base_position, loads.base_quaternion, x0)]
        shapes += [loads.point_force.shape[:-2], loads.point_torque.shape[:-2], loads.field_scale.shape,
                   prm.ks_inv.shape[:-2], prm.magnet_moment.shape[:-2]]
        if field is not None and self.rod.magnets:
            shapes.append(self._field_batch(field, t, loads, flat))
        return broadcast_shape(*shapes)

    def _loads(self, kw: dict) -> StaticLoads:
        """:meth:`make_loads` of ``kw``, cached per solver when every value is a number, a sequence of
        numbers or ``None`` (a control loop re-solving for new fields then builds its loads once; the
        solver never writes to them)."""
        try:
            key = tuple(sorted((k, _frozen(v)) for k, v in kw.items()))
        except TypeError:  # tensors and other objects: no caching
            return self.make_loads(**kw)
        loads = self._loads_cache.get(key)
        if loads is None:
            loads = self.make_loads(**kw)
            if len(self._loads_cache) >= 64:
                self._loads_cache.clear()
            self._loads_cache[key] = loads
        return loads

    def _field_batch(self, field, t, loads, flat=None) -> tuple[int, ...]:
        """Batch shape of the field's output (probed once at the base position; for a field that the
        compiled path can trace, once per field structure, since its shapes cannot depend on values)."""
        pos = loads.base_position.detach().unsqueeze(-2)
        B = getattr(field, "B", None)
        if isinstance(field, UniformField) and isinstance(B, Tensor):  # B (..., 1, 3) for a batch (checked by it)
            return B.shape[:-2]
        key = None if flat is None else (flat[0], tuple(pos.shape), float(t))
        if key is not None and key in self._field_shapes:
            return self._field_shapes[key]
        with torch.no_grad():
            if callable(field):
                out = field(t, pos)
                B = out[0] if isinstance(out, tuple) else out
            else:
                B = field.wrench(t, pos, torch.ones_like(pos))[1]
        if key is not None:
            if len(self._field_shapes) >= 64:
                self._field_shapes.clear()
            self._field_shapes[key] = B.shape[:-2]
        return B.shape[:-2]

    def _implicit(self, x, J, prm, loads, field, t):
        with torch.no_grad():
            T = shoot(x, _detach(prm), self.rod.grid, _detach(loads), self.scales, field, t, tangent=True,
                      record_tangent=True, fd_step=self.fd_step).T
        res = shoot(x, prm, self.rod.grid, loads, self.scales, field, t, tangent=False, fd_step=self.fd_step)
        dx = -torch.linalg.solve(J, res.r)
        return res.Y + (T * dx[..., None, :, None]).sum(-2), x + dx


def _broadcasts_to(shape, target) -> bool:
    """Whether a batch ``shape`` broadcasts to ``target`` (without changing it)."""
    return len(shape) <= len(target) and all(d in (1, t) for d, t in zip(reversed(shape), reversed(target)))


def _lm_math(x, r, J, Y, rn, lam, act, xt, rt, Jt, Yt, its, budget, tol, live):
    """Accept or reject the trial ``xt`` (residual ``rt``, Jacobian ``Jt``, states ``Yt``) of the active
    problems, update ``lambda`` by the gain ratio, count the iteration, and propose the next trial."""
    rnt = rt.norm(dim=-1)
    dx = xt - x
    pred = rn * rn - (r + (J @ dx.unsqueeze(-1)).squeeze(-1)).square().sum(-1)  # the model's decrease
    rho = (rn * rn - rnt * rnt) / pred.clamp_min(1e-300)
    ok = act & torch.isfinite(rnt) & (rnt < rn) & torch.isfinite(Jt).all(-1).all(-1)
    o1 = ok.unsqueeze(-1)
    x, r, rn = torch.where(o1, xt, x), torch.where(o1, rt, r), torch.where(ok, rnt, rn)
    J, Y = torch.where(o1.unsqueeze(-1), Jt, J), torch.where(o1.unsqueeze(-1), Yt, Y)
    good = torch.where(rho > 0.75, lam / 10, torch.where(rho > 0.25, lam, lam * 2)).clamp_min(1e-15)
    good = torch.where(torch.isfinite(rho), good, lam)  # the start point has no model
    lam = torch.where(ok, good, torch.where(act, (lam * 10).clamp_min(1e-3), lam))
    its = its + act.to(its.dtype)
    act = live & (rn > tol) & (its < budget) & (lam < _LAM_MAX)
    JtJ = J.transpose(-1, -2) @ J
    g = (J.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)
    d = torch.diagonal(JtJ, dim1=-2, dim2=-1).clamp_min(1e-12)
    A = JtJ + torch.diag_embed(lam.unsqueeze(-1) * d)
    A = torch.where(torch.isfinite(A).all(-1).all(-1)[..., None, None], A, torch.eye(6, dtype=A.dtype, device=A.device))
    step = -_spd_solve(A, torch.where(torch.isfinite(g), g, torch.zeros_like(g)))
    return x, r, J, Y, rn, lam, its, act, x + torch.where(act.unsqueeze(-1), step, torch.zeros_like(step))


def _chord_evaluations(max_steps: int, block: int) -> int:
    """The most residual evaluations of ``max_steps`` chord steps: one more than the steps (the last one checks),
    in whole blocks of ``block``."""
    return -(-(max_steps + 1) // block) * block


def _chord_math(x, r, Jinv, xp, rp, best, best_rn, prev, its, budget, live, tol):
    """One chord iteration's bookkeeping at ``x`` with residual ``r`` (``xp``, ``rp``: the point and residual of
    the last iteration; ``prev`` its residual norm, inf before the first): the inverse Jacobian ``Jinv`` updated by
    Broyden's secant (``(x - xp, r - rp)``), the best point kept, and a step ``x - J^-1 r`` where the problem is
    live, has steps left (``its < budget``), is not yet within ``tol`` and its residual shrank by
    :data:`CHORD_RATE` since the last step. ``start`` is
    where LM is to start: the new point where the contraction predicts it within ``tol`` (LM's first evaluation
    checks it), else the best one; ``go`` whether any problem steps on unpredicted.
    ``-> (x, Jinv, xp, rp, best, best_rn, prev, its, start, go)``"""
    rn = r.norm(dim=-1)
    s, y = (x - xp).unsqueeze(-1), (r - rp).unsqueeze(-1)
    Hy = Jinv @ y
    den = (s.transpose(-1, -2) @ Hy)[..., 0, 0]
    upd = torch.isfinite(prev) & torch.isfinite(rn) & (den.abs() > 1e-300)
    den = torch.where(upd, den, torch.ones_like(den))
    Jinv = torch.where(upd[..., None, None], Jinv + (s - Hy) @ (s.transpose(-1, -2) @ Jinv) / den[..., None, None],
                       Jinv)
    ok = torch.isfinite(rn) & (rn < best_rn)
    best, best_rn = torch.where(ok.unsqueeze(-1), x, best), torch.where(ok, rn, best_rn)
    step = live & (its < budget) & ~(best_rn <= tol) & ok & (rn <= CHORD_RATE * prev)
    xn = torch.where(step.unsqueeze(-1), x - (Jinv @ r.unsqueeze(-1)).squeeze(-1), x)
    pred = step & torch.isfinite(prev) & (rn * rn <= tol * prev)
    start = torch.where(pred.unsqueeze(-1), xn, best)
    return xn, Jinv, x, r, best, best_rn, rn, its + step.to(its.dtype), start, (step & ~pred).any()


_COMPILED: list = []


def _compiled():
    """The compiled LM update and lane step, shared by all solvers of the process (the graphs do not
    depend on the rod or its node count; batch shape, dtype, magnets and field type specialise them).
    Inductor options: one fused loop per step (no fusion-size cap) and a C++ wrapper (low call cost)."""
    if not _COMPILED:
        opts = {"max_fusion_size": 100000, "cpp_wrapper": True}
        _COMPILED.extend((torch.compile(_lm_math, dynamic=False), torch.compile(lane_step, dynamic=False, options=opts),
                          torch.compile(lane_chunk, dynamic=False, options=opts)))
    return tuple(_COMPILED)


def _spd_solve(A: Tensor, b: Tensor) -> Tensor:
    """``A^{-1} b`` for symmetric positive definite (..., n, n): LAPACK in eager, an unrolled
    Cholesky (pointwise, fusable) under ``torch.compile``."""
    if not (torch.compiler.is_compiling() or _UNROLLED[0]):
        return torch.linalg.solve(A, b)
    n = A.shape[-1]
    Lm = [[None] * n for _ in range(n)]
    for j in range(n):
        d = A[..., j, j] - sum((Lm[j][k] * Lm[j][k] for k in range(j)), torch.zeros_like(A[..., 0, 0]))
        Lm[j][j] = torch.sqrt(d.clamp_min(torch.finfo(A.dtype).tiny))
        for i in range(j + 1, n):
            s = A[..., i, j] - sum((Lm[i][k] * Lm[j][k] for k in range(j)), torch.zeros_like(d))
            Lm[i][j] = s / Lm[j][j]
    z = []
    for i in range(n):
        z.append((b[..., i] - sum((Lm[i][k] * z[k] for k in range(i)), torch.zeros_like(b[..., 0]))) / Lm[i][i])
    xs = [None] * n
    for i in reversed(range(n)):
        xs[i] = (z[i] - sum((Lm[k][i] * xs[k] for k in range(i + 1, n)), torch.zeros_like(z[i]))) / Lm[i][i]
    return torch.stack(xs, -1)


_UNROLLED = [False]


@contextlib.contextmanager
def _spd_unrolled():
    """While tracing a program for :mod:`physics.cosserat_fast`: the unrolled Cholesky."""
    _UNROLLED[0] = True
    try:
        yield
    finally:
        _UNROLLED[0] = False


def _frozen(v):
    """``v`` as a hashable key when it is a number, a (nested) sequence of numbers or ``None``; else
    ``TypeError``."""
    if v is None or isinstance(v, (bool, int, float)):
        return v
    if isinstance(v, (tuple, list)):
        return tuple(_frozen(a) for a in v)
    raise TypeError(type(v).__name__)


def _cat_tip(pts: Tensor, tip: Tensor) -> list[Tensor]:
    shp = broadcast_shape(pts.shape[:-2], tip.shape[:-1])
    return [pts.expand(*shp, *pts.shape[-2:]), tip.expand(*shp, 3).unsqueeze(-2)]


def _detach(nt):
    """``nt`` itself when nothing in it requires grad (keeps caches keyed on it valid), else detached."""
    if not any(isinstance(v, Tensor) and v.requires_grad for v in nt):
        return nt
    return type(nt)(*(v.detach() if isinstance(v, Tensor) else v for v in nt))


def solve_static(rod: CosseratRod, *, dtype: torch.dtype = torch.float64, device=None, tol: float | None = None,
                 max_iter: int = 50, jacobian: str = "forward", **kw) -> StaticSolution:
    """One-off :meth:`CosseratSolver.solve` (build a :class:`CosseratSolver` to reuse it)."""
    return CosseratSolver(rod, dtype=dtype, device=device, tol=tol, max_iter=max_iter, jacobian=jacobian).solve(**kw)

