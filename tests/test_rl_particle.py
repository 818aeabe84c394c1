"""Magnetic particle under the end-effector magnet: force direction and decay, force map accuracy,
capture range, losing the particle, stability check."""
import math

import numpy as np
import pytest
import torch

from cmlearn.rl.particle import ParticleParams, ParticleSim, direct_force, force_map
from physics.magnetics import MU0, dipole_field, dipole_field_gradient

P = ParticleParams()


@pytest.fixture(scope="module")
def sim():
    return ParticleSim(P)


def point_dipole_force(offset):
    """Force on the field-aligned particle from the magnet collapsed to one dipole (far-field model)."""
    M = torch.tensor([0.0, 0.0, -P.magnet_br * np.prod(P.magnet_dims) / MU0], dtype=torch.float64)
    d = torch.tensor([offset[0], offset[1], P.particle_diameter / 2 - P.magnet_height], dtype=torch.float64)
    B, G = dipole_field(d, M), dipole_field_gradient(d, M)
    m = P.moment * B / B.norm()
    return (G.T @ m).numpy()


def test_force_points_to_the_magnet_projection(sim):
    for th in np.linspace(0, 2 * math.pi, 9)[:-1]:
        for r in (0.005, 0.03, 0.08, 0.15):
            off = np.array([r * math.cos(th), r * math.sin(th)])
            f = np.array(sim.fmap(*off))
            assert f[:2] @ off < 0  # pulls back toward the projection
            cos = -(f[:2] @ off) / (np.linalg.norm(f[:2]) * r)
            assert cos > 0.97
            assert f[2] > 0  # and up, toward the magnet


def test_force_decays_as_the_dipole_model():
    far = np.array([[0.35, 0.0], [0.0, 0.4], [0.3, 0.3]])
    ours = direct_force(P, far)
    ref = np.stack([point_dipole_force(o) for o in far])
    assert np.abs(ours - ref).max() / np.abs(ref).max() < 0.02  # the block is a dipole from far away
    r = np.array([0.3, 0.4, 0.6])  # far field: |F| ~ r^-4
    f = np.linalg.norm(direct_force(P, np.stack([r, 0 * r], 1)), axis=1)
    slope = np.polyfit(np.log(r), np.log(f), 1)[0]
    assert -4.3 < slope < -3.7


def test_dipole_count_and_interpolation_accuracy(sim):
    rng = np.random.default_rng(0)
    off = rng.uniform(-0.2, 0.2, (200, 2))
    dense = direct_force(P, off, dipoles=3000)
    peak = np.abs(sim.fmap.grid).max()
    assert np.abs(direct_force(P, off) - dense).max() / peak < 1e-3  # 300 dipoles vs 3000
    interp = np.array([sim.fmap(*o) for o in off])
    assert np.abs(interp - dense).max() / peak < 5e-3  # bilinear map on a 2.5 mm grid


def test_particle_follows_a_slow_magnet(sim):
    sim.reset(0.0, 0.0)
    x = 0.0
    for _ in range(40):  # 0.1 m/s
        sim.advance((x, 0.0), (x + 0.01, 0.0), 0.1)
        x += 0.01
    assert 0.0 < x - sim.x < 0.025 and abs(sim.y) < 1e-9


def test_particle_is_lost_beyond_capture_range(sim):
    cap = sim.fmap.capture_radius()
    assert 0.05 < cap < 0.12
    sim.reset(cap + 0.01, 0.0)
    sim.advance((0.0, 0.0), (0.0, 0.0), 2.0)
    assert sim.position == (cap + 0.01, 0.0)  # static friction holds it
    sim.reset(cap - 0.02, 0.0)
    sim.advance((0.0, 0.0), (0.0, 0.0), 2.0)
    assert abs(sim.x) < 0.01  # inside the range it is pulled in


def test_particle_is_lost_when_the_magnet_moves_too_fast(sim):
    sim.reset(0.0, 0.0)
    sim.advance((0.0, 0.0), (0.25, 0.0), 0.5)  # 0.5 m/s: faster than F_max / c
    assert 0.25 - sim.x > sim.fmap.capture_radius()
    x0 = sim.x
    sim.advance((0.25, 0.0), (0.25, 0.0), 1.0)
    assert abs(sim.x - x0) < 1e-3  # and it stays behind


def test_wall_stops_the_simulation(sim):
    sim.reset(0.0, 0.0)
    hit = sim.advance((0.0, 0.0), (0.05, 0.0), 0.5, wall=lambda x, y: x > 0.01)
    assert hit and sim.x > 0.01


def test_stability_and_parameter_errors():
    with pytest.raises(ValueError, match="substep"):
        ParticleSim(ParticleParams(substep=0.5))
    with pytest.raises(ValueError, match="magnet_height"):
        force_map(ParticleParams(magnet_height=0.07))
    with pytest.raises(ValueError, match="mu_kinetic"):
        ParticleParams(mu_static=0.1, mu_kinetic=0.2)
    with pytest.raises(ValueError, match="viscous"):
        ParticleParams(viscous=-1.0)
    with pytest.raises(ValueError, match="gravity must be a real number"):
        ParticleParams(gravity="9.81")
    # numpy numbers and a list of magnet dimensions are taken (the params key the cached force maps)
    listed = ParticleParams(magnet_dims=[0.05, 0.025, 0.01], substep=np.float64(0.005))
    assert listed.magnet_dims == (0.05, 0.025, 0.01) and listed == ParticleParams(substep=0.005)
    one = direct_force(ParticleParams(), np.array([0.01, 0.0]), dipoles=64)  # a single offset (2,) -> force (3,)
    assert one.shape == (3,) and np.allclose(one, direct_force(ParticleParams(), np.array([[0.01, 0.0]]),
                                                               dipoles=64)[0])


def test_bad_duration_and_magnet_parameters(sim):
    sim.reset(0.0, 0.0)
    for duration in (-0.1, math.nan):  # a negative duration integrated backwards: the particle flew 0.86 m
        with pytest.raises(ValueError, match="duration must be finite and >= 0"):
            sim.advance((0.0, 0.0), (0.02, 0.0), duration)
    assert sim.position == (0.0, 0.0)
    with pytest.raises(ValueError, match="magnet_dims must be 3 positive lengths"):  # was a NaN force map
        ParticleParams(magnet_dims=(math.nan, 0.025, 0.01))
    with pytest.raises(ValueError, match="magnet_dipoles must be an int >= 1, got 2.5"):  # was silently 2
        ParticleParams(magnet_dipoles=2.5)
