"""The 13-state Cosserat ODE of :mod:`physics.cosserat`, its variational equation, the magnet field
hook with derivatives, and the RK4 shot from the base to the tip on the rod's fixed grid."""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .cosserat import CosseratGrid, CosseratParams, StaticLoads
from .lie import mtv3, mv3
from .loads import UniformField

__all__ = ["ShootResult", "cosserat_rhs", "shoot", "quat_matrix"]


# ----------------------------------------------------------------------------------------- algebra
# R(q) = C vec(q q^T) (homogeneous form); Xi(q) u = q (x) (0, u), Xi(q) = reshape(q @ X).
def _quat_constants(dtype, device):
    C = torch.zeros(4, 4, 3, 3, dtype=dtype, device=device)
    w, x, y, z = 0, 1, 2, 3
    for (a, b), coef, (i, j) in [
        ((w, w), 1, (0, 0)), ((x, x), 1, (0, 0)), ((y, y), -1, (0, 0)), ((z, z), -1, (0, 0)),
        ((w, w), 1, (1, 1)), ((x, x), -1, (1, 1)), ((y, y), 1, (1, 1)), ((z, z), -1, (1, 1)),
        ((w, w), 1, (2, 2)), ((x, x), -1, (2, 2)), ((y, y), -1, (2, 2)), ((z, z), 1, (2, 2)),
        ((x, y), 2, (0, 1)), ((w, z), -2, (0, 1)), ((x, z), 2, (0, 2)), ((w, y), 2, (0, 2)),
        ((x, y), 2, (1, 0)), ((w, z), 2, (1, 0)), ((y, z), 2, (1, 2)), ((w, x), -2, (1, 2)),
        ((x, z), 2, (2, 0)), ((w, y), -2, (2, 0)), ((y, z), 2, (2, 1)), ((w, x), 2, (2, 1)),
    ]:
        C[a, b, i, j] += coef / 2
        C[b, a, i, j] += coef / 2
    X = torch.zeros(4, 4, 3, dtype=dtype, device=device)  # Xi[r, c] = sum_k q_k X[k, r, c]
    for k, r, c, v in [(1, 0, 0, -1), (2, 0, 1, -1), (3, 0, 2, -1), (0, 1, 0, 1), (3, 1, 1, -1), (2, 1, 2, 1),
                       (0, 2, 1, 1), (3, 2, 0, 1), (1, 2, 2, -1), (0, 3, 2, 1), (2, 3, 0, -1), (1, 3, 1, 1)]:
        X[k, r, c] = v
    return C.reshape(16, 9), X.reshape(4, 12)


_CONST: dict = {}


def _consts(t: Tensor):
    key = (t.dtype, t.device)
    if key not in _CONST:
        _CONST[key] = _quat_constants(t.dtype, t.device)
    return _CONST[key]


def _rbil(a: Tensor, b: Tensor) -> Tensor:
    """Symmetric bilinear form with ``R(q) = _rbil(q, q)``: ``dR = 2 _rbil(q, dq)``."""
    if not torch.compiler.is_compiling():
        C, _ = _consts(a)
        o = (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)
        return (o @ C).unflatten(-1, (3, 3))
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    ww, xx, yy, zz = aw * bw, ax * bx, ay * by, az * bz
    xy, wz, xz = ax * by + ay * bx, aw * bz + az * bw, ax * bz + az * bx
    wy, yz, wx = aw * by + ay * bw, ay * bz + az * by, aw * bx + ax * bw
    return torch.stack((ww + xx - yy - zz, xy - wz, xz + wy, xy + wz, ww - xx + yy - zz, yz - wx,
                        xz - wy, yz + wx, ww - xx - yy + zz), -1).unflatten(-1, (3, 3))


def quat_matrix(q: Tensor) -> Tensor:
    """``R(q)`` as the homogeneous quadratic form (the rotation matrix for unit ``q``)."""
    return _rbil(q, q)


def _xi_mul(q: Tensor, u: Tensor) -> Tensor:
    """``q (x) (0, u)`` for (..., 4) and (..., 3)."""
    if not torch.compiler.is_compiling():
        _, X = _consts(q)
        return ((q @ X).unflatten(-1, (4, 3)) @ u.unsqueeze(-1)).squeeze(-1)
    w, v = q[..., :1], q[..., 1:]
    return torch.cat((-(v * u).sum(-1, keepdim=True), w * u + torch.linalg.cross(v, u, dim=-1)), -1)


