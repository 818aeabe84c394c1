"""The static Cosserat rod (Paper II appendix) against analytic solutions, an independent solve_bvp
elastica, the LGVI at rest, finite differences; batching, warm starts, failures and bad input."""
import math

import numpy as np
import pytest
import scipy.integrate as si
import torch

from physics import CircularSection, Magnet, Material, Rod, SolverError, UniformField
from physics.cosserat import CosseratRod, MagnetDipole, Segment
from physics import cosserat_fast
from physics.cosserat_fast import fast_lm, flatten_field
from physics.cosserat_lanes import lane_step, lane_tables, shoot_lanes, step_table
from physics.cosserat_ode import shoot
from physics.cosserat_inverse import fit_uniform_field, tip_angle
from physics.cosserat_shooting import CHORD_MAX, CosseratSolver, solve_static
from physics.relax import static_equilibrium
from physics.scene import MU0
from physics.scenes_cosserat import NDFEB, PMC770, LinearField, paper2_magnetic_rod
from problems import EI, cantilever_tip_force, cantilever_tip_moment, cantilever_uniform_load_tip, steel_like_rod

D = torch.float64
G = (0.0, -9.81, 0.0)


def uniform(rod: Rod, n_nodes: int = 21, **kw) -> CosseratRod:
    return CosseratRod.uniform(rod.length, rod.section, rod.material, n_nodes=n_nodes, **kw)


def tip_magnet_rod(n_nodes=13, moment=(0.0, 0.0, 2e-3), mass=2e-4, E=2e6):
    return CosseratRod.uniform(0.06, CircularSection(3e-3), Material(E=E, density=1100.0, nu=0.5), n_nodes=n_nodes,
                               magnets=(MagnetDipole(0.06, moment, mass=mass),))


# ------------------------------------------------------------------------------------ small deflection
def test_small_deflection_tip_force_and_moment():
    base = steel_like_rod()
    rod, L = uniform(base, 13), base.length
    P, M = 1e-3 * EI(base) / L**2, 1e-3 * EI(base) / L
    sol = solve_static(rod, tip_force=torch.tensor([[P, 0, 0], [0, 0, 0]], dtype=D),
                       tip_moment=torch.tensor([[0, 0, 0], [0, M, 0]], dtype=D))
    assert bool(sol.converged.all()) and sol.p.shape == (2, 13, 3)
    assert abs(float(sol.tip_position[0, 0]) / cantilever_tip_force(base, P) - 1) < 5e-3
    assert abs(float(sol.tip_position[1, 0]) / cantilever_tip_moment(base, M) - 1) < 5e-3
    # the base reaction balances the tip load
    assert torch.allclose(sol.base_wrench[0, :3], torch.tensor([P, 0, 0], dtype=D), rtol=1e-9, atol=1e-15)


def test_self_weight_and_piecewise_stiffness():
    base = steel_like_rod()
    q = base.line_mass * 9.81 * 1e-3
    sol = solve_static(uniform(base, 13), gravity=(0.0, -9.81e-3, 0.0))
    assert abs(-float(sol.tip_position[1]) / cantilever_uniform_load_tip(base, q) - 1) < 5e-3
    # two segments of bending stiffness EI and 4 EI under a tip force: delta = P int (L - s)^2 / EI(s) ds
    L, a = base.length, 0.3 * base.length
    soft, stiff = base.material, Material(E=4 * base.material.E, density=1000.0, nu=0.3)
    rod = CosseratRod((Segment(a, base.section, stiff), Segment(L - a, base.section, soft)), n_nodes=13)
    P = 1e-3 * EI(base) / L**2
    ref = P / EI(base) * ((L - a) ** 3 / 3 + (L**3 - (L - a) ** 3) / 3 / 4)
    sol = solve_static(rod, tip_force=(P, 0.0, 0.0))
    assert abs(float(sol.tip_position[0]) / ref - 1) < 5e-3
    assert rod.grid.s[4] == pytest.approx(a) and set(rod.grid.step_segment) == {0, 1}


# ------------------------------------------------------------------------------------ large deflection
def elastica_tip(rod: Rod, P: float, tol: float, nodes: int) -> np.ndarray:
    """Planar Reissner rod (shear and extension included) under a dead tip force P along +x, clamped
    along +z: x' = cos(th) v1 + sin(th) v3, z' = -sin(th) v1 + cos(th) v3, th' = M/EI, M' = -P z',
    v1 = P cos(th)/GA, v3 = 1 + P sin(th)/EA; x = z = th = 0 at s = 0, M(L) = 0."""
    E, A = rod.material.E, rod.section.area
    GA, ei, L = rod.material.shear_modulus * A, EI(rod), rod.length

    def f(s, y):
        x, z, th, M = y
        v1, v3 = P * np.cos(th) / GA, 1 + P * np.sin(th) / (E * A)
        dz = -np.sin(th) * v1 + np.cos(th) * v3
        return np.vstack((np.cos(th) * v1 + np.sin(th) * v3, dz, M / ei, -P * dz))

    s = np.linspace(0, L, nodes)
    guess = np.vstack((0 * s, s, 0 * s, P * (L - s)))
    sol = si.solve_bvp(f, lambda a, b: np.array([a[0], a[1], a[2], b[3]]), s, guess, tol=tol, max_nodes=200000)
    assert sol.success, sol.message
    return sol.sol(L)[:2]


