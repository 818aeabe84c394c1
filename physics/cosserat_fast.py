"""The compiled fast path of the Cosserat shooting (``CosseratSolver(..., compile=True)``): a whole
Levenberg-Marquardt iteration (the shot through the grid with its six tangents, then the update) as
one compiled program, called through a thin wrapper.

Layout. For batches of 8 problems or more the state of ``N`` problems is one tensor ``Z`` (91, N):
rows 0-12 the primal ``y`` and rows ``13 + 13 j + c`` the tangent ``dy_c/dxi_j``, each row
contiguous over the problems, so that the compiled loops run over ``N`` with vector loads and
stores; the primal right-hand side and its intermediates (``R``, ``v``, ``u``, ``p'``) are computed
once per problem and shared by the six tangents (the variational equation of
:mod:`physics.cosserat_ode`, written out per component); ``n' = -f`` does not depend on the state, so
the tangents of ``n`` only change at the jumps. Smaller batches run on six *lanes* (``Z`` (N, 6, 26):
lane ``j`` a copy of the primal and the tangent ``dy/dxi_j``), which inductor fuses into one loop
per step.

Compilation. An iteration is traced with ``make_fx`` (fake tensors: a data-dependent branch
anywhere, e.g. in a field hook, fails the trace and the solver falls back to
:mod:`physics.cosserat_lanes`) and compiled with ``torch._inductor.compile``; the callable it returns
costs a few microseconds a call, against about 30 us for a ``torch.compile`` d function (guards,
config and autograd wrappers). The grid is unrolled in the program and each step applies only the
magnets at its end node; the field hook's tensors are inputs of the program (a field object is
rebuilt around the traced inputs), so a new field of the same kind and shapes reuses it. On lanes a
shot of more than ``MAX_ROWS`` grid steps is split into near-equal stretches, one program each (the
last one with the update), which bounds the size of a generated kernel (and its compile time, about
15 s per step here). A warm solve at batch 1 is then a few calls, one per LM iteration: the kernel
costs about 180 us for the 12 steps of the Paper II rod and the call a few us, where one program
per step cost 52 calls of 7-36 us of kernel plus 5-10 us of call each. In the layout for batches a
fused shot compiled for more than ten minutes, so there every step is its own program (the call
overhead is small against the work of a batch); the programs of steps without magnets are shared.

Chord iterations (``CosseratSolver.solve(chord=...)``) run :func:`chord_program`: a block of
``CosseratSolver.chord_block`` (3) chord iterations, each the whole shot without tangents and the chord step, one
program in either layout (at batch 1 on the Paper II rod about 45 us an iteration against about 220 us for an LM
iteration's shot, warm; in a real-time loop each program runs from a cold cache). A real-time loop's frames reuse the programs and their inputs through
:class:`physics.cosserat_frames.FrameSolve` (:func:`chord_setup` and :func:`lm_setup` look them up, :func:`run_chord`
and :func:`run_lm` run them).
"""
from __future__ import annotations

import copy
import math

import torch
from torch import Tensor

from .cosserat_lanes import end_of_step, rk4_tangent_step
from .cosserat_ode import _field_wrench
from .programs import compile_program

__all__ = ["NZ", "step_program", "flatten_field", "fast_lm", "fast_chord", "chord_setup", "run_chord", "lm_setup",
           "run_lm"]

NZ = 13 * 7  # primal + six tangents


# ----------------------------------------------------------------------------------------- the ODE
def _rot(w, x, y, z):
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return (ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz)


def _drot(q, d):
    """``dR = 2 B(q, dq)`` (the derivative of the quadratic form ``R(q)``)."""
    w, x, y, z = q
    dw, dx, dy, dz = d
    aw, ax, ay, az = w * dw, x * dx, y * dy, z * dz
    axy, axz, ayz = x * dy + y * dx, x * dz + z * dx, y * dz + z * dy
    awx, awy, awz = w * dx + x * dw, w * dy + y * dw, w * dz + z * dw
    return (2 * (aw + ax - ay - az), 2 * (axy - awz), 2 * (axz + awy),
            2 * (axy + awz), 2 * (aw - ax + ay - az), 2 * (ayz - awx),
            2 * (axz - awy), 2 * (ayz + awx), 2 * (aw - ax - ay + az))


def _mtv(M, a):  # M^T a
    return (M[0] * a[0] + M[3] * a[1] + M[6] * a[2], M[1] * a[0] + M[4] * a[1] + M[7] * a[2],
            M[2] * a[0] + M[5] * a[1] + M[8] * a[2])


def _mv(M, a):  # M a
    return (M[0] * a[0] + M[1] * a[1] + M[2] * a[2], M[3] * a[0] + M[4] * a[1] + M[5] * a[2],
            M[6] * a[0] + M[7] * a[1] + M[8] * a[2])


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _xi(q, u):  # q (x) (0, u)
    w, x, y, z = q
    return (-(x * u[0] + y * u[1] + z * u[2]), w * u[0] + y * u[2] - z * u[1],
            w * u[1] + z * u[0] - x * u[2], w * u[2] + x * u[1] - y * u[0])


