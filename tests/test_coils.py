"""Coils: elliptic integrals, the exact circular loop (against magpylib and the on-axis formula),
its gradient, multi-turn coils, Helmholtz pairs and the Paper I nested pairs / rotating field."""
import math

import numpy as np
import pytest
import scipy.constants
import scipy.special
import torch

from physics.magnetics import (CircularLoop, Coil, HelmholtzPair, NestedHelmholtz, RotatingField, ellipe,
                                     ellipk, helmholtz_centre_field, loop_field_per_amp, loop_on_axis_field,
                                     paper1_rotating_field)
from physics.magnetics.dipole import MU0, dipole_field

magpy = pytest.importorskip("magpylib")
from scipy.spatial.transform import Rotation  # noqa: E402

F64 = torch.float64
MAGPY_SCALE = MU0 / scipy.constants.mu_0  # magpylib uses the CODATA mu0, we use 4 pi 1e-7


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.linalg.norm(a - b, axis=-1) / np.linalg.norm(b, axis=-1)


def _magpy_loop(loop):
    rot = Rotation.align_vectors([loop.axis], [[0.0, 0.0, 1.0]])[0]
    return magpy.current.Circle(current=loop.current * loop.turns, diameter=2 * loop.radius, position=loop.centre,
                                orientation=rot)


