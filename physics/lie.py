"""SO(3) utilities on batch-first tensors: hat/vee, exp/log, Cayley map, quaternions.

Every function accepts any number of leading batch dimensions: vectors are ``(..., 3)``,
matrices ``(..., 3, 3)``, quaternions ``(..., 4)`` scalar-first ``(w, x, y, z)``.

Cayley convention. ``cay(v) = (I - v^/2)^{-1} (I + v^/2)``: ``v`` approximates the rotation
vector (``|v| = 2 tan(theta/2)``) so that ``cay_inv(O_a^T O_b) / l`` is a curvature. T. Lee's
Newton iteration writes ``F = (I + f^)(I - f^)^{-1}``, which is ``cay(2 f)``.

Small-angle branches switch to Taylor series below thresholds taken from
``torch.finfo(dtype).eps``; the branch not taken is fed a safe argument so that autograd
never sees a 0/0 (``gradcheck`` in float64 in the tests).
"""
from __future__ import annotations

import torch
from torch import Tensor

from .programs import is_tracing

__all__ = [
    "hat", "vee", "skew_vee", "so3_exp", "so3_log", "cay", "cay_inv", "dcay_inv",
    "quat_to_matrix", "matrix_to_quat", "quat_normalize", "rot_x", "rot_y", "rot_z",
    "mtm3", "mv3", "mtv3",
]


def _eps(t: Tensor) -> float:
    return torch.finfo(t.dtype).eps


def hat(v: Tensor) -> Tensor:
    """``(..., 3) -> (..., 3, 3)`` skew matrix with ``hat(a) @ b == cross(a, b)``."""
    if v.shape[-1] != 3:
        raise ValueError(f"hat: v must have trailing size 3, got shape {tuple(v.shape)}")
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).reshape(*v.shape[:-1], 3, 3)


def vee(m: Tensor) -> Tensor:
    """Inverse of :func:`hat` for a skew matrix ``(..., 3, 3) -> (..., 3)``."""
    return torch.stack((m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]), dim=-1)


def skew_vee(m: Tensor) -> Tensor:
    """``vee(m - m^T)`` for any square ``m`` (twice the vee of its skew part)."""
    return torch.stack(
        (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), dim=-1
    )


def _eye_like(v: Tensor) -> Tensor:
    return torch.eye(3, dtype=v.dtype, device=v.device).expand(*v.shape[:-1], 3, 3)