def test_large_deflection_elastica_matches_solve_bvp():
    base = steel_like_rod()
    L, ei = base.length, EI(base)
    loads = (1.0, 3.0, 10.0)  # P L^2 / (E I)
    refs = []
    for a in loads:
        r1, r2 = elastica_tip(base, a * ei / L**2, 1e-8, 101), elastica_tip(base, a * ei / L**2, 1e-11, 401)
        assert np.abs(r1 - r2).max() < 1e-7 * L  # the reference itself is converged
        refs.append(r2)
    P = torch.tensor([[a * ei / L**2, 0.0, 0.0] for a in loads], dtype=D)
    sol = solve_static(uniform(base, 81), tip_force=P, load_steps=4)  # batched, with continuation
    tips = sol.tip_position[:, [0, 2]].numpy()
    assert refs[-1][0] > 0.8 * L  # large: the tip swings past 80 % of L sideways
    assert np.abs(tips - np.array(refs)).max() < 1e-4 * L


# ------------------------------------------------------------------------------------ against the LGVI
def test_static_shape_matches_lgvi_at_rest():
    mom, B = (0.0, 0.0, 2e-3), (0.0, 0.01, 0.004)
    mat, sec = Material(E=4e5, density=1100.0, nu=0.5), CircularSection(3e-3)
    lg = Rod(length=0.06, section=sec, material=mat, n_elements=20, magnets=(Magnet(s=0.06, mass=2e-4, moment=mom),))
    p0 = torch.zeros(lg.n_nodes, 3, dtype=D)
    p0[:, 2] = lg.arclength
    p, _ = static_equilibrium(lg, p0, torch.eye(3, dtype=D).expand(lg.n_nodes, 3, 3).clone(), gravity=G, field=B)
    sol = solve_static(tip_magnet_rod(41, mom, E=4e5), gravity=G, field=UniformField(torch.tensor(B, dtype=D)),
                       load_steps=3)
    assert float(p[-1, 1]) < -0.5 * 0.06  # large deflection
    s = lg.arclength.numpy()
    pc = np.stack([np.interp(s, sol.s.numpy(), sol.p[:, i].numpy()) for i in range(3)], -1)
    assert np.abs(pc - p.numpy()).max() < 5e-3 * 0.06


# ------------------------------------------------------------------------------------ batching, Jacobians
def test_batched_equals_one_by_one_and_jacobian_modes_agree():
    rod = tip_magnet_rod()
    Bs = torch.tensor([[0.0, 0.004, 0.001], [0.003, -0.002, 0.0], [0.0, 0.0, -0.005]], dtype=D)
    F = torch.tensor([[1e-4, 0, 0], [0, 0, 0], [0, -2e-4, 1e-4]], dtype=D)
    solver = CosseratSolver(rod)
    batch = solver.solve(field=UniformField(Bs[:, None, :]), tip_force=F, gravity=G)
    for i in range(3):
        one = solver.solve(field=UniformField(Bs[i]), tip_force=F[i], gravity=G)
        assert torch.allclose(batch.y[i], one.y, atol=1e-12, rtol=0)
        assert int(batch.iterations[i]) == int(one.iterations)
    jf = CosseratSolver(rod, jacobian="jacfwd").solve(field=UniformField(Bs[:, None, :]), tip_force=F, gravity=G)
    assert torch.allclose(jf.jacobian, batch.jacobian, atol=1e-10) and torch.allclose(jf.y, batch.y, atol=1e-12)


def test_forward_jacobian_matches_finite_differences_with_field_gradient():
    rod = CosseratRod.uniform(0.05, CircularSection(2e-3), Material(E=2e6, density=1000.0, nu=0.3), n_nodes=13,
                              magnets=(MagnetDipole(0.03, (0, 0, 0.01), mass=1e-4), MagnetDipole(0.05, (0, 3e-3, 0.01))),
                              load_points=(0.0, 0.02))
    Gm = torch.tensor([[0.02, 0.01, 0.0], [0.01, -0.01, 0.0], [0.0, 0.0, -0.01]], dtype=D)
    fld = LinearField(torch.tensor([0.01, 0.005, -0.003], dtype=D), Gm)
    s = CosseratSolver(rod)
    L = s.make_loads(gravity=G, tip_force=(1e-3, 2e-4, 0), point_forces=[[1e-4, 0, 0], [0, 2e-4, 1e-4]],
                     point_torques=[[0, 0, 1e-5], [1e-5, 0, 0]])
    x = torch.tensor([0.3, -0.2, 0.1, 0.2, 0.5, -0.1], dtype=D)
    res = shoot(x, s.params, rod.grid, L, s.scales, fld, tangent=True, fd_step=s.fd_step)
    e, Jfd = 1e-6, torch.zeros(6, 6, dtype=D)
    for j in range(6):
        dx = torch.zeros(6, dtype=D)
        dx[j] = e
        Jfd[:, j] = (shoot(x + dx, s.params, rod.grid, L, s.scales, fld).r
                     - shoot(x - dx, s.params, rod.grid, L, s.scales, fld).r) / (2 * e)
    assert (res.J - Jfd).abs().max() < 1e-7 * res.J.abs().max()
    # the compiled path's lane formulation (run eagerly here) gives the same shot
    tabs = lane_tables(s.params, rod.grid, L)
    r2, J2, Y2 = shoot_lanes(lane_step, x, s.params, tabs, L, s.scales, fld, 0.0, s.fd_step)
    assert (res.r - r2).abs().max() < 1e-13 and (res.J - J2).abs().max() < 1e-12 and (res.Y - Y2).abs().max() < 1e-14


