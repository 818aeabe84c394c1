"""Electromagnetic navigation system: geometry, unit-current maps, superposition, actuation matrix and
current allocation (round trips, Tikhonov, current limits against scipy's bounded least squares)."""
import itertools
import math

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from physics.magnetics.coils import Coil
from physics.magnetics.dipole import force_map, gradient_to_five
from physics.magnetics.emns import EMNS, Allocation, allocate_currents, six_coil_emns

F64 = torch.float64
OFF = torch.tensor([[0.01, -0.02, 0.015]], dtype=F64)  # an off-centre point of the workspace


@pytest.fixture(scope="module")
def emns():
    return six_coil_emns()


def test_geometry_outside_workspace_and_full_rank(emns):
    assert emns.n_coils == 6
    for coil in emns.coils:
        c, n, r, _ = coil.loops()
        # every loop of the winding lies outside the 50 mm workspace (nearest wire point >= 65 mm)
        z = (c * n).sum(-1)
        rho = (c - z[:, None] * n).norm(dim=-1)
        assert float(torch.sqrt(z ** 2 + (r - rho).clamp_min(0) ** 2).min()) >= 0.065 - 1e-12
    w = torch.tensor([1.0] * 3 + [0.05] * 5, dtype=F64)
    for p in (torch.zeros(1, 3, dtype=F64), OFF):
        s = torch.linalg.svdvals(w[:, None] * emns.actuation_matrix(p)[0])
        assert s[-1] / s[0] > 0.05  # rank 6, well conditioned
    # a cube-face arrangement (antiparallel axes) is rank deficient at the centre
    cube = EMNS([Coil(0.03, turns=100, centre=tuple(0.1 * s * e), axis=tuple(-s * e))
                 for e in np.eye(3) for s in (1.0, -1.0)])
    s = torch.linalg.svdvals(w[:, None] * cube.actuation_matrix(torch.zeros(1, 3, dtype=F64))[0])
    assert s[-1] / s[0] < 1e-10


def test_superposition_and_actuation_matrix(emns):
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(3, 7, 3, generator=g, dtype=F64) * 0.02
    I = torch.randn(6, generator=g, dtype=F64) * 5
    B, dB = emns.field_and_gradient(pts, I)
    Bs = sum(Ii * c.unit_field_and_gradient(pts)[0] for Ii, c in zip(I, emns.coils))
    dBs = sum(Ii * c.unit_field_and_gradient(pts)[1] for Ii, c in zip(I, emns.coils))
    assert torch.allclose(B, Bs, rtol=1e-12, atol=1e-12 * float(B.abs().max()))
    assert torch.allclose(dB, dBs, rtol=1e-12, atol=1e-12 * float(dB.abs().max()))
    beta, beta_grad = emns.unit_field_and_gradient(pts)
    assert beta.shape == (3, 7, 6, 3) and beta_grad.shape == (3, 7, 6, 3, 3)
    A = emns.actuation_matrix(pts)
    assert A.shape == (3, 7, 8, 6)
    y = (A @ I[:, None])[..., 0]
    assert torch.allclose(y[..., :3], B, rtol=1e-12, atol=1e-15) and torch.allclose(y[..., 3:], gradient_to_five(dB))
    # a FieldModel with stored currents, batched currents, float32
    model = emns.with_currents(I)
    assert torch.allclose(model.field(pts), B, rtol=1e-12, atol=1e-18)
    Ib = torch.stack([I, 2 * I])  # (2, 6) currents for a batch of two scenes
    Bb = emns.field(pts[0][None].expand(2, 7, 3), Ib)
    assert torch.allclose(Bb[1], 2 * Bb[0], rtol=1e-12, atol=0)
    B32, dB32 = model.field_and_gradient(pts.float())
    assert B32.dtype == torch.float32 and ((B32.double() - B).norm(dim=-1) / B.norm(dim=-1)).max() < 1e-5
    m = torch.tensor([0.0, 0.01, 0.0], dtype=F64).expand(3, 7, 3)
    F, T = model.wrench(0.0, pts, m)
    assert torch.allclose(F, (force_map(m) @ y[..., 3:, None])[..., 0], rtol=1e-10, atol=1e-20)


