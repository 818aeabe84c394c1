import math

import pytest
import torch

from physics import CircularSection, Magnet, Material, Rod, SquareSection
from problems import aluminium_rod, pdms_rod


def test_material_validation():
    with pytest.raises(ValueError, match="Material.E"):
        Material(E=-1.0, density=1000, nu=0.3)
    with pytest.raises(ValueError, match="density"):
        Material(E=1e6, density=0.0, nu=0.3)
    with pytest.raises(ValueError, match="nu"):
        Material(E=1e6, density=1000, nu=0.6)
    with pytest.raises(ValueError, match="nu"):
        Material(E=1e6, density=1000, nu=-1.0)
    with pytest.raises(ValueError, match="nu or the shear modulus"):
        Material(E=1e6, density=1000)
    with pytest.raises(ValueError, match="inconsistent"):
        Material(E=1e6, density=1000, nu=0.3, G=1e6)
    assert Material(E=1e6, density=1000, G=4e5).shear_modulus == 4e5
    with pytest.raises(ValueError, match="E"):
        Material(E=float("nan"), density=1000, nu=0.3)


def test_rod_validation():
    mat = Material(E=1e6, density=1000, nu=0.3)
    with pytest.raises(ValueError, match="length"):
        Rod(length=0.0, section=CircularSection(1e-3), material=mat, n_elements=4)
    with pytest.raises(ValueError, match="diameter"):
        CircularSection(-1e-3)
    with pytest.raises(ValueError, match="edge"):
        SquareSection(0.0)
    for n in (0, 2.0, True):  # 2.0 failed later in the mesh, True made a one-element rod
        with pytest.raises(ValueError, match=f"Rod.n_elements must be an integer >= 1, got {n}"):
            Rod(length=1.0, section=CircularSection(1e-3), material=mat, n_elements=n)
    with pytest.raises(ValueError, match="sum to"):
        Rod(length=1.0, section=CircularSection(1e-3), material=mat, element_lengths=(0.5, 0.4))
    with pytest.raises(ValueError, match="outside the rod"):
        Rod(length=1.0, section=CircularSection(1e-3), material=mat, n_elements=4, magnets=(Magnet(s=1.5, mass=1e-3),))
    with pytest.raises(ValueError, match="Magnet.mass"):
        Magnet(s=0.1, mass=-1.0)
    with pytest.raises(ValueError, match="moment"):
        Magnet(s=0.1, mass=1.0, moment=(0.0, float("inf"), 0.0))
    with pytest.raises(TypeError, match="section"):
        Rod(length=1.0, section=1e-3, material=mat, n_elements=4)
    for bad in ((float("nan"), 0.0, 0.0), (1.0, 2.0)):  # was a NaN energy, or a shape error deep in params()
        with pytest.raises(ValueError, match="Rod.intrinsic_curvature"):
            Rod(length=1.0, section=CircularSection(1e-3), material=mat, n_elements=4, intrinsic_curvature=bad)
    with pytest.raises(TypeError, match="Rod.magnets must be Magnet"):
        Rod(length=1.0, section=CircularSection(1e-3), material=mat, n_elements=4, magnets=("tip",))


def test_derived_parameters_circular():
    rod = aluminium_rod(15)
    A, I = math.pi * 1e-6, math.pi * 2e-3**4 / 64
    G = 75e9 / (2 * 1.33)
    assert rod.line_mass == pytest.approx(2690 * A)
    assert rod.C1 == pytest.approx((G * A, G * A, 75e9 * A))
    assert rod.C2 == pytest.approx((75e9 * I, 75e9 * I, G * 2 * I))
    # J_d of Table I.3 is diag(0, 2.11, 2.11) g mm^2 with the axial entry 0: ours has the axis as E3
    assert rod.line_inertia_d == pytest.approx((2690 * I, 2690 * I, 0.0), abs=1e-30)
    # Table I.3: C1 = diag(2.35, 0.88, 0.88)e14 mg mm/s^2 = (2.35e5, 0.88e5) N; C2 = 5.89e13 mg mm^3/s^2
    assert rod.C1[2] == pytest.approx(2.35e5, rel=0.01)
    assert rod.C1[0] == pytest.approx(0.88e5, rel=0.01)
    assert rod.C2[0] == pytest.approx(5.89e-2, rel=0.01)