def test_fast_path_programs_match_the_reference_shooting(monkeypatch):
    """The compiled path's programs (run eagerly here: component layout for batches, lanes for single
    problems) give the reference solver's iterates, shape and Jacobian to round-off."""
    sc = paper2_magnetic_rod()
    Gm = torch.diag(torch.tensor([0.02, -0.01, -0.01], dtype=D))
    B = torch.tensor([[0.004, 0.0015, 0.0], [0.003, -0.002, 0.001]], dtype=D)
    solver = CosseratSolver(sc.rod)
    near = sc.solve(solver, field=LinearField(B * 0.99, Gm))
    ref = sc.solve(solver, field=LinearField(B, Gm), init=near)

    def fast(self, x, prm, loads, field, t, its, lam0, live, flat=None, max_iter=None):
        return fast_lm(self, x, prm, loads, field, t, its, lam0, live, step_table(prm, self.rod.grid), compiled=False,
                       flat=flat, max_iter=max_iter)

    monkeypatch.setattr(CosseratSolver, "_lm", fast)
    for lanes_below, max_rows in ((1, 16), (8, 16), (8, 5)):  # component layout, lanes, the shot in 3 programs
        monkeypatch.setattr(cosserat_fast, "LANES_BELOW", lanes_below)
        monkeypatch.setattr(cosserat_fast, "MAX_ROWS", max_rows)
        out = sc.solve(solver, field=LinearField(B, Gm), init=near)
        assert out.iterations.tolist() == ref.iterations.tolist() and bool(out.converged.all())
        assert (out.y - ref.y).abs().max() < 1e-14 and (out.jacobian - ref.jacobian).abs().max() < 1e-12
    capped = sc.solve(solver, field=LinearField(B, Gm), init=near, max_iter=2, max_load_steps=1,
                      raise_on_failure=False)  # a per-call cap on the iterations binds the programs too (ref: 3)
    assert capped.iterations.tolist() == [2, 2] and not bool(capped.converged.any())
    assert flatten_field(lambda t, x: x) is None  # a plain function: the torch.compile path instead


def test_chord_iterations_from_a_neighbouring_jacobian_reach_the_lm_solution_with_one_shot_of_tangents(monkeypatch):
    """``solve(chord=J)``: Newton steps with a nearby solution's Jacobian frozen (Broyden-updated), each a shot
    without tangents, reach the equilibrium LM reaches; LM then evaluates once (the tangents, the check). The
    compiled path's chord program (run eagerly here) takes the same steps; a useless Jacobian hands over to LM."""
    sc = paper2_magnetic_rod()
    Gm = torch.diag(torch.tensor([0.02, -0.01, -0.01], dtype=D))
    B = torch.tensor([[0.004, 0.0015, 0.0], [0.003, -0.002, 0.001]], dtype=D)
    solver = CosseratSolver(sc.rod)
    near = sc.solve(solver, field=LinearField(B * 0.99, Gm))
    evaluate, shots = CosseratSolver._evaluate, []

    def counted(self, *a, **k):
        shots.append(1)
        return evaluate(self, *a, **k)
    monkeypatch.setattr(CosseratSolver, "_evaluate", counted)
    ref = sc.solve(solver, field=LinearField(B, Gm), init=near)
    lm_shots, shots[:] = len(shots), []
    out = sc.solve(solver, field=LinearField(B, Gm), init=near, chord=near.jacobian)
    assert len(shots) == 1 < lm_shots and bool(out.converged.all()) and bool((out.iterations >= 2).all())
    assert (out.y - ref.y).abs().max() < 1e-9 and (out.jacobian - ref.jacobian).abs().max() < 1e-8
    shots[:] = []
    bad = sc.solve(solver, field=LinearField(B, Gm), init=near, chord=50 * torch.eye(6, dtype=D))
    assert len(shots) > 1 and bool(bad.converged.all()) and (bad.y - ref.y).abs().max() < 1e-9
    # the chord program (compiled path, eagerly) takes the eager chord's steps
    loads = solver._loads(dict(gravity=sc.gravity, base_quaternion=sc.base_quaternion))
    x0 = (near.base_wrench / solver._sc).contiguous()
    live, its = torch.ones(2, dtype=torch.bool), torch.zeros(2, dtype=torch.long)
    start, it1 = cosserat_fast.fast_chord(solver, x0, torch.linalg.inv(near.jacobian), solver.params, loads,
                                          LinearField(B, Gm), 0.0, its, its + CHORD_MAX, live,
                                          step_table(solver.params, sc.rod.grid), CHORD_MAX, solver.chord_block,
                                          compiled=False)
    start2, it2 = solver._chord(x0, near.jacobian, solver.params, loads, LinearField(B, Gm), 0.0, its, live)
    assert it1.tolist() == it2.tolist() and (start - start2).abs().max() < 1e-13
    with pytest.raises(ValueError, match="chord iterations need load_steps=1"):
        sc.solve(solver, field=LinearField(B, Gm), init=near, chord=near.jacobian, load_steps=2)
    with pytest.raises(ValueError, match=r"chord must be a finite scaled Jacobian \(\.\.\., 6, 6\)"):
        sc.solve(solver, field=LinearField(B, Gm), init=near, chord=torch.eye(3, dtype=D))
    with pytest.raises(ValueError, match=r"chord: its batch shape \(3,\) does not broadcast to the problems' \(2,\)"):
        sc.solve(solver, field=LinearField(B, Gm), init=near, chord=torch.eye(6, dtype=D).expand(3, 6, 6))
    shots[:] = []
    singular = sc.solve(solver, field=LinearField(B, Gm), init=near, chord=torch.zeros(6, 6, dtype=D))
    assert len(shots) == lm_shots and (singular.y - ref.y).abs().max() < 1e-12  # no chord steps: LM from the start