@pytest.mark.parametrize("point", [torch.zeros(1, 3, dtype=F64), OFF])
def test_allocation_round_trips_feasible_requests(emns, point):
    A = emns.actuation_matrix(point)[0]
    I_true = torch.tensor([3.0, -2.0, 5.0, 1.0, -4.0, 2.0], dtype=F64)
    y = A @ I_true
    # field and 5 gradient terms (8 rows, rank 6): the request is in the range of A
    al = emns.allocate(point, field=y[None, :3], gradient=y[None, 3:])
    assert isinstance(al, Allocation)
    assert (al.currents - I_true).abs().max() < 1e-8 * I_true.abs().max()
    assert al.feasible and not al.limits_active and float(al.residual_norm) < 1e-8 * float(y.norm())
    assert torch.allclose(al.field[0], y[:3], rtol=1e-8) and torch.allclose(al.gradient[0], y[3:], rtol=1e-8)
    # field only (3 rows, 6 coils): the minimum-norm solution
    al = emns.allocate(point, field=y[None, :3])
    assert ((al.field[0] - y[:3]).norm() / y[:3].norm()) < 1e-8 and al.feasible
    assert torch.allclose(al.currents, torch.linalg.pinv(A[:3]) @ y[:3], rtol=1e-8, atol=1e-12)
    # field and force on a dipole (6 rows, square)
    mom = torch.tensor([[0.02, -0.01, 0.03]], dtype=F64)
    F = force_map(mom[0]) @ y[3:]
    al = emns.allocate(point, field=y[None, :3], force=F[None], moment=mom)
    assert (al.currents - I_true).abs().max() < 1e-8 * I_true.abs().max() and al.feasible
    assert torch.allclose(al.achieved, torch.cat([y[:3], F]), rtol=1e-8)


def test_batched_currents_need_points_with_a_points_axis(emns):
    """Points (T, 3), one magnet per frame, with currents (T, C) gave a (T, T, 3) field in the eMNS and its table
    (every frame's currents at every frame's point); a batch of currents now needs points (..., P, 3) whose batch
    dims broadcast against its: (T, 1, 3) gives each frame its own field."""
    from physics.magnetics.field_table import CoilFieldTable
    table = CoilFieldTable.from_emns(emns, radius=0.03, spacing=2e-3, order=2)
    g = torch.Generator().manual_seed(5)
    x = torch.rand(4, 3, generator=g, dtype=F64) * 0.02
    I = torch.rand(4, 6, generator=g, dtype=F64) * 4
    calls = (emns.field_and_gradient, emns.field, table.field_and_gradient, table.field,
             lambda p, i: table.field_and_gradient(p, i, check=False))
    for call in calls:
        with pytest.raises(ValueError, match=r"give points \(\.\.\., P, 3\) for a batch of currents"):
            call(x, I)
        with pytest.raises(ValueError, match=r"do not line up with points of shape \(3, 1, 3\)"):
            call(x[:3, None], I)
    for model in (emns, table):
        B, dB = model.field_and_gradient(x[:, None], I)
        assert B.shape == (4, 1, 3) and dB.shape == (4, 1, 3, 3)
        for k in range(4):
            Bk, dBk = model.field_and_gradient(x[k:k + 1], I[k])
            assert torch.allclose(B[k], Bk, rtol=1e-13, atol=0) and torch.allclose(dB[k], dBk, rtol=1e-13, atol=0)
    assert emns.field(x[None], I).shape == (4, 4, 3)  # the same points for every member: a batch axis of 1
    assert torch.equal(emns.field(x[:1], I), emns.field(x[:1][None], I))  # one point (1, 3) is shared too
    with pytest.raises(ValueError, match="EMNS.currents of shape"):  # stored currents are checked the same way
        emns.with_currents(I).field(x)


