"""The compiled fast path of the Cosserat shooting (``CosseratSolver(..., compile=True)``): one RK4
step with its six tangents as a single fused pointwise loop over the problems, compiled ahead of
the solve and called through a thin wrapper.

Layout. The state of ``N`` problems is one tensor ``Z`` (91, N): rows 0-12 the primal ``y`` and rows
``13 + 13 j + c`` the tangent ``dy_c/dxi_j``, each row contiguous over the problems, so that the
compiled loop runs over ``N`` with vector loads and stores. The primal right-hand side and its
intermediates (``R``, ``v``, ``u``, ``p'``) are computed once per problem and shared by the six
tangents (the variational equation of :mod:`physics.cosserat_ode`, written out per component);
``n' = -f`` does not depend on the state, so the tangents of ``n`` only change at the jumps.

Compilation. A step is traced with ``make_fx`` (fake tensors: a data-dependent branch anywhere, e.g.
in a field hook, fails the trace and the solver falls back to :mod:`physics.cosserat_lanes`) and
compiled with ``torch._inductor.compile``; the callable it returns costs a few microseconds a call,
against about 30 us for a ``torch.compile`` d function (guards, config and autograd wrappers),
which dominated the per-step cost at batch 1. Two step programs per batch shape: without magnets,
and with the (masked) magnet code and the field. The field hook's tensors are inputs of the program
(a field object is rebuilt around the traced inputs), so a new field of the same kind and shapes
reuses it. Each row of the step table (grid step: ``h``, compliances, intrinsic strains; its loads;
which magnets sit at its end node) is its own contiguous tensor.

A Levenberg-Marquardt update (accept/reject, gain ratio, damped normal equations by an unrolled
Cholesky) with the start state of the next shot is a third program: a warm solve is then a few
shots of ``n_nodes - 1`` step calls and one update call each.
"""
from __future__ import annotations

import copy
import math

import torch
from torch import Tensor

from .cosserat_lanes import end_of_step, rk4_tangent_step
from .cosserat_ode import _field_wrench

__all__ = ["NZ", "step_program", "flatten_field", "compile_program"]

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
def step_program(magnets: bool, batch: tuple[int, ...], field_rebuild, t: float, fd_step: float):
    """The step ``(Z, row, [mag_moment, mag_mass, gravity, field_scale, *field_tensors]) -> Z'``
    (``Z`` (91, N), ``row`` (N | 1, 25 + K): h, K_s^-1, K_b^-1, v_hat, u_hat, distributed force and
    moment, point force and moment at the end node, magnet flags)."""

    def step(Z, row, *rest):
        zs = Z.unbind(0)
        y, T = zs[:13], [zs[13 + 13 * j: 26 + 13 * j] for j in range(6)]
        r = row.unbind(-1)
        h, ks, kb, vh, uh = r[0], r[1:4], r[4:7], r[7:10], r[10:13]
        f, tau, F, M, fl = r[13:16], r[16:19], r[19:22], r[22:25], r[25:]
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
        if magnets:
            dy, dT = _magnet_jumps(y, T, fl, rest, batch, field_rebuild, t, fd_step)
            y[7:13] = [a + b for a, b in zip(y[7:13], dy)]
            for tj, dj in zip(T, dT):
                tj[7:13] = [a + b for a, b in zip(tj[7:13], dj)]
        y = [c.expand(Z.shape[1:]) for c in y]
        T = [c.expand(Z.shape[1:]) for tj in T for c in tj]
        return torch.stack((*y, *T), 0)

    return step


