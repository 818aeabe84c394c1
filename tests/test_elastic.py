import torch

from physics.elastic import elastic_energy, internal_loads, relative_cayley
from physics.errors import SolverError
from physics.lie import rot_x, so3_exp
from problems import aluminium_rod

import pytest


def random_configuration(n, batch=(), seed=0, pos=0.01, rot=0.3):
    g = torch.Generator().manual_seed(seed)
    p = torch.zeros(*batch, n, 3, dtype=torch.float64)
    p[..., 2] = torch.linspace(0, 0.2, n, dtype=torch.float64)
    p = p + pos * torch.randn(*batch, n, 3, generator=g, dtype=torch.float64)
    R = so3_exp(rot * torch.randn(*batch, n, 3, generator=g, dtype=torch.float64))
    return p, R


def test_internal_loads_are_the_energy_gradient():
    rod = aluminium_rod(6, intrinsic_curvature=(3.0, -1.0, 0.5))
    prm = rod.params()
    p, R = random_configuration(rod.n_nodes, batch=(2,))
    force, torque = internal_loads(p, R, prm)
    pp = p.clone().requires_grad_(True)
    eta = torch.zeros_like(p, requires_grad=True)
    V = elastic_energy(pp, R @ so3_exp(eta), prm).sum()
    gp, geta = torch.autograd.grad(V, (pp, eta))
    assert torch.allclose(force, -gp, rtol=1e-10, atol=1e-10 * gp.abs().max())
    assert torch.allclose(torque, -geta, rtol=1e-10, atol=1e-10 * geta.abs().max())


def test_energy_is_frame_invariant_and_zero_when_straight():
    rod = aluminium_rod(5)
    prm = rod.params()
    p, R = random_configuration(rod.n_nodes)
    Q = so3_exp(torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64))
    V1 = elastic_energy(p, R, prm)
    V2 = elastic_energy(p @ Q.T + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), Q @ R, prm)
    assert torch.allclose(V1, V2, rtol=1e-12)
    p0, _ = random_configuration(rod.n_nodes, pos=0.0)
    R0 = Q.expand(rod.n_nodes, 3, 3)
    assert float(elastic_energy(p0 @ Q.T, R0, prm)) < 1e-20 * float(V1)
    # internal loads balance: total force and moment vanish
    f, tau = internal_loads(p, R, prm)
    assert f.sum(0).abs().max() < 1e-9 * f.abs().max()
    moment = torch.linalg.cross(p, f, dim=-1).sum(0) + (R @ tau[..., None])[..., 0].sum(0)
    assert moment.abs().max() < 1e-9 * (tau.abs().max() + (p.abs().max() * f.abs().max()))


def test_uniform_bending_energy():
    # a circular arc with node frames tangent: curvature k gives energy L/2 EI k^2 (the averaged
    # shear strain adds a spurious axial strain -(k l)^2/6, whose energy falls as l^4)
    rod = aluminium_rod(40)
    prm = rod.params()
    k = 2.0  # 1/m
    s = rod.arclength
    th = k * s
    p = torch.stack((torch.zeros_like(s), (1 - torch.cos(th)) / k, torch.sin(th) / k), -1)
    R = rot_x(-th, dtype=torch.float64)
    V = float(elastic_energy(p, R, prm))
    ref = 0.5 * rod.length * rod.C2[0] * k**2
    assert abs(V - ref) / ref < 1e-3


def test_half_turn_element_raises():
    R = torch.stack([torch.eye(3, dtype=torch.float64), rot_x(torch.pi, dtype=torch.float64),
                     torch.eye(3, dtype=torch.float64)])
    with pytest.raises(SolverError, match="half turn"):
        relative_cayley(R)


