"""Bad input to the rod, its equilibrium and modes, the scenes' load classes and the quasi-static/baseline surrogates:
each is refused with an error that names the parameter, where it used to give a silent wrong result, NaN or an
error from deep inside torch/scipy."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from physics.rod import CircularSection, Magnet, Material, Rod

MAT = Material(E=75e9, density=2690.0, nu=0.33)
SEC = CircularSection(2e-3)


def small_rod(n: int = 4, **kw) -> Rod:
    return Rod(0.2, SEC, MAT, n_elements=n, **kw)


def straight(rod: Rod):
    p0 = torch.zeros(rod.n_nodes, 3, dtype=torch.float64)
    p0[:, 2] = rod.arclength
    return p0, torch.eye(3, dtype=torch.float64).expand(rod.n_nodes, 3, 3).clone()


# ---------------------------------------------------------------------------------------------- physics.rod
def test_rod_numbers_given_as_strings_are_refused_naming_the_parameter():
    """YAML reads ``1e6`` as a string: it passed the checks (float("1e6")) and failed later in C1 ("can't multiply
    sequence by non-int of type 'float'")."""
    with pytest.raises(TypeError, match=r"Material.E \(Young's modulus, Pa\) must be a real number, got str"):
        Material(E="1e6", density=1000.0, nu=0.3)
    with pytest.raises(TypeError, match=r"Material.nu \(Poisson ratio\) must be a real number"):
        Material(E=1e6, density=1000.0, nu="0.3")
    with pytest.raises(TypeError, match=r"CircularSection.diameter \(m\) must be a real number"):
        CircularSection("0.01")
    with pytest.raises(TypeError, match=r"Rod.length \(m\) must be a real number"):
        Rod("0.2", SEC, MAT, n_elements=4)
    with pytest.raises(TypeError, match=r"Magnet.s \(arclength, m\) must be a real number"):
        Magnet(s=None, mass=0.01)
    assert small_rod().C1 == Rod(0.2, CircularSection(2e-3), Material(E=75e9, density=2690, nu=0.33),
                                 n_elements=4).C1  # numbers as before


def test_magnet_vectors_given_as_lists_or_tensors_are_kept_as_float_tuples():
    """A list moment left the rod unhashable (stable_time_step: "unhashable type: 'list'"); a tensor one failed in
    Rod.params ("only one element tensors can be converted")."""
    for moment in ([0.0, 0.0, 0.01], torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64), np.array([0.0, 0.0, 0.01])):
        rod = small_rod(magnets=(Magnet(0.2, 1e-4, moment=moment, inertia=[1e-9, 1e-9, 1e-9]),))
        assert rod.magnets[0].moment == (0.0, 0.0, 0.01) and rod.magnets[0].inertia == (1e-9,) * 3
        assert rod.params().magnet_moment.tolist() == [[0.0, 0.0, 0.01]]
        assert rod.stable_time_step().dt_max > 0
    with pytest.raises(ValueError, match="Magnet.moment must be 3 finite numbers, got 0.01"):
        Magnet(0.2, 1e-4, moment=0.01)
    with pytest.raises(ValueError, match=r"Rod.intrinsic_curvature \(1/m\) must be 3 finite numbers, got 2.0"):
        small_rod(intrinsic_curvature=2.0)  # was "'float' object is not iterable"


def test_frequencies_take_a_numpy_integer_mode_count():
    rod = small_rod()
    assert torch.equal(rod.natural_frequencies(n_modes=np.int64(2)), rod.natural_frequencies(n_modes=2))