def _magnet_jumps(y, T, fl, rest, batch, field_rebuild, t, fd_step):
    """Point wrenches of the magnets flagged in ``fl`` at the step's end node, from the primal ``y``
    (13 components (N,)) and tangents ``T`` (6 lists of 13): the increments of ``n``, ``m`` (6 (N,))
    and of their tangents (6 lists of 6)."""
    mag_moment, mag_mass, gravity, field_scale, *ftens = rest
    N = math.prod(batch)
    eye = torch.eye(3, dtype=y[0].dtype, device=y[0].device)

    def vec(c, lead=(N,)):  # a (..., 3) vector by multiply-adds, not a stack (no concat buffers)
        return sum(ci.reshape(*ci.shape, 1) * eye[i] for i, ci in enumerate(c)).expand(*lead, 3)

    R = _rot(*y[3:7])
    dR = [_drot(y[3:7], tj[3:7]) for tj in T]
    lane = torch.eye(6, dtype=y[0].dtype, device=y[0].device)

    def vec6(cs):  # (N, 6, 3) from six 3-tuples
        return sum(vec(c).unsqueeze(-2) * lane[j].unsqueeze(-1) for j, c in enumerate(cs))

    pos = vec(y[0:3])
    dpos = vec6([tj[0:3] for tj in T])
    field = field_rebuild(ftens) if field_rebuild is not None else None
    dy = [0.0] * 6
    dT = [[0.0] * 6 for _ in T]
    for k in range(len(fl)):
        mub = mag_moment[..., k, :].unbind(-1)  # (N | 1,) each
        mu = vec(_mv(R, mub))
        dmu = vec6([_mv(S, mub) for S in dR])
        Fm = mag_mass[..., k, None] * gravity
        Tm = torch.zeros_like(mu)
        dF = dM = torch.zeros_like(dpos)
        if field is not None:
            Fw, Tw, dF, dM = _field_wrench(field, t, pos.reshape(*batch, 3), mu.reshape(*batch, 3),
                                           dpos.reshape(*batch, 6, 3), dmu.reshape(*batch, 6, 3), fd_step)
            sc = field_scale.reshape(-1).unsqueeze(-1)
            Fw, Tw = Fw.reshape(-1, 3), Tw.reshape(-1, 3)
            dF, dM = dF.reshape(-1, 6, 3), dM.reshape(-1, 6, 3)
            Fm, Tm, dF, dM = Fm + Fw * sc, Tw * sc, dF * sc.unsqueeze(-1), dM * sc.unsqueeze(-1)
        W = (*Fm.expand(N, 3).unbind(-1), *Tm.expand(N, 3).unbind(-1))
        dF, dM = dF.expand(N, 6, 3), dM.expand(N, 6, 3)
        for i in range(6):
            dy[i] = dy[i] - fl[k] * W[i]
            for j in range(len(T)):
                dT[j][i] = dT[j][i] - fl[k] * (dF if i < 3 else dM)[:, j, i % 3]
    return dy, dT


def lane_program(magnets: bool, batch: tuple[int, ...], field_rebuild, t: float, fd_step: float):
    """The step on lanes for small batches: ``Z`` (N, 6, 26) holds in lane ``j`` a copy of the primal
    (last dim 0-12) and the tangent ``dy/dxi_j`` (13-25), so that six lanes share one vector register
    (see :mod:`physics.cosserat_lanes`); ``row`` and ``rest`` as in :func:`step_program`."""

    def step(Z, row, *rest):
        zs = Z.unbind(-1)
        y, tg = zs[:13], zs[13:]
        r = row.unsqueeze(-2).unbind(-1)  # (N | 1, 1): broadcast over the lanes
        h, ks, kb, vh, uh = r[0], r[1:4], r[4:7], r[7:10], r[10:13]
        f, tau, F, M = r[13:16], r[16:19], r[19:22], r[22:25]

        y, tg = rk4_tangent_step(y, tg, h, ks, kb, vh, uh, f, tau, F, M)
        if magnets:
            fl = row.unbind(-1)[25:]
            y0 = [c.expand(Z.shape[:-1])[:, 0] for c in y]
            T = [[c.expand(Z.shape[:-1])[:, j] for c in tg] for j in range(6)]
            dy, dT = _magnet_jumps(y0, T, fl, rest, batch, field_rebuild, t, fd_step)
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


