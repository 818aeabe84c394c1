"""Point dipoles, dipole sets and permanent magnets against magpylib and autograd."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physics.magnetics import (MU0, CuboidMagnet, CylinderMagnet, DipoleSet, SphereMagnet, UniformField,
                               dipole_dipole_force, dipole_field, dipole_field_gradient, dipole_torque,
                               five_to_gradient, force_from_gradient, force_map, gradient_to_five,
                               moment_from_remanence)

magpylib = pytest.importorskip("magpylib")
D = torch.float64
CUBE = 0.0508  # m, the Paper V block magnet


def rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _fd_gradient(getB, pts: np.ndarray, h: float) -> np.ndarray:
    """4th-order central differences of a reference field: G[..., i, j] = dB_i/dx_j."""
    G = np.zeros(pts.shape + (3,))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        G[..., j] = (-getB(pts + 2 * e) + 8 * getB(pts + e) - 8 * getB(pts - e) + getB(pts - 2 * e)) / (12 * h)
    return G


@pytest.fixture
def pair():
    g = torch.Generator().manual_seed(3)
    ms = torch.randn(3, generator=g, dtype=D)
    mt = 0.1 * torch.randn(3, generator=g, dtype=D)
    ps = torch.tensor([0.01, -0.02, 0.03], dtype=D)
    pt = torch.tensor([0.1, 0.05, -0.04], dtype=D)
    return ms, mt, ps, pt


def test_dipole_field_gradient_force_torque_match_magpylib(pair):
    ms, mt, ps, pt = pair
    src = magpylib.misc.Dipole(moment=ms.numpy(), position=ps.numpy())
    tgt = magpylib.misc.Dipole(moment=mt.numpy(), position=pt.numpy())
    d = pt - ps
    g = torch.Generator().manual_seed(0)
    pts = ps + 0.05 * torch.randn(50, 3, generator=g, dtype=D)
    assert rel(dipole_field(pts - ps, ms), src.getB(pts.numpy())) < 1e-9
    G_ref = _fd_gradient(src.getB, pts.numpy(), 1e-6 * 0.05)
    assert rel(dipole_field_gradient(pts - ps, ms), G_ref) < 1e-8  # limited by the reference's differences
    F_ref, T_ref = magpylib.getFT(src, tgt, eps=1e-6 * float(d.norm()))
    B = dipole_field(d, ms)
    assert rel(dipole_torque(mt, B), T_ref) < 1e-9
    assert rel(dipole_dipole_force(d, ms, mt), F_ref) < 1e-9
    assert rel(force_from_gradient(mt, dipole_field_gradient(d, ms)), F_ref) < 1e-9


def test_gradient_is_symmetric_traceless_and_the_autograd_jacobian(pair):
    ms, mt, ps, pt = pair
    d = (pt - ps).requires_grad_(True)
    G = dipole_field_gradient(d, ms).detach()
    J = torch.func.jacfwd(lambda x: dipole_field(x, ms))(d).detach()
    assert torch.allclose(G, J, rtol=1e-12, atol=1e-12 * float(G.abs().max()))
    assert torch.allclose(G, G.T, atol=1e-14 * float(G.abs().max()))
    assert abs(float(G.trace())) < 1e-13 * float(G.abs().max())
    # F = grad(m . B) by autograd, by the gradient, and by the 3x5 map on the five terms
    F_auto = torch.autograd.grad((mt * dipole_field(d, ms)).sum(), d)[0]
    F_map = force_map(mt) @ gradient_to_five(G)
    assert torch.allclose(F_auto, force_from_gradient(mt, G), rtol=1e-12)
    assert torch.allclose(F_auto, F_map, rtol=1e-12)
    assert torch.allclose(five_to_gradient(gradient_to_five(G)), G, rtol=1e-12, atol=1e-14 * float(G.abs().max()))
    # and the torque is minus the derivative of the energy -m.B under a rotation of m
    w = torch.zeros(3, dtype=D, requires_grad=True)
    Rm = torch.linalg.matrix_exp(torch.stack([torch.stack([0 * w[0], -w[2], w[1]]), torch.stack([w[2], 0 * w[0], -w[0]]),
                                              torch.stack([-w[1], w[0], 0 * w[0]])])) @ mt
    dU = torch.autograd.grad(-(Rm * dipole_field(d.detach(), ms)).sum(), w)[0]
    assert torch.allclose(-dU, dipole_torque(mt, dipole_field(d.detach(), ms)), rtol=1e-12)


def test_dipole_dipole_force_is_equal_opposite_and_the_energy_gradient(pair):
    ms, mt, ps, pt = pair
    d = pt - ps
    F2 = dipole_dipole_force(d, ms, mt)
    F1 = dipole_dipole_force(-d, mt, ms)
    assert torch.allclose(F1, -F2, rtol=1e-13)
    U = lambda x: -(mt * dipole_field(x, ms)).sum()  # interaction energy as a function of x2 - x1
    h = 1e-7
    fd = torch.stack([-(U(d + h * e) - U(d - h * e)) / (2 * h) for e in torch.eye(3, dtype=D)])
    assert rel(F2, fd) < 1e-7


def test_batching_superposition_and_dtypes():
    g = torch.Generator().manual_seed(1)
    pos = 0.01 * torch.randn(40, 3, generator=g, dtype=D)
    mom = torch.randn(40, 3, generator=g, dtype=D)
    pts = 0.1 + 0.05 * torch.randn(2, 5, 3, generator=g, dtype=D)  # leading batch dims
    B, G = DipoleSet(pos, mom).field_and_gradient(pts)
    d = pts[..., :, None, :] - pos
    assert B.shape == (2, 5, 3) and G.shape == (2, 5, 3, 3)
    assert torch.allclose(B, dipole_field(d, mom).sum(-2), rtol=1e-12, atol=1e-20)
    assert torch.allclose(G, dipole_field_gradient(d, mom).sum(-3), rtol=1e-11, atol=1e-18)
    mt = torch.randn(2, 5, 3, generator=g, dtype=D)
    F, T = DipoleSet(pos, mom).force_torque(pts, mt)
    assert torch.allclose(F, force_from_gradient(mt, G), rtol=1e-10, atol=1e-16)
    assert torch.allclose(T, torch.linalg.cross(mt, B, dim=-1), rtol=1e-12, atol=1e-20)
    # matches magpylib's collection of dipoles, and the chunked path equals the one-shot path
    col = magpylib.Collection([magpylib.misc.Dipole(moment=m, position=p) for m, p in zip(mom.numpy(), pos.numpy())])
    assert rel(B.reshape(-1, 3), col.getB(pts.reshape(-1, 3).numpy())) < 1e-9
    import physics.magnetics.sources as src_mod
    old, src_mod._CHUNK_ELEMENTS = src_mod._CHUNK_ELEMENTS, 80
    try:
        B2, G2 = DipoleSet(pos, mom).field_and_gradient(pts)
    finally:
        src_mod._CHUNK_ELEMENTS = old
    assert torch.allclose(B2, B) and torch.allclose(G2, G)
    # sources batched (a magnet at two poses), points shared and chunked unevenly (2 points a chunk, 5 points)
    R2 = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.0], [0.3, 0, 0.0], [0.0, 0.0, 0]], dtype=D))
    poses = DipoleSet(torch.stack([pos, pos @ R2.T]), torch.stack([mom, mom @ R2.T]))
    d = pts[0, :, None, None, :] - poses.positions  # (5, 2, 40, 3)
    want = dipole_field(d, poses.moments).sum(-2).transpose(0, 1), \
        dipole_field_gradient(d, poses.moments).sum(-3).transpose(0, 1)
    old, src_mod._CHUNK_ELEMENTS = src_mod._CHUNK_ELEMENTS, 80
    try:
        got, Bc = poses.field_and_gradient(pts[0]), poses.field(pts[0])
    finally:
        src_mod._CHUNK_ELEMENTS = old
    assert got[0].shape == (2, 5, 3) and got[1].shape == (2, 5, 3, 3)
    assert torch.allclose(got[0], want[0], rtol=1e-12, atol=1e-20) and torch.allclose(Bc, want[0], rtol=1e-12,
                                                                                       atol=1e-20)
    assert torch.allclose(got[1], want[1], rtol=1e-11, atol=1e-18)
    # float32: same answer to single precision
    B32 = DipoleSet(pos.float(), mom.float()).field(pts.float())
    assert B32.dtype == torch.float32 and rel(B32.double(), B) < 1e-5
    # a moved set equals the set of moved dipoles
    R = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.1], [-0.2, 0.1, 0]], dtype=D))
    p = torch.tensor([0.01, 0.0, -0.02], dtype=D)
    moved = DipoleSet(pos, mom).transformed(R, p)
    assert torch.allclose(moved.field(pts), DipoleSet(pos @ R.T + p, mom @ R.T).field(pts), rtol=1e-12, atol=1e-20)


def test_a_sum_with_a_time_varying_field_follows_the_time():
    """A sum of models as the solvers' hook passes the time on: a rotating uniform field plus a static dipole set
    gives the sum of each part's hook and wrench at that time, and the rotating part's field at no time is an
    error naming B."""
    g = torch.Generator().manual_seed(4)
    spin = UniformField(lambda t: 1e-3 * torch.tensor([math.cos(t), math.sin(t), 0.0], dtype=D))
    dipoles = DipoleSet(0.01 * torch.randn(6, 3, generator=g, dtype=D), torch.randn(6, 3, generator=g, dtype=D))
    both = spin + dipoles
    pts, mom = 0.1 + 0.02 * torch.randn(3, 3, generator=g, dtype=D), torch.randn(3, 3, generator=g, dtype=D)
    for t in (0.0, 2.0):
        B, dB = both(t, pts)
        assert torch.allclose(B, spin(t, pts) + dipoles.field(pts), rtol=1e-12, atol=0)
        assert torch.equal(dB, dipoles.field_and_gradient(pts)[1])
        F, T = both.wrench(t, pts, mom)
        Fs, Ts = spin.wrench(t, pts, mom)
        Fd, Td = dipoles.force_torque(pts, mom)
        assert torch.allclose(F, Fs + Fd, rtol=1e-12, atol=0) and torch.allclose(T, Ts + Td, rtol=1e-12, atol=0)
    assert not torch.allclose(both.wrench(0.0, pts, mom)[1], both.wrench(2.0, pts, mom)[1])
    with pytest.raises(ValueError, match="B is a function of time"):
        both.field(pts)


def test_singular_distance_raises_or_is_softened():
    m = torch.tensor([0.0, 0.0, 1.0], dtype=D)
    with pytest.raises(ValueError, match="points"):
        dipole_field(torch.zeros(3, dtype=D), m)
    with pytest.raises(ValueError, match="min_distance"):
        DipoleSet(torch.zeros(1, 3, dtype=D), m[None], min_distance=1e-3).field(torch.tensor([[1e-4, 0, 0]], dtype=D))
    B = dipole_field(torch.zeros(3, dtype=D), m, softening=1e-3)
    assert bool(torch.isfinite(B).all())
    far = torch.tensor([0.5, 0.2, 0.1], dtype=D)
    assert torch.allclose(dipole_field(far, m, softening=1e-6), dipole_field(far, m), rtol=1e-10)
    with pytest.raises(ValueError, match="not finite"):
        dipole_field(torch.tensor([0.1, float("nan"), 0.0], dtype=D), m)
    with pytest.raises(ValueError, match=r"d \(displacements from the dipoles\) must have shape \(\.\.\., 3\), got \(2,\)"):
        dipole_field(far[:2], m)
    for kw in ({"softening": -1e-3}, {"min_distance": float("nan")}):
        with pytest.raises(ValueError, match=f"{next(iter(kw))} must be a finite length >= 0"):
            dipole_field(far, m, **kw)


def test_softening_keeps_min_distance():
    """softening > 0 switched min_distance off: a point 0.1 mm from a dipole with min_distance = 1 mm gave a 0.2 MT
    field; min_distance now applies to the true (unsoftened) distance, for the dipole functions and a dipole set,
    and softening alone still allows a point at the dipole."""
    m = torch.tensor([0.0, 0.0, 1.0], dtype=D)
    d = torch.tensor([0.0, 0.0, 1e-4], dtype=D)
    kw = dict(softening=1e-6, min_distance=1e-3)
    for fn in (lambda: dipole_field(d, m, **kw), lambda: dipole_field_gradient(d, m, **kw),
               lambda: dipole_dipole_force(d, m, m, **kw),
               lambda: DipoleSet(torch.zeros(1, 3, dtype=D), m[None], **kw).field(d[None]),
               lambda: DipoleSet(torch.zeros(1, 3, dtype=D), m[None], **kw).field_and_gradient(d[None]),
               lambda: DipoleSet(torch.zeros(1, 3, dtype=D), m[None], **kw).force_torque(d[None], m[None])):
        with pytest.raises(ValueError, match="min_distance"):
            fn()
    far = torch.tensor([[0.0, 0.002, 0.001]], dtype=D)  # beyond min_distance: the softened field
    got = DipoleSet(torch.zeros(1, 3, dtype=D), m[None], softening=1e-4, min_distance=1e-3).field(far)
    assert torch.allclose(got, dipole_field(far, m, softening=1e-4), rtol=1e-12, atol=0)
    assert not torch.allclose(got, dipole_field(far, m), rtol=1e-6, atol=0)
    at = torch.zeros(1, 3, dtype=D)  # at the dipole
    assert torch.isfinite(DipoleSet(at, m[None], softening=1e-3).field(at)).all()


def test_a_moved_magnet_needs_a_proper_rotation():
    """MagnetField.transformed accepted 2 I (the dipoles moved twice as far and their moments doubled) and a
    reflection; R must now be a rotation to its dtype's precision (float32 rotations pass), batched too."""
    model = CuboidMagnet(polarization=(0, 0, 1.2), dimensions=(0.01, 0.01, 0.01)).field_model(27)
    zero = torch.zeros(3, dtype=D)
    for bad in (2 * torch.eye(3, dtype=D), torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=D)),
                torch.eye(3, dtype=D) + 1e-6, torch.stack([torch.eye(3, dtype=D), 2 * torch.eye(3, dtype=D)])):
        with pytest.raises(ValueError, match="R must be proper rotation matrices"):
            model.transformed(bad, zero)
    with pytest.raises(ValueError, match=r"R must be finite \(\.\.\., 3, 3\) rotation matrices"):
        model.transformed(torch.eye(2, dtype=D), zero)
    with pytest.raises(ValueError, match="p must be a finite translation"):
        model.transformed(torch.eye(3, dtype=D), torch.zeros(2, dtype=D))
    W = torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.1], [-0.2, 0.1, 0]])
    R32 = torch.linalg.matrix_exp(W)  # float32: orthonormal to ~1e-6 only
    pt = torch.tensor([[0.0, 0.0, 0.05]], dtype=D)
    B = model.transformed(R32, zero).field(pt)
    assert torch.allclose(B, model.transformed(torch.linalg.matrix_exp(W.double()), zero).field(pt), rtol=1e-5)
    Rb = torch.stack([torch.eye(3, dtype=D), torch.linalg.matrix_exp(W.double())])
    assert model.transformed(Rb, torch.zeros(2, 3, dtype=D)).field(pt).shape == (2, 1, 3)