def _rhs(y, ks, kb, vh, uh, f, tau):
    """Primal right-hand side (13-tuple) and the intermediates its tangents need."""
    q, n, m = y[3:7], y[7:10], y[10:13]
    R = _rot(*q)
    an, am = _mtv(R, n), _mtv(R, m)
    v = tuple(ks[i] * an[i] + vh[i] for i in range(3))
    u = tuple(kb[i] * am[i] + uh[i] for i in range(3))
    p = _mv(R, v)
    dq = tuple(0.5 * c for c in _xi(q, u))
    dm = tuple(-c - tau[i] for i, c in enumerate(_cross(p, n)))
    return (*p, *dq, -f[0], -f[1], -f[2], *dm), (R, v, u, p)


def _rhs_tangent(y, ctx, t, ks, kb):
    """Tangent right-hand side (13-tuple, ``None`` for the constant ``n``) of one direction."""
    R, v, u, p = ctx
    q, n, m = y[3:7], y[7:10], y[10:13]
    tq, tn, tm = t[3:7], t[7:10], t[10:13]
    S = _drot(q, tq)
    sn, sm, rn, rm = _mtv(S, n), _mtv(S, m), _mtv(R, tn), _mtv(R, tm)
    dv = tuple(ks[i] * (sn[i] + rn[i]) for i in range(3))
    du = tuple(kb[i] * (sm[i] + rm[i]) for i in range(3))
    sv, rv = _mv(S, v), _mv(R, dv)
    tp = tuple(a + b for a, b in zip(sv, rv))
    x1, x2 = _xi(tq, u), _xi(q, du)
    tdq = tuple(0.5 * (a + b) for a, b in zip(x1, x2))
    c1, c2 = _cross(tp, n), _cross(p, tn)
    tdm = tuple(-(a + b) for a, b in zip(c1, c2))
    return (*tp, *tdq, None, None, None, *tdm)


def _axpy(a, c, b):
    return tuple(ai if bi is None else ai + c * bi for ai, bi in zip(a, b))


# ----------------------------------------------------------------------------------------- one step
def step_program(mags: tuple[int, ...], batch: tuple[int, ...], field_rebuild, t: float, fd_step: float):
    """The step ``(Z, row, mag_moment, mag_mass, gravity, field_scale, *field_tensors) -> Z'``
    (``Z`` (91, N), ``row`` (N | 1, 25): h, K_s^-1, K_b^-1, v_hat, u_hat, distributed force and
    moment, point force and moment at the end node) with the point wrenches of the magnets ``mags``
    (indices) at its end node."""

    def step(Z, row, *rest):
        zs = Z.unbind(0)
        y, T = _rk4_row(zs[:13], [zs[13 + 13 * j: 26 + 13 * j] for j in range(6)], row, mags, rest, batch,
                        field_rebuild, t, fd_step)
        y = [c.expand(Z.shape[1:]) for c in y]
        T = [c.expand(Z.shape[1:]) for tj in T for c in tj]
        return torch.stack((*y, *T), 0)

    return step


def _rk4_row(y, T, row, mags, rest, batch, field_rebuild, t, fd_step):
    """One grid row in component form: the RK4 step of the primal ``y`` (13 components) and the tangents ``T`` (lists
    of 13; none for the residual alone), the quaternion renormalised, the point loads and the magnets ``mags`` applied
    at the row's end node; ``row`` (N | 1, 25) as in :func:`step_program`. Returns the new ``(y, T)``."""
    r = row.unbind(-1)
    h, ks, kb, vh, uh = r[0], r[1:4], r[4:7], r[7:10], r[10:13]
    f, tau, F, M = r[13:16], r[16:19], r[19:22], r[22:25]
    k1, c1 = _rhs(y, ks, kb, vh, uh, f, tau)
    d1 = [_rhs_tangent(y, c1, tj, ks, kb) for tj in T]
    y2 = _axpy(y, h / 2, k1)
    T2 = [_axpy(tj, h / 2, dj) for tj, dj in zip(T, d1)]
    k2, c2 = _rhs(y2, ks, kb, vh, uh, f, tau)
    d2 = [_rhs_tangent(y2, c2, tj, ks, kb) for tj in T2]
    y3 = _axpy(y, h / 2, k2)
    T3 = [_axpy(tj, h / 2, dj) for tj, dj in zip(T, d2)]
    k3, c3 = _rhs(y3, ks, kb, vh, uh, f, tau)
    d3 = [_rhs_tangent(y3, c3, tj, ks, kb) for tj in T3]
    y4 = _axpy(y, h, k3)
    T4 = [_axpy(tj, h, dj) for tj, dj in zip(T, d3)]
    k4, c4 = _rhs(y4, ks, kb, vh, uh, f, tau)
    d4 = [_rhs_tangent(y4, c4, tj, ks, kb) for tj in T4]
    h6 = h / 6
    y = [a + h6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(y, k1, k2, k3, k4)]
    T = [[a if b is None else a + h6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(*z)]
         for z in zip(T, d1, d2, d3, d4)]
    end_of_step(y, T, F, M)
    if mags:
        dy, dT = _magnet_jumps(y, T, mags, rest, batch, field_rebuild, t, fd_step)
        y[7:13] = [a + b for a, b in zip(y[7:13], dy)]
        for tj, dj in zip(T, dT):
            tj[7:13] = [a + b for a, b in zip(tj[7:13], dj)]
    return y, T