def test_a_frame_solve_keeps_its_programs_and_solves_what_the_solver_call_solves(monkeypatch):
    """``FrameSolve`` (a real-time loop's repeated solve; its programs run eagerly here) equals
    ``solve(load_steps=1, max_load_steps=1, raise_on_failure=False, ...)`` frame after frame, looks its programs up
    only when the field's structure or the start's shape changes, and hands what its fast path does not take to
    that call."""
    from physics.cosserat_frames import FrameSolve
    sc = paper2_magnetic_rod()
    Gm = torch.diag(torch.tensor([0.02, -0.01, -0.01], dtype=D))
    B = torch.tensor([[0.004, 0.0015, 0.0], [0.003, -0.002, 0.001]], dtype=D)
    eager, fast = CosseratSolver(sc.rod), CosseratSolver(sc.rod, compile=True)
    frame = sc.frame_solve(fast, max_iter=10, compiled=False)
    setups, setup = [], FrameSolve._setup
    monkeypatch.setattr(FrameSolve, "_setup", lambda self, *a: setups.append(1) or setup(self, *a))
    prev = sol = sc.solve(eager, field=LinearField(B * 0.98, Gm))
    for k, scale in enumerate((0.99, 1.0, 1.01)):
        chord = None if k == 0 else 2 * sol.jacobian - prev.jacobian
        field = LinearField(B * scale, Gm)
        got = frame(field, sol, chord)
        ref = sc.solve(eager, field=field, init=sol, chord=chord, load_steps=1, max_load_steps=1, max_iter=10,
                       raise_on_failure=False)
        assert bool(got.converged.all()) and got.iterations.tolist() == ref.iterations.tolist()
        assert (got.y - ref.y).abs().max() < 1e-12 and (got.jacobian - ref.jacobian).abs().max() < 1e-9
        assert (got.base_wrench - ref.base_wrench).abs().max() < 1e-12 * ref.base_wrench.abs().max()
        prev, sol = sol, got
    assert len(setups) == 2  # the first frame without a chord Jacobian, then with one
    capped = sc.frame_solve(fast, max_iter=2, compiled=False)(LinearField(B * 1.1, Gm), sol)
    ref = sc.solve(eager, field=LinearField(B * 1.1, Gm), init=sol, max_iter=2, max_load_steps=1,
                   raise_on_failure=False)
    assert not bool(capped.converged.any()) and capped.iterations.tolist() == ref.iterations.tolist() == [2, 2]
    # what the fast path does not take (here: an eager solver) goes to the solver's call
    calls, solve = [], CosseratSolver.solve
    monkeypatch.setattr(CosseratSolver, "solve", lambda self, **k: calls.append(1) or solve(self, **k))
    out = sc.frame_solve(eager, max_iter=10)(LinearField(B, Gm), prev)
    assert calls and (out.y - prev.y).abs().max() < 1e-9  # (prev: the frame at B)
    with pytest.raises(ValueError, match="init must have shape"):
        frame(LinearField(B, Gm), torch.zeros(5, dtype=D))
    with pytest.raises(ValueError, match="max_iter must be an integer >= 1"):
        sc.frame_solve(fast, max_iter=0)
    with pytest.raises(ValueError, match="chord_block must be an integer >= 1"):
        CosseratSolver(sc.rod, chord_block=0)
    # a load that requires grad: the solver's call, with its implicit gradients (run here by the eager solver)
    calls[:] = []
    monkeypatch.setattr(CosseratSolver, "solve", lambda self, **k: calls.append(1) or solve(eager, **k))
    g = torch.tensor(sc.gravity, dtype=D, requires_grad=True)
    out = sc.frame_solve(fast, max_iter=10, compiled=False, gravity=g)(LinearField(B, Gm), prev)
    assert calls and out.y.requires_grad
    # the solver's parameters changed in place (a stiffer rod) or replaced: the next frame solves the new rod
    monkeypatch.setattr(CosseratSolver, "solve", solve)
    own = CosseratSolver(sc.rod, compile=True)
    frame = sc.frame_solve(own, max_iter=20, compiled=False)
    first = frame(LinearField(B, Gm), prev)
    with torch.no_grad():
        own.params.kb_inv.mul_(0.5)
    stiffer = frame(LinearField(B, Gm), first)
    ref = sc.solve(eager, field=LinearField(B, Gm), params=own.params, init=first)
    assert (stiffer.y - ref.y).abs().max() < 1e-9 and (stiffer.y - first.y).abs().max() > 1e-4
    own.params = sc.rod.params(D)
    again = frame(LinearField(B, Gm), stiffer)
    assert (again.y - first.y).abs().max() < 1e-9