def cosserat_rhs(y: Tensor, ks_inv: Tensor, kb_inv: Tensor, v_hat: Tensor, u_hat: Tensor, f: Tensor,
                 tau: Tensor, dy: Tensor | None = None):
    """``y' `` (..., 13) of the module docstring's ODE; with tangents ``dy`` (..., D, 13) also their
    derivative ``(dy)'`` (..., D, 13) (the variational equation), returned as ``(y', dy')``."""
    q, n, m = y[..., 3:7], y[..., 7:10], y[..., 10:13]
    R = quat_matrix(q)
    v = ks_inv * mtv3(R, n) + v_hat
    u = kb_inv * mtv3(R, m) + u_hat
    dp = mv3(R, v)
    dn = (-f).expand_as(n)
    out = torch.cat((dp, 0.5 * _xi_mul(q, u), dn, -torch.linalg.cross(dp, n, dim=-1) - tau), -1)
    if dy is None:
        return out
    tq, tn, tm = dy[..., 3:7], dy[..., 7:10], dy[..., 10:13]
    Ru, dR = R.unsqueeze(-3), 2.0 * _rbil(q.unsqueeze(-2), tq)
    tv = ks_inv.unsqueeze(-2) * (mtv3(dR, n.unsqueeze(-2)) + mtv3(Ru, tn))
    tu = kb_inv.unsqueeze(-2) * (mtv3(dR, m.unsqueeze(-2)) + mtv3(Ru, tm))
    tdp = mv3(dR, v.unsqueeze(-2)) + mv3(Ru, tv)
    tdq = 0.5 * (_xi_mul(tq, u.unsqueeze(-2)) + _xi_mul(q.unsqueeze(-2), tu))
    tdm = -torch.linalg.cross(tdp, n.unsqueeze(-2), dim=-1) - torch.linalg.cross(dp.unsqueeze(-2), tn, dim=-1)
    return out, torch.cat((tdp, tdq, torch.zeros_like(tn), tdm), -1)


# ----------------------------------------------------------------------------------------- field hook
def _check_dtype(B: Tensor, pos: Tensor) -> None:
    """A TypeError unless the hook's field ``B`` has the points' dtype (a float32 field in a float64 solve failed in
    torch with "expected scalar type Double but found Float"; dtype only, so traced programs keep their graph)."""
    if not isinstance(B, Tensor) or B.dtype != pos.dtype:
        raise TypeError(f"the field hook field(t, positions) returned B of "
                        f"{f'dtype {B.dtype}' if isinstance(B, Tensor) else type(B).__name__} for positions of dtype "
                        f"{pos.dtype} (the solver's): return a tensor of the positions' dtype (e.g. B.to(positions))")