def _magnet_jumps(y, T, mags, rest, batch, field_rebuild, t, fd_step):
    """Point wrenches of the magnets ``mags`` (indices) at the step's end node, from the primal ``y``
    (13 components (N,)) and tangents ``T`` (6 lists of 13): the increments of ``n``, ``m`` (6 (N,))
    and of their tangents (6 lists of 6)."""
    mag_moment, mag_mass, gravity, field_scale, *ftens = rest
    N = math.prod(batch)
    tan = bool(T)  # no tangents: the primal jumps alone (the residual program)
    eye = torch.eye(3, dtype=y[0].dtype, device=y[0].device)

    def vec(c, lead=(N,)):  # a (..., 3) vector by multiply-adds, not a stack (no concat buffers)
        return sum(ci.reshape(*ci.shape, 1) * eye[i] for i, ci in enumerate(c)).expand(*lead, 3)

    R = _rot(*y[3:7])
    dR = [_drot(y[3:7], tj[3:7]) for tj in T]
    lane = torch.eye(6, dtype=y[0].dtype, device=y[0].device)

    def vec6(cs):  # (N, 6, 3) from six 3-tuples
        return sum(vec(c).unsqueeze(-2) * lane[j].unsqueeze(-1) for j, c in enumerate(cs))

    pos = vec(y[0:3])
    dpos = vec6([tj[0:3] for tj in T]) if tan else None
    field = field_rebuild(ftens) if field_rebuild is not None else None
    dy = [0.0] * 6
    dT = [[0.0] * 6 for _ in T]
    for k in mags:
        mub = mag_moment[..., k, :].unbind(-1)  # (N | 1,) each
        mu = vec(_mv(R, mub))
        dmu = vec6([_mv(S, mub) for S in dR]) if tan else None
        Fm = mag_mass[..., k, None] * gravity
        Tm = torch.zeros_like(mu)
        dF = dM = torch.zeros_like(dpos) if tan else None
        if field is not None:
            Fw, Tw, dF, dM = _field_wrench(field, t, pos.reshape(*batch, 3), mu.reshape(*batch, 3),
                                           dpos.reshape(*batch, 6, 3) if tan else None,
                                           dmu.reshape(*batch, 6, 3) if tan else None, fd_step)
            sc = field_scale.reshape(-1).unsqueeze(-1)
            Fm, Tm = Fm + Fw.reshape(-1, 3) * sc, Tw.reshape(-1, 3) * sc
            if tan:
                dF, dM = dF.reshape(-1, 6, 3) * sc.unsqueeze(-1), dM.reshape(-1, 6, 3) * sc.unsqueeze(-1)
        W = (*Fm.expand(N, 3).unbind(-1), *Tm.expand(N, 3).unbind(-1))
        for i in range(6):
            dy[i] = dy[i] - W[i]
        if tan:
            dF, dM = dF.expand(N, 6, 3), dM.expand(N, 6, 3)
            for i in range(6):
                for j in range(len(T)):
                    dT[j][i] = dT[j][i] - (dF if i < 3 else dM)[:, j, i % 3]
    return dy, dT


def lane_program(mags: tuple[int, ...], batch: tuple[int, ...], field_rebuild, t: float, fd_step: float):
    """The step on lanes for small batches: ``Z`` (N, 6, 26) holds in lane ``j`` a copy of the primal
    (last dim 0-12) and the tangent ``dy/dxi_j`` (13-25) (see :mod:`physics.cosserat_lanes`); ``row``
    and ``rest`` as in :func:`step_program`. (A lane-minor layout (26, N, 6) that inductor vectorises
    over the lanes was measured slower, and fused over a shot it crashed gcc 12.)"""

    def step(Z, row, *rest):
        zs = Z.unbind(-1)
        y, tg = zs[:13], zs[13:]
        r = row.unsqueeze(-2).unbind(-1)  # (N | 1, 1): broadcast over the lanes
        h, ks, kb, vh, uh = r[0], r[1:4], r[4:7], r[7:10], r[10:13]
        f, tau, F, M = r[13:16], r[16:19], r[19:22], r[22:25]

        y, tg = rk4_tangent_step(y, tg, h, ks, kb, vh, uh, f, tau, F, M)
        if mags:
            y0 = [c.expand(Z.shape[:-1])[:, 0] for c in y]
            T = [[c.expand(Z.shape[:-1])[:, j] for c in tg] for j in range(6)]
            dy, dT = _magnet_jumps(y0, T, mags, rest, batch, field_rebuild, t, fd_step)
            lane = torch.eye(6, dtype=Z.dtype, device=Z.device)
            for i in range(6):  # multiply-adds with one-hot lanes, not a stack (no concat buffers)
                y[7 + i] = y[7 + i] + dy[i].unsqueeze(-1)
                tg[7 + i] = tg[7 + i] + sum(dT[j][i].unsqueeze(-1) * lane[j] for j in range(6))
        return torch.stack([c.expand(Z.shape[:-1]) for c in (*y, *tg)], -1)

    return step