# ------------------------------------------------------------------------------------ gradients
def test_implicit_gradients_match_finite_differences():
    mat = Material(E=2e6, density=1100.0, nu=0.5)
    sec = CircularSection(3e-3)
    rod = CosseratRod((Segment(0.03, sec, mat), Segment(0.03, sec, mat)), n_nodes=13,
                      magnets=(MagnetDipole(0.06, (0.0, 0.0, 2e-3), mass=2e-4),))
    solver = CosseratSolver(rod, tol=1e-13)
    w = torch.tensor([0.3, -1.0, 0.7], dtype=D)

    def objective(B, F, E, grad=True, init=None):
        prm = rod.params(D, youngs_modulus=E)
        sol = solver.solve(field=UniformField(B), tip_force=F, gravity=G, params=prm, differentiable=grad, init=init)
        return (sol.tip_position * w).sum() + 0.01 * tip_angle(sol, (1, 2)), sol

    B0 = torch.tensor([0.0, 0.03, 0.01], dtype=D, requires_grad=True)
    F0 = torch.tensor([1e-3, 0.0, -5e-4], dtype=D, requires_grad=True)
    E0 = torch.tensor([2e6, 3e6], dtype=D, requires_grad=True)
    val, base = objective(B0, F0, E0)
    assert float(tip_angle(base, (1, 2)).detach().abs()) > 0.3  # a large deflection
    gB, gF, gE = torch.autograd.grad(val, (B0, F0, E0))
    for x, g, h in ((B0, gB, 1e-6), (F0, gF, 1e-7), (E0, gE, 10.0)):
        for i in range(x.numel()):
            d = torch.zeros_like(x)
            d.view(-1)[i] = h
            args = [B0.detach(), F0.detach(), E0.detach()]
            k = [id(B0), id(F0), id(E0)].index(id(x))
            ap, am = list(args), list(args)
            ap[k], am[k] = args[k] + d, args[k] - d
            with torch.no_grad():
                fd = (objective(*ap, grad=False, init=base)[0] - objective(*am, grad=False, init=base)[0]) / (2 * h)
            assert abs(float(g.view(-1)[i]) - float(fd)) <= 1e-5 * abs(float(fd)) + 1e-9 * float(g.abs().max())


def test_gradients_reach_a_field_model_inside_a_sum():
    """A field whose tensors sit a level down (a ``Superposition``'s list of models) still gets the implicit gradient
    (it was solved without autograd, and a loss with another term in the field got that term's gradient alone)."""
    from physics.magnetics.base import Superposition
    sc = paper2_magnetic_rod()
    solver = CosseratSolver(sc.rod)
    B0 = torch.tensor([0.015, 0.0, 0.005], dtype=D, requires_grad=True)
    grads = []
    for field in (UniformField(B0), Superposition([UniformField(B0)])):
        sol = sc.solve(solver, field=field)
        grads.append(torch.autograd.grad(sol.tip_position[0] + 1e-3 * (B0 ** 2).sum(), B0)[0])
    assert grads[0].abs().max() > 0.1 and torch.allclose(grads[1], grads[0], rtol=1e-9, atol=0)


def test_inverse_problem_finds_field_for_target_tip_angle():
    rod = CosseratRod.uniform(0.05, CircularSection(1e-3), Material(E=2e6, density=1100.0, nu=0.5),
                              magnets=(MagnetDipole(0.05, (0.0, 0.0, 5e-3)),))
    target = math.radians(45.0)
    fit = fit_uniform_field(CosseratSolver(rod), target, magnitude=2e-4, field_angle=math.radians(170))
    assert abs(fit.tip_angle - target) < math.radians(0.5) and fit.reached
    b_min = rod.bending_scale * target / (0.05 * 5e-3)  # pure end moment, field across the tip
    assert abs(float(fit.field.norm()) / b_min - 1) < 0.03 and abs(float(fit.field[1])) < 1e-12
    far = fit_uniform_field(CosseratSolver(rod), math.radians(120))  # its L-BFGS ends on another branch, and says so
    assert not far.reached and abs(far.tip_angle - math.radians(120)) > math.radians(10)


# ------------------------------------------------------------------------------------ warm start, continuation, failure
def test_warm_start_continuation_and_failure_flags():
    rod = tip_magnet_rod()
    solver = CosseratSolver(rod, max_iter=30)
    B = torch.tensor([0.0, 0.05, 0.0], dtype=D)
    cold = solver.solve(field=UniformField(B), gravity=G)
    warm = solver.solve(field=UniformField(B * 1.01), gravity=G, init=cold)
    assert int(warm.iterations) <= 3 < int(cold.iterations)
    # a soft rod turned by 80 deg needs continuation; without it the problem is flagged
    rod = tip_magnet_rod(E=4e5)
    big = torch.tensor([[0.0, 0.004, 0.0], [0.0, 0.02 * math.sin(2.5), 0.02 * math.cos(2.5)]], dtype=D)
    with pytest.raises(SolverError, match="did not converge for 1 of 2"):
        CosseratSolver(rod).solve(field=UniformField(big[:, None, :]), max_load_steps=1)
    flagged = CosseratSolver(rod).solve(field=UniformField(big[:, None, :]), max_load_steps=1, raise_on_failure=False)
    assert flagged.converged.tolist() == [True, False] and float(flagged.residual[1]) > solver.tol
    ok = CosseratSolver(rod).solve(field=UniformField(big[:, None, :]))  # automatic continuation for the hard one
    assert bool(ok.converged.all()) and float(tip_angle(ok, (1, 2))[1]) > math.radians(70)
    assert int(ok.iterations[1]) > int(ok.iterations[0])
    # a per-call cap on the iterations of each load step; the solver's own budget stays as it was
    capped = CosseratSolver(rod).solve(field=UniformField(big[:, None, :]), load_steps=4, max_load_steps=4, max_iter=2,
                                       raise_on_failure=False)
    assert int(capped.iterations[1]) <= 4 * 2 and not bool(capped.converged[1])
    with pytest.raises(ValueError, match="max_iter must be an integer >= 1"):
        solver.solve(field=UniformField(B), gravity=G, max_iter=0)
    assert solver.max_iter == 30