def _field_wrench(fld, t, pos: Tensor, mu: Tensor, dpos: Tensor | None, dmu: Tensor | None, h: float):
    """World force and torque (..., 3) of the field on a dipole ``mu`` at ``pos``; with tangents
    (..., D, 3) also their derivatives. Position derivatives of ``B`` (without ``dB``) and of ``dB``
    are central differences with step ``h`` in one batched field call; a ``wrench`` is assumed linear
    in the moment; :class:`~physics.loads.UniformField` is exact."""
    tan = dpos is not None
    zero = torch.zeros_like(mu)
    if isinstance(fld, UniformField) or (callable(fld) and not tan):
        out = fld(t, pos.unsqueeze(-2))
        B, dB = out if isinstance(out, tuple) else (out, None)
        _check_dtype(B, pos)
        B = B[..., 0, :].expand_as(mu)
        T = torch.linalg.cross(mu, B, dim=-1)
        F = zero if dB is None else (dB[..., 0, :, :] * mu.unsqueeze(-1)).sum(-2)
        if not tan:
            return F, T, None, None
        return F, T, torch.zeros_like(dmu), torch.linalg.cross(dmu, B.unsqueeze(-2), dim=-1)
    eye = h * torch.eye(3, dtype=pos.dtype, device=pos.device)
    P = pos.unsqueeze(-2)
    if callable(fld):
        out = fld(t, torch.cat((P, P + eye, P - eye), -2))
        B, dB = out if isinstance(out, tuple) else (out, None)
        _check_dtype(B, pos)
        B = B.expand(*mu.shape[:-1], 7, 3)
        B0 = B[..., 0, :]
        if dB is None:
            G0 = ((B[..., 1:4, :] - B[..., 4:7, :]) / (2 * h)).transpose(-1, -2)  # G0[i, j] = dB_i/dx_j
            F, dF = zero, torch.zeros_like(dmu)
        else:
            dB = dB.expand(*mu.shape[:-1], 7, 3, 3)
            G0 = dB[..., 0, :, :]
            H = (dB[..., 1:4, :, :] - dB[..., 4:7, :, :]) / (2 * h)  # H[j] = d(dB)/dx_j
            F = (G0 * mu.unsqueeze(-1)).sum(-2)
            HtM = (H * mu[..., None, :, None]).sum(-2)  # (..., j, k) = sum_i H[j, i, k] mu_i
            dF = (G0.unsqueeze(-3) * dmu.unsqueeze(-1)).sum(-2) + (dpos.unsqueeze(-1) * HtM.unsqueeze(-3)).sum(-2)
        T = torch.linalg.cross(mu, B0, dim=-1)
        dT = (torch.linalg.cross(dmu, B0.unsqueeze(-2), dim=-1)
              + torch.linalg.cross(mu.unsqueeze(-2), (G0.unsqueeze(-3) * dpos.unsqueeze(-2)).sum(-1), dim=-1))
        return F, T, dF, dT
    if not hasattr(fld, "wrench"):
        raise TypeError("field must be callable as field(t, positions) or have wrench(t, positions, moments)")
    if not tan:
        Fw, Tw = fld.wrench(t, P, mu.unsqueeze(-2))
        return Fw[..., 0, :].expand_as(mu), Tw[..., 0, :].expand_as(mu), None, None
    D = dmu.shape[-2]
    M = mu.unsqueeze(-2)
    pts = torch.cat((P, P + eye, P - eye, P.expand(*P.shape[:-2], D, 3)), -2)
    moms = torch.cat((M.expand(*M.shape[:-2], 7, 3), dmu), -2)
    Fw, Tw = fld.wrench(t, pts, moms)
    Fw, Tw = Fw.expand(*mu.shape[:-1], 7 + D, 3), Tw.expand(*mu.shape[:-1], 7 + D, 3)
    dF = (dpos.unsqueeze(-1) * ((Fw[..., 1:4, :] - Fw[..., 4:7, :]) / (2 * h)).unsqueeze(-3)).sum(-2) + Fw[..., 7:, :]
    dT = (dpos.unsqueeze(-1) * ((Tw[..., 1:4, :] - Tw[..., 4:7, :]) / (2 * h)).unsqueeze(-3)).sum(-2) + Tw[..., 7:, :]
    return Fw[..., 0, :], Tw[..., 0, :], dF, dT


# ----------------------------------------------------------------------------------------- shooting
class ShootResult(NamedTuple):
    """Scaled residual ``r = [n(L+)/F_s, m(L+)/M_s]`` (..., 6); its Jacobian ``J`` (..., 6, 6) w.r.t. the
    scaled base wrench; the node states ``Y`` (..., n_nodes, 13) (after the jumps at each node) and
    their tangents ``T`` (..., n_nodes, 6, 13) when recorded."""

    r: Tensor
    J: Tensor | None
    Y: Tensor | None
    T: Tensor | None


