"""Validation of the LGVI against analytic solutions and conservation laws (float64)."""
import math
import warnings

import pytest
import torch

from physics import LGVI, Loads, Magnet, SolverError, UniformField
from physics.lie import rot_y, so3_exp
from problems import (EI, aluminium_rod, cantilever_tip_force, cantilever_tip_moment, cantilever_uniform_load_tip,
                      clamped_clamped_mid, eb_first_frequency, pdms_rod, steel_like_rod)

D = torch.float64


def stiff_rod(n_elements=10, **kw):
    """L/r = 40, E = 2 GPa: small static deflections; rotational inertia scaled (statics unchanged)."""
    return steel_like_rod(n_elements, E=2e9, rotational_inertia_scale=16.0, **kw)


def critical_damping(rod):
    """Translational damping per length that critically damps the first bending mode."""
    return 2 * rod.line_mass * eb_first_frequency(rod)


def settle(sim, n_periods=2.5, **kw):
    T = 2 * math.pi / eb_first_frequency(sim.rod)
    state, _ = sim.simulate(sim.initial_state(), n_steps=int(n_periods * T / sim.dt), record_every=10**9, **kw)
    return state


def safe_dt(rod, frac=0.8):
    return frac * rod.stable_time_step().dt_max


def test_cantilever_first_frequency_vs_euler_bernoulli():
    rod = steel_like_rod(20)
    w_eb = eb_first_frequency(rod)
    sim = LGVI(rod, dt=safe_dt(rod, 0.5))
    # initial velocity in the first Euler-Bernoulli mode shape
    s = rod.arclength / rod.length
    b = 1.8751040687
    sig = (math.cosh(b) + math.cos(b)) / (math.sinh(b) + math.sin(b))
    bs = b * s
    phi = torch.cosh(bs) - torch.cos(bs) - sig * (torch.sinh(bs) - torch.sin(bs))
    v = torch.zeros(rod.n_nodes, 3, dtype=D)
    v[:, 0] = 1e-3 * phi
    state = sim.initial_state(v=v)
    T = 2 * math.pi / w_eb
    _, traj = sim.simulate(state, n_steps=int(1.3 * T / sim.dt))
    x = traj.p[:, -1, 0]
    t = traj.t
    sign = torch.sign(x[1:])
    idx = ((sign[1:] * sign[:-1]) < 0).nonzero().flatten() + 1  # zero crossings after the start
    assert len(idx) >= 2
    tz = [float(t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])) for i in idx[:2]]
    w_sim = 2 * math.pi / (2 * (tz[1] - tz[0]))
    assert abs(w_sim - w_eb) / w_eb < 0.02
    # and the linearised discrete model agrees with the simulation
    assert abs(w_sim - float(rod.natural_frequencies(n_modes=1)[0])) / w_eb < 0.005


def test_frequency_converges_with_elements():
    w_eb = eb_first_frequency(aluminium_rod(4))
    errs = [abs(float(aluminium_rod(N).natural_frequencies(n_modes=1)[0]) - w_eb) / w_eb for N in (5, 10, 20)]
    assert errs[0] > errs[1] > errs[2]
    assert errs[1] < 0.02 and errs[2] < 0.02


def test_static_gravity_deflection():
    rod = stiff_rod(damping=0.0)
    rod = type(rod)(**{**rod.__dict__, "damping": critical_damping(rod)})
    g = 9.81
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(gravity=(-g, 0.0, 0.0)))
    state = settle(sim, 3.0)
    ref = cantilever_uniform_load_tip(rod, rod.line_mass * g)
    tip = -float(state.p[-1, 0])
    assert ref / rod.length < 2e-3  # small deflection
    assert abs(tip - ref) / ref < 0.02


