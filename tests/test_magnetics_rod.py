"""Field models from physics.magnetics driving the LGVI through its magnet hook."""
from __future__ import annotations

import torch

from physics import LGVI, Loads, Magnet
from physics.elastic import relative_cayley
from physics.loads import magnet_poses
from physics.magnetics import CuboidMagnet
from tests.problems import pdms_rod

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
