"""The ``torch.compile`` path of the Cosserat shooting (``CosseratSolver(..., compile=True)`` with a field
hook :mod:`physics.cosserat_fast` cannot trace, or ``steps_per_call > 1``).

Why a second formulation. ``torch.compile`` turns the vector-shaped RK4 of :mod:`physics.cosserat`
(3-vectors, 3x3 matrices, (6, 13) tangents) into hundreds of tiny loops with an intermediate buffer
each, and the unrolled 12-step shot takes minutes to compile. Here one RK4 step with its tangents is
written per scalar component, on *lanes*: lane ``j`` (six of them) carries a copy of the primal
state and the tangent ``dy/dxi_j``, so that a step is one pointwise program over (batch, lane) that
inductor fuses into a single loop (the primal is computed six times; that costs less than the
buffers it saves). The step graph is compiled once and called once per grid step with that step's
row of parameters and loads (so it does not depend on the rod or its node count); the point loads
and magnet wrenches at the step's end node are applied inside it, the field being evaluated only
in the graph variant used for steps that end at a magnet.

Measured here (1 CPU thread, float64, 13 nodes): a compiled step call costs about 40 us, of which
about 8 us is the fused kernel and the rest the per-call overhead of the compiled-function wrapper;
the step compiles in about 20 s. Fusing several steps per call (:func:`lane_chunk`) cuts the calls
but carries the masked magnet code in every step and compiles longer; a ``torch.while_loop`` over the
steps (one call per shot) was tried too: inductor then did not fuse the loop body (a few hundred
buffer allocations per step) and it was slower still.

The equations, the grid and the results are those of :func:`physics.cosserat.shoot` (the tests
compare the two to round-off).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .cosserat import CosseratGrid, CosseratParams, StaticLoads, broadcast_shape
from .cosserat_ode import _field_wrench, _rbil

__all__ = ["LaneTables", "lane_tables", "step_table", "lane_step", "lane_chunk", "shoot_lanes", "base_constants"]


def _rhs(y, t, ks, kb, vh, uh, f, tau):
    """Component form of :func:`physics.cosserat.cosserat_rhs` with one tangent per lane."""
    w, x, yq, z, n1, n2, n3, m1, m2, m3 = y[3:]
    dw, dx, dy, dz, dn1, dn2, dn3, dm1, dm2, dm3 = t[3:]
    ww, xx, yy, zz = w * w, x * x, yq * yq, z * z
    xy, xz, yz, wx, wy, wz = x * yq, x * z, yq * z, w * x, w * yq, w * z
    R = (ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy),
         2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx),
         2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz)
    aw, ax, ay, az = w * dw, x * dx, yq * dy, z * dz
    axy, axz, ayz = x * dy + yq * dx, x * dz + z * dx, yq * dz + z * dy
    awx, awy, awz = w * dx + x * dw, w * dy + yq * dw, w * dz + z * dw
    S = (2 * (aw + ax - ay - az), 2 * (axy - awz), 2 * (axz + awy),
         2 * (axy + awz), 2 * (aw - ax + ay - az), 2 * (ayz - awx),
         2 * (axz - awy), 2 * (ayz + awx), 2 * (aw - ax - ay + az))

    def rt(M, a1, a2, a3):  # M^T a
        return (M[0] * a1 + M[3] * a2 + M[6] * a3, M[1] * a1 + M[4] * a2 + M[7] * a3,
                M[2] * a1 + M[5] * a2 + M[8] * a3)

    def rv(M, a1, a2, a3):  # M a
        return (M[0] * a1 + M[1] * a2 + M[2] * a3, M[3] * a1 + M[4] * a2 + M[5] * a3,
                M[6] * a1 + M[7] * a2 + M[8] * a3)

    an, am = rt(R, n1, n2, n3), rt(R, m1, m2, m3)
    sn, sm = rt(S, n1, n2, n3), rt(S, m1, m2, m3)
    dn_, dm_ = rt(R, dn1, dn2, dn3), rt(R, dm1, dm2, dm3)
    v = tuple(ks[i] * an[i] + vh[i] for i in range(3))
    u = tuple(kb[i] * am[i] + uh[i] for i in range(3))
    dv = tuple(ks[i] * (sn[i] + dn_[i]) for i in range(3))
    du = tuple(kb[i] * (sm[i] + dm_[i]) for i in range(3))
    p = rv(R, *v)
    sp, rp = rv(S, *v), rv(R, *dv)
    tp = tuple(sp[i] + rp[i] for i in range(3))
    u1, u2, u3 = u
    d1, d2, d3 = du
    q_ = (-0.5 * (x * u1 + yq * u2 + z * u3), 0.5 * (w * u1 + yq * u3 - z * u2),
          0.5 * (w * u2 + z * u1 - x * u3), 0.5 * (w * u3 + x * u2 - yq * u1))
    tq = (-0.5 * (dx * u1 + dy * u2 + dz * u3 + x * d1 + yq * d2 + z * d3),
          0.5 * (dw * u1 + dy * u3 - dz * u2 + w * d1 + yq * d3 - z * d2),
          0.5 * (dw * u2 + dz * u1 - dx * u3 + w * d2 + z * d1 - x * d3),
          0.5 * (dw * u3 + dx * u2 - dy * u1 + w * d3 + x * d2 - yq * d1))
    mm = (-(p[1] * n3 - p[2] * n2) - tau[0], -(p[2] * n1 - p[0] * n3) - tau[1], -(p[0] * n2 - p[1] * n1) - tau[2])
    tm = (-(tp[1] * n3 - tp[2] * n2 + p[1] * dn3 - p[2] * dn2), -(tp[2] * n1 - tp[0] * n3 + p[2] * dn1 - p[0] * dn3),
          -(tp[0] * n2 - tp[1] * n1 + p[0] * dn2 - p[1] * dn1))
    zero = torch.zeros_like(w)
    return (*p, *q_, -f[0] + zero, -f[1] + zero, -f[2] + zero, *mm), (*tp, *tq, zero, zero, zero, *tm)


class LaneTables(NamedTuple):
    """Per-row tables of one solve (a row is a grid step; a zero-length first row carries the base
    node's point loads when there are any): ``step`` (..., S, 13) = h, K_s^-1, K_b^-1, v_hat, u_hat;
    ``loads`` (..., S, 12) = distributed force and moment, point force and moment at the row's end
    node; ``flags`` (S, K) which magnets sit at that node, and ``magnet_rows`` the same as a tuple
    of magnet indices per row; ``record_base`` whether the base state is recorded before the first
    row (no zero-length row)."""

    step: Tensor
    loads: Tensor
    flags: Tensor
    record_base: bool
    magnet_rows: tuple[tuple[int, ...], ...]



def rk4_tangent_step(y, tg, h, ks, kb, vh, uh, f, tau, F, M):
    """One RK4 step of the state components ``y`` (13) and their tangents ``tg``, then the quaternion
    renormalised (tangent projected accordingly) and the point force ``F`` / moment ``M`` at the
    step's end subtracted from n and m. Returns two lists of components."""
    def ax(a, c, b):
        return tuple(ai + c * bi for ai, bi in zip(a, b))

    k1, d1 = _rhs(y, tg, ks, kb, vh, uh, f, tau)
    k2, d2 = _rhs(ax(y, h / 2, k1), ax(tg, h / 2, d1), ks, kb, vh, uh, f, tau)
    k3, d3 = _rhs(ax(y, h / 2, k2), ax(tg, h / 2, d2), ks, kb, vh, uh, f, tau)
    k4, d4 = _rhs(ax(y, h, k3), ax(tg, h, d3), ks, kb, vh, uh, f, tau)
    y = [a + (h / 6) * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(y, k1, k2, k3, k4)]
    tg = [a + (h / 6) * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(tg, d1, d2, d3, d4)]
    end_of_step(y, [tg], F, M)
    return y, tg


def end_of_step(y: list, tangents: list, F, M) -> None:
    """In place: renormalise the quaternion components of ``y`` (projecting each tangent list in
    ``tangents`` accordingly) and subtract the point force ``F`` / moment ``M`` from n and m."""
    qn = torch.sqrt(y[3] * y[3] + y[4] * y[4] + y[5] * y[5] + y[6] * y[6])
    qh = [c / qn for c in y[3:7]]
    for tj in tangents:
        dot = sum(a * b for a, b in zip(qh, tj[3:7]))
        tj[3:7] = [(dc - c * dot) / qn for c, dc in zip(qh, tj[3:7])]
    y[3:7] = qh
    for i in range(3):
        y[7 + i] = y[7 + i] - F[i]
        y[10 + i] = y[10 + i] - M[i]

def _static(grid: CosseratGrid, dtype, device):
    """Grid-only parts, cached: point-load gather matrix (S+1, P), magnet flags (S+1, K), and whether
    the base node has loads (then a zero-length first row applies them)."""
    key = (grid, dtype, str(device))
    if key not in _STATIC:
        S, K, P = len(grid.h), len(grid.magnet_nodes), len(grid.load_nodes)
        A = torch.zeros(S + 1, P, dtype=dtype, device=device)
        A[list(grid.load_nodes), list(range(P))] = 1.0
        flags = torch.zeros(S + 1, K, dtype=dtype, device=device)
        if K:
            flags[list(grid.magnet_nodes), list(range(K))] = 1.0
        base = bool(flags[0].any()) or bool((A[0] != 0).any())
        fl = flags if base else flags[1:]
        mags = tuple(tuple(k for k in range(K) if bool(r[k])) for r in fl)
        _STATIC[key] = (A, fl, base, mags)
    return _STATIC[key]


_STATIC: dict = {}


def step_table(prm: CosseratParams, grid: CosseratGrid) -> Tensor:
    """The parameter part of :class:`LaneTables` (..., rows, 13) (reusable while ``prm`` is unchanged)."""
    S = len(grid.h)
    h = torch.tensor(grid.h, dtype=prm.ks_inv.dtype, device=prm.ks_inv.device)
    shp = broadcast_shape(prm.ks_inv.shape[:-2], prm.kb_inv.shape[:-2], prm.v_hat.shape[:-2],
                                 prm.u_hat.shape[:-2])
    step = torch.cat([t.expand(*shp, S, t.shape[-1]) for t in
                      (h[:, None], prm.ks_inv, prm.kb_inv, prm.v_hat, prm.u_hat)], -1)
    if _static(grid, step.dtype, step.device)[2]:
        step = torch.cat((torch.zeros_like(step[..., :1, :]), step), -2)
    return step


def lane_tables(prm: CosseratParams, grid: CosseratGrid, loads: StaticLoads, step: Tensor | None = None) -> LaneTables:
    """Build the :class:`LaneTables` of ``prm`` and ``loads`` on ``grid`` (``step``: a cached
    :func:`step_table`)."""
    S = len(grid.h)
    A, flags, base, mag_rows = _static(grid, prm.ks_inv.dtype, prm.ks_inv.device)
    step = step_table(prm, grid) if step is None else step
    f = prm.line_density.unsqueeze(-1) * loads.gravity.unsqueeze(-2) + loads.line_force.unsqueeze(-2)
    F = A @ loads.point_force  # point loads gathered onto nodes 0..S
    M = A @ loads.point_torque
    lshp = broadcast_shape(f.shape[:-2], loads.line_torque.shape[:-1], F.shape[:-2])
    tau = loads.line_torque.unsqueeze(-2)
    parts = [t.expand(*lshp, S, 3) for t in (f, tau)]
    if base:  # a zero-length first row applies the base node's loads
        z = torch.zeros(*lshp, 1, 3, dtype=f.dtype, device=f.device)
        parts = [torch.cat((z, t), -2) for t in parts]
        F, M = F.expand(*lshp, S + 1, 3), M.expand(*lshp, S + 1, 3)
    else:
        F, M = F[..., 1:, :].expand(*lshp, S, 3), M[..., 1:, :].expand(*lshp, S, 3)
    return LaneTables(step, torch.cat((*parts, F, M), -1), flags, not base, mag_rows)


def lane_step(Yp: Tensor, Yt: Tensor, step: Tensor, ld: Tensor, flags: Tensor, mag_moment: Tensor,
              mag_mass: Tensor, gravity: Tensor, field_scale: Tensor, field, t: float, fd_step: float):
    """One RK4 step on lanes ``Yp``, ``Yt`` (..., 6, 13) with the row ``step`` (..., 13), loads
    ``ld`` (..., 12) and magnet ``flags`` (K,) of :class:`LaneTables`, quaternion renormalisation and
    the jumps at the step's end node. Returns the new ``(Yp, Yt)``. (Rows are passed one by one so
    that the compiled graph does not depend on the number of nodes.)"""
    row = step.unsqueeze(-2).unbind(-1)  # each (..., 1), broadcasting over lanes
    lrow = ld.unsqueeze(-2).unbind(-1)
    h, ks, kb, vh, uh = row[0], row[1:4], row[4:7], row[7:10], row[10:13]
    f, tau, F, M = lrow[0:3], lrow[3:6], lrow[6:9], lrow[9:12]
    y, tg = rk4_tangent_step(Yp.unbind(-1), Yt.unbind(-1), h, ks, kb, vh, uh, f, tau, F, M)
    Yp, Yt = torch.stack(y, -1), torch.stack(tg, -1)
    K = flags.shape[-1]
    if K:
        fl = flags  # (K,)
        q0 = Yp[..., 0, 3:7]
        R = _rbil(q0, q0)
        dR = 2.0 * _rbil(q0.unsqueeze(-2), Yt[..., 3:7])
        for j in range(K):
            mub = mag_moment[..., j, :]
            mu = (R * mub.unsqueeze(-2)).sum(-1)
            dmu = (dR * mub[..., None, None, :]).sum(-1)
            Fm = mag_mass[..., j, None] * gravity
            Tm = torch.zeros_like(mu)
            dF = dT = torch.zeros_like(Yt[..., 0:3])
            if field is not None:
                Fw, Tw, dF, dT = _field_wrench(field, t, Yp[..., 0, 0:3], mu, Yt[..., 0:3], dmu, fd_step)
                sc = field_scale.unsqueeze(-1)
                Fm, Tm, dF, dT = Fm + Fw * sc, Tw * sc, dF * sc.unsqueeze(-1), dT * sc.unsqueeze(-1)
            z7 = torch.zeros_like(Yp[..., :7])
            Yp = Yp - fl[j] * torch.cat((z7, Fm.unsqueeze(-2).expand_as(Yp[..., 7:10]),
                                         Tm.unsqueeze(-2).expand_as(Yp[..., 10:13])), -1)
            Yt = Yt - fl[j] * torch.cat((torch.zeros_like(Yt[..., :7]), dF, dT), -1)
    return Yp, Yt


def base_constants(scales: tuple[float, float], dtype, device) -> tuple[Tensor, Tensor]:
    """The tangent at the base ``T0`` (6, 13) and the residual scales (6,), cached."""
    key = (scales, dtype, str(device))
    if key not in _CONSTS:
        fs, ms = scales
        kw = dict(dtype=dtype, device=device)
        T0 = torch.zeros(6, 13, **kw)
        T0[:3, 7:10] = fs * torch.eye(3, **kw)
        T0[3:, 10:13] = ms * torch.eye(3, **kw)
        _CONSTS[key] = (T0, torch.tensor([fs] * 3 + [ms] * 3, **kw))
    return _CONSTS[key]


def lane_chunk(Yp: Tensor, Yt: Tensor, steps: Tensor, lds: Tensor, flags: Tensor, mag_moment: Tensor,
               mag_mass: Tensor, gravity: Tensor, field_scale: Tensor, field, t: float, fd_step: float):
    """``c`` consecutive :func:`lane_step` s (rows ``steps`` (..., c, 13), ``lds`` (..., c, 12), ``flags``
    (c, K); every step carries the (masked) magnet code). Returns ``(Yp, Yt, states (..., c, 13))``."""
    rec = []
    for i in range(steps.shape[-2]):
        Yp, Yt = lane_step(Yp, Yt, steps[..., i, :], lds[..., i, :], flags[i], mag_moment, mag_mass, gravity,
                           field_scale, field, t, fd_step)
        rec.append(Yp[..., 0, :])
    return Yp, Yt, torch.stack(rec, -2)


def shoot_lanes(step_fn, x: Tensor, prm: CosseratParams, tabs: LaneTables, loads: StaticLoads,
                scales: tuple[float, float], field, t: float, fd_step: float, chunk: int = 1):
    """Residual, Jacobian and node states of :func:`physics.cosserat_ode.shoot` (with
    ``tangent=True``) by ``step_fn``: :func:`lane_step` (``chunk=1``; rows without magnets then run a
    graph without the field) or :func:`lane_chunk` with ``chunk`` steps per call (the rows padded with
    zero-length steps to a multiple of ``chunk``), compiled or not."""
    T0, sc = base_constants(scales, x.dtype, x.device)
    shp = x.shape[:-1]
    y0 = torch.cat((loads.base_position.expand(*shp, 3), loads.base_quaternion.expand(*shp, 4), x * sc), -1)
    Yp = y0.unsqueeze(-2).expand(*shp, 6, 13).contiguous()  # fixed strides: no recompiles
    Yt = T0.expand(*shp, 6, 13).contiguous()
    Ys = [y0] if tabs.record_base else []
    if chunk > 1:
        R = tabs.step.shape[-2]
        pad = (-R) % chunk
        st, ld, fl = tabs.step, tabs.loads, tabs.flags
        if pad:
            st = torch.cat((st, torch.zeros_like(st[..., :pad, :])), -2)
            ld = torch.cat((ld, torch.zeros_like(ld[..., :pad, :])), -2)
            fl = torch.cat((fl, torch.zeros_like(fl[:pad])), 0)
        recs = []
        for a in range(0, R + pad, chunk):
            Yp, Yt, rec = step_fn(Yp, Yt, st[..., a:a + chunk, :], ld[..., a:a + chunk, :], fl[a:a + chunk],
                                  prm.magnet_moment, prm.magnet_mass, loads.gravity, loads.field_scale, field, t,
                                  fd_step)
            recs.append(rec)
        Y = torch.cat(recs, -2)[..., :R, :]
        Y = torch.cat((y0.unsqueeze(-2), Y), -2) if tabs.record_base else Y
        return Y[..., -1, 7:13] / sc, (Yt[..., 7:13].transpose(-1, -2) / sc.unsqueeze(-1)).contiguous(), Y
    no_mag = tabs.flags[0, :0]
    for st, ld, fl, mag in zip(tabs.step.unbind(-2), tabs.loads.unbind(-2), tabs.flags.unbind(0), tabs.magnet_rows):
        # rows without magnets run a graph without the field
        Yp, Yt = step_fn(Yp, Yt, st, ld, fl if mag else no_mag, prm.magnet_moment, prm.magnet_mass,
                         loads.gravity, loads.field_scale, field if mag else None, t, fd_step)
        Ys.append(Yp[..., 0, :])
    y = Ys[-1]
    return y[..., 7:13] / sc, (Yt[..., 7:13].transpose(-1, -2) / sc.unsqueeze(-1)).contiguous(), torch.stack(Ys, -2)


_CONSTS: dict = {}