def test_field_table_returns_the_points_dtype(emns):
    """The table returned float64 for float32 points (a float32 Cosserat solve then failed deep in torch) and
    read list currents as float32; it now computes in float64 and returns the points' dtype, like the exact
    eMNS, and list currents are float64."""
    from physics.magnetics.field_table import CoilFieldTable
    table = CoilFieldTable.from_emns(emns, radius=0.03, spacing=2e-3, order=2)
    x = torch.tensor([[0.01, -0.005, 0.002], [0.0, 0.0, -0.01]], dtype=F64)
    I = [2.0, -1.0, 0.1, 1.0, 0.3, -2.0]
    B, dB = table.field_and_gradient(x, torch.tensor(I, dtype=F64))
    B32, dB32 = table.field_and_gradient(x.float(), I)
    beta32, grad32 = table.unit_field_and_gradient(x.float())
    assert B32.dtype == dB32.dtype == beta32.dtype == grad32.dtype == table.field(x.float(), I).dtype == torch.float32
    assert torch.allclose(B32.double(), B, rtol=1e-6, atol=0) and torch.allclose(dB32.double(), dB, rtol=1e-5, atol=0)
    Bl, dBl = table.field_and_gradient(x, I)  # list currents in float64: no float32 rounding of 0.1 and 0.3
    assert Bl.dtype == torch.float64 and torch.equal(Bl, B) and torch.equal(dBl, dB)


def test_allocation_checks_its_weights_and_tol(emns):
    """Per-point weights (P, 3) raised a bare expand error and tol = -1 or NaN made every allocation infeasible;
    weights (..., P, k) now weight each point's rows, a weight of another shape is refused naming it, and tol
    must be finite and >= 0."""
    pts = torch.cat([OFF, -OFF])
    field = torch.tensor([[5e-3, 0.0, 1e-3], [0.0, -2e-3, 4e-3]], dtype=F64)
    al = emns.allocate(pts, field=field, field_weight=torch.ones(2, 3))
    assert torch.allclose(al.currents, emns.allocate(pts, field=field).currents, rtol=1e-12, atol=1e-12)
    w = torch.tensor([[1.0, 2.0, 3.0], [10.0, 0.5, 1.0]], dtype=F64)
    al = emns.allocate(pts, field=field, field_weight=w, regularization=0.05)
    A = emns.actuation_matrix(pts)[..., :3, :].flatten(0, 1)
    want, _ = allocate_currents(A, field.flatten(), weights=w.flatten(), regularization=0.05)
    assert torch.allclose(al.currents, want, rtol=1e-12, atol=1e-12)
    assert float((al.residual_norm - (w.flatten() * al.residual).norm()).abs()) < 1e-12 * float(al.residual_norm)
    for bad, match in ((torch.ones(3, 3), r"field_weight of shape \(3, 3\) does not broadcast"),
                       (torch.ones(2, 4), r"field_weight must be a scalar, one weight per row \(3,\)"),
                       (torch.ones(2, 2, 3), "field_weight of shape")):
        with pytest.raises(ValueError, match=match):
            emns.allocate(pts, field=field, field_weight=bad)
    with pytest.raises(ValueError, match="gradient_weight"):
        emns.allocate(pts, gradient=torch.zeros(2, 5, dtype=F64), gradient_weight=torch.ones(2, 3))
    with pytest.raises(ValueError, match="force_weight"):
        emns.allocate(OFF, force=torch.zeros(1, 3, dtype=F64), moment=torch.ones(1, 3, dtype=F64),
                      force_weight=torch.tensor([1.0, 0.0, 1.0]))
    for tol in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="tol must be a finite"):
            emns.allocate(OFF, field=field[:1], tol=tol)
    assert bool(emns.allocate(OFF, field=field[:1], tol=0.0).residual_norm >= 0)