def lm_program(lanes: bool, scales, record_base: bool):
    """One Levenberg-Marquardt update after a shot (``physics.cosserat_shooting._lm_math``) from the
    shot's states ``Zs``, and the base state of the next trial."""
    from .cosserat_shooting import _lm_math
    fs, ms = scales

    def update(x, r, J, Y, rn, lam, act, xt, its, budget, tol, live, base_p, base_q, *Zs):
        sc = torch.tensor([fs] * 3 + [ms] * 3, dtype=x.dtype, device=x.device)
        yl, Tl = split_state(Zs[-1], lanes)
        rt = yl[:, 7:13] / sc
        Jt = Tl[..., 7:13].transpose(-1, -2) / sc.unsqueeze(-1)
        ys = [split_state(z, lanes)[0] for z in Zs]
        if record_base:
            N = x.shape[0]
            ys.insert(0, torch.cat((base_p.expand(N, 3), base_q.expand(N, 4), xt * sc), -1))
        Yt = torch.stack(ys, -2)
        x, r, J, Y, rn, lam, its, act, xn = _lm_math(x, r, J, Y, rn, lam, act, xt, rt, Jt, Yt, its, budget, tol, live)
        out = (x, r, J, Y, rn, lam, its, act, xn, initial_state(xn, base_p, base_q, scales, lanes))
        return tuple(o.contiguous() for o in out)  # the same strides as the inputs of the next call

    return update


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
            return ("T", tuple(o.shape), o.dtype, str(o.device))
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


def compile_program(fn, inputs: list[Tensor]):
    """``make_fx`` (fake tensors) + ``torch._inductor.compile`` of ``fn(*inputs)`` for these shapes."""
    from torch.fx.experimental.proxy_tensor import make_fx
    with torch.no_grad():
        gm = make_fx(fn, tracing_mode="fake")(*inputs)
        return torch._inductor.compile(gm, list(inputs), options={"max_fusion_size": 100000, "cpp_wrapper": True})


# ----------------------------------------------------------------------------------------- the driver
_PROGRAMS: dict = {}
_FAILED: set = set()
LANES_BELOW = 8  # batches smaller than this run on lanes (six tangents in one vector register)


def _flat(v: Tensor, shp: tuple[int, ...], trail: int) -> Tensor:
    """``v`` (..., *trail dims) as (N, *trail) when it carries batch dims, else unchanged; contiguous."""
    if v.dim() > trail:
        v = v.expand(*shp, *v.shape[v.dim() - trail:]).reshape(-1, *v.shape[v.dim() - trail:])
    return v.contiguous()


def _sig(ts) -> tuple:
    return tuple((tuple(a.shape), a.stride(), a.dtype) for a in ts)


