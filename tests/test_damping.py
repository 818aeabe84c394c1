"""Distributed damping-capacity filters (I.17)-(I.21) against a reference LGVI with known damping."""
import pytest
import torch

from physics import LGVI, Loads
from physics.damping import DistributedDampingFilter, run_filtered_model
from problems import pdms_rod

D = torch.float64
C_TRUE = 0.02  # N s / m^2, uniform viscous damping per unit length of the reference


@pytest.fixture(scope="module")
def reference():
    rod = pdms_rod(8, damping=C_TRUE)
    sim = LGVI(rod, dt=9e-5, loads=Loads(gravity=(0.0, -9.81, 0.0)))
    s = rod.arclength / rod.length
    v = torch.zeros(rod.n_nodes, 3, dtype=D)
    v[:, 0], v[:, 1] = 0.3 * s**2, 0.2 * s**2
    _, traj = sim.simulate(sim.initial_state(v=v), duration=0.25, record_R=True)
    undamped = type(rod)(**{**rod.__dict__, "damping": 0.0})
    model = LGVI(undamped, dt=9e-5, loads=Loads(gravity=(0.0, -9.81, 0.0)))
    return rod, v, traj, model


@pytest.mark.parametrize("forgetting,isotropic", [(0.0, False), (0.995, False), (0.995, True)])
def test_estimates_converge_to_the_true_capacity(reference, forgetting, isotropic):
    rod, _, traj, model = reference
    filt = DistributedDampingFilter(model, forgetting=forgetting, isotropic=isotropic)
    fs, hist = filt.run(traj.p, traj.R[1])
    true = C_TRUE * rod.node_weights()[1:, None]  # K_a = c w_a at the free nodes
    rel = (fs.K[1:] - true).abs() / true
    assert float(rel[:, :2].max()) < 0.1  # both transverse axes of every free node
    if isotropic:
        assert float(rel.max()) < 0.1
    assert torch.equal(fs.K[0], torch.zeros(3, dtype=D))  # the clamped node has no filter
    # it converges early: after 10 % of the record already within 10 %
    k = hist.shape[0] // 10
    assert float(((hist[k:, 1:, :2] - true[..., :2]).abs() / true[..., :2]).max()) < 0.1


def test_noisy_measurements_with_forgetting(reference):
    rod, _, traj, model = reference
    g = torch.Generator().manual_seed(0)
    noisy = traj.p + 2e-12 * torch.randn(traj.p.shape, generator=g, dtype=D)
    noisy[:, 0] = traj.p[:, 0]  # the clamped node is known
    filt = DistributedDampingFilter(model, forgetting=0.999, isotropic=True)
    fs, _ = filt.run(noisy, traj.R[1])
    true = C_TRUE * rod.node_weights()[1:, None]
    assert float(((fs.K[1:] - true).abs() / true).max()) < 0.1
    pointwise = DistributedDampingFilter(model, forgetting=0.0, isotropic=True)
    fs0, _ = pointwise.run(noisy, traj.R[1])
    # averaging is what makes the noisy estimate usable
    assert float((fs.K[1:] - true).abs().max()) < float((fs0.K[1:] - true).abs().max())


def test_filtered_model_tracks_better_than_undamped(reference):
    rod, v, traj, model = reference
    filt = DistributedDampingFilter(model, forgetting=0.995, isotropic=True)
    p_filtered, _ = run_filtered_model(model, model.initial_state(v=v), filt, traj.p)
    _, und = model.simulate(model.initial_state(v=v), n_steps=traj.p.shape[0] - 1)
    err_f = (p_filtered - traj.p).norm(dim=-1).amax()
    err_u = (und.p - traj.p).norm(dim=-1).amax()
    assert float(err_f) < 0.01 * float(err_u)


def test_filter_input_validation(reference):
    rod, _, traj, model = reference
    with pytest.raises(ValueError, match="forgetting"):
        DistributedDampingFilter(model, forgetting=1.0)
    damped = LGVI(rod, dt=9e-5)
    with pytest.raises(ValueError, match="undamped"):
        DistributedDampingFilter(damped)
    filt = DistributedDampingFilter(model)
    with pytest.raises(ValueError, match="same nodes"):
        filt.init(traj.p[0], traj.p[1][:-1], traj.R[1])
    with pytest.raises(ValueError, match="at least 3"):
        filt.run(traj.p[:2], traj.R[1])
    with pytest.raises(ValueError, match="record_every must be an integer >= 1, got 0"):  # ZeroDivisionError
        filt.run(traj.p[:4], traj.R[1], record_every=0)
    # a NaN weight estimated K = 0 at every node (no damping found) and a (5,) weight broadcast over nodes
    for bad, match in ((dict(R=float("nan")), "R must be finite, got nan"), (dict(W=float("inf")), "W must be finite"),
                       (dict(R=torch.ones(5)), r"R must be a scalar or a \(3,\) diagonal, got shape \(5,\)"),
                       (dict(W=torch.zeros(2, 3)), r"W must be a scalar or a \(3,\) diagonal")):
        with pytest.raises(ValueError, match=match):
            DistributedDampingFilter(model, **bad)


def test_zero_regularisation_gives_no_nan(reference):
    # W = 0 (allowed: positive semi-definite) is 0/0 at the clamped node and on axes not yet moving
    rod, v, traj, model = reference
    p = traj.p[:200]
    for isotropic in (False, True):
        filt = DistributedDampingFilter(model, W=0.0, forgetting=0.995, isotropic=isotropic)
        fs, hist = filt.run(p, traj.R[1])
        assert torch.isfinite(hist).all()
        assert torch.equal(fs.K[0], torch.zeros(3, dtype=D))
        true = C_TRUE * rod.node_weights()[1:, None]
        assert float(((fs.K[1:, :2] - true).abs() / true).max()) < 0.1
    p_filtered, _ = run_filtered_model(model, model.initial_state(v=v), filt, p)
    assert torch.isfinite(p_filtered).all()