def shoot(x: Tensor, prm: CosseratParams, grid: CosseratGrid, loads: StaticLoads, scales: tuple[float, float],
          field=None, t: float = 0.0, *, tangent: bool = False, record: bool = True,
          record_tangent: bool = False, fd_step: float = 1e-6) -> ShootResult:
    """Integrate from the base with the scaled base wrench ``x`` (..., 6) (``n(0) = x[:3] F_s``,
    ``m(0) = x[3:] M_s``) by RK4 on ``grid``; ``tangent`` also propagates ``dy/dx`` (6 directions)."""
    fs, ms = scales
    n0, m0 = x[..., :3] * fs, x[..., 3:] * ms
    p0 = loads.base_position.expand_as(n0)
    y = torch.cat((p0, loads.base_quaternion.expand(*n0.shape[:-1], 4), n0, m0), -1)
    T = None
    if tangent:
        T0 = torch.zeros(6, 13, dtype=x.dtype, device=x.device)
        T0[:3, 7:10] = fs * torch.eye(3, dtype=x.dtype, device=x.device)
        T0[3:, 10:13] = ms * torch.eye(3, dtype=x.dtype, device=x.device)
        T = T0.expand(*y.shape[:-1], 6, 13)
    f_line = prm.line_density.unsqueeze(-1) * loads.gravity.unsqueeze(-2) + loads.line_force.unsqueeze(-2)
    tau = loads.line_torque
    events: dict[int, tuple[list, list]] = {}
    for i, j in enumerate(grid.load_nodes):
        events.setdefault(j, ([], []))[0].append(i)
    for k, j in enumerate(grid.magnet_nodes):
        events.setdefault(j, ([], []))[1].append(k)
    Ys, Ts = [], []

    def jump(y, T, node):
        loads_i, mags = events.get(node, ((), ()))
        if loads_i:
            idx = list(loads_i)
            F = loads.point_force[..., idx, :].sum(-2)
            M = loads.point_torque[..., idx, :].sum(-2)
            y = y - torch.cat((torch.zeros_like(y[..., :7]), F.expand_as(y[..., 7:10]), M.expand_as(y[..., 10:])), -1)
        for k in mags:
            R = quat_matrix(y[..., 3:7])
            mu_b = prm.magnet_moment[..., k, :]
            mu = mv3(R, mu_b.expand(*y.shape[:-1], 3))
            dpos = dmu = None
            if T is not None:
                dpos = T[..., 0:3]
                dmu = mv3(2.0 * _rbil(y[..., None, 3:7], T[..., 3:7]), mu_b.unsqueeze(-2))
            if field is not None:
                # a shot that ran off to infinity (a trial step far too long) is no point to ask the field
                # about: the field sees the base there and the wrench is NaN, a trial the solver rejects
                fin = torch.isfinite(y[..., 0:3]).all(-1, keepdim=True)
                pos = torch.where(fin, y[..., 0:3], p0)
                F, M, dF, dM = _field_wrench(field, t, pos, mu, dpos, dmu, fd_step)
                sc = torch.where(fin, loads.field_scale.unsqueeze(-1), torch.nan)
                F, M = F * sc, M * sc
                if T is not None:
                    dF, dM = dF * sc.unsqueeze(-1), dM * sc.unsqueeze(-1)
                    T = T - torch.cat((torch.zeros_like(T[..., :7]), dF, dM), -1)
            else:
                F = M = torch.zeros_like(mu)
            F = F + prm.magnet_mass[..., k, None] * loads.gravity
            y = y - torch.cat((torch.zeros_like(y[..., :7]), F, M), -1)
        if record:
            Ys.append(y)
            if record_tangent and T is not None:
                Ts.append(T)
        return y, T

    y, T = jump(y, T, 0)
    for k, h in enumerate(grid.h):
        a = (prm.ks_inv[..., k, :], prm.kb_inv[..., k, :], prm.v_hat[..., k, :], prm.u_hat[..., k, :],
             f_line[..., k, :], tau)
        if T is None:
            k1 = cosserat_rhs(y, *a)
            k2 = cosserat_rhs(y + (h / 2) * k1, *a)
            k3 = cosserat_rhs(y + (h / 2) * k2, *a)
            k4 = cosserat_rhs(y + h * k3, *a)
            y = y + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)
        else:
            k1, d1 = cosserat_rhs(y, *a, dy=T)
            k2, d2 = cosserat_rhs(y + (h / 2) * k1, *a, dy=T + (h / 2) * d1)
            k3, d3 = cosserat_rhs(y + (h / 2) * k2, *a, dy=T + (h / 2) * d2)
            k4, d4 = cosserat_rhs(y + h * k3, *a, dy=T + h * d3)
            y = y + (h / 6) * (k1 + 2 * k2 + 2 * k3 + k4)
            T = T + (h / 6) * (d1 + 2 * d2 + 2 * d3 + d4)
        q = y[..., 3:7]
        qn = q.norm(dim=-1, keepdim=True)
        qh = q / qn
        y = torch.cat((y[..., :3], qh, y[..., 7:]), -1)
        if T is not None:
            tq = T[..., 3:7]
            tq = (tq - qh.unsqueeze(-2) * (tq * qh.unsqueeze(-2)).sum(-1, keepdim=True)) / qn.unsqueeze(-2)
            T = torch.cat((T[..., :3], tq, T[..., 7:]), -1)
        y, T = jump(y, T, k + 1)
    sc = torch.tensor([fs] * 3 + [ms] * 3, dtype=x.dtype, device=x.device)
    r = y[..., 7:13] / sc
    J = None if T is None else T[..., 7:13].transpose(-1, -2) / sc.unsqueeze(-1)
    return ShootResult(r, J, torch.stack(Ys, -2) if record else None,
                       torch.stack(Ts, -3) if (record_tangent and T is not None) else None)