def test_static_equilibrium_fixed_counts_negative_indices_from_the_tip():
    from physics.relax import static_equilibrium
    from problems import steel_like_rod
    rod = steel_like_rod(6)
    n = rod.n_nodes
    p0 = torch.zeros(n, 3, dtype=torch.float64)
    p0[:, 2] = rod.arclength
    R0 = torch.eye(3, dtype=torch.float64).expand(n, 3, 3).clone()
    g = (0.0, -0.01, 0.0)
    p, _ = static_equilibrium(rod, p0, R0, gravity=g, fixed=(0, -1))
    assert torch.equal(p[-1], p0[-1])  # the tip stays clamped
    p_ref, _ = static_equilibrium(rod, p0, R0, gravity=g, fixed=(0, n - 1))
    assert torch.allclose(p, p_ref, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="fixed"):
        static_equilibrium(rod, p0, R0, gravity=g, fixed=(0, n))
    # each failed late or misleadingly: NaN gravity in scipy ("array must not contain infs or NaNs"), a (2,)
    # gravity or short p0 in torch broadcasting/indexing, R0 = 2 I and tol NaN as "did not converge" after seconds
    for kw, msg in (({"gravity": (float("nan"), 0.0, 0.0)}, r"gravity must be a finite 3-vector \(m/s\^2\)"),
                    ({"gravity": (0.0, -9.81)}, "gravity must be a finite 3-vector"),
                    ({"field": (0.0, float("inf"), 0.0)}, r"field must be a finite 3-vector \(T\)"),
                    ({"p0": p0[:3]}, rf"p0 must be finite node positions \({n}, 3\) for this rod, got \(3, 3\)"),
                    ({"R0": 2 * R0}, "R0 must be proper rotation matrices"), ({"tol": float("nan")}, "tol must be"),
                    ({"rounds": 0}, "rounds must be an integer >= 1, got 0")):
        args = {"p0": p0, "R0": R0, "gravity": g, **kw}
        with pytest.raises(ValueError, match="static_equilibrium: " + msg):
            static_equilibrium(rod, args.pop("p0"), args.pop("R0"), **args)


def test_sparse_free_free_frequencies_match_dense(monkeypatch):
    import physics.modal as modal
    rod = aluminium_rod(20)
    dense = modal.frequencies(rod, "free-free", 3)
    monkeypatch.setattr(modal, "_DENSE_MAX", 0)  # the path taken by fine meshes (> 1500 DOFs)
    sparse = modal.frequencies(rod, "free-free", 3)
    assert torch.allclose(sparse, dense, rtol=1e-6)
    assert torch.allclose(modal.frequencies(rod, "clamped-free", 3), rod.natural_frequencies(n_modes=3), rtol=1e-6)
    for bad in (0, 2.0, True):  # 0 failed in scipy's eigh, 2.0 in a slice
        with pytest.raises(ValueError, match=f"n_modes must be an integer >= 1, got {bad}"):
            modal.frequencies(rod, "clamped-free", bad)
    two = aluminium_rod(2)  # 12 non-rigid modes either way; 13 returned 12 frequencies, silently
    assert modal.frequencies(two, "free-free", 12).shape == (12,)
    for bc in ("clamped-free", "free-free"):
        with pytest.raises(ValueError, match=rf"n_modes=13 exceeds the 12 non-rigid modes of this 2-element rod \({bc}\)"):
            modal.frequencies(two, bc, 13)


def test_circular_arc_of_no_turn_is_straight_and_a_nan_turn_is_refused():
    """turning_angle 0 divided by zero (a RuntimeWarning, then the straight rod); NaN gave NaN positions."""
    import warnings

    import numpy as np

    from physics.shapes import circular_arc
    s = np.linspace(0.0, 0.5, 6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p, R = circular_arc(s, 0.0)
    assert torch.allclose(p[:, 1], torch.as_tensor(s, dtype=p.dtype)) and float(p[:, [0, 2]].abs().max()) == 0
    with pytest.raises(ValueError, match="turning_angle must be finite"):
        circular_arc(s, float("nan"))