# ---------------------------------------------------------------------------------------------- physics.relax
def test_static_equilibrium_fixed_nodes_must_be_integers_and_leave_a_free_node():
    from physics.relax import static_equilibrium
    rod = small_rod()
    p0, R0 = straight(rod)
    g = (9.81, 0.0, 0.0)
    for bad in ((0, 1.7), (0.5,), (True,)):  # 1.7 fixed node 1 and 0.5 node 0, silently; True node 1
        with pytest.raises(ValueError, match="static_equilibrium: fixed must hold integer node indices"):
            static_equilibrium(rod, p0, R0, fixed=bad, gravity=g)
    with pytest.raises(ValueError, match="fixed holds every node of this 5-node rod"):  # IndexError in torch
        static_equilibrium(rod, p0, R0, fixed=range(5), gravity=g)
    with pytest.raises(ValueError, match="no fixed node under gravity has no equilibrium"):  # 30 s, then failed
        static_equilibrium(rod, p0, R0, fixed=(), gravity=g)
    p, _ = static_equilibrium(rod, p0, R0, fixed=(np.int64(0), torch.tensor(-1)), gravity=g)  # integer types
    assert torch.equal(p[[0, -1]], p0[[0, -1]]) and float(p[2, 0]) > 0


# ---------------------------------------------------------------------------------------------- scenes
def test_magnet_block_rod_elements_must_be_whole_and_are_kept_as_a_tuple():
    from physics.scenes_magnetic_rod import MagnetBlockRod, modal_damping, rod
    kw = dict(length=0.2, section=SEC, material=MAT, n_elements=4, rigid_factor=2.0)
    with pytest.raises(ValueError, match=r"MagnetBlockRod.rigid_elements\[i\] must be an integer >= 0, got 1.5"):
        MagnetBlockRod(**kw, rigid_elements=(1.5,))  # stiffened element 1, silently
    r = MagnetBlockRod(**kw, rigid_elements=[2])  # a list: "unhashable type: 'list'" in stable_time_step
    assert r.rigid_elements == (2,) and r.stable_time_step().dt_max > 0
    assert torch.equal(r.params().C2[2], 2 * small_rod().params().C2[2])
    coarse = rod(1)
    with pytest.raises(ValueError, match="modal_damping: n_modes=100 exceeds the 24 clamped-free modes"):
        modal_damping(coarse, n_modes=100)  # scipy's "Requested eigenvalue indices are not valid"
    with pytest.raises(ValueError, match="modal_damping: n_modes must be an integer >= 1, got 2.5"):
        modal_damping(coarse, n_modes=2.5)  # gave 2 modes
    with pytest.raises(ValueError, match="per_part must be an integer >= 1, got nan"):
        rod(math.nan)


def test_scene_field_and_force_classes_check_their_numbers_when_built():
    from physics.scenes import RotatingField, SweptField
    from physics.scenes_paper2 import NodePulse, SquareTipForce
    with pytest.raises(ValueError, match=r"RotatingField.static \(T\) must have 3 components, got shape \(2,\)"):
        RotatingField((0.0, 1e-3), 1e-3, 0.5, (0, 1, 0), (1, 0, 0))  # failed in torch at the first step
    with pytest.raises(ValueError, match=r"RotatingField.frequency \(Hz\) must be finite, got nan"):
        RotatingField((0.0, 1e-3, 0.0), 1e-3, math.nan, (0, 1, 0), (1, 0, 0))  # NaN field
    for period in (0.0, -1.0):  # ZeroDivisionError at the first step; a constant field along e_a
        with pytest.raises(ValueError, match=r"SweptField.period \(s\) must be finite and > 0"):
            SweptField(20e-3, 19e-3, period, 1.0, (0, 0, 1), (0, 1, 0))
    with pytest.raises(ValueError, match="SweptField.e_b must have 3 components"):
        SweptField(20e-3, 19e-3, 1.0, 1.0, (0, 0, 1), (0, 1))
    with pytest.raises(ValueError, match=r"NodePulse.node must lie in \[-11, 10\], got 20"):
        NodePulse(11, 20, (0, 1, 0), 1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="NodePulse.node must be an integer"):
        NodePulse(11, 5.5, (0, 1, 0), 1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"NodePulse.direction must have 3 components, got shape \(2,\)"):
        NodePulse(11, 5, (0, 1), 1.0, 0.0, 1.0)  # an (11, 2) force
    with pytest.raises(ValueError, match=r"NodePulse.amplitude \(N\) must be finite"):
        NodePulse(11, 5, (0, 1, 0), math.nan, 0.0, 1.0)
    with pytest.raises(ValueError, match=r"NodePulse.t1 \(s\) must be >= t0 = 1"):
        NodePulse(11, 5, (0, 1, 0), 1.0, 1.0, 0.5)  # no force at all
    assert float(NodePulse(11, -1, (0, 1, 0), 2.0, 0.0, math.inf)(3.0)[-1, 1]) == 2.0
    with pytest.raises(ValueError, match=r"SquareTipForce.half_side \(m\) must be finite"):
        SquareTipForce(small_rod(), math.nan, (1.0,) * 6)


