"""The coil currents and the cached coil field traced for compiled programs: the magnetic rod's compiled LGVI."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from physics.coil_currents import BatchedCurrents, CoilField, MinJerkCurrents
from physics.programs import tracing
from physics.scenes import get_scene
from physics.scenes_magnetic_rod import eMNS, heldout_currents, planar_heldout_currents, printed_currents

F64 = torch.float64


def test_current_profiles_traced_equal_eager():
    """While traced, each profile is evaluated in tensor operations (every move's clamped quintic at once, the
    sinusoids at a tensor time); it equals the eager evaluation at and between the set-point moves' knots and after
    the end (1e-12 A, measured ~1e-15), and the printed profile compiles with no graph break (every scene's loads:
    tests/test_scenes.py)."""
    printed = printed_currents()
    profiles = {"printed": printed, "held out": heldout_currents(), "planar": planar_heldout_currents(),
                "batched": BatchedCurrents([printed, heldout_currents(seed=3)]),
                "one set-point": MinJerkCurrents(printed.setpoints[1:2], (), (1.0,))}
    knots = torch.tensor(printed._knots, dtype=F64)
    times = torch.cat([torch.linspace(0.0, printed.duration + 2.0, 301, dtype=F64), knots, knots + 1e-3,
                       knots - 1e-3])
    eager = {k: [p(float(t)) for t in times] for k, p in profiles.items()}
    with tracing():
        for k, p in profiles.items():
            for t, want in zip(times, eager[k]):
                got = p(t)
                assert got.shape == want.shape and float((got - want).abs().max()) < 1e-12, (k, float(t))
    assert float(torch.stack(eager["printed"]).abs().max()) > 1.0
    fn = torch.compile(lambda t: printed(t), backend="eager", fullgraph=True)
    t = torch.tensor(2.3, dtype=F64)
    assert torch.allclose(fn(t), printed(2.3), rtol=0, atol=1e-12)


def test_coil_field_checks_the_currents_shape():
    """CoilField broadcast (1,) currents to all six coils and gave a bare RuntimeError for (5,); the currents' last
    dim must now be the eMNS's coil count, and a batch of currents needs positions (..., n, 3) with a batch dim.
    The check reads shapes only: the hook still compiles in one graph."""
    from physics.magnetics.emns import six_coil_emns
    emns = six_coil_emns(n_axial=2, n_radial=2)
    x = torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.01, -0.01]], dtype=F64)
    for bad in (torch.tensor([2.0]), torch.ones(5, dtype=F64), torch.tensor(1.0)):
        with pytest.raises(ValueError, match=r"currents must return the coil currents .* C = 6 coils.*got shape"):
            CoilField(emns, lambda t, bad=bad: bad)(0.0, x)
    with pytest.raises(ValueError, match=r"give points \(\.\.\., P, 3\) for a batch of currents"):
        CoilField(emns, lambda t: torch.ones(2, 6, dtype=F64))(0.0, x)
    assert CoilField(emns, lambda t: torch.ones(2, 6, dtype=F64))(0.0, x.expand(2, 2, 3))[0].shape == (2, 2, 3)
    profile = MinJerkCurrents(torch.tensor([[0.0] * 6, [1.0, -1, 2, 0, 0, 1]], dtype=F64), (0.5,), (0.1, 1.0))
    field = CoilField(emns, profile)
    B, dB = field(0.3, x)  # eager: evaluates and keeps the maps
    fn = torch.compile(lambda t, p: field(t, p), backend="eager", fullgraph=True)
    Bc, dBc = fn(torch.tensor(0.3, dtype=F64), x)
    assert torch.allclose(Bc, B, rtol=1e-12, atol=0) and torch.allclose(dBc, dB, rtol=1e-12, atol=0)


def test_profiles_refuse_a_non_finite_time():
    """MinJerkCurrents at t = NaN returned the last set-point (and SinusoidCurrents NaN currents); an eager
    evaluation now refuses a non-finite time. The traced form (a 0-d tensor time, no branch on its value) does
    not look, as any value check there would need a data-dependent branch."""
    from physics.coil_currents import SinusoidCurrents
    mj = MinJerkCurrents(torch.tensor([[0.0, 1.0], [2.0, -1.0]], dtype=F64), (0.5,), (0.1, 1.0))
    sn = SinusoidCurrents([[1.0, 0.5]], [0.3], [[0.0, 1.0]])
    for profile in (mj, sn):
        for t in (math.nan, math.inf, -math.inf, torch.tensor(math.nan, dtype=F64)):
            with pytest.raises(ValueError, match="t must be a finite time"):
                profile(t)
        assert torch.isfinite(profile(0.4)).all()
    assert torch.equal(mj(5.0), torch.tensor([2.0, -1.0], dtype=F64))


@pytest.mark.slow
def test_compiled_magnetic_rod_refreshes_the_field_where_the_eager_rollout_does():
    """The magnetic rod's compiled LGVI (2 steps a call) under two fast set-point moves (batch 2): the blocks in
    which the cached coil maps would be refreshed run eagerly, so the compiled rollout refreshes them at the same
    steps (9 blocks of 80, and the initial state) and equals the eager one to 1e-12 m (measured 2e-17), where keeping the first maps throughout
    moves the rod by 8e-6 m; the rod moves 2.7 mm."""
    sp = printed_currents().setpoints
    moves = [MinJerkCurrents(torch.stack([sp[0], 2 * sp[k]]), (0.01,), (0.002, 1.0)) for k in (1, 3)]
    base = get_scene("magnetic_rod")

    def run(compiled: bool, tol: float = 2e-4):
        field = CoilField(eMNS(), BatchedCurrents(moves), tol=tol)
        sim = replace(base, loads=replace(base.loads, field=field)).make_integrator()
        cfg = base.initial_configuration()
        s0 = sim.initial_state(p=cfg["p"].expand(2, -1, -1), R=cfg["R"].expand(2, -1, -1, -1))
        end = sim.compiled_rollout(s0, n_steps=160, steps_per_call=2)[0] if compiled else \
            sim.simulate(s0, n_steps=160, record_every=160)[0]
        return end, field.refreshes, sim.eager_blocks, s0

    eager, refreshes, _, s0 = run(False)
    comp, comp_refreshes, eager_blocks, _ = run(True)
    kept = run(False, tol=1.0)[0]
    assert refreshes == comp_refreshes == eager_blocks + 1 == 10  # the first at the initial state's half kick
    assert float((comp.p - eager.p).abs().max()) < 1e-12 and float((comp.R - eager.R).abs().max()) < 1e-12
    assert float((kept.p - eager.p).abs().max()) > 1e-6
    assert float((eager.p - s0.p).abs().max()) > 2e-3
    assert math.isclose(comp.t, eager.t, abs_tol=1e-12) and comp.step == eager.step == 160