def test_moment_from_remanence_and_sphere_is_exact():
    V = 4 * math.pi * 1e-9
    assert moment_from_remanence(1.0, V) == pytest.approx(V / MU0)
    sph = SphereMagnet(diameter=5e-3, polarization=(0.0, 0.0, 1.32), position=(0.01, 0.0, 0.0))
    ref = magpylib.magnet.Sphere(diameter=5e-3, polarization=(0, 0, 1.32), position=(0.01, 0, 0))
    pts = np.array([[0.02, 0.01, 0.0], [0.01, 0.0, 0.004], [-0.03, 0.02, 0.01]])
    model = sph.field_model()
    assert model.dipoles.count == 1
    assert rel(model.field(torch.tensor(pts)), ref.getB(pts)) < 1e-9
    assert float(sph.moment[2]) == pytest.approx(1.32 * sph.volume / MU0, rel=1e-14)


def _sphere_points(r: float, n: int = 64) -> torch.Tensor:
    g = torch.Generator().manual_seed(7)
    u = torch.randn(n, 3, generator=g, dtype=D)
    return r * u / u.norm(dim=-1, keepdim=True)


def test_cube_as_dipole_grid_matches_exact_cuboid_at_75mm():
    cube = CuboidMagnet(dimensions=(CUBE,) * 3, polarization=(0.0, 0.0, 1.3))
    ref = magpylib.magnet.Cuboid(dimension=(CUBE,) * 3, polarization=(0, 0, 1.3))
    model = cube.field_model(1728)
    assert model.dipoles.count == 1728 and cube.grid(2000) == (13, 13, 13)
    assert torch.allclose(model.dipoles.total_moment, cube.moment, rtol=1e-13)
    pts = _sphere_points(0.075)
    B, G = model.field_and_gradient(pts)
    B_ref = ref.getB(pts.numpy())
    G_ref = _fd_gradient(ref.getB, pts.numpy(), 1e-5)
    err_B = np.linalg.norm(B.numpy() - B_ref, axis=-1) / np.linalg.norm(B_ref, axis=-1)
    err_G = np.linalg.norm((G.numpy() - G_ref).reshape(-1, 9), axis=-1) / np.linalg.norm(G_ref.reshape(-1, 9), axis=-1)
    assert err_B.max() < 1e-4 and err_G.max() < 1e-3
    # fourth-order convergence in the cell size: 8x the cells (h/2) cuts the error by ~16
    B8 = cube.field_model(8 * 1728).field(pts).numpy()
    err8 = np.linalg.norm(B8 - B_ref, axis=-1) / np.linalg.norm(B_ref, axis=-1)
    assert 10 < err_B.max() / err8.max() < 25