def test_elliptic_integrals_match_scipy():
    m = torch.cat([torch.linspace(-5, 0.999, 3001, dtype=F64), 1 - torch.logspace(-15, -3, 200, dtype=F64),
                   torch.tensor([0.0, 1e-300], dtype=F64)])
    for ours, ref in ((ellipk, scipy.special.ellipk), (ellipe, scipy.special.ellipe)):
        r = ref(m.numpy())
        assert np.abs(ours(m).numpy() / r - 1).max() < 1e-12
    assert torch.isinf(ellipk(torch.tensor(1.0, dtype=F64))) and float(ellipe(torch.tensor(1.0, dtype=F64))) == 1.0
    m32 = torch.linspace(0, 0.99, 50)
    assert np.abs(ellipk(m32).numpy() / scipy.special.ellipk(m32.double().numpy()) - 1).max() < 1e-6
    # differentiable: dE/dm = (E - K) / (2 m)
    mm = torch.tensor([0.3, 0.7], dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(ellipe(mm).sum(), mm)
    assert torch.allclose(g, (ellipe(mm) - ellipk(mm)).detach() / (2 * mm.detach()), rtol=1e-12)
    for bad in (1.5, math.nan):
        with pytest.raises(ValueError, match="m"):
            ellipk(torch.tensor([bad], dtype=F64))


@pytest.mark.parametrize("seed", [0, 1])
def test_loop_matches_magpylib(seed):
    g = np.random.default_rng(seed)
    loop = CircularLoop(radius=g.uniform(0.01, 0.1), current=g.uniform(-5, 5), turns=int(g.integers(1, 50)),
                        centre=tuple(g.normal(0, 0.02, 3)), axis=tuple(g.normal(size=3)))
    pts = torch.as_tensor(np.array(loop.centre) + g.normal(0, 1.5 * loop.radius, (3000, 3)))
    B = loop.field(pts).numpy()
    Bm = _magpy_loop(loop).getB(pts.numpy()) * MAGPY_SCALE
    assert _rel(B, Bm).max() < 1e-9
    # near the wire (1e-4 R away) and far away (100 R)
    n = np.array(loop.axis)
    e = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
    e /= np.linalg.norm(e)
    near = np.array(loop.centre) + loop.radius * (1 + 1e-4) * e + 1e-4 * loop.radius * n
    far = np.array(loop.centre) + 100 * loop.radius * (0.6 * e + 0.8 * n)
    pts = torch.as_tensor(np.stack([near, far]))
    assert _rel(loop.field(pts).numpy(), _magpy_loop(loop).getB(pts.numpy()) * MAGPY_SCALE).max() < 1e-9


def test_loop_on_axis_and_axis_limit():
    R, I = 0.03, 2.0
    loop = CircularLoop(R, current=I)
    z = torch.linspace(-0.2, 0.2, 41, dtype=F64)
    for rho in (0.0, 1e-300, 1e-200, 1e-12 * R):
        pts = torch.stack([torch.full_like(z, rho), torch.zeros_like(z), z], -1)
        B, dB = loop.field_and_gradient(pts)
        assert torch.isfinite(B).all() and torch.isfinite(dB).all()
        ref = loop_on_axis_field(z, R, I)
        assert ((B[:, 2] - ref).abs() / ref).max() < 1e-13
        assert B[:, :2].abs().max() < 1e-12 * ref.max()
        db_dz = -3 * MU0 * I * R ** 2 * z / (2 * (R ** 2 + z ** 2) ** 2.5)
        scale = db_dz.abs().max()
        assert (dB[:, 2, 2] - db_dz).abs().max() < 1e-12 * scale
        assert (dB[:, 0, 0] + db_dz / 2).abs().max() < 1e-12 * scale
        assert (dB[:, 1, 1] + db_dz / 2).abs().max() < 1e-12 * scale


def test_loop_gradient_closed_form_vs_autograd_and_fd():
    g = torch.Generator().manual_seed(3)
    loop = CircularLoop(0.05, current=1.5, turns=7, centre=(0.01, 0.0, -0.02), axis=(1.0, 2.0, -0.5))
    pts = torch.randn(200, 3, generator=g, dtype=F64) * 0.06
    B, dB = loop.field_and_gradient(pts)
    scale = dB.flatten(-2).norm(dim=-1)[:, None, None]
    assert ((dB - dB.transpose(-1, -2)).abs() / scale).max() < 1e-12
    assert (dB.diagonal(dim1=-2, dim2=-1).sum(-1).abs() / scale[:, 0, 0]).max() < 1e-12
    J = torch.autograd.functional.jacobian(lambda x: loop.field(x).sum(0), pts).permute(1, 0, 2)
    assert ((J - dB).abs() / scale).max() < 1e-12
    h = 1e-6
    fd = torch.stack([(loop.field(pts + h * e) - loop.field(pts - h * e)) / (2 * h) for e in torch.eye(3, dtype=F64)],
                     -1)
    assert ((fd - dB).abs() / scale).max() < 1e-7
    # the gradient itself is differentiable (e.g. for force sensitivities)
    x = pts[:3].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: loop.field_and_gradient(p)[1], (x,))
    # also on the axis (where the radial direction is undefined), its centre included
    n = torch.tensor([1.0, 2.0, -0.5], dtype=F64) / math.sqrt(5.25)
    on_axis = (torch.tensor([0.01, 0.0, -0.02], dtype=F64) + torch.tensor([0.0, 0.01, -0.03])[:, None] * n)
    assert torch.autograd.gradcheck(lambda p: loop.field_and_gradient(p)[1], (on_axis.requires_grad_(True),))


def test_loop_float32_and_batch_dims():
    loop = CircularLoop(0.04, current=3.0, axis=(0.0, 1.0, 1.0))
    pts = torch.randn(2, 5, 7, 3, dtype=F64) * 0.05
    B, dB = loop.field_and_gradient(pts)
    assert B.shape == (2, 5, 7, 3) and dB.shape == (2, 5, 7, 3, 3)
    B32, dB32 = loop.field_and_gradient(pts.float())
    assert B32.dtype == torch.float32 and dB32.dtype == torch.float32
    assert _rel(B32.double().numpy(), B.numpy()).max() < 1e-5
    Bl, dBl = loop_field_per_amp(pts, torch.zeros(2, 3), torch.tensor([[0.0, 1, 1], [1, 0, 0]]),
                                 torch.tensor([0.04, 0.1], dtype=F64))
    assert Bl.shape == (2, 5, 7, 2, 3) and dBl.shape == (2, 5, 7, 2, 3, 3)
    assert torch.allclose(3.0 * Bl[..., 0, :], B, rtol=1e-13, atol=1e-13 * float(B.abs().max()))