def test_float32_close_to_float64():
    rod = tip_magnet_rod()
    B = torch.tensor([0.0, 0.01, 0.002])
    s32 = CosseratSolver(rod, dtype=torch.float32).solve(field=UniformField(B), gravity=G)
    s64 = CosseratSolver(rod).solve(field=UniformField(B.double()), gravity=G)
    assert s32.y.dtype == torch.float32 and bool(s32.converged)
    assert (s32.tip_position.double() - s64.tip_position).abs().max() < 1e-4 * 0.06


# ------------------------------------------------------------------------------------ the Paper II scene
def test_paper2_scene_and_dead_wrench_equivalence():
    sc = paper2_magnetic_rod()
    rod = sc.rod
    assert len(rod.grid.s) == 13 and rod.length == pytest.approx(0.05)
    assert [s.material for s in rod.segments] == [PMC770, NDFEB, PMC770, NDFEB]
    assert rod.magnets[1].moment[2] == pytest.approx(1.345 * 2e-3 * 2e-3 * 3e-3 / (4e-7 * math.pi)) and MU0 == 4e-7 * math.pi
    fld = LinearField(torch.tensor([0.004, 0.0015, 0.0], dtype=D), torch.diag(torch.tensor([0.02, -0.01, -0.01], dtype=D)))
    sol = sc.solve(field=fld)
    assert bool(sol.converged) and float(sol.tip_position[2]) < -0.04  # hangs down, bent sideways
    assert float(sol.tip_position[0]) > 0.01
    # the magnets' wrenches at the solved poses, applied as dead point loads, give the same shape
    R = sol.R
    nodes = rod.grid.magnet_nodes
    pos = sol.p[list(nodes)]
    mom = torch.stack([R[j] @ torch.tensor(m.moment, dtype=D) for j, m in zip(nodes, rod.magnets)])
    Bv, dB = fld(0.0, pos)
    F = (dB * mom[:, :, None]).sum(-2)
    T = torch.linalg.cross(mom, Bv, dim=-1)
    dead = sc.solve(point_forces=F, point_torques=T, init=sol)
    assert (dead.p - sol.p).abs().max() < 1e-9


# ------------------------------------------------------------------------------------ bad input
def test_bad_input_raises_clear_errors():
    base = steel_like_rod()
    sec, mat = base.section, base.material
    with pytest.raises(ValueError, match="Material.E"):
        Material(E=-1.0, density=1000.0, nu=0.3)
    with pytest.raises(ValueError, match="Segment.length"):
        Segment(0.0, sec, mat)
    with pytest.raises(TypeError, match="Segment.section"):
        Segment(0.1, 0.01, mat)
    with pytest.raises(ValueError, match=r"Segment.intrinsic_strain\[2\] \(the rest stretch"):
        Segment(0.1, sec, mat, intrinsic_strain=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"load_points\[0\]"):
        CosseratRod.uniform(0.2, sec, mat, load_points=(0.3,))
    with pytest.raises(ValueError, match=r"magnets\[0\].s"):
        CosseratRod.uniform(0.2, sec, mat, magnets=(MagnetDipole(-0.01, (0, 0, 1)),))
    with pytest.raises(ValueError, match="n_nodes must be >= 4"):
        CosseratRod.uniform(0.2, sec, mat, n_nodes=3, load_points=(0.05, 0.1))
    rod = uniform(base, 13)
    solver = CosseratSolver(rod)
    with pytest.raises(ValueError, match="base_quaternion"):
        solver.solve(base_quaternion=(1.0, 0.1, 0.0, 0.0))
    with pytest.raises(ValueError, match="tip_force"):
        solver.solve(tip_force=(1.0, 0.0))
    with pytest.raises(ValueError, match="gravity must be finite"):
        solver.solve(gravity=(0.0, float("nan"), 0.0))
    with pytest.raises(ValueError, match="point_forces"):
        solver.solve(point_forces=torch.zeros(1, 3))
    with pytest.raises(TypeError, match="field"):
        solver.solve(field=3.0)
    with pytest.raises(ValueError, match="youngs_modulus"):
        rod.params(youngs_modulus=torch.tensor([-1.0]))
    with pytest.raises(ValueError, match="tol"):
        CosseratSolver(rod, tol=0.0)
    with pytest.raises(ValueError, match="fd_step .* must be finite and > 0, got -1e-06"):
        CosseratSolver(rod, fd_step=-1e-6)
    with pytest.raises(ValueError, match="load_steps"):
        solver.solve(load_steps=0)