def test_posed_cylinder_grid_converges_to_exact_field():
    R = torch.linalg.matrix_exp(torch.tensor([[0, -0.4, 0.1], [0.4, 0, -0.7], [-0.1, 0.7, 0]], dtype=D))
    cyl = CylinderMagnet(diameter=0.02, height=0.01, polarization=(0.3, 0.0, 1.2), position=(0.005, 0.0, 0.01),
                         orientation=R)
    from scipy.spatial.transform import Rotation
    ref = magpylib.magnet.Cylinder(dimension=(0.02, 0.01), polarization=(0.3, 0, 1.2), position=(0.005, 0, 0.01),
                                   orientation=Rotation.from_matrix(R.numpy()))
    pts = _sphere_points(0.04) + torch.tensor([0.005, 0.0, 0.01], dtype=D)
    errs = [rel(cyl.field_model(n).field(pts), ref.getB(pts.numpy())) for n in (100, 1000)]
    assert errs[1] < 2e-4 and errs[1] < errs[0] / 8
    assert torch.allclose(cyl.field_model(1000).dipoles.total_moment, cyl.moment, rtol=1e-12)


def test_moving_magnet_is_differentiable_in_its_pose():
    model = CuboidMagnet(dimensions=(0.02, 0.02, 0.01), polarization=(0, 0, 1.3)).field_model(27)
    pt = torch.tensor([[0.0, 0.0, 0.05]], dtype=D)
    ang = torch.tensor(0.3, dtype=D, requires_grad=True)
    c, s = torch.cos(ang), torch.sin(ang)
    z, o = torch.zeros((), dtype=D), torch.ones((), dtype=D)
    Ry = torch.stack([torch.stack([c, z, s]), torch.stack([z, o, z]), torch.stack([-s, z, c])])
    Bx = model.transformed(Ry, torch.zeros(3, dtype=D)).field(pt)[0, 0]
    (g,) = torch.autograd.grad(Bx, ang)
    h = 1e-6

    def bx(a):
        ca, sa = math.cos(a), math.sin(a)
        Ra = torch.tensor([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]], dtype=D)
        return float(model.transformed(Ra, torch.zeros(3, dtype=D)).field(pt)[0, 0])

    assert float(g) == pytest.approx((bx(0.3 + h) - bx(0.3 - h)) / (2 * h), rel=1e-6)