def test_points_on_wire_raise():
    loop = CircularLoop(0.03, centre=(0.0, 0.0, 0.01))
    with pytest.raises(ValueError, match="points.*wire"):
        loop.field(torch.tensor([[0.0, 0.03, 0.01]], dtype=F64))
    guarded = CircularLoop(0.03, min_distance=1e-3)
    with pytest.raises(ValueError, match="points.*wire"):
        guarded.field_and_gradient(torch.tensor([[0.0305, 0.0, 0.0]], dtype=F64))


@pytest.mark.parametrize("kwargs, err, match", [
    (dict(radius=0.0), ValueError, "radius"), (dict(radius=-1.0), ValueError, "radius"),
    (dict(radius=math.nan), ValueError, "radius"), (dict(radius="1"), TypeError, "radius"),
    (dict(radius=0.1, turns=0), ValueError, "turns"), (dict(radius=0.1, turns=-3), ValueError, "turns"),
    (dict(radius=0.1, current=math.inf), ValueError, "current"),
    (dict(radius=0.1, axis=(0, 0, 0)), ValueError, "axis"), (dict(radius=0.1, centre=(0, 0)), ValueError, "centre"),
    (dict(radius=0.1, min_distance=-1), ValueError, "min_dist"),
])
def test_bad_loop_input(kwargs, err, match):
    with pytest.raises(err, match=match):
        CircularLoop(**kwargs)


