"""Field models from physics.magnetics driving the LGVI through its magnet hook."""
from __future__ import annotations

import torch

from physics import LGVI, Loads, Magnet
from physics.elastic import relative_cayley
from physics.loads import magnet_poses
from physics.magnetics import CuboidMagnet
from problems import pdms_rod

D = torch.float64
M_TIP = 0.0109  # A m^2: N45 cylinder 2 mm x 4 mm (Paper I)


def tip_magnet_rod(n=10, **kw):
    return pdms_rod(n, magnets=(Magnet(s=0.06055, mass=9.6e-5, moment=(0.0, 0.0, M_TIP)),), **kw)


def test_rod_pulled_by_a_permanent_magnet_conserves_total_energy():
    """Undamped tip magnet attracted and twisted by a nearby cuboid magnet (force and torque from the
    dipole grid): kinetic + elastic - m.B stays constant, which a wrong sign or a missing factor in the
    force or torque applied to the nodes would break."""
    rod = tip_magnet_rod(10)
    source = CuboidMagnet(dimensions=(0.01, 0.01, 0.01), polarization=(0.0, 0.0, 1.3),
                          position=(0.03, 0.0, 0.085)).field_model(27)
    sim = LGVI(rod, dt=0.5 * rod.stable_time_step().dt_max, loads=Loads(field=source))
    prm = sim.params

    def total(state):
        pos, _, mom = magnet_poses(state.p, state.R, relative_cayley(state.R), prm)
        return sim.energy(state) - (mom * source.field(pos)).sum()

    state = sim.initial_state()
    E0 = float(total(state))
    kinetic, drift = 0.0, 0.0
    for _ in range(40):
        state, _ = sim.simulate(state, n_steps=100, record_every=10**9)
        E = float(total(state))
        kinetic = max(kinetic, float(sim.energy(state) - sim.potential_energy(state)))
        drift = max(drift, abs(E - E0))
    assert float(state.p[-1, 0]) > 2e-3  # the tip is pulled toward the source (+x)
    assert kinetic > 0 and drift < 2e-3 * kinetic


def test_helmholtz_pair_bends_a_tip_magnet_to_the_small_angle_equilibrium():
    """A real coil pair (not an ideal uniform field) around the rod: tip rotation m B L / (E I) within 3 %."""
    from physics.magnetics import HelmholtzPair
    from problems import EI
    from test_lgvi import critical_damping, safe_dt, settle, so3_log_y

    B = 2e-4
    coils = HelmholtzPair(radius=0.15, turns=100, axis=(1.0, 0.0, 0.0), centre=(0.0, 0.0, 0.03))
    coils = type(coils)(**{**coils.__dict__, "current": B / coils.centre_field_per_amp})
    base = tip_magnet_rod(4)  # a pure end moment bends every element equally: few elements are exact
    rod = type(base)(**{**base.__dict__, "damping": 2 * critical_damping(base)})
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=coils))
    state = settle(sim, 3.0)
    theta = float(so3_log_y(state.R[-1]))
    ref = M_TIP * B * rod.length / EI(rod)
    assert abs(theta - ref) / ref < 0.03


def test_tip_magnet_follows_the_paper1_rotating_field():
    """Paper I's nested Helmholtz pairs: 7.75 mT on E2 plus 14.5 mT rotating in the E1E2 plane, across the
    rod (along E3). The tip swings toward the field and its lateral direction turns with it."""
    import math

    from physics.magnetics import paper1_rotating_field
    from test_lgvi import critical_damping, safe_dt

    w = 2 * math.pi * 0.5
    field = paper1_rotating_field(w)
    base = tip_magnet_rod(4)
    rod = type(base)(**{**base.__dict__, "damping": critical_damping(base)})
    sim = LGVI(rod, dt=safe_dt(rod), loads=Loads(field=field))
    state, traj = sim.simulate(sim.initial_state(), duration=0.4, record_every=200)
    tip = traj.p[:, -1]
    tip_angle = torch.atan2(tip[:, 0], tip[:, 1])  # lateral direction in the E1E2 plane, from E2 toward E1
    B = field.requested_field(traj.t)
    field_angle = torch.atan2(B[:, 0], B[:, 1])
    late = traj.t > 0.15
    assert float(tip[late, :2].norm(dim=-1).min()) > 0.1 * rod.length  # strongly bent toward the field
    lag = (field_angle - tip_angle)[late]
    assert float(lag.abs().max()) < math.radians(20)  # the damped tip lags the 0.5 Hz field by ~11-14 deg
    assert bool((tip_angle[late][1:] > tip_angle[late][:-1]).all())  # turns with the field


def test_cosserat_rod_in_the_six_coil_field_matches_its_linearisation():
    """The Paper II rod (static Cosserat model) loaded by the eMNS itself, with currents allocated for
    10 mT across the rod: converged, bent toward the field, and within 10 % of L of the same solve in the
    eMNS field linearised (B0 + G dx) about the rod's middle (the coils are ~10 cm away, so the field's
    curvature over the 5 cm rod is a few per cent: measured 6 % of L)."""
    from physics.magnetics import six_coil_emns
    from physics.scenes_cosserat import LinearField, paper2_magnetic_rod

    scene = paper2_magnetic_rod()
    emns = six_coil_emns()
    mid = torch.tensor([[0.0, 0.0, -0.025]], dtype=D)
    alloc = emns.allocate(mid, field=torch.tensor([[0.01, 0.0, 0.0]], dtype=D))
    assert bool(alloc.feasible)
    field = emns.with_currents(alloc.currents)
    full = scene.solve(field=field, load_steps=4)
    B0, G = field.field_and_gradient(mid)
    lin = scene.solve(field=LinearField(B0[0], G[0], mid[0]), load_steps=4)
    assert bool(full.converged) and bool(lin.converged)
    tip = full.p[..., -1, :]
    assert float(tip[0]) > 0.2 * 0.05  # bent toward +x by more than 20 % of L
    assert float((tip - lin.p[..., -1, :]).norm()) < 0.1 * 0.05