def initial_state(x: Tensor, base_p: Tensor, base_q: Tensor, scales, lanes: bool) -> Tensor:
    """``Z`` at the base for scaled base wrenches ``x`` (N, 6) (base pose (N | 1, 3), (N | 1, 4))."""
    fs, ms = scales
    N = x.shape[0]
    sc = torch.tensor([fs] * 3 + [ms] * 3, dtype=x.dtype, device=x.device)
    y0 = torch.cat((base_p.expand(N, 3), base_q.expand(N, 4), x * sc), -1)
    T0 = torch.zeros(6, 13, dtype=x.dtype, device=x.device)
    T0[:, 7:13] = torch.diag(sc)
    if lanes:
        return torch.cat((y0.unsqueeze(-2).expand(N, 6, 13), T0.expand(N, 6, 13)), -1).contiguous()
    return torch.cat((y0.transpose(0, 1), T0.reshape(78, 1).expand(78, N)), 0).contiguous()


def split_state(Z: Tensor, lanes: bool) -> tuple[Tensor, Tensor]:
    """Primal (N, 13) and tangents (N, 6, 13) of ``Z``."""
    if lanes:
        return Z[:, 0, :13], Z[:, :, 13:]
    return Z[:13].transpose(0, 1), Z[13:].reshape(6, 13, -1).permute(2, 0, 1)


def shot_program(lanes: bool, magnet_rows, batch: tuple[int, ...], field_rebuild, t: float, fd_step: float,
                 scales, record_base: bool, start: bool, n_prev: int | None):
    """A stretch of rows of one Levenberg-Marquardt iteration as one program (row ``i`` applies the point
    wrenches of the magnets ``magnet_rows[i]`` at its end node), from the trial base wrench ``xt``
    (``start``) or the state ``Z`` of the previous stretch:
    ``(Z, rows (R, N | 1, 25), x, r, J, Y, rn, lam, act, xt, its, budget, tol, live, base_p, base_q, *rest)
    -> (Z, its node states (N, R', 13))``. The last stretch (``n_prev`` not ``None``) takes the node
    states of the ``n_prev`` stretches before it after ``rest`` and ends with the update of
    ``physics.cosserat_shooting._lm_math`` (accept or reject the trial, next trial):
    ``-> (x, r, J, Y, rn, lam, its, act, next xt)``."""
    from .cosserat_shooting import _lm_math
    make = lane_program if lanes else step_program
    steps = [make(m, batch, field_rebuild, t, fd_step) for m in magnet_rows]
    fs, ms = scales

    def run(Z, rows, x, r, J, Y, rn, lam, act, xt, its, budget, tol, live, base_p, base_q, *rest):
        prev = ()
        if n_prev:
            rest, prev = rest[:-n_prev], rest[-n_prev:]
        ys = []
        if start:
            Z = initial_state(xt, base_p, base_q, scales, lanes)
            if record_base:
                ys.append(split_state(Z, lanes)[0])
        for step, row in zip(steps, rows.unbind(0)):
            Z = step(Z, row, *rest)
            ys.append(split_state(Z, lanes)[0])
        Yt = torch.stack(ys, -2)
        if n_prev is None:
            return Z.contiguous(), Yt.contiguous()
        Yt = torch.cat((*prev, Yt), -2)
        sc = torch.tensor([fs] * 3 + [ms] * 3, dtype=x.dtype, device=x.device)
        yl, Tl = split_state(Z, lanes)
        rt = yl[:, 7:13] / sc
        Jt = Tl[..., 7:13].transpose(-1, -2) / sc.unsqueeze(-1)
        out = _lm_math(x, r, J, Y, rn, lam, act, xt, rt, Jt, Yt, its, budget, tol, live)
        return tuple(o.contiguous() for o in out)  # the same strides as the inputs of the next call

    return run