def test_batched_requests_and_two_points(emns):
    g = torch.Generator().manual_seed(1)
    pts = torch.cat([OFF, -OFF])
    I_true = torch.rand(4, 6, generator=g, dtype=F64) * 8 - 4
    B = emns.field(pts[None].expand(4, 2, 3), I_true)  # (4, 2, 3): field at two magnets, four requests
    al = emns.allocate(pts, field=B)
    assert al.currents.shape == (4, 6) and al.feasible.shape == (4,) and al.field.shape == (4, 2, 3)
    assert bool(al.feasible.all()) and ((al.field - B).norm(dim=-1) / B.norm(dim=-1)).max() < 1e-8
    single = emns.allocate(pts, field=B[2])
    assert torch.allclose(single.currents, al.currents[2], rtol=1e-10, atol=1e-12)


def test_tikhonov_regularization(emns):
    A = emns.actuation_matrix(OFF)[0]
    y = A @ torch.tensor([3.0, -2.0, 5.0, 1.0, -4.0, 2.0], dtype=F64)
    w = torch.tensor([1.0] * 3 + [0.05] * 5, dtype=F64)
    reg = 0.1
    I, _ = allocate_currents(A, y, weights=w, regularization=reg)
    M = w[:, None] * A
    lam = reg * torch.linalg.matrix_norm(M, ord=2)
    ref = torch.linalg.solve(M.T @ M + lam ** 2 * torch.eye(6, dtype=F64), M.T @ (w * y))
    assert torch.allclose(I, ref, rtol=1e-10, atol=1e-12)
    I0, _ = allocate_currents(A, y, weights=w)
    assert I.norm() < I0.norm()


def _scipy_bounded(M, y, imax):
    lam = 1e-9 * np.linalg.norm(M, 2)
    C = M.shape[1]
    return lsq_linear(np.vstack([M, lam * np.eye(C)]), np.r_[y, np.zeros(C)], bounds=(-imax, imax), method="bvls",
                      tol=1e-15).x


def test_allocation_respects_limits_infeasible(emns):
    for point, req in ((torch.zeros(1, 3, dtype=F64), [0.05, 0.0, 0.0]), (OFF, [0.01, -0.03, 0.02])):
        field, grad = torch.tensor([req], dtype=F64), torch.zeros(1, 5, dtype=F64)
        al = emns.allocate(point, field=field, gradient=grad, gradient_weight=0.05)
        assert float(al.currents.abs().max()) <= 10.0 + 1e-12
        assert al.limits_active and int(al.at_limit.sum()) >= 1 and not al.feasible
        assert torch.allclose(al.currents[al.at_limit].abs(), torch.full_like(al.currents[al.at_limit], 10.0))
        w = torch.tensor([1.0] * 3 + [0.05] * 5, dtype=F64)
        assert math.isclose(float(al.residual_norm), float((w * al.residual).norm()), rel_tol=1e-12)
        assert float(al.residual_norm) > 0.1 * float(field.norm())
        A = emns.actuation_matrix(point)[0]
        ref = _scipy_bounded((w[:, None] * A).numpy(), (w * torch.cat([field[0], grad[0]])).numpy(), 10.0)
        assert np.abs(al.currents.numpy() - ref).max() < 1e-6
        al_s = emns.allocate(point, field=field, gradient=grad, gradient_weight=0.05, method="scipy")
        assert torch.allclose(al_s.currents, al.currents, atol=1e-6, rtol=0)
        # per-coil limits and a tighter override
        al2 = emns.allocate(point, field=field, max_current=torch.tensor([1.0, 2, 3, 4, 5, 6], dtype=F64))
        assert bool((al2.currents.abs() <= torch.tensor([1.0, 2, 3, 4, 5, 6], dtype=F64) + 1e-12).all())
        lim = torch.tensor([math.inf, 2, 2, 2, 2, 2], dtype=F64)  # one unlimited coil
        al3 = emns.allocate(point, field=field, gradient=grad, gradient_weight=0.05, max_current=lim)
        assert torch.isfinite(al3.currents).all() and bool((al3.currents.abs() <= lim + 1e-12).all())
        ref = _scipy_bounded((w[:, None] * A).numpy(), (w * torch.cat([field[0], grad[0]])).numpy(), lim.numpy())
        assert np.abs(al3.currents.numpy() - ref).max() < 1e-6