def test_bad_input_is_rejected_with_the_parameter_name():
    with pytest.raises(ValueError, match="dimensions"):
        CuboidMagnet(dimensions=(0.01, 0.0, 0.01))
    with pytest.raises(ValueError, match="dimensions"):
        CuboidMagnet(dimensions=(0.01, -1.0, 0.01))
    with pytest.raises(ValueError, match="diameter"):
        CylinderMagnet(diameter=-0.01, height=0.01)
    with pytest.raises(ValueError, match="polarization"):
        SphereMagnet(diameter=0.01, polarization=(0.0, float("nan"), 1.0))
    with pytest.raises(ValueError, match="orientation"):
        CuboidMagnet(dimensions=(0.01, 0.01, 0.01), orientation=((1, 0, 0), (0, 1, 0), (0, 0, 2)))
    with pytest.raises(ValueError, match="moments"):
        DipoleSet(torch.zeros(2, 3, dtype=D), torch.tensor([[0, 0, 1.0], [0, float("inf"), 0]], dtype=D))
    with pytest.raises(ValueError, match="points"):  # inside the magnet
        CuboidMagnet(dimensions=(0.02, 0.02, 0.02)).field_model(8).field(torch.tensor([[0.005, 0.0, 0.0]], dtype=D))
    with pytest.raises(ValueError, match="volume"):
        moment_from_remanence(1.3, 0.0)
    with pytest.raises(ValueError, match=r"B must be a finite field in tesla of shape \(3,\).* got shape \(2,\)$"):
        UniformField([0.0, 1.0])
    with pytest.raises(ValueError, match=r"got shape \(3,\) with non-finite values"):  # it named only the shape
        UniformField([0.0, float("nan"), 0.0])
    with pytest.raises(ValueError, match="count"):
        CuboidMagnet(dimensions=(0.01, 0.01, 0.01)).dipoles(0)
    for magnet in (CuboidMagnet(dimensions=(0.01, 0.01, 0.01)), CylinderMagnet(diameter=0.01, height=0.01)):
        with pytest.raises(ValueError, match=r"count must be an integer >= 1, got 2.9"):  # it ran as 2
            magnet.dipoles(2.9)