def _residual_shot(magnet_rows, batch: tuple[int, ...], field_rebuild, t: float, fd_step: float, scales):
    """A whole shot without tangents, to the scaled tip residual:
    ``(x (N, 6), rows (R, N | 1, 25), base_p, base_q, *rest) -> r (N, 6)`` (row ``i`` applies the point wrenches
    of the magnets ``magnet_rows[i]``): the primal alone, about a seventh of the work of a shot with tangents."""
    fs, ms = scales

    def shot(x, rows, base_p, base_q, *rest):
        N = x.shape[0]
        sc = torch.tensor([fs] * 3 + [ms] * 3, dtype=x.dtype, device=x.device)
        y = list(torch.cat((base_p.expand(N, 3), base_q.expand(N, 4), x * sc), -1).unbind(-1))
        for mags, row in zip(magnet_rows, rows.unbind(0)):
            y = [c.expand(N) for c in _rk4_row(y, [], row, mags, rest, batch, field_rebuild, t, fd_step)[0]]
        return torch.stack(y[7:13], -1) / sc

    return shot


def chord_program(magnet_rows, batch: tuple[int, ...], field_rebuild, t: float, fd_step: float, scales,
                  evaluations: int):
    """``evaluations`` chord iterations (``CosseratSolver.solve(chord=...)``, a block of
    ``CosseratSolver.chord_block``) as one program: each the residual by a shot without tangents
    (:func:`_residual_shot`), then ``physics.cosserat_shooting._chord_math``:
    ``(x, J^-1, xp, rp, best, best_rn, prev, its, budget, live, tol, rows, base_p, base_q, *rest)
    -> (x, J^-1, xp, rp, best, best_rn, prev, its, start, go)``."""
    from .cosserat_shooting import _chord_math
    shot = _residual_shot(magnet_rows, batch, field_rebuild, t, fd_step, scales)

    def run(x, Jinv, xp, rp, best, best_rn, prev, its, budget, live, tol, rows, base_p, base_q, *rest):
        for _ in range(evaluations):
            r = shot(x, rows, base_p, base_q, *rest)
            x, Jinv, xp, rp, best, best_rn, prev, its, start, go = _chord_math(x, r, Jinv, xp, rp, best, best_rn,
                                                                              prev, its, budget, live, tol)
        return tuple(o.contiguous() for o in (x, Jinv, xp, rp, best, best_rn, prev, its, start, go))

    return run


def fast_chord(solver, x: Tensor, Jinv: Tensor, prm, loads, field, t: float, its: Tensor, budget: Tensor,
               live: Tensor, step_tab, max_steps: int, block: int, compiled: bool = True, flat=None):
    """The chord iterations of ``CosseratSolver._chord`` with the inverse Jacobian ``Jinv`` (..., 6, 6) on the
    compiled :func:`chord_program`, ``block`` evaluations a call: ``(start, its)``, or ``None`` where the field hook
    cannot be traced (the caller then shoots eagerly)."""
    setup = chord_setup(solver, x, Jinv, prm, loads, field, t, its, budget, live, step_tab, block, compiled, flat)
    if setup is None:
        return None
    shp = setup[-1]
    N = math.prod(shp)
    return run_chord(*setup[:3], x.reshape(N, 6).contiguous(), Jinv.reshape(N, 6, 6).contiguous(),
                     its.reshape(N).contiguous(), shp, max_steps, block)


def chord_setup(solver, x: Tensor, Jinv: Tensor, prm, loads, field, t: float, its: Tensor, budget: Tensor,
                live: Tensor, step_tab, block: int, compiled: bool = True, flat=None):
    """The chord program for inputs like these and what it takes besides the start, the inverse Jacobian and the
    iteration counts: ``(program, start values, fixed inputs, batch shape)`` (:func:`run_chord`; the field's tensors
    are the last fixed inputs), or ``None`` where the field hook cannot be traced."""
    inputs = _inputs(solver, x, prm, loads, field, step_tab, flat)
    if inputs is None:
        return None
    fkey, ftens, rebuild, shp, N, tabs, rows, rest, bp, bq = inputs
    key = ("chord", N, solver.tol, x.dtype, str(x.device))
    if key not in _STARTS:
        kw = dict(dtype=x.dtype, device=x.device)
        _STARTS[key] = (torch.zeros(N, 6, **kw), torch.full((N,), math.inf, **kw), torch.tensor(solver.tol, **kw))
    zero, inf, tol = _STARTS[key]
    state = _chord_state(x.reshape(N, 6).contiguous(), Jinv.reshape(N, 6, 6).contiguous(),
                         its.reshape(N).contiguous(), (zero, inf))
    fixed = [budget.reshape(N).contiguous(), live.reshape(N).contiguous(), tol, rows, bp, bq, *rest, *ftens]
    key = ("chord", compiled, block, shp, tabs.magnet_rows, solver.scales, fkey, float(t), float(solver.fd_step),
           _sig(state + fixed))
    if key in _FAILED:
        return None
    try:
        prog = _program(key, lambda: chord_program(tabs.magnet_rows, shp, rebuild, t, solver.fd_step,
                                                   solver.scales, block), state + fixed, compiled)
    except Exception as e:  # an untraceable field hook: fall back (once per key)
        import warnings
        warnings.warn(f"Cosserat fast chord iterations unavailable ({type(e).__name__}: {e}); shooting eagerly",
                      stacklevel=4)
        _FAILED.add(key)
        return None
    return prog, (zero, inf), fixed, shp