def test_allocation_uses_null_space_when_min_norm_exceeds_limits(emns):
    A = emns.actuation_matrix(OFF)[0, :3]
    pinv = torch.linalg.pinv(A)
    for pat in itertools.product((-9.5, 0.0, 9.5), repeat=6):  # a request reachable within 10 A ...
        I_true = torch.tensor(pat, dtype=F64)
        if float((pinv @ (A @ I_true)).abs().max()) > 10.5:  # ... whose minimum-norm currents are not
            break
    else:
        pytest.skip("no such request for this geometry")
    B = (A @ I_true)[None]
    al = emns.allocate(OFF, field=B)
    assert float(al.currents.abs().max()) <= 10.0 + 1e-12 and al.limits_active
    assert al.feasible and float((al.field - B).norm() / B.norm()) < 1e-8


def test_bad_input(emns):
    with pytest.raises(ValueError, match="currents"):
        emns.field(OFF, torch.ones(5, dtype=F64))
    with pytest.raises(ValueError, match="currents"):
        emns.field(OFF, torch.tensor([1.0, 2, 3, 4, 5, math.nan], dtype=F64))
    with pytest.raises(ValueError, match="max_current"):
        EMNS(emns.coils, max_current=0.0)
    with pytest.raises(ValueError, match="max_current"):
        EMNS(emns.coils, max_current=(1.0, 2.0))
    with pytest.raises(ValueError, match="coils"):
        EMNS([])
    with pytest.raises(TypeError, match="coils"):
        EMNS(["coil"])
    with pytest.raises(ValueError, match="at least one"):
        emns.allocate(OFF)
    with pytest.raises(ValueError, match="moment"):
        emns.allocate(OFF, force=torch.zeros(1, 3, dtype=F64))
    with pytest.raises(ValueError, match="field"):
        emns.allocate(OFF, field=torch.zeros(1, 2, dtype=F64))
    with pytest.raises(ValueError, match="gradient"):
        emns.allocate(OFF, gradient=torch.zeros(1, 3, dtype=F64))
    with pytest.raises(ValueError, match="weights"):
        emns.allocate(OFF, field=torch.zeros(1, 3, dtype=F64), field_weight=-1.0)
    with pytest.raises(ValueError, match="regularization"):
        emns.allocate(OFF, field=torch.zeros(1, 3, dtype=F64), regularization=-0.1)
    with pytest.raises(ValueError, match="method"):
        emns.allocate(OFF, field=torch.zeros(1, 3, dtype=F64), method="magic")
    with pytest.raises(ValueError, match="finite"):
        emns.allocate(OFF, field=torch.tensor([[math.inf, 0, 0]], dtype=F64))
    A_nan = torch.eye(3, dtype=F64)
    A_nan[0, 0] = math.nan  # numpy's LinAlgError ("SVD did not converge") came out of the solve
    with pytest.raises(ValueError, match=r"A \(the actuation matrix\) must be finite"):
        allocate_currents(A_nan, torch.ones(3, dtype=F64))
    c, n, r, _ = emns.coils[0].loops()
    e = torch.linalg.cross(n[0], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    on_wire = (c[0] + r[0] * e / e.norm())[None]
    with pytest.raises(ValueError, match="points.*wire"):
        emns.field(on_wire, torch.ones(6, dtype=F64))


def test_field_table_matches_the_exact_coils_over_the_workspace(emns):
    """The tabulated unit-current maps (physics.magnetics.field_table) against the exact loop superposition at
    random points of the 50 mm ball, on a coil axis (rho = 0, where the stencil reads the table's mirrored
    rows) and at its centre: within 1e-7 of the field and 1e-6 of the gradient (measured 2.5e-9 and 1.4e-8),
    which a wrong sign or factor of a tabulated function or of the Lagrange weights would break by far. Coils with
    the same loops share one table; a point outside the ball raises, naming it."""
    from physics.magnetics.field_table import CoilFieldTable
    table = CoilFieldTable.from_emns(emns, radius=0.05, spacing=1e-3, order=6)
    assert table.tables.shape[0] == 1 and table.n_coils == 6
    g = torch.Generator().manual_seed(3)
    p = torch.randn(300, 3, generator=g, dtype=F64)
    p = 0.05 * p / p.norm(dim=-1, keepdim=True) * torch.rand(300, 1, generator=g, dtype=F64) ** (1 / 3)
    axis = emns.coils[4].axis
    p = torch.cat([p, torch.zeros(1, 3, dtype=F64), torch.tensor([[0.03 * x for x in axis]], dtype=F64),
                   torch.tensor([[-0.0499 * x for x in axis]], dtype=F64)])
    B, dB = emns.unit_field_and_gradient(p)
    Bt, dBt = table.unit_field_and_gradient(p)
    assert float(((Bt - B).norm(dim=-1) / B.norm(dim=-1)).max()) < 1e-7
    assert float(((dBt - dB).flatten(-2).norm(dim=-1) / dB.flatten(-2).norm(dim=-1)).max()) < 1e-6
    I = torch.tensor([3.0, -1.0, 0.5, 2.0, -4.0, 1.5], dtype=F64)
    for got, want in zip(table.field_and_gradient(p[:5], I), emns.field_and_gradient(p[:5], I)):
        assert torch.allclose(got, want, rtol=1e-6, atol=1e-12)
    assert torch.allclose(table.field(p[:5], I), emns.field(p[:5], I), rtol=1e-6, atol=1e-12)
    # the gradient is the Hessian of a potential: symmetric and traceless (curl- and divergence-free)
    assert float((dBt - dBt.transpose(-1, -2)).abs().max() / dBt.abs().max()) < 1e-6
    assert float(dBt.diagonal(dim1=-2, dim2=-1).sum(-1).abs().max() / dBt.abs().max()) < 1e-6
    with pytest.raises(ValueError, match=r"points\[1\] lies 0.06 m from the centre"):
        table.unit_field_and_gradient(torch.tensor([[0.0, 0.0, 0.01], [0.0, 0.06, 0.0]], dtype=F64))
    assert table.outside(torch.tensor([[0.0, 0.0, 0.0501], [0.03, 0.0, 0.0]], dtype=F64)).tolist() == [True, False]
    for kw, name in (({"radius": 0.0}, "radius"), ({"spacing": 0.1}, "spacing"), ({"order": 3}, "order"),
                     ({"centre": (0.0, 0.0)}, "centre")):
        with pytest.raises(ValueError, match=name):
            CoilFieldTable.from_emns(emns, **kw)


def test_field_table_rejects_non_finite_currents(emns):
    """The tabulated field gave a NaN field for NaN currents where the exact eMNS raises; it now raises too
    (with ``check=False``, for compiled programs, it does not look)."""
    from physics.magnetics.field_table import CoilFieldTable
    table = CoilFieldTable.from_emns(emns, radius=0.01, spacing=2e-3, order=2)
    I = torch.tensor([1.0, math.nan, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    for call in (table.field, table.field_and_gradient):
        with pytest.raises(ValueError, match="currents must be finite"):
            call(OFF * 0.1, I)
    assert torch.isnan(table.field_and_gradient(OFF * 0.1, I, check=False)[0]).all()