def test_derived_parameters_square_and_pdms_tables():
    rod = pdms_rod(10)
    # Table I.6: C1 = diag(4.58, 1.53, 1.53)e9 mg mm/s^2 (= 4.58 N), C2 = diag(3.06, 4.59, 4.59)e9 mg mm^3/s^2
    assert rod.C1[2] == pytest.approx(4.58, rel=0.01)
    assert rod.C1[0] == pytest.approx(1.53, rel=0.01)
    assert rod.C2[0] == pytest.approx(4.59e-6, rel=0.01)
    assert rod.C2[2] == pytest.approx(3.06e-6, rel=0.01)
    sq = Rod(length=0.0855, section=SquareSection(2e-3), material=Material(E=3.65e6, density=1100, nu=0.5), n_elements=10)
    assert sq.section.area == pytest.approx(4e-6)
    assert sq.C2[0] == pytest.approx(3.65e6 * 16e-12 / 12)
    assert sq.C2[0] == pytest.approx(4.87e-6, rel=0.01)  # Table I.7
    assert sq.C2[2] == pytest.approx(3.65e6 / 3 * 0.1406 * 16e-12)


def test_node_masses_and_magnet_lumping():
    rod = pdms_rod(10, magnets=(Magnet(s=0.06055, mass=9.6e-5), Magnet(s=0.06055 * 0.25, mass=1e-4)))
    m = rod.node_masses()
    total = rod.line_mass * rod.length + 9.6e-5 + 1e-4
    assert float(m.sum()) == pytest.approx(total)
    l = rod.length / 10
    assert float(m[-1]) == pytest.approx(rod.line_mass * l / 2 + 9.6e-5)  # tip magnet all on the tip node
    # s = 2.5 elements: half of the magnet to nodes 2 and 3 (Remark I.3.1)
    assert float(m[2]) == pytest.approx(rod.line_mass * l + 0.5e-4)
    assert float(m[3]) == pytest.approx(rod.line_mass * l + 0.5e-4)


def test_non_uniform_elements():
    mat = Material(E=1e6, density=1000, nu=0.3)
    rod = Rod(length=1.0, section=CircularSection(1e-2), material=mat, element_lengths=(0.1, 0.2, 0.3, 0.4))
    assert rod.N == 4 and rod.n_nodes == 5
    assert torch.allclose(rod.arclength, torch.tensor([0, 0.1, 0.3, 0.6, 1.0], dtype=torch.float64))
    w = rod.node_weights()
    assert torch.allclose(w, torch.tensor([0.05, 0.15, 0.25, 0.35, 0.2], dtype=torch.float64))
    prm = rod.params(torch.float32)
    assert prm.l.dtype == torch.float32 and prm.C1.shape == (4, 3) and prm.inertia.shape == (5, 3)


def test_stability_estimate_and_limits():
    al = aluminium_rod(10).stable_time_step()
    # the shear-rotation mode of a node limits thin rods: dt ~ r sqrt(rho/G)
    r, rho, G = 1e-3, 2690.0, 75e9 / 2.66
    assert al.dt_max == pytest.approx(r * math.sqrt(rho / G), rel=0.15)
    assert al.limiting == "shear_rotation"
    assert al.dt_max < al.dt_axial
    pd = pdms_rod(10).stable_time_step()
    assert 9e-5 < pd.dt_max < 1e-3  # the thesis's 9e-5 s is stable for the 4 mm PDMS rod
    scaled = aluminium_rod(10, rotational_inertia_scale=16.0).stable_time_step()
    assert scaled.dt_max == pytest.approx(4 * al.dt_max, rel=0.15)


def test_frequency_correction():
    # with the locking-free shear evaluation the discrete frequency converges fast: gamma ~ 1
    g10 = aluminium_rod(10).frequency_correction()
    g40 = aluminium_rod(40).frequency_correction()
    assert 1.0 < g10 < 1.01 and 1.0 < g40 < g10
    corrected = aluminium_rod(10).frequency_corrected()
    w = float(corrected.natural_frequencies(n_modes=1)[0])
    assert w == pytest.approx(corrected.euler_bernoulli_first_frequency(), rel=1e-6)
    with pytest.raises(ValueError, match="bc"):
        aluminium_rod(4).natural_frequencies(bc="hinged")
    # a mesh correction: a tip magnet's mass lowers the frequency physically and changes nothing of it
    bare = pdms_rod(10)
    tipped = pdms_rod(10, magnets=(Magnet(s=bare.length, mass=2e-3),))
    assert float(tipped.natural_frequencies(n_modes=1)[0]) < 0.8 * float(bare.natural_frequencies(n_modes=1)[0])
    assert tipped.frequency_correction() == bare.frequency_correction()
    # the modes are about the straight rod: one with intrinsic curvature is not at rest there
    with pytest.raises(ValueError, match="intrinsic_curvature"):
        aluminium_rod(4, intrinsic_curvature=(20.0, 0.0, 0.0)).natural_frequencies()