def test_uniform_field_batches_over_members_and_refuses_integer_points():
    """Integer field points gave B = 0 (the field cast to int64); a (V, 3) B lined its batch up with the
    field points. B (V, 1, 3) gives each member its own field at every point."""
    B = torch.tensor([[[0.0, 0.01, 0.0]], [[0.02, 0.0, 0.0]]], dtype=D)
    out = UniformField(B).field(torch.zeros(2, 4, 3, dtype=D))
    assert out.shape == (2, 4, 3) and torch.equal(out, B.expand(2, 4, 3))
    with pytest.raises(ValueError, match=r"does not broadcast against points of shape \(3, 4, 3\)"):
        UniformField(B).field(torch.zeros(3, 4, 3, dtype=D))
    with pytest.raises(ValueError, match=r"got shape \(2, 3\)"):  # a function of time is checked as it is called
        UniformField(lambda t: B[:, 0])(0.0, torch.zeros(2, 2, 3, dtype=D))
    for model in (UniformField((0.0, 0.01, 0.0)), DipoleSet([[0, 0, 0]], [[0.0, 0.0, 1.0]])):
        with pytest.raises(TypeError, match="points must be a floating-point tensor, got torch.int64"):
            model.field(torch.tensor([[0, 0, 1]]))
    # whole-number dipole positions written as integers are coordinates, not an error
    assert DipoleSet([[0, 0, 0]], [[0.0, 0.0, 1.0]]).positions.is_floating_point()