def test_static_tip_force_and_tip_moment_batched():
    rod = stiff_rod()
    rod = type(rod)(**{**rod.__dict__, "damping": critical_damping(rod)})
    n = rod.n_nodes
    P, M = 0.05, 0.005
    force = torch.zeros(2, n, 3, dtype=D)
    torque = torch.zeros(2, n, 3, dtype=D)
    force[0, -1, 0] = P      # tip force along +x
    torque[1, -1, 1] = M     # tip moment about +y bends the tip toward +x
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(force=force, torque=torque))
    p0 = sim.initial_state().p.expand(2, n, 3)
    T = 2 * math.pi / eb_first_frequency(rod)
    state, _ = sim.simulate(sim.initial_state(p=p0), n_steps=int(3.0 * T / sim.dt), record_every=10**9)
    assert abs(float(state.p[0, -1, 0]) - cantilever_tip_force(rod, P)) / cantilever_tip_force(rod, P) < 0.005
    assert abs(float(state.p[1, -1, 0]) - cantilever_tip_moment(rod, M)) / cantilever_tip_moment(rod, M) < 0.005
    # tip rotation under the tip moment: M L / (E I) about +y
    th = float(so3_log_y(state.R[1, -1]))
    assert abs(th - M * rod.length / EI(rod)) / (M * rod.length / EI(rod)) < 0.005


def so3_log_y(R):
    return torch.atan2(R[0, 2], R[2, 2])