def test_bad_coil_input_and_points():
    with pytest.raises(ValueError, match="thickness"):
        Coil(0.02, thickness=0.05)
    with pytest.raises(ValueError, match="length"):
        Coil(0.02, length=-0.01)
    with pytest.raises(ValueError, match="n_axial"):
        Coil(0.02, n_axial=0)
    with pytest.raises(ValueError, match="separation"):
        HelmholtzPair(0.1, separation=0.0)
    loop = CircularLoop(0.1)
    with pytest.raises(ValueError, match="points"):
        loop.field(torch.zeros(4, 2, dtype=F64))
    with pytest.raises(TypeError, match="points"):
        loop.field([[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="points"):
        loop.field(torch.tensor([[math.nan, 0.0, 0.0]]))
    far = {F64: 1e160, torch.float32: 1e20}  # squared distances overflow
    for dt, x in far.items():
        assert torch.isfinite(loop.field(torch.tensor([[x / 1e10, 0.0, x / 1e10]], dtype=dt))).all()
        with pytest.raises(ValueError, match=r"points: a field point is too far .* \(up to 1\.000e\+(160|20) m"):
            loop.field(torch.tensor([[x, 0.0, x]], dtype=dt))


def test_a_coil_with_a_winding_pack_needs_its_loops():
    """Coil(length=..., thickness=...) left n_axial = n_radial = 1 and was silently one thin loop (41 % off the
    6 x 4 pack on its axis 10 mm beyond its end); the loops along an extent are now required, numpy integers
    count, and a copy of a thin coil given a length (dataclasses.replace) is checked again."""
    from dataclasses import replace
    with pytest.raises(ValueError, match="n_axial must be given for a coil of length 0.08"):
        Coil(0.03, turns=100, length=0.08, thickness=0.025)
    with pytest.raises(ValueError, match="n_radial must be given for a coil of thickness 0.025"):
        Coil(0.03, turns=100, length=0.08, thickness=0.025, n_axial=6)
    with pytest.raises(ValueError, match="n_axial"):
        replace(Coil(0.03), length=0.05)
    pack = Coil(0.03, turns=100, length=0.08, thickness=0.025, n_axial=np.int64(6), n_radial=np.int32(4))
    assert (pack.n_axial, pack.n_radial) == (6, 4) and type(pack.n_axial) is int and len(pack.loops()[2]) == 24
    assert len(Coil(0.03, length=0.08, n_axial=3).loops()[2]) == 3  # no thickness: one loop across
    p = torch.tensor([[0.0, 0.0, 0.06]], dtype=F64)
    assert torch.equal(Coil(0.03, turns=100).field(p), CircularLoop(0.03, turns=100).field(p))
    for bad in (0, 2.0, True, np.bool_(True)):
        with pytest.raises(ValueError, match="n_axial must be an integer"):
            Coil(0.03, length=0.01, n_axial=bad)


def test_loop_field_per_amp_checks_its_loops():
    """Weights (L,) gave an einsum error, radii (3,) for two loops a size mismatch and min_distance=NaN the
    message that a point 0.1 m away lies on the wire; each now names the parameter and the expected shape."""
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]], dtype=F64)
    c, n = torch.zeros(2, 3, dtype=F64), torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64)
    r = torch.tensor([0.1, 0.2], dtype=F64)
    with pytest.raises(ValueError, match=r"weights must have shape \(L, C\) = \(2, C\).*got \(2,\)"):
        loop_field_per_amp(pts, c, n, r, torch.ones(2))
    with pytest.raises(ValueError, match=r"radii \(L,\).*radii \(3,\)"):
        loop_field_per_amp(pts, c, n, torch.tensor([0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match=r"centres and axes must have shape \(L, 3\)"):
        loop_field_per_amp(pts, c[:1], n, r)
    for bad in (math.nan, -1e-3, math.inf):
        with pytest.raises(ValueError, match="min_distance must be a finite distance"):
            loop_field_per_amp(pts, c, n, r, min_distance=bad)
    with pytest.raises(ValueError, match="weights finite"):
        loop_field_per_amp(pts, c, n, r, torch.tensor([[1.0], [math.nan]]))
    B, _ = loop_field_per_amp(pts, c, n, r, torch.tensor([[1.0], [2.0]]))
    assert B.shape == (2, 1, 3)


def test_coil_winding_pack():
    thin = Coil(0.03, turns=100, current=2.0, centre=(0.0, 0.01, 0.0), axis=(0.0, 0.0, 1.0))
    loop = CircularLoop(0.03, turns=100, current=2.0, centre=(0.0, 0.01, 0.0))
    pts = torch.randn(20, 3, dtype=F64) * 0.05
    assert torch.allclose(thin.field(pts), loop.field(pts), rtol=1e-14, atol=0)
    # superposition of the Gauss-Legendre loops equals magpylib's collection of the same loops
    coil = Coil(0.03, turns=500, current=1.2, length=0.04, thickness=0.01, n_axial=5, n_radial=3, axis=(1.0, 1.0, 0.0))
    c, n, r, w = coil.loops()
    assert math.isclose(float(w.sum()), 500.0, rel_tol=1e-14)
    rot = Rotation.align_vectors([coil.axis], [[0.0, 0.0, 1.0]])[0]
    coll = magpy.Collection(*[magpy.current.Circle(current=1.2 * float(wi), diameter=2 * float(ri), position=ci.numpy(),
                                                   orientation=rot) for ci, ri, wi in zip(c, r, w)])
    pts = torch.randn(200, 3, dtype=F64) * 0.01 + torch.tensor([0.08, 0.0, 0.0], dtype=F64)
    assert _rel(coil.field(pts).numpy(), coll.getB(pts.numpy()) * MAGPY_SCALE).max() < 1e-9
    # far away the coil is a dipole m = n I pi <r^2>, <r^2> = R^2 + t^2/12 over the winding
    far = torch.tensor([[0.0, 0.0, 3.0], [2.0, -1.0, 2.5]], dtype=F64)
    m = 500 * 1.2 * math.pi * (0.03 ** 2 + 0.01 ** 2 / 12) * torch.tensor(coil.axis, dtype=F64)
    assert _rel(coil.field(far).numpy(), dipole_field(far, m).numpy()).max() < 1e-3


def test_helmholtz_centre_and_uniformity():
    R, n, I = 0.1, 50, 2.0
    pair = HelmholtzPair(R, turns=n, current=I, centre=(0.01, 0.02, -0.03), axis=(0.0, 1.0, 0.0))
    c = torch.tensor([pair.centre], dtype=F64)
    Bc = pair.field(c)[0]
    ref = helmholtz_centre_field(R, n, I)
    assert abs(float(Bc[1]) / ref - 1) < 1e-6 and abs(pair.centre_field_per_amp * I / ref - 1) < 1e-12
    assert float(Bc[[0, 2]].abs().max()) < 1e-12 * ref
    for s in (0.2, -0.2):
        p = c + torch.tensor([[0.0, s * R, 0.0]], dtype=F64)
        dev = abs(float(pair.field(p)[0].norm()) / ref - 1)
        assert dev < 2.5e-3, dev
    Bu, dBu = pair.unit_field_and_gradient(c)
    B, dB = pair.field_and_gradient(c)
    assert torch.allclose(I * Bu, B) and torch.allclose(I * dBu, dB)
    assert dB.abs().max() < 1e-9 * ref / R  # the gradient vanishes at the centre


def test_nested_pairs_rotating_field():
    coils = NestedHelmholtz()
    rf = paper1_rotating_field(omega=2 * math.pi * 0.5, coils=coils)
    assert isinstance(rf, RotatingField)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(2000, 3, generator=g, dtype=F64)
    pts = d / d.norm(dim=-1, keepdim=True) * torch.rand(2000, 1, generator=g, dtype=F64) ** (1 / 3) * 0.03
    for t in np.linspace(0.0, 2.0, 9):
        req = 7.75e-3 * torch.tensor([0.0, 1, 0], dtype=F64) + 14.5e-3 * torch.tensor(
            [math.sin(math.pi * t), math.cos(math.pi * t), 0.0], dtype=F64)
        assert torch.allclose(rf.requested_field(t), req, rtol=0, atol=1e-15)
        B0, _ = rf(t, torch.zeros(1, 3, dtype=F64))
        assert (B0[0] - req).norm() < 1e-12 * req.norm()
        B, dB = rf(t, pts)
        assert ((B - req).norm(dim=-1) / req.norm()).max() < 5e-3  # uniform to 0.5 % over a 30 mm sphere
        assert rf.currents(t).abs().max() < 10.0
    # as a TimeVarying model and in float32, batched positions
    B32, dB32 = rf(0.3, pts.float().reshape(4, 500, 3))
    assert B32.shape == (4, 500, 3) and dB32.shape == (4, 500, 3, 3) and B32.dtype == torch.float32
    Bm = rf.make(0.3).field(pts[:5])
    assert torch.allclose(Bm, rf(0.3, pts[:5])[0], rtol=1e-12, atol=0)
    m = torch.tensor([0.0, 0.0, 0.02], dtype=F64).expand(5, 3)
    F, T = rf.wrench(0.3, pts[:5], m)
    F2, T2 = rf.make(0.3).force_torque(pts[:5], m)
    assert torch.allclose(F, F2, rtol=1e-12, atol=0) and torch.allclose(T, T2, rtol=1e-12, atol=0)
    # currents for a requested field round-trip; out-of-plane request is rejected
    I = coils.currents_for_field(torch.tensor([0.02, -0.01, 0.0], dtype=F64))
    assert torch.allclose(coils.with_currents(I.tolist()).field(torch.zeros(1, 3, dtype=F64))[0],
                          torch.tensor([0.02, -0.01, 0.0], dtype=F64), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="E1E2"):
        coils.currents_for_field(torch.tensor([0.0, 0.0, 0.01], dtype=F64))
    with pytest.raises(ValueError, match="currents"):
        coils.field(torch.zeros(1, 3), currents=torch.tensor([1.0, math.inf]))


def test_nested_pairs_line_batched_currents_up_with_the_points():
    """Points (T, 3) with currents (T, 2), one point per frame, gave a (T, T, 3) field (every frame's currents at
    every frame's point); a batch of currents needs points (..., P, 3) whose batch dims broadcast against its."""
    coils = NestedHelmholtz()
    x = torch.tensor([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=F64)
    I = torch.tensor([[1.0, 0.0], [0.0, 2.0], [-1.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"give points \(\.\.\., P, 3\) for a batch of currents.*\(T, 1, 3\)"):
        coils.field_and_gradient(x, I)
    with pytest.raises(ValueError, match="give points"):
        coils.field(x, I)
    B, dB = coils.field_and_gradient(x[:, None], I)
    assert B.shape == (3, 1, 3) and dB.shape == (3, 1, 3, 3)
    for k in range(3):
        assert torch.allclose(B[k], coils.field(x[k:k + 1], I[k]), rtol=1e-14, atol=0)
    assert coils.field(x[None], I).shape == (3, 3, 3)  # the same points in every frame
    with pytest.raises(ValueError, match=r"do not line up with points of shape \(2, 1, 3\)"):
        coils.field(x[:2, None], I)


def test_superposition_of_coils():
    a = CircularLoop(0.05, current=2.0, axis=(1.0, 0.0, 0.0))
    b = HelmholtzPair(0.08, turns=3, current=-1.0, centre=(0.0, 0.01, 0.0))
    pts = torch.randn(10, 3, dtype=F64) * 0.02
    B, dB = (a + b).field_and_gradient(pts)
    assert torch.allclose(B, a.field(pts) + b.field(pts), rtol=1e-14, atol=0)
    m = torch.tensor([0.0, 0.0, 0.1], dtype=F64).expand(10, 3)
    F, T = (a + b).force_torque(pts, m)
    assert torch.allclose(F, (dB * m[..., :, None]).sum(-2)) and torch.allclose(T, torch.linalg.cross(m, B))


def test_loop_on_axis_field_rejects_a_bad_radius():
    """A negative radius gave the field of the positive one and a zero radius a ZeroDivisionError."""
    for bad in (0.0, -0.03, math.nan):
        with pytest.raises(ValueError, match="radius"):
            loop_on_axis_field(0.01, bad)


def test_nested_pairs_on_other_axes_give_the_requested_field():
    """Currents for a requested centre field with pairs not on E1/E2: a tilted outer pair gave a field with an
    E3 component nobody asked for (the solve used the E1, E2 rows only) and pairs on E3/E2 a singular-matrix
    error; the request must lie in the plane of the pairs' axes, and one off it is refused."""
    origin = torch.zeros(1, 3, dtype=F64)
    n = torch.tensor([1.0, 0.0, 0.3], dtype=F64) / math.hypot(1.0, 0.3)
    for outer_axis in (tuple(n.tolist()), (0.0, 0.0, 1.0)):
        coils = NestedHelmholtz(outer=HelmholtzPair(0.25, turns=1250, axis=outer_axis),
                                inner=HelmholtzPair(0.12, turns=600, axis=(0.0, 1.0, 0.0)))
        want = 2e-3 * torch.tensor(outer_axis, dtype=F64) - 1e-3 * torch.tensor([0.0, 1.0, 0.0], dtype=F64)
        I = coils.currents_for_field(want)
        assert torch.allclose(coils.field(origin, I)[0], want, rtol=0, atol=1e-15)
        with pytest.raises(ValueError, match="plane of the pairs' axes"):
            coils.currents_for_field(torch.tensor([2e-3, 0.0, 0.0], dtype=F64) if outer_axis[2] == 1.0
                                     else torch.tensor([0.0, 0.0, 1e-3], dtype=F64))
    # float32 requests in the default E1E2 plane still pass and come back in float32
    I32 = NestedHelmholtz().currents_for_field(torch.tensor([1e-3, 2e-3, 0.0]))
    assert I32.dtype == torch.float32 and torch.allclose(I32.double(), NestedHelmholtz().currents_for_field(
        torch.tensor([1e-3, 2e-3, 0.0], dtype=F64)), rtol=1e-6)