def test_dipole_set_rejects_a_non_finite_softening():
    """A NaN softening made every field NaN and an infinite one every field zero, silently; like the dipole
    functions, the set now refuses both, naming the parameter."""
    pos, mom = torch.zeros(1, 3, dtype=D), torch.tensor([[0.0, 0.0, 1.0]], dtype=D)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="softening must be a finite length >= 0"):
            DipoleSet(pos, mom, softening=bad)
    with pytest.raises(ValueError, match="min_distance must be a finite length >= 0"):
        DipoleSet(pos, mom, min_distance=-1e-3)


def test_dipole_set_force_torque_on_no_points():
    """An empty batch of target dipoles gives empty force and torque (as ``field`` does), not a torch.cat error."""
    ds = DipoleSet(torch.zeros(2, 3, dtype=D), torch.eye(3, dtype=D)[:2])
    F, T = ds.force_torque(torch.zeros(0, 3, dtype=D), torch.zeros(0, 3, dtype=D))
    assert F.shape == (0, 3) and T.shape == (0, 3)


def test_moment_from_remanence_rejects_a_nan_remanence():
    with pytest.raises(ValueError, match="Br must be finite"):
        moment_from_remanence(float("nan"), 1e-6)
    with pytest.raises(ValueError, match="Br must be finite"):
        moment_from_remanence(torch.tensor([0.0, math.inf, 1.3], dtype=D), 1e-6)