def test_clamped_clamped_midspan_deflection():
    # at N = 20 the discrete solution is within 1 % of Euler-Bernoulli + Timoshenko shear
    # (q L^2 / (8 k G A) adds 1.95 % here) and converges to it as N grows
    rod = stiff_rod(20)
    rod = type(rod)(**{**rod.__dict__, "damping": 3 * critical_damping(rod)})
    g = 9.81
    sim = LGVI(rod, dt=safe_dt(rod), bc="clamped-clamped", loads=Loads(gravity=(-g, 0.0, 0.0)))
    state = settle(sim, 1.2)
    ref = clamped_clamped_mid(rod, rod.line_mass * g)
    mid = -float(state.p[rod.N // 2, 0])
    assert abs(mid - ref) / ref < 0.02
    timoshenko = ref + rod.line_mass * g * rod.length**2 / (8 * rod.C1[0])
    assert abs(mid - timoshenko) / timoshenko < 0.01
    assert torch.equal(state.p[-1], sim.initial_state().p[-1])


def test_batched_equals_one_by_one():
    rod = pdms_rod(6)
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(gravity=(0.0, -9.81, 0.0)))
    g = torch.Generator().manual_seed(1)
    v = 0.05 * torch.randn(3, rod.n_nodes, 3, generator=g, dtype=D)
    base = sim.initial_state()
    batch, _ = sim.simulate(sim.initial_state(p=base.p.expand(3, -1, -1), v=v), n_steps=200, record_every=10**9)
    for b in range(3):
        one, _ = sim.simulate(sim.initial_state(v=v[b]), n_steps=200, record_every=10**9)
        assert torch.allclose(batch.p[b], one.p, rtol=0, atol=1e-14)
        assert torch.allclose(batch.R[b], one.R, rtol=0, atol=1e-14)


def free_rod_state(sim, seed=0):
    rod = sim.rod
    g = torch.Generator().manual_seed(seed)
    p = sim.initial_state().p + 1e-3 * rod.length * torch.randn(rod.n_nodes, 3, generator=g, dtype=D)
    R = so3_exp(0.02 * torch.randn(rod.n_nodes, 3, generator=g, dtype=D))
    v = 0.05 * torch.randn(rod.n_nodes, 3, generator=g, dtype=D)
    w = 2.0 * torch.randn(rod.n_nodes, 3, generator=g, dtype=D)
    return sim.initial_state(p=p, R=R, v=v, omega=w)


def test_free_free_momentum_and_orthogonality():
    rod = pdms_rod(8)
    sim = LGVI(rod, dt=safe_dt(rod), bc="free-free")
    s0 = free_rod_state(sim)
    P0, L0 = sim.momentum(s0)
    s1, traj = sim.simulate(s0, n_steps=3000, record_every=10**9)
    P1, L1 = sim.momentum(s1)
    assert float((P1 - P0).norm() / P0.norm()) < 1e-9
    assert float((L1 - L0).norm() / L0.norm()) < 1e-9
    assert float(sim.orthogonality_error(s1)) < 1e-12
    assert traj.newton_iters.max() <= 4 and traj.newton_residual < 1e-12


@pytest.mark.slow
def test_energy_bounded_over_1e5_steps():
    rod = pdms_rod(4)
    sim = LGVI(rod, dt=safe_dt(rod, 0.25), bc="clamped-free", newton_iters=3)
    s = rod.arclength / rod.length
    v = torch.zeros(rod.n_nodes, 3, dtype=D)
    v[:, 1] = 0.05 * s**2
    w = torch.zeros(rod.n_nodes, 3, dtype=D)
    w[:, 0] = -2 * 0.05 * s / rod.length  # cross-sections turn with the velocity field
    s1 = sim.initial_state(v=v, omega=w)
    E0 = float(sim.energy(s1))
    # the compiled path (the same update as the eager one, test_compiled_rollout_matches_eager) runs the
    # 1e5 steps in a fifth of the eager time; the energy is read every 1000 steps
    energy = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(100):
            s1, _ = sim.compiled_rollout(s1, n_steps=1000, steps_per_call=1, newton_iters=3)
            energy.append(float(sim.energy(s1)))
    rel = (torch.tensor(energy, dtype=D) - E0).abs() / E0
    assert float(rel.max()) < 1e-4
    # no secular drift: the last tenth is no worse than the first tenth (+ a small margin)
    k = len(rel) // 10
    assert float(rel[-k:].max()) < 2 * float(rel[:k].max()) + 1e-6
    assert float(sim.orthogonality_error(s1)) < 1e-12


def test_time_convergence_order_two():
    # released under gravity from straight; dt0 resolves every mode (h omega_max = 0.4)
    rod = pdms_rod(6)
    dt0 = safe_dt(rod, 0.2)
    T = 400 * dt0

    def tip(dt):
        sim = LGVI(rod, dt=dt, loads=Loads(gravity=(0.0, -9.81, 0.0)))
        st, _ = sim.simulate(sim.initial_state(), n_steps=round(T / dt), record_every=10**9)
        return st.p[-1]

    ref = tip(dt0 / 16)
    errs = [float((tip(dt0 / k) - ref).norm()) for k in (1, 2, 4)]
    orders = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(1.8 < o < 2.3 for o in orders), orders


@pytest.mark.parametrize("make", [aluminium_rod, pdms_rod], ids=["aluminium", "pdms"])
def test_stability_limit(make):
    rod = make(10)
    est = rod.stable_time_step()
    sim = LGVI(rod, dt=0.8 * est.dt_max, bc="free-free")
    s1, _ = sim.simulate(free_rod_state(sim), n_steps=3000, record_every=10**9)
    assert float(s1.p.abs().max()) < 2 * rod.length
    with pytest.raises(ValueError, match="stability limit dt_max"):
        LGVI(rod, dt=2 * est.dt_max)
    with pytest.warns(RuntimeWarning, match="stability limit"):
        fast = LGVI(rod, dt=2 * est.dt_max, bc="free-free", stability="warn", check_every=50)
    with pytest.raises(SolverError, match=r"step=\d+, time=.*node=\d+"):
        fast.simulate(free_rod_state(fast), n_steps=5000)


def test_nan_load_raises_solver_error_with_location():
    rod = pdms_rod(6)

    def force(t):
        f = torch.zeros(rod.n_nodes, 3, dtype=D)
        if float(t) > 4.5 * dt:
            f[3, 1] = float("nan")
        return f

    dt = safe_dt(rod)
    sim = LGVI(rod, dt=dt, loads=Loads(force=force), check_every=7)
    with pytest.raises(SolverError) as err:
        sim.simulate(sim.initial_state(), n_steps=20)
    assert err.value.step == 6 and err.value.node == 3
    assert err.value.time == pytest.approx(6 * dt)


def test_newton_failure_is_reported():
    rod = pdms_rod(4)
    sim = LGVI(rod, dt=safe_dt(rod), bc="free-free", newton_max_iter=1)
    w = torch.zeros(rod.n_nodes, 3, dtype=D)
    w[2] = torch.tensor([0.0, 3e4, 1e4])
    with pytest.raises(SolverError, match="Newton.*node=2"):
        sim.simulate(sim.initial_state(omega=w), n_steps=3)


def test_a_newton_failure_between_checks_is_reported_at_its_step():
    """With check_every > 1 every step's residual counts, not only the checked step's: a one-step torque that
    leaves step 3 unconverged (2 fixed Newton iterations) is reported at step 3, also when steps 4 and 5 converge."""
    rod = pdms_rod(10)
    dt = 0.5 * rod.stable_time_step().dt_max

    def kick(t):
        if round(float(t) / dt) == 2:
            T = torch.zeros(rod.n_nodes, 3, dtype=D)
            T[-1, 0] = 2.5e-3
            return T
    for every in (1, 5):
        sim = LGVI(rod, dt=dt, loads=Loads(torque=kick), newton_iters=2, check_every=every)
        with pytest.raises(SolverError, match="Newton") as err:
            sim.simulate(sim.initial_state(), n_steps=10)
        assert err.value.step == 3 and err.value.node == rod.n_nodes - 1


def test_the_time_is_the_start_plus_whole_steps():
    """Steps of 1e-4 s end at 0.5 s after 5,000 (summed one by one they ended at 0.49999999999996, inside a load
    window [0, 0.5)), so a pulse over [0, 0.5) acts for 5,000 steps."""
    rod = pdms_rod(2)
    seen = []

    def force(t):
        seen.append(float(t) < 0.5)
    sim = LGVI(rod, dt=1e-4, loads=Loads(force=force), stability="off")
    end, traj = sim.simulate(sim.initial_state(), n_steps=5001, record_every=1000)
    assert traj.t[5].item() == 0.5 and end.step == 5001
    # initial_state's check of the load and its half kick, simulate's check at the start, steps 0..4999; step 5000
    # at 0.5 s
    assert len(seen) == 5004 and sum(seen) == 5003
    assert not seen[-1]
    later = sim.initial_state(t=1.0)
    assert sim.simulate(later, n_steps=10_000, record_every=10**9)[0].t == 2.0


def test_damping_too_strong_for_the_step_is_refused():
    """The damping is explicit: c dt / m (or c_r dt / J) of 2 or more grows a velocity instead of damping it."""
    rod = pdms_rod(10, rotational_damping=3e-4)
    with pytest.raises(ValueError, match="damping.*must stay below 2"):
        LGVI(rod, dt=0.5 * rod.stable_time_step().dt_max)
    LGVI(pdms_rod(10, rotational_damping=1e-4), dt=0.5 * rod.stable_time_step().dt_max)  # c dt / J = 0.68


def test_default_initial_state_of_batched_params():
    rod = pdms_rod(6)
    prm = rod.params()
    batched = prm._replace(**{k: getattr(prm, k).expand(2, *getattr(prm, k).shape).clone()
                              for k in ("l", "C1", "C2", "kappa0", "mass", "inertia", "damping", "rot_damping")})
    sim = LGVI(None, dt=safe_dt(rod), params=batched)
    state = sim.initial_state()
    assert state.p.shape == (2, rod.n_nodes, 3)
    assert torch.allclose(state.p[1, :, 2], torch.cat((torch.zeros(1, dtype=D), prm.l.cumsum(0))))


def test_prescribed_base_translation_moves_rod_rigidly():
    rod = pdms_rod(5)
    vel = torch.tensor([0.01, -0.02, 0.03], dtype=D)
    sim = LGVI(rod, dt=safe_dt(rod), bc="prescribed-base",
               base_motion=lambda t: (vel * t, torch.eye(3, dtype=D)))
    s0 = sim.initial_state(v=vel)
    s1, _ = sim.simulate(s0, n_steps=300, record_every=10**9)
    assert torch.allclose(s1.p, s0.p + vel * s1.t, atol=1e-12)


def test_prescribed_base_rotation_drags_the_rod():
    rod = pdms_rod(5)
    rate = 2.0  # rad/s about +y
    sim = LGVI(rod, dt=safe_dt(rod), bc="prescribed-base",
               base_motion=lambda t: (torch.zeros(3, dtype=D), rot_y(rate * t, dtype=D)))
    s1, _ = sim.simulate(sim.initial_state(), n_steps=int(0.2 / sim.dt), record_every=10**9)
    assert torch.allclose(s1.R[0], rot_y(rate * s1.t, dtype=D), atol=1e-12)
    assert float(s1.p[-1, 0]) > 0.0  # the free end swings toward +x


def test_tip_magnet_in_uniform_field_small_angle_equilibrium():
    m = 0.0109  # A m^2, N45 2 mm x 4 mm magnet
    B = 2e-4    # T: small angle
    base = pdms_rod(10, magnets=(Magnet(s=0.06055, mass=9.6e-5, moment=(0.0, 0.0, m)),))
    rod = type(base)(**{**base.__dict__, "damping": 2 * critical_damping(base)})
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=UniformField(torch.tensor([B, 0.0, 0.0], dtype=D))))
    state = settle(sim, 3.0)
    theta = float(so3_log_y(state.R[-1]))
    ref = m * B * rod.length / EI(rod)
    assert 0 < ref < 0.1
    assert abs(theta - ref) / ref < 0.03