def test_a_shot_that_runs_off_gives_a_nan_residual_not_a_field_error():
    """A trial base wrench far too large sends the RK4 shot to infinity: the field is not asked about the
    non-finite magnet position (a point dipole raised "field point at distance nan"), the residual is NaN,
    which the Levenberg-Marquardt step rejects."""
    from physics.magnetics.dipole import dipole_field, dipole_field_gradient
    L = 0.05
    rod = CosseratRod.uniform(L, CircularSection(1e-3), Material(E=1e6, density=1000.0, nu=0.5), n_nodes=21,
                              magnets=(MagnetDipole(0.03, (1e-3, 0.0, 2e-3), 1e-5),))
    solver = CosseratSolver(rod)
    src, m = torch.tensor([0.03, 0.02, 0.06], dtype=torch.float64), torch.tensor([0.0, 0.3, 0.5], dtype=torch.float64)

    def field(t, pos):
        return dipole_field(pos - src, m), dipole_field_gradient(pos - src, m)
    x = torch.tensor([[0.1] * 6, [1000.0] * 6], dtype=torch.float64)
    for tangent in (False, True):
        r = shoot(x, solver.params, rod.grid, solver.make_loads(), solver.scales, field, tangent=tangent).r
        assert bool(torch.isfinite(r[0]).all()) and not bool(torch.isfinite(r[1]).any())


def test_integer_and_tolerance_arguments_name_themselves():
    """NaN, inf or None for a count gave "cannot convert float NaN to integer" or an int() TypeError naming nothing;
    a numpy float tolerance was refused as not "a finite positive number"."""
    from physics.cosserat_frames import FrameSolve
    base = steel_like_rod()
    for v in (float("nan"), float("inf"), None):
        with pytest.raises(ValueError, match="CosseratRod.n_nodes must be an integer >= 2"):
            CosseratRod.uniform(0.2, base.section, base.material, n_nodes=v)
        with pytest.raises(ValueError, match="max_iter must be an integer >= 1"):
            CosseratSolver(uniform(base, 13), max_iter=v)
    solver = CosseratSolver(uniform(base, 13))
    with pytest.raises(ValueError, match="max_iter must be an integer >= 1, got nan"):
        solver.solve(max_iter=float("nan"))
    with pytest.raises(ValueError, match="max_iter must be an integer >= 1, got inf"):
        FrameSolve(solver, max_iter=float("inf"))
    with pytest.raises(ValueError, match="max_load_steps must be an integer >= 1, got nan"):
        solver.solve(max_load_steps=float("nan"))
    assert CosseratSolver(uniform(base, 13), tol=np.float32(1e-6)).tol == pytest.approx(1e-6)


def test_params_and_loads_that_do_not_fit_the_solver_are_refused():
    """Parameters of another dtype failed deep in torch ("expected m1 and m2 to have the same dtype"); those of
    another rod or node count were used silently on the wrong grid; ``loads=`` beside load keywords dropped the
    keywords silently (a tip force that did nothing)."""
    base = steel_like_rod()
    L, soft = base.length, base.material
    stiff = Material(E=4 * soft.E, density=1000.0, nu=0.3)
    rod = CosseratRod((Segment(0.3 * L, base.section, stiff), Segment(0.7 * L, base.section, soft)), n_nodes=13,
                      magnets=(MagnetDipole(L, (0.0, 0.0, 1e-3)),))
    solver = CosseratSolver(rod)
    with pytest.raises(TypeError, match=r"params.ks_inv has dtype torch.float32, the solver's is torch.float64"):
        solver.solve(params=rod.params(torch.float32))
    with pytest.raises(TypeError, match="params.ks_inv has dtype torch.float32"):
        CosseratSolver(rod, params=rod.params(torch.float32))
    finer = CosseratRod(rod.segments, n_nodes=21, magnets=rod.magnets)
    with pytest.raises(ValueError, match=r"params are for 20 RK4 steps and 1 magnets, the solver's rod has 12 steps"):
        solver.solve(params=finer.params(D))
    loads = solver.make_loads(gravity=G)
    with pytest.raises(ValueError, match=r"either as loads= or as keywords, not both \(got loads= and tip_force=\)"):
        solver.solve(loads=loads, tip_force=(1e-3, 0.0, 0.0))
    sc = paper2_magnetic_rod()
    s2 = CosseratSolver(sc.rod)
    own = sc.solve(s2, loads=s2.make_loads(gravity=sc.gravity, base_quaternion=sc.base_quaternion))
    assert (own.p - sc.solve(s2).p).abs().max() < 1e-12  # a scene's solve takes loads= (its pose not added)



