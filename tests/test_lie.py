import math

import pytest
import torch
from torch.autograd import gradcheck

from physics.lie import (cay, cay_inv, dcay_inv, hat, matrix_to_quat, quat_to_matrix, rot_x, rot_y, rot_z,
                         skew_vee, so3_exp, so3_log, vee)

D = torch.float64


def rand_vec(*shape, scale=1.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn(*shape, 3, generator=g, dtype=D)


def test_hat_vee_cross():
    a, b = rand_vec(4, 5), rand_vec(4, 5, seed=1)
    assert torch.allclose(hat(a) @ b[..., None], torch.linalg.cross(a, b, dim=-1)[..., None])
    assert torch.allclose(vee(hat(a)), a)
    assert torch.allclose(skew_vee(hat(a)), 2 * a)
    with pytest.raises(ValueError, match="trailing size 3"):
        hat(torch.zeros(4))
    # a zero quaternion normalised to a NaN matrix; a 2 x 2 matrix failed with an IndexError
    with pytest.raises(ValueError, match="quat_to_matrix: q must be non-zero"):
        quat_to_matrix(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]], dtype=D))
    for fn in (so3_log, matrix_to_quat):
        with pytest.raises(ValueError, match=rf"{fn.__name__}: R must be \(\.\.\., 3, 3\) rotation matrices, got shape \(2, 2\)"):
            fn(torch.eye(2, dtype=D))


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.5, 2.0])
def test_exp_log_roundtrip_and_orthogonality(scale):
    w = rand_vec(64, scale=scale)
    w = w * torch.clamp(3.0 / w.norm(dim=-1, keepdim=True), max=1.0)  # angles below pi
    R = so3_exp(w)
    eye = torch.eye(3, dtype=D)
    assert (R.transpose(-1, -2) @ R - eye).abs().max() < 1e-14
    assert torch.allclose(torch.linalg.det(R), torch.ones(64, dtype=D))
    assert torch.allclose(so3_log(R), w, atol=1e-12, rtol=1e-10)
    assert torch.allclose(R, torch.linalg.matrix_exp(hat(w)), atol=1e-14)


def test_log_near_pi():
    axis = torch.nn.functional.normalize(rand_vec(16), dim=-1)
    for th in (math.pi - 1e-7, math.pi - 1e-4, math.pi - 0.02):
        w = th * axis
        assert torch.allclose(so3_log(so3_exp(w)), w, atol=1e-7)


def test_cayley_roundtrip_and_small_angle():
    v = rand_vec(32)
    R = cay(v)
    assert (R.transpose(-1, -2) @ R - torch.eye(3, dtype=D)).abs().max() < 1e-14
    assert torch.allclose(cay_inv(R), v, atol=1e-12)
    # the scaled Cayley vector approximates the rotation vector: |v| = 2 tan(theta/2)
    th = so3_log(R).norm(dim=-1)
    assert torch.allclose(v.norm(dim=-1), 2 * torch.tan(th / 2), rtol=1e-10)
    tiny = rand_vec(8, scale=1e-8)
    assert torch.allclose(cay(tiny), so3_exp(tiny), atol=1e-20)
    with pytest.raises(ValueError, match="pi"):
        cay_inv(rot_x(math.pi, dtype=D))


def test_dcay_inv_is_the_trivialised_tangent():
    v, dv = rand_vec(), 1e-7 * rand_vec(seed=3)
    R, R2 = cay(v), cay(v + dv)
    left = 0.5 * skew_vee(R2 @ R.T)   # R2 = exp(eta^) R
    right = 0.5 * skew_vee(R.T @ R2)  # R2 = R exp(eta^)
    assert torch.allclose(torch.linalg.solve(dcay_inv(v), dv), left, rtol=1e-5)
    assert torch.allclose(torch.linalg.solve(dcay_inv(-v), dv), right, rtol=1e-5)


def test_quaternions():
    w = rand_vec(50, scale=1.5)
    R = so3_exp(w)
    q = matrix_to_quat(R)
    assert torch.allclose(q.norm(dim=-1), torch.ones(50, dtype=D))
    assert (q[:, 0] >= 0).all()
    assert torch.allclose(quat_to_matrix(q), R, atol=1e-14)
    # a half turn about each axis picks the right pivot
    for Rk in (rot_x(math.pi, dtype=D), rot_y(math.pi, dtype=D), rot_z(math.pi, dtype=D)):
        assert torch.allclose(quat_to_matrix(matrix_to_quat(Rk)), Rk, atol=1e-14)
    assert torch.allclose(rot_z(math.pi / 2, dtype=D) @ torch.tensor([1.0, 0, 0], dtype=D),
                          torch.tensor([0.0, 1, 0], dtype=D), atol=1e-15)


@pytest.mark.parametrize("scale", [1e-6, 0.7])
def test_gradcheck(scale):
    w = rand_vec(3, scale=scale).requires_grad_(True)
    assert gradcheck(so3_exp, (w,))
    assert gradcheck(cay, (w,))
    assert gradcheck(lambda x: so3_log(so3_exp(x)), (w,))
    assert gradcheck(lambda x: cay_inv(cay(x)), (w,))
    q = torch.cat((torch.ones(3, 1, dtype=D), w), -1).detach().requires_grad_(True)
    assert gradcheck(quat_to_matrix, (q,))
    assert gradcheck(lambda x: matrix_to_quat(so3_exp(x)), (w,))
    assert gradcheck(dcay_inv, (w,))


def test_exp_gradient_is_finite_at_zero():
    w = torch.zeros(3, dtype=D, requires_grad=True)
    so3_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()
    w2 = torch.zeros(3, dtype=D, requires_grad=True)
    so3_log(so3_exp(w2)).sum().backward()
    assert torch.allclose(w2.grad, torch.ones(3, dtype=D))


def test_axis_rotations_keep_a_tensor_angle_precision():
    th = torch.tensor([0.1, 1.0 + 1e-12], dtype=D)
    R = rot_z(th)
    assert R.dtype == D  # not the float32 default
    assert torch.allclose(R, so3_exp(th[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=D)), atol=1e-15)
    assert rot_x(0.3).dtype == torch.get_default_dtype()
    assert rot_y(torch.tensor(0.3, dtype=D), dtype=torch.float32).dtype == torch.float32