def test_a_batch_of_uniform_fields_acts_per_member():
    """A (V, 3) batch of fields lined up with the magnets, not the batch: the member given no field bent
    under the other's (27 um in 100 steps). A batch is B (V, 1, 3); each member then matches its own run."""
    mags = (Magnet(s=0.03, mass=1e-4, moment=(0.0, 0.0, 0.01)), Magnet(s=0.06, mass=1e-4, moment=(0.0, 0.0, 0.01)))
    rod = pdms_rod(4, magnets=mags)
    B = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=D)
    with pytest.raises(ValueError, match=r"\(\.\.\., 1, 3\).*got shape \(2, 3\)"):
        UniformField(B)
    alone = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=UniformField(B[1])))
    batch = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=UniformField(B[:, None, :])))
    s = batch.initial_state(p=alone.initial_state().p.expand(2, -1, -1).clone())
    s, _ = batch.simulate(s, n_steps=100, record_every=10**9)
    assert float(s.p[0, :, :2].abs().max()) == 0.0
    one, _ = alone.simulate(alone.initial_state(), n_steps=100, record_every=10**9)
    assert float(one.p[-1, :2].abs().max()) > 1e-6
    assert torch.allclose(s.p[1], one.p, atol=1e-12)


def test_tip_magnet_follows_rotating_field():
    m = 0.0109
    base = pdms_rod(10, magnets=(Magnet(s=0.06055, mass=9.6e-5, moment=(0.0, 0.0, m)),))
    rod = type(base)(**{**base.__dict__, "damping": critical_damping(base)})
    w = 2 * math.pi * 0.5  # slow rotation in the x-z plane
    Bm = 0.02

    def field(t):
        return torch.stack((Bm * torch.sin(w * t), torch.zeros_like(t), Bm * torch.cos(w * t)))

    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=UniformField(field)))
    state, traj = sim.simulate(sim.initial_state(), duration=0.5, record_every=50, record_R=True)
    # tip direction (third director) lags but turns with the field, toward +x
    d3 = traj.R[:, -1, :, 2]
    ang = torch.atan2(d3[:, 0], d3[:, 2])
    assert float(ang[-1]) > 0.5 * w * float(traj.t[-1])
    assert bool((ang[1:] - ang[:-1] > -1e-3).all())