def test_loads_given_whole_are_checked_like_the_keywords():
    """``loads=StaticLoads`` skipped every check make_loads does: a non-unit base quaternion moved the tip of the
    magnetic rod from z = -0.05 m to +0.066 m, a point-force tensor of the wrong count was accepted, float32 loads
    ran in a float64 solver, and a NaN load spent 38 s on load stepping before "did not converge"."""
    sc = paper2_magnetic_rod()
    solver = CosseratSolver(sc.rod)
    good = solver.make_loads(gravity=sc.gravity, base_quaternion=sc.base_quaternion)
    nan = torch.tensor([float("nan"), 0.0, 0.0], dtype=D)
    for bad, err, msg in (
            ((1.0,) * 8, TypeError, "loads must be StaticLoads"),
            (good._replace(gravity=good.gravity.float()), TypeError, "loads.gravity must be a torch.float64 tensor"),
            (good._replace(line_force=nan), ValueError, "loads.line_force must be finite"),
            (good._replace(point_force=torch.zeros(5, 3, dtype=D)), ValueError,
             r"loads.point_force must have shape \(\.\.\., 3, 3\) \(the rod's 2 load_points, then the tip"),
            (good._replace(base_quaternion=2 * good.base_quaternion), ValueError,
             "loads.base_quaternion must be a unit quaternion .* got |q| = 2")):
        with pytest.raises(err, match=msg):
            sc.solve(solver, loads=bad)
    ok = sc.solve(solver, loads=good._replace(gravity=good.gravity.expand(2, 3)))  # a batch of loads still solves
    assert ok.p.shape[0] == 2 and bool(ok.converged.all())


def test_a_field_that_gives_nan_is_named_at_once():
    """A field hook returning NaN (or a NaN parameter) ran Levenberg-Marquardt through every load-stepping retry
    (1611 iterations, 38 s for the magnetic rod) into "did not converge"; no load step can mend it."""
    import time
    sc = paper2_magnetic_rod()
    solver = CosseratSolver(sc.rod)

    def nan_field(t, positions):
        return torch.full_like(positions, float("nan"))

    t0 = time.perf_counter()
    with pytest.raises(SolverError, match=r"tip residual of 1 of 1 problem\(s\) is not finite at the start point "
                                          r"\(the unloaded or warm-start base wrench under 1/64 of the loads\)"):
        sc.solve(solver, field=nan_field)
    assert time.perf_counter() - t0 < 10.0
    flags = sc.solve(solver, field=nan_field, raise_on_failure=False, max_load_steps=1)  # flags asked for: no error
    assert not bool(flags.converged.any())
    prm = sc.rod.params(D)
    with pytest.raises(SolverError, match="not finite at the start point"):
        sc.solve(solver, params=prm._replace(ks_inv=prm.ks_inv * float("nan")))
    fine = sc.solve(solver, field=lambda t, p: torch.zeros_like(p))  # a finite field still solves
    assert bool(fine.converged.all())

def test_bad_field_and_magnet_input_raise_clear_errors():
    """A NaN in a LinearField or in the magnets' moments ran Levenberg-Marquardt and its load-stepping retries
    for up to a minute into "did not converge"; a LinearField of a wrong shape, a batch of UniformFields without
    the point axis (B (2, 3)) failed deep in torch ("The expanded size of the tensor ..."); fit_uniform_field
    returned a zero field for magnitude=0."""
    rod = tip_magnet_rod()
    with pytest.raises(ValueError, match=r"LinearField.B0 must be finite with shape \(\.\.\., 3\), got shape \(3,\) "
                                         r"with non-finite values"):
        LinearField(torch.tensor([0.01, float("nan"), 0.0], dtype=D))
    with pytest.raises(ValueError, match=r"LinearField.G must be finite with shape \(\.\.\., 3, 3\), got shape \(2, 2\)"):
        LinearField([0.01, 0.0, 0.0], [[0.1, 0.0], [0.0, 0.1]])
    with pytest.raises(ValueError, match=r"LinearField.x0 must be finite with shape \(3,\), got shape \(2,\)"):
        LinearField([0.01, 0.0, 0.0], x0=(0.0, 0.0))
    with pytest.raises(ValueError, match="magnet_moments must be finite"):
        rod.params(D, magnet_moments=torch.tensor([[float("nan"), 0.0, 0.0]], dtype=D))
    B = torch.tensor([[0.0, 0.01, 0.0], [0.01, 0.0, 0.0]], dtype=D)
    with pytest.raises(ValueError, match=r"one per batch member, \(\.\.\., 1, 3\) .* got shape \(2, 3\)"):
        CosseratSolver(rod).solve(field=UniformField(B))
    with pytest.raises(ValueError, match="magnitude .* must be finite and > 0, got 0.0"):
        fit_uniform_field(CosseratSolver(rod), 0.5, magnitude=0.0)
    with pytest.raises(ValueError, match="max_evals must be an integer >= 1, got 0"):
        fit_uniform_field(CosseratSolver(rod), 0.5, max_evals=0)
    for kw, msg in (({"reg": -1.0}, "reg must be finite and >= 0, got -1.0"),  # ran: loss -1
                    ({"angle_tol": float("nan")}, "angle_tol must be finite and > 0, got nan"),  # reached nothing
                    ({"field_angle": float("inf")}, "field_angle must be finite, got inf")):
        with pytest.raises(ValueError, match=msg):
            fit_uniform_field(CosseratSolver(rod), 0.5, **kw)
    plain = CosseratRod.uniform(0.05, CircularSection(1e-3), Material(E=2e6, density=1100.0, nu=0.5), n_nodes=9)
    with pytest.raises(ValueError, match="field: this rod has no magnets"):  # the field was ignored
        CosseratSolver(plain).solve(field=UniformField((0.05, 0.0, 0.0)))