# ---------------------------------------------------------------------------------------------- programs
def test_compile_program_refuses_inputs_that_are_not_a_sequence_of_tensors():
    from physics.programs import compile_program
    with pytest.raises(TypeError, match="compile_program: inputs must be a sequence of tensors.*got Tensor"):
        compile_program(lambda x: x + 1, torch.ones(3))  # traced as three rows
    with pytest.raises(TypeError, match=r"inputs must be a sequence of tensors.*\['float'\]"):
        compile_program(lambda x: x + 1, [1.0])


# ---------------------------------------------------------------------------------------------- surrogates
def test_linear_step_fit_names_bad_data():
    from cmlearn.models import NodeLSTMConfig
    from cmlearn.surrogate.baselines import LinearStep
    config = NodeLSTMConfig.chain((0, 1, 2, 3), (1, 2, 3), eta=2)
    g = torch.Generator().manual_seed(0)
    p = torch.randn(2, 30, 4, 3, generator=g, dtype=torch.float64)
    f = torch.randn(2, 29, 3, 3, generator=g, dtype=torch.float64)
    ranges = [(0, 0, 29), (1, 0, 29)]
    LinearStep(config).fit(p, f, ranges)
    bad = p.clone()
    bad[1, 10, 2, 0] = math.nan
    with pytest.raises(ValueError, match="positions and wrench must be finite on the steps of ranges"):
        LinearStep(config).fit(bad, f, ranges)  # an internal assert in torch.linalg.lstsq (MKL's DGELSD)
    with pytest.raises(ValueError, match=r"positions must be \(V, T, n_tracked=4, 3\), got shape \(2, 30, 3, 3\)"):
        LinearStep(config).fit(p[:, :, :3], f, ranges)
    with pytest.raises(ValueError, match=r"wrench must be \(V=2, T-1=29, K=3, 3\)"):
        LinearStep(config).fit(p, f[:, :, :2], ranges)
    with pytest.raises(ValueError, match=r"range \(0, 0, 30\) lies outside positions' 2 variants of frames 0..29"):
        LinearStep(config).fit(p, f, [(0, 0, 30)])


def test_deviation_windows_need_whole_positive_horizons():
    pytest.importorskip("lightning")
    from cmlearn.surrogate.quasistatic_training import DeviationWindows
    s, d = torch.zeros(2, 40, 13), torch.zeros(2, 40, 12)
    ranges = [(0, 0, 39)]
    base = dict(eta=2, increments=3, horizon=4)
    assert len(DeviationWindows(s, d, ranges, **base)) == 34
    for kw, msg in ((dict(horizon=0), "horizon must be an integer >= 1"),  # empty targets: a NaN loss
                    (dict(stride=0), "stride must be an integer >= 1"),  # range()'s error
                    (dict(eta=-1), "eta must be an integer >= 0"),  # an empty history
                    (dict(increments=0), "increments must be an integer >= 1")):
        with pytest.raises(ValueError, match=f"DeviationWindows: {msg}"):
            DeviationWindows(s, d, ranges, **{**base, **kw})


def test_quasistatic_stepper_checks_its_stages_when_built():
    from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate
    shipped = Path(__file__).resolve().parents[1] / "checkpoints" / "magnetic_rod_quasistatic.pt"
    engine = QuasiStaticSurrogate.load(shipped, task="magnetic_rod")
    scene = engine.task.scene_by_name("magnetic_rod_heldout")
    for bad in ((1, 10), ((1, 10), (12,)), ((0, 10),)):  # the first: "cannot unpack non-iterable int" at a step
        with pytest.raises(ValueError, match=r"stages must be \(load steps, iterations\) pairs of integers >= 1"):
            engine.stepper(scene, stages=bad)