def test_float32_tracks_float64():
    rod = pdms_rod(8)
    out = {}
    for dt_ in (torch.float32, torch.float64):
        sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(gravity=(0.0, -9.81, 0.0)), dtype=dt_)
        st, _ = sim.simulate(sim.initial_state(), n_steps=1000, record_every=10**9)
        out[dt_] = st.p.double()
    assert (out[torch.float32] - out[torch.float64]).abs().max() < 1e-5 * rod.length


def test_input_validation():
    rod = pdms_rod(4)
    with pytest.raises(ValueError, match="dt"):
        LGVI(rod, dt=0.0)
    with pytest.raises(ValueError, match="clamped-free"):
        LGVI(rod, dt=1e-5, bc="hinged")
    with pytest.raises(ValueError, match="base_motion"):
        LGVI(rod, dt=1e-5, bc="prescribed-base")
    sim = LGVI(rod, dt=1e-5)
    with pytest.raises(ValueError, match=r"p must be \(\.\.\., 5, 3\)"):
        sim.initial_state(p=torch.zeros(4, 3, dtype=D))
    with pytest.raises(ValueError, match="R must be proper rotation matrices"):
        sim.initial_state(R=2 * torch.eye(3, dtype=D).expand(5, 3, 3))
    with pytest.raises(ValueError, match="finite"):
        sim.initial_state(p=torch.full((5, 3), float("nan"), dtype=D))
    for kw, msg in (({"duration": -1.0}, "duration must be a finite time >= 0"),
                    ({"duration": float("nan")}, "duration must be"), ({"n_steps": -2}, "n_steps must be >= 0"),
                    ({"n_steps": 3, "record_every": 0}, "record_every must be >= 1, got 0"),
                    ({"n_steps": 3, "duration": 1.0}, "exactly one of n_steps or duration")):
        with pytest.raises(ValueError, match=msg):
            sim.simulate(sim.initial_state(), **kw)
    for g in ((0.0, 1.0), (0.0, float("nan"), 0.0)):
        with pytest.raises(ValueError, match=r"Loads.gravity must be a finite 3-vector"):
            LGVI(rod, dt=1e-5, loads=Loads(gravity=g))
    for bad in ({"newton_max_iter": 0}, {"newton_iters": 0}, {"newton_iters": 1.5}):
        with pytest.raises(ValueError, match=rf"LGVI.{next(iter(bad))} .*integer >= 1"):
            LGVI(rod, dt=1e-5, **bad)
    for bad in ({"steps_per_call": 0}, {"newton_iters": 0}):  # refused before anything compiles
        with pytest.raises(ValueError, match="steps_per_call and newton_iters must be integers >= 1"):
            sim.compiled_rollout(sim.initial_state(), n_steps=4, **bad)