def _chord_state(x: Tensor, Jinv: Tensor, its: Tensor, starts) -> list:
    """The chord program's state at the start ``x`` (N, 6): ``x, J^-1, xp, rp, best, best_rn, prev, its`` (the
    programs never write to their inputs: one tensor may be several)."""
    zero, inf = starts
    return [x, Jinv, x, zero, x, inf, inf, its]


def run_chord(prog, starts, fixed: list, x: Tensor, Jinv: Tensor, its: Tensor, shp: tuple[int, ...],
              max_steps: int, block: int):
    """The chord program's blocks (:func:`chord_setup`) from ``x`` (N, 6) with ``Jinv`` (N, 6, 6) and the counts
    ``its`` (N,) until no problem steps on: ``(start, its)`` shaped by ``shp``."""
    from .cosserat_shooting import _chord_evaluations
    state = _chord_state(x, Jinv, its, starts)
    for _ in range(_chord_evaluations(max_steps, block) // block):
        *state, start, go = prog(*state, *fixed)
        if not bool(go):
            break
    return start.reshape(*shp, 6), state[-1].reshape(shp)


# ----------------------------------------------------------------------------------------- fields
def flatten_field(field):
    """``(key, tensors, rebuild)`` of a field hook whose state is tensors, numbers, strings and nested
    such objects or lists (``rebuild(tensors)`` a copy around other tensors), or ``None`` for any other
    hook (a function, a time function inside, ...)."""
    if field is None:
        return (None,), [], None
    leaves: list[Tensor] = []

    def walk(o, depth=0):
        if depth > 6:
            raise _Unsupported
        if isinstance(o, Tensor):
            leaves.append(o.detach())
            return ("T", o.shape, o.dtype, o.device)
        if o is None or isinstance(o, (bool, int, float, str)):
            return o
        if isinstance(o, (list, tuple)):
            return (type(o).__name__, tuple(walk(v, depth + 1) for v in o))
        if isinstance(o, dict):
            return ("dict", tuple((k, walk(v, depth + 1)) for k, v in sorted(o.items())))
        d = getattr(o, "__dict__", None)
        if d is None or callable(o) and not hasattr(type(o), "__call__") or isinstance(o, type) or \
                type(o).__module__ in ("builtins", "functools"):
            raise _Unsupported
        return (type(o), tuple((k, walk(v, depth + 1)) for k, v in sorted(d.items())))

    try:
        key = walk(field)
    except _Unsupported:
        return None

    def rebuild(tensors):
        it = iter(tensors)

        def build(o):
            if isinstance(o, Tensor):
                return next(it)
            if o is None or isinstance(o, (bool, int, float, str)):
                return o
            if isinstance(o, (list, tuple)):
                return type(o)(build(v) for v in o)
            if isinstance(o, dict):
                return {k: build(v) for k, v in sorted(o.items())}
            c = copy.copy(o)
            for k, v in sorted(vars(o).items()):
                object.__setattr__(c, k, build(v))
            return c

        return build(field)

    return key, leaves, rebuild


class _Unsupported(Exception):
    pass


# ----------------------------------------------------------------------------------------- the driver
_PROGRAMS: dict = {}
_FAILED: set = set()
LANES_BELOW = 8  # batches smaller than this run on six lanes, a whole LM iteration per program
MAX_ROWS = 16  # grid steps per program on lanes (a longer shot is split into near-equal stretches); one
# step per program in the layout for batches (fused, those compile for many minutes)
_EMPTY = torch.empty(0)


def _flat(v: Tensor, shp: tuple[int, ...], trail: int) -> Tensor:
    """``v`` (..., *trail dims) as (N, *trail) when it carries batch dims, else unchanged; contiguous."""
    if v.dim() > trail:
        v = v.expand(*shp, *v.shape[v.dim() - trail:]).reshape(-1, *v.shape[v.dim() - trail:])
    return v.contiguous()


def _sig(ts) -> tuple:
    return tuple((tuple(a.shape), a.stride(), a.dtype) for a in ts)


def _prepared(solver, prm, loads, shp: tuple[int, ...], lanes: bool, step_tab):
    """The loop-invariant inputs of the iteration program for ``prm`` and ``loads``: ``(tabs, rows, rest
    without the field tensors, base position, base quaternion)``, cached while the same ``prm`` and
    ``loads`` objects come back, their values unchanged (the solver hands out one ``StaticLoads`` per set of number
    inputs)."""
    from .cosserat import broadcast_shape
    from .cosserat_lanes import lane_tables
    from .cosserat_shooting import tensor_versions
    key = (id(solver), id(prm), id(loads), shp, lanes)
    hit = _PREP.get(key)
    ver = tensor_versions(prm, loads)
    if hit is not None and hit[0] is prm and hit[1] is loads and hit[2] is step_tab and hit[4] == ver:
        return hit[3]
    tabs = lane_tables(prm, solver.rod.grid, loads, step_tab)
    st, ld = tabs.step, tabs.loads
    nr = st.shape[-2]
    bs = broadcast_shape(st.shape[:-2], ld.shape[:-2])
    rows = torch.cat((st.expand(*bs, nr, 13), ld.expand(*bs, nr, 12)), -1)
    rows = _flat(rows, shp, 2).movedim(-2, 0).contiguous() if bs else rows.unsqueeze(1).contiguous()
    rest = [_flat(prm.magnet_moment, shp, 2), _flat(prm.magnet_mass, shp, 1), _flat(loads.gravity, shp, 1),
            _flat(loads.field_scale.reshape(*loads.field_scale.shape, 1), shp, 1).reshape(-1)]
    out = (tabs, rows, [a.contiguous() for a in rest], _flat(loads.base_position, shp, 1),
           _flat(loads.base_quaternion, shp, 1))
    if len(_PREP) >= 64:
        _PREP.clear()
    _PREP[key] = (prm, loads, step_tab, out, ver)  # (the references keep the ids from being reused)
    return out


def _inputs(solver, x: Tensor, prm, loads, field, step_tab, flat):
    """What a program of the fast path takes for the scaled base wrenches ``x`` (..., 6): ``(field key, field
    tensors, field rebuild, batch shape, N, *_prepared(...))``, or ``None`` where the field hook cannot be traced."""
    flat = flatten_field(field) if flat is None else flat
    if flat is None:
        return None
    fkey, ftens, rebuild = flat
    shp = tuple(x.shape[:-1])
    N = math.prod(shp)
    return (fkey, [a.contiguous() for a in ftens], rebuild, shp, N,
            *_prepared(solver, prm, loads, shp, N < LANES_BELOW, step_tab))


def _start(N: int, n_rec: int, lam0: float, tol: float, dtype, device):
    """Start values of the LM state (r, J, Y, |r|, lambda, tol); the programs never write to their inputs,
    so these are shared between solves."""
    key = (N, n_rec, lam0, tol, dtype, str(device))
    if key not in _STARTS:
        kw = dict(dtype=dtype, device=device)
        _STARTS[key] = (torch.zeros(N, 6, **kw), torch.eye(6, **kw).expand(N, 6, 6).contiguous(),
                        torch.zeros(N, n_rec, 13, **kw), torch.full((N,), math.inf, **kw),
                        torch.full((N,), lam0, **kw), torch.tensor(tol, **kw))
    return _STARTS[key]


_PREP: dict = {}
_STARTS: dict = {}


def fast_lm(solver, x: Tensor, prm, loads, field, t: float, its: Tensor, lam0: float, live: Tensor, step_tab,
            compiled: bool = True, flat=None, max_iter: int | None = None):
    """:meth:`CosseratSolver._lm` on the compiled iteration program; ``None`` where the field hook
    cannot be traced (the caller then takes the ``torch.compile`` path). ``compiled=False`` runs the
    same program eagerly (tests); ``flat``: :func:`flatten_field` of ``field`` when already known;
    ``max_iter``: the iterations allowed (default the solver's)."""
    max_iter = solver.max_iter if max_iter is None else max_iter
    setup = lm_setup(solver, x, prm, loads, field, t, its, lam0, live, step_tab, compiled, flat, max_iter)
    if setup is None:
        return None
    chunks, starts, base, fixed, shp, n_rec = setup
    N = math.prod(shp)
    itf = its.reshape(N).contiguous()
    return run_lm(chunks, starts, base, fixed, x.reshape(N, 6).contiguous(), itf, itf + max_iter,
                  live.reshape(N).contiguous(), shp, n_rec)


def lm_setup(solver, x: Tensor, prm, loads, field, t: float, its: Tensor, lam0: float, live: Tensor, step_tab,
             compiled: bool = True, flat=None, max_iter: int | None = None):
    """The programs of an LM iteration for inputs like these and what they take besides the start, the iteration
    counts, their budget and the live problems: ``(chunks, start values, (base position, base quaternion), fixed
    inputs, batch shape, records)`` (:func:`run_lm`; the field's tensors are the last fixed inputs), or ``None`` where
    the field hook cannot be traced."""
    from .cosserat_shooting import _spd_unrolled
    inputs = _inputs(solver, x, prm, loads, field, step_tab, flat)
    if inputs is None:
        return None
    fkey, ftens, rebuild, shp, N, tabs, rows, rest, bp, bq = inputs
    lanes = N < LANES_BELOW
    n_rec = rows.shape[0] + int(tabs.record_base)
    starts = _start(N, n_rec, lam0, solver.tol, x.dtype, x.device)
    key = (compiled, lanes, tabs.magnet_rows, tabs.record_base, solver.scales, fkey, float(t), float(solver.fd_step),
           x.dtype, str(x.device), shp, tuple(rows.shape), _sig((bp, bq, *rest)), its.dtype)
    if key in _FAILED:
        return None
    chain = _CHAINS.get(key)
    if chain is None:
        xf, itf, livef = x.reshape(N, 6).contiguous(), its.reshape(N).contiguous(), live.reshape(N).contiguous()
        lm_args = _lm_args(xf, itf, itf + (solver.max_iter if max_iter is None else max_iter), livef.clone(), livef,
                           starts, (bp, bq))
        lm_args[7] = xf.clone()  # (traced with no input passed twice: a trace would tie the two)
        try:
            with _spd_unrolled():  # (eagerly: LAPACK)
                progs = _build_chain(solver, lanes, tabs, shp, fkey, rebuild, t, rows, lm_args, rest + ftens,
                                     compiled)
        except Exception as e:  # an untraceable field hook: fall back (once per key)
            import warnings
            warnings.warn(f"Cosserat fast path unavailable ({type(e).__name__}: {e}); using torch.compile",
                          stacklevel=4)
            _FAILED.add(key)
            return None
        chain = _CHAINS[key] = [progs, None, None]
    if chain[1] is not rows:  # the programs with their stretches of rows, kept while the rows are
        chain[1:] = rows, [(prog, rows[a:b]) for prog, a, b in chain[0]]
    return chain[2], starts, (bp, bq), rest + ftens, shp, n_rec


def _lm_args(x: Tensor, its: Tensor, budget: Tensor, act: Tensor, live: Tensor, starts, base) -> list:
    """The LM programs' state and loop inputs at the start ``x`` (N, 6) (evaluated first, as the trial):
    ``x, r, J, Y, |r|, lambda, act, xt, its, budget, tol, live, base_p, base_q``."""
    r, J, Y, rn, lam, tol = starts
    return [x, r, J, Y, rn, lam, act, x, its, budget, tol, live, *base]


def run_lm(chunks: list, starts, base, fixed: list, x: Tensor, its: Tensor, budget: Tensor, live: Tensor,
           shp: tuple[int, ...], n_rec: int):
    """LM iterations on the programs of :func:`lm_setup` from ``x`` (N, 6) (evaluated first), with the counts
    ``its`` (N,), their ``budget`` and the ``live`` problems, until every live problem has converged or run out of
    iterations: ``(x, r, J, Y, |r|, its)`` shaped by ``shp``."""
    lm_args, first = _lm_args(x, its, budget, live, live, starts, base), True
    while True:
        carry, ys = _EMPTY, []
        for prog, rows_k in chunks[:-1]:
            carry, Yc = prog(carry, rows_k, *lm_args, *fixed)
            ys.append(Yc)
        prog, rows_k = chunks[-1]
        xf, r, J, Y, rn, lam, itf, act, xt = prog(carry, rows_k, *lm_args, *fixed, *ys)
        if first:  # the evaluation at the start point is not an iteration
            itf, first = itf - live.to(itf.dtype), False
        if not bool(act.any()):
            break
        lm_args = [xf, r, J, Y, rn, lam, act, xt, itf, *lm_args[9:]]
    return (xf.reshape(*shp, 6), r.reshape(*shp, 6), J.reshape(*shp, 6, 6), Y.reshape(*shp, n_rec, 13),
            rn.reshape(shp), itf.reshape(shp))


def _build_chain(solver, lanes: bool, tabs, shp, fkey, rebuild, t: float, rows: Tensor, lm_args: list, rest: list,
                 compiled: bool) -> list:
    """The programs of one LM iteration, ``[(program, first row, end row), ...]`` (see :func:`shot_program`),
    each compiled for the inputs the stretch before it really produces (one dry shot)."""
    nr = rows.shape[0]
    n_chunks = -(-nr // (MAX_ROWS if lanes else 1))
    cuts = [round(k * nr / n_chunks) for k in range(n_chunks + 1)]
    chain, carry, ys = [], _EMPTY, []
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        start, n_prev = k == 0, (k if k == n_chunks - 1 else None)
        mags = tabs.magnet_rows[a:b]
        args = [carry, rows[a:b], *lm_args, *rest, *(ys if n_prev else ())]
        key = (compiled, lanes, shp, mags, start, n_prev, tabs.record_base, solver.scales, fkey, float(t),
               float(solver.fd_step), _sig(args))
        prog = _program(key, lambda: shot_program(lanes, mags, shp, rebuild, t, solver.fd_step, solver.scales,
                                                  tabs.record_base, start, n_prev), args, compiled)
        chain.append((prog, a, b))
        if n_prev is None:
            carry, Yc = prog(*args)
            ys.append(Yc)
    return chain


_CHAINS: dict = {}


def _program(key, make, inputs, compiled: bool):
    if key not in _PROGRAMS:
        _PROGRAMS[key] = compile_program(make(), inputs) if compiled else make()
    return _PROGRAMS[key]
