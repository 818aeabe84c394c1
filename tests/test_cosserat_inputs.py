"""Bad input to the static Cosserat rod's helpers (inverse fit, scenes, the real-time frame solve) gives a clear error
naming the parameter, not a silently wrong answer or a traceback from deep inside torch; and options that did
nothing are refused."""
import pytest
import torch

from physics import CircularSection, Material, UniformField
from physics.cosserat import CosseratRod, MagnetDipole
from physics.cosserat_frames import FrameSolve
from physics.cosserat_inverse import fit_uniform_field, tip_angle
from physics.cosserat_shooting import CosseratSolver
from physics.scenes_cosserat import LinearField, paper2_magnetic_rod

D = torch.float64
MAT = Material(E=2e6, density=1100.0, nu=0.5)


def tip_magnet_rod(n_nodes=7, moment=(0.0, 0.0, 2e-3), magnets=None):
    mags = (MagnetDipole(0.06, moment),) if magnets is None else magnets
    return CosseratRod.uniform(0.06, CircularSection(3e-3), MAT, n_nodes=n_nodes, magnets=mags)


def test_tip_angle_needs_two_different_world_axes():
    """plane=(0, 0) gave 45 deg whatever the shape (atan2(t_x, t_x)); (0, 3) an IndexError from torch."""
    sol = CosseratSolver(tip_magnet_rod()).solve(field=UniformField((0.01, 0.0, 0.0)))
    assert abs(float(tip_angle(sol, (0, 2)))) > 0.05  # (the valid planes as before)
    for bad in ((0, 0), (0, 3), (2,), "xz", (0.0, 2.0)):
        with pytest.raises(ValueError, match=r"plane must be two different world axes \(a, b\) out of 0, 1, 2"):
            tip_angle(sol, bad)


def test_fit_uniform_field_refuses_what_it_cannot_fit():
    """A rod for a solver gave AttributeError: 'CosseratRod' object has no attribute 'rod'; a tip magnet of zero
    moment ZeroDivisionError: float division by zero; a batch of problems (gravity (2, 3)) ran a solve and failed
    in backward() with "grad can be implicitly created only for scalar outputs"."""
    rod = tip_magnet_rod()
    with pytest.raises(TypeError, match="solver must be a CosseratSolver, got CosseratRod"):
        fit_uniform_field(rod, 0.5)
    with pytest.raises(ValueError, match="tip-most magnet has a zero moment.*give magnitude="):
        fit_uniform_field(CosseratSolver(tip_magnet_rod(moment=(0.0, 0.0, 0.0))), 0.5)
    g = torch.tensor([[0.0, 0.0, -9.81], [0.0, 0.0, -1.0]], dtype=D)
    with pytest.raises(ValueError, match=r"fit_uniform_field fits one problem, .* a batch of shape \(2,\)"):
        fit_uniform_field(CosseratSolver(rod), 0.5, gravity=g, max_evals=2)


def test_fit_uniform_field_estimates_from_the_tip_most_magnet_whatever_their_order():
    """The field estimate (start and scale of the fit) came from the last magnet listed, not the tip-most one as
    documented: listing the tip magnet first fitted with the weak proximal magnet's moment, another field."""
    tip, mid = MagnetDipole(0.06, (0.0, 0.0, 4e-3)), MagnetDipole(0.03, (0.0, 0.0, 4e-4))
    fits = [fit_uniform_field(CosseratSolver(tip_magnet_rod(magnets=m)), 0.4, max_evals=6)
            for m in ((mid, tip), (tip, mid))]
    assert (fits[0].field - fits[1].field).abs().max() <= 1e-9 * fits[0].field.abs().max()
    assert fits[0].evaluations == fits[1].evaluations


def test_a_scene_refuses_a_solver_for_another_rod():
    """scene.solve(solver) with a solver made for another rod (here the 7-node rod for the 9-node scene) solved that
    rod, with the scene's gravity and pose, without a word; a rod in place of a solver gave an AttributeError."""
    sc7, sc9 = paper2_magnetic_rod(7), paper2_magnetic_rod(9)
    with pytest.raises(ValueError, match=r"another rod than this scene's \(paper2_magnetic_rod; the solver's rod "
                                         r"has n_nodes=7, the scene's 9\)"):
        sc9.solve(sc7.solver())
    with pytest.raises(ValueError, match="another rod than this scene's"):
        sc9.frame_solve(sc7.solver())
    with pytest.raises(TypeError, match="solver must be a CosseratSolver, got CosseratRod"):
        sc9.solve(sc9.rod)
    assert bool(sc7.solve(paper2_magnetic_rod(7).solver()).converged)  # an equal rod built again is the scene's