def test_a_state_not_of_this_integrator_is_refused_naming_its_field():
    """A state of another rod, dtype or batch, or with a NaN, is refused before stepping (it failed deep in torch
    with a size or dtype mismatch, or as a solver divergence at the wrong node)."""
    sim = LGVI(pdms_rod(4), dt=1e-5)
    s0 = sim.initial_state()
    other = LGVI(pdms_rod(6), dt=1e-5).initial_state()
    nan = s0.p.clone()
    nan[3, 1] = float("nan")
    for state, msg in ((other, r"state.p must be \(\.\.\., 5, 3\) for this rod of 5 nodes, got \(7, 3\)"),
                       (s0._replace(v=s0.v.expand(2, 5, 3)), r"state.v must be .* batch shape of state.p \(\)"),
                       (s0._replace(R=s0.R.float()), "state.R is torch.float32 on cpu, but this LGVI runs torch.float64")):
        for run in (lambda: sim.simulate(state, n_steps=4), lambda: sim.compiled_rollout(state, n_steps=4)):
            with pytest.raises(ValueError, match=msg):
                run()
    with pytest.raises(ValueError, match="state.p is not finite at node 3"):  # a compiled call checks no values
        sim.simulate(s0._replace(p=nan), n_steps=4)
    with pytest.raises(TypeError, match="state must be an LGVIState"):
        sim.simulate(tuple(s0), n_steps=1)



def test_a_node_load_not_given_per_node_is_refused():
    """A force (3,) broadcast onto every node, silently: refused as a tensor at construction, as a function of time
    at the start of a rollout."""
    rod = pdms_rod(4)
    tip = torch.tensor([0.0, 1e-3, 0.0], dtype=D)
    with pytest.raises(ValueError, match=r"Loads.force must be \(\.\.\., 5, 3\).*got shape \(3,\)"):
        LGVI(rod, dt=1e-5, loads=Loads(force=tip))
    sim = LGVI(rod, dt=1e-5, loads=Loads(torque=lambda t: tip * t))
    with pytest.raises(ValueError, match=r"Loads.torque \(the value of its function at t=0 s\) must be"):
        sim.simulate(sim.initial_state(), n_steps=2)
    per_node = torch.zeros(5, 3, dtype=D)
    per_node[-1] = tip
    fine = LGVI(rod, dt=1e-5, loads=Loads(force=lambda t: per_node if t < 1.0 else None))
    assert fine.simulate(fine.initial_state(), n_steps=2)[0].p[-1, 1] > 0
    # a NaN load was reported as a non-finite state ("state.v is not finite at node 4"), and a NaN start velocity
    # stepped to NaN positions with no error
    nan = per_node.clone()
    nan[-1, 0] = float("nan")
    for loads, msg in ((Loads(force=nan), r"Loads.force is not finite at node 4"),
                       (Loads(force=lambda t: nan), r"Loads.force \(the value of its function at t=0 s\) is not finite at node 4"),
                       (Loads(torque=nan), r"Loads.torque is not finite at node 4")):
        with pytest.raises(ValueError, match=msg):
            bad = LGVI(rod, dt=1e-5, loads=loads)
            bad.simulate(bad.initial_state(), n_steps=2)
    with pytest.raises(ValueError, match="Loads.field: this rod has no magnets"):  # the field was ignored
        LGVI(rod, dt=1e-5, loads=Loads(field=UniformField((0.0, 0.01, 0.0))))
    for kw in ({"v": nan}, {"omega": torch.full((3,), float("inf"), dtype=D)}):
        with pytest.raises(ValueError, match=f"initial_state: {next(iter(kw))} must be finite"):
            fine.initial_state(**kw)


