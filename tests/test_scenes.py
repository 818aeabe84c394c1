"""Named scenes (physics.scenes): registry, thesis parameters, geometry, stability, short runs."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physics import Loads, SolverError, UniformField
from physics.lie import so3_log
from physics.scene import MU0, Scene, dipole_moment, table_to_si
from physics.scenes import SCENES, UnknownSceneError, get_scene, scene_names
from physics.scenes_paper2 import NodePulse, SquareTipForce

PAPER1 = ["al_inplane", "al_3d", "pdms_inplane", "pdms_tip_magnet", "pdms_circular", "pdms_square_two_magnets"]
PAPER2 = ["ellipse", "ellipse_horizontal", "square_tracking", "semicircle", "semicircle_heldout", "magnetic_rod",
          "magnetic_rod_heldout", "magnetic_rod_planar", "magnetic_rod_planar_heldout"]
G = 9.81


def rel(a, b):
    return abs(a - b) / abs(b)


# ------------------------------------------------------------------------------------ registry
def test_registry_lists_all_scenes():
    assert scene_names() == PAPER1 + PAPER2
    for name in SCENES:
        assert get_scene(name) is SCENES[name]
        assert SCENES[name].name == name


def test_unknown_scene_names_the_valid_ones():
    with pytest.raises(KeyError) as exc:
        get_scene("no_such_scene")
    assert isinstance(exc.value, UnknownSceneError)
    msg = str(exc.value)
    assert "no_such_scene" in msg and all(n in msg for n in SCENES)


@pytest.mark.parametrize("name", PAPER1 + PAPER2)
def test_scene_is_documented_and_consistent(name):
    sc = get_scene(name)
    assert len(sc.description) > 150 and "\n" not in sc.summary and len(sc.summary) < 100
    assert sc.thesis and isinstance(sc.chosen, dict)
    assert sc.n_steps == round(sc.duration / sc.dt) and sc.n_steps > 0
    assert all(0 <= i < sc.rod.n_nodes for i in sc.nodes_of_interest)
    assert len(sc.node_labels) == len(sc.nodes_of_interest)
    assert sc.loads.gravity is None or tuple(sc.loads.gravity) == sc.gravity
    if "dt" in sc.thesis:  # printed time step and duration are kept
        assert sc.dt == sc.thesis["dt"] and sc.duration == sc.thesis["duration"]
    if "n_elements" in sc.thesis:
        assert sc.rod.N == sc.thesis["n_elements"]


def test_energy_conserved_flags():
    conserved = {n for n, s in SCENES.items() if s.energy_conserved}
    assert conserved == {"al_inplane", "al_3d", "pdms_inplane", "pdms_tip_magnet", "ellipse", "ellipse_horizontal"}


# ------------------------------------------------------------------------------- thesis values
def test_table_conversion_units():
    t = table_to_si(table="x", n_elements=1, M=8.45e-3, J_d=(0, 2.11, 2.11), C1=(2.35e14, 0.88e14, 0.88e14),
                    C2=(4.42e13, 5.89e13, 5.89e13), F_c=8.29e4, dt=1e-6, duration=1.0)
    assert t["C1"] == pytest.approx((0.88e5, 0.88e5, 2.35e5))  # axis-first -> (E1, E2, E3), N
    assert t["C2"] == pytest.approx((5.89e-2, 5.89e-2, 4.42e-2))  # N m^2
    assert t["J_d"] == pytest.approx((2.11e-9, 2.11e-9, 0.0))  # kg m
    assert t["F_c"] == pytest.approx(0.0829)  # N/m


@pytest.mark.parametrize("name", PAPER1)
def test_paper1_parameters_match_tables(name):
    sc = get_scene(name)
    rod, th = sc.rod, sc.thesis
    tol = 0.02  # printed values have 3 significant digits; a factor 2 or a unit slip fails
    assert rel(rod.line_mass, th["M"]) < tol
    Jd = [j / rod.rotational_inertia_scale for j in rod.line_inertia_d]  # physical inertia
    for k in (0, 1):
        assert rel(Jd[k], th["J_d"][k]) < tol
    assert th["J_d"][2] == 0 and abs(Jd[2]) < 1e-20
    for k in range(3):
        assert rel(rod.C1[k], th["C1"][k]) < tol
    for k in (0, 1):
        assert rel(rod.C2[k], th["C2"][k]) < tol
    if name == "pdms_square_two_magnets":  # Saint-Venant torsion 0.1406 a^4 vs the table's a^4/6
        assert rel(rod.C2[2] / th["C2"][2], 0.1406 * 6) < tol
    else:
        assert rel(rod.C2[2], th["C2"][2]) < tol
    fc = th["F_c"] if not isinstance(th["F_c"], dict) else min(th["F_c"].values())
    assert rel(rod.line_mass * G, fc) < tol
    assert math.sqrt(sum(g * g for g in sc.gravity)) == pytest.approx(G)
    errors = th["errors"]
    assert errors and all(0 < e["mean"] <= e["max"] < 2e-3 and 1 < e["max_percent"] < 6 for e in errors.values())


def test_magnets_follow_the_thesis():
    mag = get_scene("pdms_tip_magnet").rod.magnets[0]
    V = 4 * math.pi * 1e-9  # 4 pi mm^3
    lo, hi = 1.32 * V / MU0, 1.37 * V / MU0
    assert lo <= mag.moment[2] <= hi and mag.moment[:2] == (0.0, 0.0)
    assert mag.mass == 9.6e-5 and mag.s == pytest.approx(0.06055)
    assert dipole_moment(1.0, V) == pytest.approx(1e-2)
    sq = get_scene("pdms_square_two_magnets").rod
    s = sorted(m.s for m in sq.magnets)
    assert s == pytest.approx([0.0855 - 0.0361, 0.0855])
    assert all(m.mass == 7.2e-5 for m in sq.magnets)
    assert sq.magnets[0].moment[2] == -sq.magnets[1].moment[2] != 0
    assert get_scene("pdms_circular").rod.magnets == get_scene("pdms_tip_magnet").rod.magnets


# --------------------------------------------------------------------------------- stability
@pytest.mark.parametrize("name", PAPER1 + PAPER2)
def test_dt_below_stability_limit(name):
    st = get_scene(name).stability()
    assert st["ratio"] <= 0.8, st


@pytest.mark.parametrize("name", ["al_inplane", "al_3d", "pdms_square_two_magnets"])
def test_mass_scaling_is_needed_and_harmless(name):
    from dataclasses import replace

    sc = get_scene(name)
    phys = replace(sc.rod, rotational_inertia_scale=1.0)
    dt_phys = phys.stable_time_step().dt_max
    assert rel(dt_phys, sc.chosen["dt_max_physical"]) < 0.05
    assert sc.dt > dt_phys  # the printed step is unstable without the scaling
    w_phys = float(phys.natural_frequencies(n_modes=1)[0])
    w_scaled = float(sc.rod.natural_frequencies(n_modes=1)[0])
    assert rel(w_scaled, w_phys) < 1e-3


# ---------------------------------------------------------------------------------- geometry
def _angle_deg(R):
    return math.degrees(float(so3_log(R).norm()))


def test_cantilever_initial_shapes():
    cfg = get_scene("al_inplane").initial_configuration()
    p, R = cfg["p"], cfg["R"]
    assert _angle_deg(R[-1]) == pytest.approx(3.69, abs=1e-9)
    assert float(p[-1, 0]) == pytest.approx(2 / 3 * 0.2 * math.tan(math.radians(3.69)), rel=0.01)
    assert float((p[1:] - p[:-1]).norm(dim=-1).sum()) == pytest.approx(0.2, rel=1e-4)
    tip = get_scene("al_3d").initial_configuration()["p"][-1]
    assert tip[:2].tolist() == pytest.approx([10e-3, -8e-3], abs=1e-9)
    R = get_scene("pdms_tip_magnet").initial_configuration()["R"][-1]
    w = so3_log(R)
    assert math.degrees(float(w[0])) == pytest.approx(-41.74, abs=1e-9) and float(w[1:].abs().max()) < 1e-12


def test_ellipse_geometry_reconciles_printed_end_orientations():
    cfg = get_scene("ellipse").initial_configuration()
    p, R = cfg["p"], cfg["R"]
    assert p.shape == (59, 3) and float(p[0].abs().max()) == 0 and float(p[-1].abs().max()) == 0
    assert torch.allclose(R[0], R[-1]) and torch.allclose(R[0][:, 2], torch.tensor([1.0, 0, 0], dtype=R.dtype))
    assert p[29].tolist() == pytest.approx([0.0, -0.6, 0.0], abs=1e-9)
    assert float(p[:, 0].max() - p[:, 0].min()) == pytest.approx(0.2, rel=1e-3)
    chord = p[1] - p[0]
    assert abs(math.degrees(math.atan2(float(chord[1]), float(chord[0])))) == pytest.approx(18.07, abs=1.5)
    rod = get_scene("ellipse").rod
    assert get_scene("ellipse_horizontal").rod is rod  # one rod, two boundary conditions
    assert rod.length == pytest.approx(1.3365, rel=0.01) and rod.length < 1.3365  # chords < arcs
    # every element starts free of axial strain (only bending and a little shear are stored)
    for name in ("ellipse", "ellipse_horizontal"):
        c = get_scene(name).initial_configuration()
        q, F = c["p"], c["R"]
        d = q[1:] - q[:-1]
        ax = 0.5 * ((F[:-1, :, 2] * d).sum(-1) + (F[1:, :, 2] * d).sum(-1))
        assert torch.allclose(ax, torch.full_like(ax, rod.lengths[0]), rtol=1e-10, atol=0)
    ph = get_scene("ellipse_horizontal").initial_configuration()["p"]
    ch = ph[1] - ph[0]
    assert abs(math.degrees(math.atan2(float(ch[1]), float(ch[0])))) < 1.0  # printed: identity
    assert ph[29].tolist() == pytest.approx([0.0, -0.2, 0.0], abs=1e-4)


def test_semicircle_geometry_and_end_frames():
    cfg = get_scene("semicircle").initial_configuration()
    p, R = cfg["p"], cfg["R"]
    r = 0.6 / math.pi
    assert p[50].tolist() == pytest.approx([r, r, 0.0], rel=1e-3)
    assert p[-1].tolist() == pytest.approx([2 * r, 0.0, 0.0], abs=1e-4)
    rel_rot = so3_log(R[-1] @ R[0].T)  # world-frame rotation taking the first end frame to the last
    assert math.degrees(float(rel_rot.norm())) == pytest.approx(181.81, abs=2.0)
    assert float(rel_rot[:2].abs().max()) < 1e-6  # about z


def test_initial_frames_are_rotations_tangent_to_the_centreline():
    for name in SCENES:
        cfg = get_scene(name).initial_configuration()
        p = cfg["p"]
        assert p.shape == (SCENES[name].rod.n_nodes, 3) and p.dtype == torch.float64
        if "R" in cfg:
            R = cfg["R"]
            assert float((R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype)).abs().max()) < 1e-12
            d = p[1:] - p[:-1]
            d = d / d.norm(dim=-1, keepdim=True)
            e3 = R[:-1, :, 2] + R[1:, :, 2]
            e3 = e3 / e3.norm(dim=-1, keepdim=True)
            assert float((d * e3).sum(-1).min()) > 0.999  # frames follow the curve


# ------------------------------------------------------------------------------ loads/fields
def test_field_profiles():
    B = get_scene("pdms_circular").loads.field.B
    assert B(0.0).tolist() == pytest.approx([0.0, 22.25e-3, 0.0])
    assert B(0.5).tolist() == pytest.approx([14.5e-3, 7.75e-3, 0.0])
    assert B(2.0).tolist() == pytest.approx(B(0.0).tolist())
    Bs = get_scene("pdms_square_two_magnets").loads.field.B
    assert Bs(0.0).tolist() == pytest.approx([0, 0, 20e-3])
    assert Bs(7.5).tolist() == pytest.approx([0, 0, 19.85e-3])
    assert Bs(3.75).tolist() == pytest.approx([0, 19.925e-3, 0], abs=1e-12)
    assert Bs(torch.tensor(7.5)).tolist() == pytest.approx(Bs(7.5).tolist())
    assert B(torch.tensor(0.5, dtype=torch.float64)).tolist() == pytest.approx(B(0.5).tolist())


def test_square_tracking_force_schedule():
    sc = get_scene("square_tracking")
    f = sc.loads.force
    assert isinstance(f, SquareTipForce)
    E, I, L = 10e6, math.pi * 0.01**4 / 4, 0.55
    assert f.k == pytest.approx(3 * E * I / L**3)
    for t, xy in ((0.0, (0, 0)), (2.0, (0.05, 0.05)), (5.0, (-0.05, 0.05)), (8.0, (-0.05, -0.05)),
                  (11.0, (0.05, -0.05)), (14.0, (0.05, 0.05)), (16.0, (0, 0))):
        assert f.desired(t)[0] == pytest.approx(xy, abs=1e-12)
        F = f(t)
        assert F.shape == (9, 3) and float(F[:-1].abs().max()) == 0 and float(F[-1, 2]) == 0
        assert F[-1, :2].tolist() == pytest.approx([f.k * xy[0], f.k * xy[1]], abs=1e-12)


def test_semicircle_pulses():
    f = get_scene("semicircle").loads.force
    assert isinstance(f, NodePulse)
    F = f(0.25)
    assert F[50].tolist() == pytest.approx([0, -0.02, 0]) and float(F.abs().sum()) == pytest.approx(0.02)
    assert f(0.5) is None and f(1.5) is None
    h = get_scene("semicircle_heldout").loads.force
    assert h(0.5) is None
    assert h(1.0)[50].tolist() == pytest.approx([0, 0, 0.1])  # -100 cos(pi) mN
    assert h(1.5)[50].tolist() == pytest.approx([0, 0, 0.0], abs=1e-12)
    # the LGVI passes time as a 0-d tensor
    assert h(torch.tensor(1.0, dtype=torch.float64))[50].tolist() == pytest.approx([0, 0, 0.1])
    assert f(torch.tensor(0.6, dtype=torch.float32)) is None


def test_semicircle_pulses_traced_equal_eager(monkeypatch):
    """While torch.compile traces (LGVI.compiled_rollout) a pulse branches on no time value: the force is zero
    outside its interval, and equal to the eager one inside."""
    for name in ("semicircle", "semicircle_heldout"):
        f = get_scene(name).loads.force
        times = (0.0, 0.25, 0.4999, 0.5, 0.6, 1.0, 1.5, 1.99, 2.0, 2.5)
        eager = [f(torch.tensor(t, dtype=torch.float64)) for t in times]
        with monkeypatch.context() as m:
            m.setattr(torch.compiler, "is_compiling", lambda: True)
            for t, e in zip(times, eager):
                traced = f(torch.tensor(t, dtype=torch.float64))
                assert traced.shape == (101, 3)
                torch.testing.assert_close(traced, torch.zeros(101, 3, dtype=torch.float64) if e is None else e,
                                           rtol=0, atol=1e-15)
        assert sum(e is not None for e in eager) == (3 if name == "semicircle" else 4)


def test_tip_path_force_rejects_bad_paths():
    from cmlearn.data.tasks import TipPathForce
    rod = get_scene("square_tracking").rod
    for pts, dur, name in (([(0, 0), (0.1, 0)], [0.0], "durations"), ([(0, 0), (0.1, 0)], [1.0, 1.0], "durations"),
                           ([(0, 0), (0.1, 0)], [math.inf], "durations"), ([(0, 0)], [], "waypoints"),
                           ([(0, 0, 0), (0.1, 0, 0)], [1.0], "waypoints"), ([(0, 0), ("a", 0)], [1.0], "waypoints")):
        with pytest.raises(ValueError, match=name):
            TipPathForce(rod, pts, dur)
    assert TipPathForce(rod, [(0, 0), (0.1, 0)], [2.0])(torch.tensor(1.0))[-1, 0] > 0


def test_tip_path_forces_traced_equal_eager(monkeypatch):
    """Simulation II's feed-forward tip forces (the printed square, the held-out circle and figure eight, random
    waypoint paths) evaluated in tensor operations while torch.compile traces equal the eager segment search at
    and between the corners and after the end, and compile into one graph (fullgraph: no branch on the time)."""
    from cmlearn.data.tasks import _square_variants, tracking_heldout_scene
    square = get_scene("square_tracking")
    forces = [square.loads.force, *(tracking_heldout_scene(k).loads.force for k in ("circle", "figure8")),
              *_square_variants(square, 3, 0)["force"].fns[1:]]
    times = (0.0, 0.7, 1.9999, 2.0, 3.3, 5.0, 7.77, 11.0, 13.0, 15.9, 16.0, 17.5)
    for f in forces:
        eager = torch.stack([f(torch.tensor(t, dtype=torch.float64)) for t in times])
        assert float(eager[:, -1, :2].abs().amax(0).min()) > 0.05  # the force moves the tip in x and y
        with monkeypatch.context() as m:
            m.setattr(torch.compiler, "is_compiling", lambda: True)
            traced = torch.stack([f(torch.tensor(t, dtype=torch.float64)) for t in times])
        torch.testing.assert_close(traced, eager, rtol=0, atol=1e-15)
    from cmlearn.data.tasks import BatchedTipPathForce
    batch = _square_variants(square, 4, 0)["force"]  # the training paths: one tensor evaluation of all while traced
    assert isinstance(batch, BatchedTipPathForce)
    for t in times:
        eager = batch(torch.tensor(t, dtype=torch.float64))
        with monkeypatch.context() as m:
            m.setattr(torch.compiler, "is_compiling", lambda: True)
            traced = batch(torch.tensor(t, dtype=torch.float64))
        torch.testing.assert_close(traced, eager, rtol=0, atol=1e-15)
    for bad, match in (([square.loads.force, tracking_heldout_scene("circle").loads.force], "waypoints"),
                       ([square.loads.force, SquareTipForce(get_scene("semicircle").rod, 0.05, (1.0,) * 6)], "one rod")):
        with pytest.raises(ValueError, match=match):
            BatchedTipPathForce(bad, square.rod.n_nodes)
    graph = torch.compile(lambda t: square.loads.force(t), backend="eager", fullgraph=True)
    torch.testing.assert_close(graph(torch.tensor(4.2, dtype=torch.float64)),
                               square.loads.force(torch.tensor(4.2, dtype=torch.float64)), rtol=0, atol=1e-15)


# ------------------------------------------------------------------------------------ runs
@pytest.mark.parametrize("name", PAPER1 + PAPER2)
def test_short_run_is_finite(name):
    sc = get_scene(name)
    integ = sc.make_integrator(stability="off")  # the limit is checked in test_dt_below_stability_limit
    s0 = sc.initial_state(integ)
    s, tr = integ.simulate(s0, n_steps=200, record_every=50)
    assert torch.isfinite(tr.p).all() and tr.newton_residual < 1e-10
    assert float(integ.orthogonality_error(s)) < 1e-10
    fixed = [0] if sc.bc == "clamped-free" else [0, sc.rod.n_nodes - 1]
    assert torch.equal(s.p[fixed], s0.p[fixed]) and torch.equal(s.R[fixed], s0.R[fixed])
    assert float((s.p - s0.p).abs().max()) < 0.05 * sc.rod.length  # 200 steps: no blow-up


@pytest.mark.parametrize("name", PAPER1 + PAPER2)
def test_scene_loads_trace_into_one_graph(name):
    """What the LGVI's compiled rollout traces of a scene's loads (gravity, forces, torques, the magnets' field:
    ``LGVI.external_loads``) compiles into one graph for every time (no graph break, no recompile: where a load reads
    the time as a Python number, dynamo breaks the graph there and specializes on its value) and equals the eager
    loads at times across the scene, its force pulses and current moves included (1e-12 relative to the largest
    load; the coil field's cache filled eagerly first, as the compiled rollout's guard requires)."""
    from physics.elastic import relative_cayley
    sc = get_scene(name)
    sim = sc.make_integrator(stability="off")
    st = sc.initial_state(sim)
    args = (st.p, st.v + 0.01, st.R, st.pi, relative_cayley(st.R))
    graphs = []

    def count(gm, _):
        graphs.append(gm)
        return gm.forward
    torch._dynamo.reset()  # the code object is shared by every scene's integrator: each test compiles it afresh
    traced = torch.compile(sim.external_loads, backend=count)  # a graph break or a recompile: a second graph
    times = torch.linspace(0.0, sc.duration, 13, dtype=torch.float64)[1:]
    for t in times:
        want = sim.external_loads(t, *args)
        got = traced(t, *args)
        scale = max(float(w.abs().max()) for w in want)
        for g, w in zip(got, want):
            torch.testing.assert_close(g, w, rtol=0, atol=1e-12 * scale)
    assert len(graphs) == 1


def test_make_integrator_overrides_and_default_stability_check():
    sc = get_scene("pdms_inplane")
    integ = sc.make_integrator(dtype=torch.float32, dt=4e-5)
    assert integ.dt == 4e-5 and integ.params.mass.dtype == torch.float32
    assert integ.stability_estimate is not None and integ.stability_estimate.dt_max > sc.dt
    s = sc.initial_state(integ)
    assert s.p.dtype == torch.float32
    with pytest.raises(ValueError, match="stability limit"):
        sc.make_integrator(dt=1e-3)


@pytest.mark.parametrize("name", ["pdms_tip_magnet", "al_inplane"])
def test_conservative_scene_keeps_its_energy(name):
    sc = get_scene(name)
    integ = sc.make_integrator(stability="off")
    _, tr = integ.simulate(sc.initial_state(integ), n_steps=1000, record_every=50, record_energy=True)
    E = tr.energy
    assert float((E - E[0]).abs().max()) < 1e-4 * float(E[0].abs())


@pytest.mark.parametrize("name", ["al_inplane", "al_3d", "pdms_tip_magnet", "semicircle"])
def test_open_initial_shapes_store_only_bending_energy(name):
    from physics.elastic import elastic_energy

    sc = get_scene(name)
    cfg = sc.initial_configuration()
    prm = sc.rod.params()
    bending = elastic_energy(cfg["p"], cfg["R"], prm._replace(C1=torch.zeros_like(prm.C1)))
    stretch = elastic_energy(cfg["p"], cfg["R"], prm._replace(C2=torch.zeros_like(prm.C2)))
    assert float(bending) > 0 and float(stretch) < 1e-12 * float(bending)


def test_magnetic_scenes_start_in_equilibrium():
    for name in ("pdms_circular", "pdms_square_two_magnets"):
        sc = get_scene(name)
        B0 = sc.loads.field.B(0.0)
        integ = sc.make_integrator(stability="off", loads=Loads(gravity=sc.gravity, field=UniformField(B0)))
        s0 = sc.initial_state(integ)
        assert abs(float(s0.p[-1, 1])) > 0.005  # bent by gravity and the field, not straight
        s, _ = integ.simulate(s0, n_steps=100, record_every=100)
        assert float((s.p - s0.p).abs().max()) < 1e-8


def test_an_overridden_rod_starts_in_its_own_equilibrium():
    """Scene.initial_state(rod=...) started a stiffer rod from the scene rod's sag (out of equilibrium: it sprang
    up); an integrator given beside overrides silently ignored them (float32 asked, float64 returned)."""
    import dataclasses

    sc = get_scene("pdms_circular")
    stiff = dataclasses.replace(sc.rod, modulus_scale=2.0)
    loads = Loads(gravity=sc.gravity, field=UniformField(sc.loads.field.B(0.0)))
    s0 = sc.initial_state(rod=stiff, stability="off", loads=loads)
    own = sc.initial_state(sc.make_integrator(stability="off", loads=loads))
    assert float((s0.p - own.p).abs().max()) > 1e-3  # the stiffer rod sags less
    s, _ = sc.make_integrator(rod=stiff, stability="off", loads=loads).simulate(s0, n_steps=100, record_every=100)
    assert float((s.p - s0.p).abs().max()) < 1e-8
    with pytest.raises(ValueError, match=r"give an integrator or the overrides \['dtype'\] .*not both"):
        sc.initial_state(sc.make_integrator(), dtype=torch.float32)


def test_clamped_semicircle_is_an_equilibrium():
    sc = get_scene("semicircle_heldout")  # no force before t = 1 s
    integ = sc.make_integrator(stability="off")
    s0 = sc.initial_state(integ)
    s, _ = integ.simulate(s0, n_steps=200, record_every=200)
    assert float((s.p - s0.p).abs().max()) < 1e-12


@pytest.mark.parametrize("name", ["pdms_circular", "pdms_square_two_magnets"])
def test_damping_is_five_percent_of_critical_in_mode_one(name):
    rod = get_scene(name).rod
    w1 = float(rod.natural_frequencies(n_modes=1)[0])
    zeta = rod.damping * rod.length / (2 * w1 * float(rod.node_masses().sum()))
    assert zeta == pytest.approx(0.05, rel=0.05) and get_scene(name).chosen["damping"] == rod.damping


def test_scene_validation():
    rod = get_scene("pdms_inplane").rod
    with pytest.raises(ValueError, match="dt"):
        Scene(name="x", description="d", rod=rod, bc="clamped-free", dt=-1.0, duration=1.0)
    with pytest.raises(ValueError, match="nodes_of_interest"):
        Scene(name="x", description="d", rod=rod, bc="clamped-free", dt=1e-4, duration=1.0, nodes_of_interest=(99,))
    with pytest.raises(ValueError):
        Scene(name="x", description="d", rod=rod, bc="nonsense", dt=1e-4, duration=1.0)
    with pytest.raises(ValueError, match="gravity"):
        Scene(name="x", description="d", rod=rod, bc="clamped-free", dt=1e-4, duration=1.0, gravity=(0, 0, 1),
              loads=Loads(gravity=(0, 0, 2)))
    sc = Scene(name="x", description="A test. More.", rod=rod, bc="clamped-free", dt=1e-4, duration=1.0)
    assert sc.nodes_of_interest == (rod.n_nodes - 1,) and sc.summary == "A test."
    assert sc.initial_configuration()["p"][-1, 2] == pytest.approx(rod.length)


def test_solver_error_is_reported_not_nan():
    sc = get_scene("pdms_inplane")
    integ = sc.make_integrator(dt=6e-4, stability="off")  # ~2.6x the stability limit
    with pytest.raises(SolverError):
        integ.simulate(sc.initial_state(integ), n_steps=3000)


def test_paper2_scenes_on_another_mesh():
    """The Paper II builders' ``n_elements`` (mesh studies): the same rod and loads, the headline node where the
    printed mesh has it, the loop closed and free of axial strain, the semicircle still an equilibrium at rest."""
    from physics.scenes_paper2 import ellipse, ellipse_horizontal, semicircle, semicircle_heldout, square_tracking
    assert ellipse(58).chosen == ellipse().chosen and "n_elements" not in ellipse().chosen
    for build, height in ((ellipse, 0.6), (ellipse_horizontal, 0.2)):
        sc = build(30)
        assert sc.rod.N == 30 and sc.rod.length == pytest.approx(ellipse().rod.length, rel=1e-12)
        assert sc.chosen["n_elements"] == 30 and sc.nodes_of_interest[0] == 15
        cfg = sc.initial_configuration()
        p, F = cfg["p"], cfg["R"]
        assert float(p[-1].abs().max()) == 0 and torch.allclose(F[0], F[-1])
        d = p[1:] - p[:-1]
        ax = 0.5 * ((F[:-1, :, 2] * d).sum(-1) + (F[1:, :, 2] * d).sum(-1))
        assert torch.allclose(ax, torch.full_like(ax, sc.rod.lengths[0]), rtol=1e-10, atol=0)
        # the same rod on longer chords closes a slightly larger ellipse
        assert -float(p[15, 1]) == pytest.approx(height * sc.chosen["ellipse_scale"], rel=1e-6)
        assert 1.0 < sc.chosen["ellipse_scale"] < 1.05
    for n in (20, 24):
        with pytest.raises(ValueError, match=f"n_elements={n} is too coarse for the 0.2 m x 0.6 m ellipse "
                                             f"\\(ellipse_loop: n_elements={n} equal elements cannot close"):
            ellipse(n)  # no l closes the loop (at 24 the march's jump once passed for a lopsided closure)
    sc = semicircle_heldout(50)
    assert sc.nodes_of_interest == (25, 7) and sc.loads.force.node == 25 and sc.loads.force.n_nodes == 51
    integ = sc.make_integrator(stability="off")
    s0 = sc.initial_state(integ)
    s, _ = integ.simulate(s0, n_steps=100, record_every=100)
    assert float((s.p - s0.p).abs().max()) < 1e-12
    tip = square_tracking(4)
    assert tip.nodes_of_interest == (4, 3) and tip.loads.force(1.0).shape == (5, 3)
    for bad in (7, 0, 2.0):
        with pytest.raises(ValueError, match="n_elements must be an even integer >= 2"):
            semicircle(bad)


def test_ellipse_loop_coarse_meshes_close_or_raise():
    from physics.shapes import ellipse_loop
    for n in (5, 6):  # a regular pentagon / hexagon: projected chords r sin(2 pi / n)
        p, R, l = ellipse_loop(n, 0.1, 0.1)
        assert l == pytest.approx(0.05 * math.sin(2 * math.pi / n), rel=1e-12)
        assert (p[1:] - p[:-1]).norm(dim=-1).tolist() == pytest.approx([0.1 * math.sin(math.pi / n)] * n, rel=1e-12)
        assert float(p[-1].norm()) == 0.0 and torch.allclose(R[-1], R[0], atol=1e-15)
    for bad in ((3, 0.1, 0.1), (8, 0.2, 0.05), (24, 0.2, 0.6)):  # the last once "closed" with a 4.5 % longer chord
        with pytest.raises(ValueError, match="n_elements"):
            ellipse_loop(*bad)
    with pytest.raises(ValueError, match="width and height"):
        ellipse_loop(20, 0.0, 0.1)
    with pytest.raises(ValueError, match="element_length"):
        ellipse_loop(20, 0.1, 0.1, element_length=-0.01)
    for bad in (0, 2.5, True):  # a ZeroDivisionError, a TypeError from range(), one element
        with pytest.raises(ValueError, match="n_elements must be an integer >= 3"):
            ellipse_loop(bad, 0.1, 0.1)


def test_shape_builders_refuse_what_gave_nan_or_singular_frames():
    """A NaN tip rotation or arclengths that do not increase from 0 gave NaN or folded rods; a tangent
    along the plane normal gave a frame of determinant 0."""
    from physics.shapes import bent_cantilever, cantilever_rotation_for_offset, circular_arc, planar_frames
    s = np.linspace(0.0, 0.1, 5)
    p, R = bent_cantilever(s, (0.1, 0.0, 0.0))
    assert torch.allclose(torch.linalg.det(R), torch.ones(5, dtype=torch.float64), atol=1e-12)
    with pytest.raises(ValueError, match=r"tip_rotation must be a finite rotation vector \(3,\)"):
        bent_cantilever(s, (float("nan"), 0.0, 0.0))
    for bad in (s[::-1], [0.0, 0.05, 0.05, 0.1], [0.0, float("nan"), 0.1], [0.0], [0.01, 0.05, 0.1]):
        for build in (lambda x: bent_cantilever(x, (0.1, 0.0, 0.0)), lambda x: circular_arc(x, 1.0),
                      lambda x: cantilever_rotation_for_offset(x, (0.01, 0.0))):
            with pytest.raises(ValueError, match="node_s must be finite node arclengths"):
                build(bad)
    with pytest.raises(ValueError, match="offset must be finite"):
        cantilever_rotation_for_offset(s, (float("nan"), 0.0))
    with pytest.raises(ValueError, match=r"tangents must lie in the plane .* reaches 1"):
        planar_frames(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="normal must be a finite non-zero"):
        planar_frames(np.array([[1.0, 0.0, 0.0]]), normal=(0.0, 0.0, 0.0))
    F = planar_frames(np.array([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0]]), normal=(0.0, 0.0, 5.0))  # normalised
    assert torch.allclose(torch.linalg.det(F), torch.ones(2, dtype=torch.float64), atol=1e-15)


def test_min_jerk_durations_must_be_sequences():
    from physics.coil_currents import MinJerkCurrents
    with pytest.raises(TypeError, match="moves"):
        MinJerkCurrents(torch.zeros(2, 3), 0.5, (0.1, 0.1))
    with pytest.raises(TypeError, match="holds"):
        MinJerkCurrents(torch.zeros(2, 3), (0.5,), 0.1)