def test_linear_field_batches_of_b0_and_g_must_broadcast():
    """B0 (2, 3) with G (3, 3, 3) was accepted and failed at the first solve deep in torch ("The size of tensor a
    (2) must match the size of tensor b (3) at non-singleton dimension 0")."""
    with pytest.raises(ValueError, match=r"LinearField: the batch shapes of B0 \(2, 3\) and G \(3, 3, 3\) do not "
                                         r"broadcast"):
        LinearField(torch.full((2, 3), 0.01, dtype=D), torch.zeros(3, 3, 3, dtype=D))
    LinearField(torch.full((2, 3), 0.01, dtype=D), torch.zeros(1, 3, 3, dtype=D))  # (broadcasting ones still pass)


def test_steps_per_call_without_compile_is_refused():
    """steps_per_call > 1 fuses grid steps per compiled call; without compile=True it was silently ignored."""
    rod = tip_magnet_rod()
    with pytest.raises(ValueError, match=r"steps_per_call=2 \(grid steps fused per compiled call\) needs compile=True"):
        CosseratSolver(rod, steps_per_call=2)
    assert CosseratSolver(rod, steps_per_call=2, compile=True).steps_per_call == 2  # (nothing compiles yet)


def _frame_setup():
    sc = paper2_magnetic_rod(7)
    fast = CosseratSolver(sc.rod, compile=True)
    field = LinearField(torch.tensor([0.004, 0.0015, 0.0], dtype=D), torch.diag(torch.tensor([0.02, -0.01, -0.01],
                                                                                              dtype=D)))
    return sc, fast, field, sc.solve(field=field)


def test_a_frame_solve_takes_whole_loads_like_the_solver():
    """FrameSolve(solver, loads=StaticLoads) (what scene.frame_solve passes on, and solve(loads=) takes) failed with
    "make_loads() got an unexpected keyword argument 'loads'"."""
    sc, fast, field, sol = _frame_setup()
    loads = fast.make_loads(gravity=sc.gravity, base_quaternion=sc.base_quaternion)
    ref = sc.frame_solve(fast, max_iter=10, compiled=False)(field, sol)
    for frame in (FrameSolve(fast, max_iter=10, compiled=False, loads=loads),
                  sc.frame_solve(fast, max_iter=10, compiled=False, loads=loads)):
        out = frame(field, sol)
        assert bool(out.converged) and (out.y - ref.y).abs().max() < 1e-14
    with pytest.raises(ValueError, match=r"either as loads= or as keywords, not both \(got loads= and gravity=\)"):
        FrameSolve(fast, loads=loads, gravity=sc.gravity)
    with pytest.raises(TypeError, match="loads must be StaticLoads"):
        FrameSolve(fast, loads={"gravity": sc.gravity})


def test_a_frame_solve_refuses_a_field_for_a_rod_without_magnets():
    """On the fast path a field for a rod without magnets was ignored (the frame converged); the solver's call refuses
    it. (A NaN start is not checked there: it costs 22 us a frame, and the frame then ends unconverged.)"""
    plain = CosseratRod.uniform(0.05, CircularSection(1e-3), MAT, n_nodes=5)
    with pytest.raises(ValueError, match="field: this rod has no magnets"):
        FrameSolve(CosseratSolver(plain, compile=True), compiled=False)(UniformField((0.05, 0.0, 0.0)),
                                                                        torch.zeros(6, dtype=D))


def test_a_field_hook_of_another_dtype_is_named():
    """A hook returning float32 B (torch.tensor's default) in a float64 solve failed inside torch.linalg.cross with
    "expected scalar type Double but found Float"."""
    solver = CosseratSolver(tip_magnet_rod())

    def hook(t, x):
        return torch.zeros(x.shape) + torch.tensor([0.01, 0.0, 0.0])

    with pytest.raises(TypeError, match=r"field hook field\(t, positions\) returned B of dtype torch.float32 for "
                                        r"positions of dtype torch.float64"):
        solver.solve(field=hook)
    ok = solver.solve(field=lambda t, x: hook(t, x).to(x))
    assert bool(ok.converged) and float(ok.tip_position[0]) > 1e-3