@pytest.mark.slow
def test_compiled_rollout_matches_eager():
    rod = pdms_rod(6)
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(gravity=(0.0, -9.81, 0.0)))
    s0 = sim.initial_state()
    eager, _ = sim.simulate(s0, n_steps=40, record_every=10**9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        comp, rec = sim.compiled_rollout(s0, n_steps=40, steps_per_call=2, record_every=5)
    assert torch.allclose(comp.p, eager.p, atol=1e-13) and torch.allclose(comp.R, eager.R, atol=1e-13)
    assert rec.shape == (5, rod.n_nodes, 3)


def test_compiled_rollout_falls_back_to_torch_compile_for_untraceable_loads():
    """A force that branches on the time as a Python number cannot be traced into a program of fixed shapes: the
    compiled rollout says so in a warning and runs it by torch.compile instead, equal to the eager rollout."""
    rod = pdms_rod(4)
    tip = torch.zeros(rod.n_nodes, 3, dtype=D)
    tip[-1, 0] = 1e-3
    dt = safe_dt(rod)
    sim = LGVI(rod, dt=dt, loads=Loads(force=lambda t: tip if float(t) < 4 * dt else None))
    s0 = sim.initial_state()
    eager, _ = sim.simulate(s0, n_steps=8, record_every=8)
    with pytest.warns(RuntimeWarning, match="could not be traced into a program"):
        comp, _ = sim.compiled_rollout(s0, n_steps=8, steps_per_call=2)
    assert torch.allclose(comp.p, eager.p, atol=1e-13) and float((eager.p - s0.p).abs().max()) > 1e-9


def test_undamped_motion_is_time_reversible():
    """What the surrogates' --time-reversal relies on: the LGVI's frames played backwards are an LGVI
    trajectory. From step N, with the velocity and body momentum of the reversed motion (the previous
    frame is frame N + 1: v = (p^N - p^{N+1})/h, pi = -R^N^T R^{N+1} pi^{N+1}), N steps return to the
    start frame by frame, to round-off; with light viscous damping (0.05 N s/m^2) they do not."""
    def run(damping):
        rod = pdms_rod(6, damping=damping)
        sim = LGVI(rod, dt=safe_dt(rod, 0.5), bc="clamped-free")
        s = rod.arclength / rod.length
        v = torch.zeros(rod.n_nodes, 3, dtype=D)
        v[:, 1], v[:, 0] = 0.05 * s**2, -0.02 * s
        w = torch.zeros(rod.n_nodes, 3, dtype=D)
        w[:, 0] = -0.1 * s / rod.length
        states = [sim.initial_state(v=v, omega=w)]
        for _ in range(301):
            states.append(sim.step(states[-1]))
        a, b = states[-2], states[-1]  # frames N and N + 1
        back = a._replace(v=(a.p - b.p) / sim.dt, pi=-torch.einsum("nji,njk,nk->ni", a.R, b.R, b.pi))
        err = []
        for k in range(len(states) - 2, 0, -1):
            back = sim.step(back)
            err.append(max(float((back.p - states[k - 1].p).abs().max()),
                           float((back.R - states[k - 1].R).abs().max()) * rod.length))
        travel = float((states[-2].p - states[0].p).norm(dim=-1).max())
        return max(err), travel

    err, travel = run(0.0)
    assert travel > 1e-3 and err < 1e-10 * travel  # measured: 2e-16 m against 1.4 mm of motion
    err_damped, _ = run(0.05)
    assert err_damped > 0.05 * travel  # measured: 0.15 mm