def so3_exp(w: Tensor) -> Tensor:
    """Exponential map: rotation vector ``(..., 3)`` to rotation matrix (Rodrigues)."""
    th2 = (w * w).sum(-1)
    small = th2 < _eps(w) ** 0.5  # theta < eps^(1/4): Taylor error ~theta^6/5040
    th2_safe = torch.where(small, torch.ones_like(th2), th2)
    th = th2_safe.sqrt()
    a = torch.where(small, 1 - th2 / 6 + th2 * th2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - torch.cos(th)) / th2_safe)
    W = hat(w)
    return _eye_like(w) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def _check_matrix(R: Tensor, where: str) -> None:
    """ValueError unless ``R`` is (..., 3, 3) (a shape check alone: free, and traced by torch.compile)."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"{where}: R must be (..., 3, 3) rotation matrices, got shape {tuple(R.shape)}")


def so3_log(R: Tensor) -> Tensor:
    """Logarithm: rotation matrix to rotation vector with angle in ``[0, pi]``.

    Three branches: Taylor near 0, the standard formula, and an eigenvector-based one near pi
    where ``sin(theta)`` vanishes.
    """
    _check_matrix(R, "so3_log")
    s = skew_vee(R)  # 2 sin(theta) n
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    sin = 0.5 * s.norm(dim=-1)
    th = torch.atan2(sin, cos)
    eps = _eps(R)
    small = th < eps ** 0.25
    near_pi = th > torch.pi - 1e-3 ** 0.5 if R.dtype == torch.float64 else th > torch.pi - 0.05
    ok = ~(small | near_pi)
    th_ok = torch.where(ok, th, torch.ones_like(th))
    th2 = th * th
    coef = torch.where(small, 0.5 + th2 / 12 + 7 * th2 * th2 / 720, th_ok / (2 * torch.sin(th_ok)))
    w_reg = coef[..., None] * s
    # near pi: (R + R^T)/2 - cos I = (1 - cos) n n^T ; take the best-conditioned column.
    B = 0.5 * (R + R.transpose(-1, -2)) - cos[..., None, None] * _eye_like(s)
    diag = torch.diagonal(B, dim1=-2, dim2=-1)
    k = diag.argmax(-1, keepdim=True)
    col = torch.gather(B, -1, k[..., None].expand(*B.shape[:-1], 1)).squeeze(-1)
    n = col / col.norm(dim=-1, keepdim=True).clamp_min(eps)
    sign = torch.where((n * s).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(R.dtype)
    w_pi = sign * n * th[..., None]
    return torch.where(near_pi[..., None], w_pi, w_reg)


def cay(v: Tensor) -> Tensor:
    """Cayley map ``(I - v^/2)^{-1}(I + v^/2) = I + 4/(4+|v|^2) (v^ + v^ v^/2)``."""
    V = hat(v)
    c = 4.0 / (4.0 + (v * v).sum(-1))
    return _eye_like(v) + c[..., None, None] * (V + 0.5 * (V @ V))


def cay_inv(R: Tensor) -> Tensor:
    """Inverse Cayley map ``2 vee((R - I)(R + I)^{-1}) = 2 vee(R - R^T) / (1 + tr R)``.

    Defined for rotation angles below pi; raises ``ValueError`` at a half turn.
    """
    den = 1.0 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    if bool((den.abs() <= 100 * _eps(R)).any()):
        raise ValueError("cay_inv: rotation by pi has no Cayley coordinates (1 + trace(R) == 0)")
    return 2.0 * skew_vee(R) / den[..., None]


def dcay_inv(v: Tensor) -> Tensor:
    """Inverse of the right-trivialised Cayley tangent: ``I - v^/2 + v v^T / 4``.

    ``cay(v + dv) = exp(hat(dcay(v) dv)) cay(v)`` to first order, with ``dcay(v)^{-1}`` this
    matrix; for a right perturbation ``cay(v) exp(hat(eta))`` use ``dcay_inv(-v) @ eta``.
    """
    return _eye_like(v) - 0.5 * hat(v) + 0.25 * v[..., :, None] * v[..., None, :]


def quat_normalize(q: Tensor) -> Tensor:
    return q / q.norm(dim=-1, keepdim=True)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternion ``(w, x, y, z)`` to rotation matrix (normalised first)."""
    if q.shape[-1] != 4:
        raise ValueError(f"quat_to_matrix: q must have trailing size 4, got {tuple(q.shape)}")
    if not bool((q.norm(dim=-1) > 0).all()):  # normalising a zero quaternion gave a NaN matrix
        raise ValueError("quat_to_matrix: q must be non-zero quaternions (w, x, y, z), got a zero one")
    w, x, y, z = quat_normalize(q).unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(R: Tensor) -> Tensor:
    """Rotation matrix to unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (Shepperd's method)."""
    _check_matrix(R, "matrix_to_quat")
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # four candidate solutions; pick the one with the largest (well-conditioned) pivot
    piv = torch.stack((1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), -1)
    s = skew_vee(R)  # (m21-m12, m02-m20, m10-m01)
    a01, a02, a12 = R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    cands = torch.stack(
        (
            torch.stack((piv[..., 0], s[..., 0], s[..., 1], s[..., 2]), -1),
            torch.stack((s[..., 0], piv[..., 1], a01, a02), -1),
            torch.stack((s[..., 1], a01, piv[..., 2], a12), -1),
            torch.stack((s[..., 2], a02, a12, piv[..., 3]), -1),
        ),
        -2,
    )  # (..., 4 candidates, 4)
    k = piv.argmax(-1)
    q = torch.gather(cands, -2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    pk = torch.gather(piv, -1, k[..., None]).clamp_min(_eps(R))
    q = q / (2 * pk.sqrt())
    return torch.where(q[..., :1] < 0, -q, q)


def _axis_rot(theta: Tensor | float, axis: int, dtype=None, device=None) -> Tensor:
    if dtype is None:  # a floating-point tensor keeps its precision
        dtype = theta.dtype if torch.is_tensor(theta) and theta.is_floating_point() else torch.get_default_dtype()
    th = torch.as_tensor(theta, dtype=dtype, device=device)
    w = torch.zeros(*th.shape, 3, dtype=th.dtype, device=th.device)
    w[..., axis] = th
    return so3_exp(w)


def rot_x(theta, dtype=None, device=None) -> Tensor:
    return _axis_rot(theta, 0, dtype, device)


def rot_y(theta, dtype=None, device=None) -> Tensor:
    return _axis_rot(theta, 1, dtype, device)


def rot_z(theta, dtype=None, device=None) -> Tensor:
    return _axis_rot(theta, 2, dtype, device)


# Small-matrix products: eager uses batched matmul (fast for large batches); under torch.compile
# they are written as broadcasts, which fuse, where a matmul of 3x3 blocks is an unfused call.
def mtm3(A: Tensor, B: Tensor) -> Tensor:
    """A^T @ B for (..., 3, 3)."""
    if is_tracing():
        return (A.unsqueeze(-1) * B.unsqueeze(-2)).sum(-3)
    return A.transpose(-1, -2) @ B


def mv3(A: Tensor, v: Tensor) -> Tensor:
    """A @ v for (..., 3, 3) and (..., 3)."""
    if is_tracing():
        return (A * v.unsqueeze(-2)).sum(-1)
    return (A @ v.unsqueeze(-1)).squeeze(-1)


def mtv3(A: Tensor, v: Tensor) -> Tensor:
    """A^T @ v for (..., 3, 3) and (..., 3)."""
    if is_tracing():
        return (A * v.unsqueeze(-1)).sum(-2)
    return (v.unsqueeze(-2) @ A).squeeze(-2)