def fast_lm(solver, x: Tensor, prm, loads, field, t: float, its: Tensor, lam0: float, live: Tensor, step_tab,
            compiled: bool = True):
    """:meth:`CosseratSolver._lm` on the compiled programs; ``None`` where the field hook cannot be
    traced (the caller then takes the ``torch.compile`` path). ``compiled=False`` runs the same programs
    eagerly (tests)."""
    from .cosserat import broadcast_shape
    from .cosserat_lanes import lane_tables
    from .cosserat_shooting import _spd_unrolled
    flat = flatten_field(field)
    if flat is None:
        return None
    fkey, ftens, rebuild = flat
    shp = tuple(x.shape[:-1])
    N = math.prod(shp)
    lanes = N < LANES_BELOW
    grid = solver.rod.grid
    tabs = lane_tables(prm, grid, loads, step_tab)
    st, ld, K = tabs.step, tabs.loads, tabs.flags.shape[-1]
    nr = st.shape[-2]
    bs = broadcast_shape(st.shape[:-2], ld.shape[:-2])
    rows = torch.cat((st.expand(*bs, nr, 13), ld.expand(*bs, nr, 12), tabs.flags.expand(*bs, nr, K)), -1)
    rows = _flat(rows, shp, 2).movedim(-2, 0).contiguous() if bs else rows.unsqueeze(1).contiguous()
    rowl = rows.unbind(0)
    rest = [_flat(prm.magnet_moment, shp, 2), _flat(prm.magnet_mass, shp, 1), _flat(loads.gravity, shp, 1),
            _flat(loads.field_scale.reshape(*loads.field_scale.shape, 1), shp, 1).reshape(-1), *ftens]
    rest = [a.contiguous() for a in rest]
    bp, bq = _flat(loads.base_position, shp, 1), _flat(loads.base_quaternion, shp, 1)
    xf = x.reshape(N, 6).contiguous()
    Z = initial_state(xf, bp, bq, solver.scales, lanes)
    base = (compiled, lanes, shp, x.dtype, str(x.device), K, fkey, float(t), float(solver.fd_step))
    make = lane_program if lanes else step_program
    key_p = ("step", False, base, _sig((Z, rowl[0])))
    key_m = ("step", True, base, _sig((Z, rowl[0], *rest)))
    if key_p in _FAILED or key_m in _FAILED:
        return None
    try:
        plain = _program(key_p, lambda: make(False, shp, rebuild, t, solver.fd_step), [Z, rowl[0]], compiled)
        mag = _program(key_m, lambda: make(True, shp, rebuild, t, solver.fd_step), [Z, rowl[0], *rest], compiled) \
            if any(tabs.magnet_rows) else None
    except Exception as e:  # an untraceable field hook: fall back (once per key)
        import warnings
        warnings.warn(f"Cosserat fast path unavailable ({type(e).__name__}: {e}); using torch.compile", stacklevel=3)
        _FAILED.update((key_p, key_m))
        return None
    kw = dict(dtype=x.dtype, device=x.device)
    n_rec = nr + int(tabs.record_base)
    r, J = torch.zeros(N, 6, **kw), torch.eye(6, **kw).expand(N, 6, 6).contiguous()
    Y, rn = torch.zeros(N, n_rec, 13, **kw), torch.full((N,), math.inf, **kw)
    lam = torch.full((N,), lam0, **kw)
    itf, livef = its.reshape(N).contiguous(), live.reshape(N).contiguous()
    act, budget = livef.clone(), itf + solver.max_iter
    tol = torch.tensor(solver.tol, **kw)
    xt = xf.clone()
    prog = [mag if m else plain for m in tabs.magnet_rows]
    first = True
    lm = None
    while True:
        Zs = []
        for p, row, m in zip(prog, rowl, tabs.magnet_rows):
            Z = p(Z, row, *rest) if m else p(Z, row)
            Zs.append(Z)
        args = [xf, r, J, Y, rn, lam, act, xt, itf, budget, tol, livef, bp, bq, *Zs]
        if lm is None:
            key_l = ("lm", compiled, lanes, tabs.record_base, solver.scales, _sig(args))
            with _spd_unrolled():  # (eagerly: LAPACK)
                lm = _program(key_l, lambda: lm_program(lanes, solver.scales, tabs.record_base), args, compiled)
        xf, r, J, Y, rn, lam, itf, act, xt, Z = lm(*args)
        if first:  # the evaluation at the start point is not an iteration
            itf, first = itf - livef.to(itf.dtype), False
        if not bool(act.any()):
            break
    return (xf.reshape(*shp, 6), r.reshape(*shp, 6), J.reshape(*shp, 6, 6), Y.reshape(*shp, n_rec, 13),
            rn.reshape(shp), itf.reshape(shp))


def _program(key, make, inputs, compiled: bool):
    if key not in _PROGRAMS:
        _PROGRAMS[key] = compile_program(make(), inputs) if compiled else make()
    return _PROGRAMS[key]
