"""The magnetic-rod surrogate task (Paper II Data-set IV, Table II.1): scene, data, orientation errors,
the static Cosserat baseline and the shipped checkpoint."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from cmlearn.data import generate_dataset, get_task, load_dataset
from cmlearn.data.magnetic import magnet_frames, magnet_wrench, rollout, wrench_inputs
from cmlearn.surrogate.magnetic import cosserat_orientations, orientation_errors, orientation_stats
from physics.coil_currents import BatchedCurrents, CoilField, MinJerkCurrents, SinusoidCurrents
from physics.lie import rot_x, rot_y, rot_z
from physics.scenes import get_scene
from physics.scenes_magnetic_rod import FIELD_POINT, MagnetBlockRod, eMNS

ROOT = Path(__file__).resolve().parents[1]
TASK = get_task("magnetic_rod")
B_STEP = 5e-3  # T at the rod's middle


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def step_response():
    """The rod after 1 s in the currents of a 5 mT field along +x (batch 0) and +y (batch 1), reached by a
    0.5 s minimum-jerk ramp: quasi-static at the end (first mode 4.1 Hz, 17 % of critical; the magnets within
    0.25 deg of the static Cosserat pose, their axes within 0.05 deg of where they point 0.5 s later)."""
    e = eMNS()
    field = torch.tensor([[[B_STEP, 0.0, 0.0]], [[0.0, B_STEP, 0.0]]], dtype=torch.float64)
    I = e.allocate(torch.tensor([FIELD_POINT], dtype=torch.float64).expand(2, 1, 3), field=field).currents
    profiles = [MinJerkCurrents(torch.stack([torch.zeros(6, dtype=torch.float64), i]), (0.5,), (0.0, 1.0)) for i in I]
    scene = replace(get_scene("magnetic_rod"), duration=1.0)
    pts, W, _ = rollout(TASK, scene, currents=BatchedCurrents(profiles))
    return scene, I, pts, W


def test_a_field_turns_the_magnets_towards_it(step_response):
    scene, I, pts, _ = step_response
    c, R, _ = magnet_frames(TASK, scene.rod, pts[:, -1])
    e3 = R[..., 2]  # moment directions (both magnets along body E3, hanging down at rest)
    B = eMNS().field(c, I)  # the field each magnet sits in at the end
    b = B / B.norm(dim=-1, keepdim=True)
    rest = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    assert float(((e3 - rest) * b).sum(-1).min()) > 0.3  # both magnets turned a lot towards their field
    for k, axis in ((0, 0), (1, 1)):  # the distal magnet swings towards +x, +y by tens of degrees
        dist, prox = e3[k, 1], e3[k, 0]
        assert float(dist[axis]) > 0.5 and float(prox[axis]) > 0.3 and float(dist[axis]) > float(prox[axis])
    assert abs(float(e3[0, 1, 1])) < 0.01  # +x field: the coils are symmetric about the xz-plane
    assert float((pts[:, -1] - pts[:, -2]).abs().max()) < 5e-5  # settled: below 2.5 mm/s at the end (measured 1.2)


def test_magnet_frames_from_points_match_the_lgvi_rotation():
    from physics.elastic import relative_cayley
    from physics.loads import magnet_poses
    from cmlearn.data.magnetic import tracked_points
    scene = get_scene("magnetic_rod")
    cfg = scene.initial_configuration()
    I = torch.tensor([2.0, -1.0, 0.5, -2.0, 1.0, 1.5], dtype=torch.float64)
    sim = scene.make_integrator(loads=replace(scene.loads, field=CoilField(eMNS(), lambda t: I)))
    s, _ = sim.simulate(sim.initial_state(p=cfg["p"], R=cfg["R"]), n_steps=2000)
    prm = scene.rod.params()
    _, Rm, _ = magnet_poses(s.p, s.R, relative_cayley(s.R), prm)
    _, R_hat, _ = magnet_frames(TASK, scene.rod, tracked_points(TASK, scene.rod, s.p, s.R))
    assert float(orientation_errors(Rm, torch.eye(3, dtype=torch.float64)).norm(dim=-1).min()) > 5.0  # it moved
    assert float(orientation_errors(R_hat, Rm).abs().max()) < 1e-6


def test_wrench_inputs_carry_the_magnets_torque_and_force(step_response):
    scene, I, pts, W = step_response
    rod = scene.rod
    c, R, d = magnet_frames(TASK, rod, pts[0, -1])
    moments = torch.tensor([m.moment for m in rod.magnets], dtype=torch.float64)
    f, tau = magnet_wrench(eMNS(), c, R, moments, I[0])
    w = wrench_inputs(TASK, rod, eMNS(), pts[0, -1], I[0])  # nodes 4, 5, 9, 10
    for k, (a, b) in enumerate(((0, 1), (2, 3))):
        assert torch.allclose(w[a] + w[b], f[k], atol=1e-12)
        assert torch.allclose(0.5 * torch.linalg.cross(d[k], w[b] - w[a], dim=-1), tau[k], rtol=1e-6, atol=1e-12)
    assert float(tau.norm(dim=-1).min()) > 1e-5  # a real torque (N m), not a vacuous identity
    # the stored inputs of the last step are the same function of the frame and the mid-step currents
    assert torch.allclose(W[0, -1], wrench_inputs(TASK, rod, eMNS(), pts[0, -2], I[0]), rtol=1e-9, atol=1e-12)


def test_static_cosserat_agrees_with_the_lgvi_at_a_quasi_static_sample(step_response):
    scene, I, pts, _ = step_response
    _, R_lgvi, _ = magnet_frames(TASK, scene.rod, pts[:, -1])
    profiles = BatchedCurrents([lambda t, i=i: i for i in I])
    for b in range(2):
        R_cos, _ = cosserat_orientations(lambda t, b=b: profiles(t)[b], [scene.duration], eMNS())
        err = orientation_errors(R_cos[0], R_lgvi[b]).norm(dim=-1)
        swing = orientation_errors(R_lgvi[b], torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]],
                                                             dtype=torch.float64)).norm(dim=-1)
        assert float(swing.min()) > 20.0 and float(err.max()) < 2.0, (swing, err)  # a wrong sign: > 40 deg


def test_orientation_error_by_hand():
    ref = rot_x(math.pi / 2, dtype=torch.float64)
    pred = rot_y(math.radians(2.0), dtype=torch.float64) @ ref  # 2 deg about the world y axis
    assert torch.allclose(orientation_errors(pred, ref), torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64), atol=1e-9)
    # 5 deg about the axis (0.6, 0, -0.8), by Rodrigues' formula: the angles about x, y, z are 3, 0, -4 deg
    n, th = torch.tensor([0.6, 0.0, -0.8], dtype=torch.float64), math.radians(5.0)
    K = torch.tensor([[0.0, -n[2], n[1]], [n[2], 0.0, -n[0]], [-n[1], n[0], 0.0]], dtype=torch.float64)
    turn = torch.eye(3, dtype=torch.float64) + math.sin(th) * K + (1 - math.cos(th)) * K @ K
    ref2 = rot_z(0.7, dtype=torch.float64)
    e = orientation_errors(turn @ ref2, ref2)
    assert torch.allclose(e, torch.tensor([3.0, 0.0, -4.0], dtype=torch.float64), atol=1e-9)
    assert not torch.allclose(orientation_errors(ref2 @ turn, ref2), e, atol=0.1)  # world, not body, axes
    err = torch.tensor([[[1.0, -2.0, 0.5], [0.0, 0.0, 0.0]], [[-3.0, 1.0, 0.5], [0.0, 4.0, 0.0]]])
    s = orientation_stats(err)
    assert s["proximal"]["x"] == {"max_deg": 3.0, "mean_deg": 2.0} and s["distal"]["y"]["max_deg"] == 4.0
    with pytest.raises(ValueError, match="R_pred"):
        orientation_errors(torch.eye(3), torch.eye(2))


def test_tiny_dataset_holds_the_markers_and_the_wrench(tmp_path):
    path = tmp_path / "mag.pt"
    meta = generate_dataset("magnetic_rod", 2, seed=39, out=path, duration=0.2)  # seed 39: moves at 0.1 s
    d = load_dataset(path, task="magnetic_rod")
    n = int(round(0.2 / TASK.delta))  # intervals
    assert d["positions"].shape == (2, n + 1, 11, 3) and d["wrench"].shape == (2, n, 4, 3)
    assert meta["tracked"] == [0, 2, 4, 5, 7, 9, 10, 11, 12, 13, 14] and meta["wrench_nodes"] == [4, 5, 9, 10]
    assert torch.equal(d["wrench"][0], torch.zeros(n, 4, 3))  # the printed profile holds zero current for 0.5 s
    assert float(d["wrench"][1].abs().max()) > 0
    centre = 0.5 * (d["positions"][:, :, 2] + d["positions"][:, :, 3])
    lateral, axial = d["positions"][:, :, 7] - centre, d["positions"][:, :, 8] - centre
    assert torch.allclose(lateral.norm(dim=-1), torch.full((2, n + 1), 0.02), atol=1e-6)  # 20 mm lever arms
    assert torch.allclose(axial[:, 0], torch.tensor([0.0, 0.0, -0.02]).expand(2, 3), atol=1e-6)  # along E3 = -z
    assert float((lateral * axial).sum(-1).abs().max()) < 1e-9
    # the wrench of many frames in chunks of frames (by_frames, for memory) is the wrench of all at once
    from cmlearn.data.magnetic import by_frames
    rod, pts = TASK.base_scene().rod, d["positions"].double()
    I = torch.linspace(-3.0, 3.0, 6, dtype=torch.float64) * torch.linspace(0.2, 1.0, n + 1, dtype=torch.float64)[:, None]
    whole = wrench_inputs(TASK, rod, eMNS(), pts, I.expand(2, -1, -1))
    assert float(whole.abs().max()) > 1e-6
    assert torch.equal(by_frames(lambda p, i: wrench_inputs(TASK, rod, eMNS(), p, i), pts, I.expand(2, -1, -1), chunk=4),
                       whole)


def test_reference_rollout_is_cached_while_it_fits(tmp_path):
    """The LGVI reference of a held-out profile is served from ``data_dir`` (its recorded wall time too) while it
    fits; it is run again for a task sampled at another step and for a file that fails its hash."""
    from cmlearn.data import reference_rollout
    name = TASK.heldout[0]
    fine, W, wall = reference_rollout(TASK, name, 0.04, tmp_path)
    assert fine.shape == (int(round(0.04 / TASK.delta)) + 1, 11, 3) and W.shape[0] == fine.shape[0] - 1
    path = tmp_path / f"{TASK.name}_{name}_0.04s_ref.pt"
    again = reference_rollout(TASK, name, 0.04, tmp_path)
    assert torch.equal(again[0], fine) and torch.equal(again[1], W) and again[2] == wall  # served from the cache
    coarse = reference_rollout(replace(TASK, delta=2 * TASK.delta), name, 0.04, tmp_path)[0]
    assert torch.equal(coarse, fine[::2])
    fine_again = reference_rollout(TASK, name, 0.04, tmp_path)  # the file held the coarse run: made again
    assert torch.equal(fine_again[0], fine) and fine_again[2] != wall
    blob = torch.load(path, weights_only=True)
    blob["positions"][-1] += 1e-3
    torch.save(blob, path)
    assert torch.equal(reference_rollout(TASK, name, 0.04, tmp_path)[0], fine)


def test_scene_rollout_runs_the_rod_as_its_module_does():
    """The generic scene_rollout (the benchmark's) runs the magnetic rod through its own module: the markers and
    the coil wrench, not node positions; it refuses the other shapes or forces only plain tasks take (its compiled
    LGVI: the compare test)."""
    from cmlearn.data import scene_rollout
    scene = TASK.base_scene()
    pts, W, _ = scene_rollout(TASK, scene, duration=0.04)
    ref, W_ref, _ = rollout(TASK, scene, duration=0.04)
    assert pts.shape == (int(round(0.04 / TASK.delta)) + 1, len(TASK.tracked), 3)
    assert torch.equal(pts, ref) and torch.equal(W, W_ref)
    for bad in ({"p0": scene.initial_configuration()["p"]}, {"force": None}):
        with pytest.raises(ValueError, match="p0, R0 and force are not accepted"):
            scene_rollout(TASK, scene, duration=0.04, **bad)


def test_nudged_free_running_spreads_only_when_nudged_and_one_start_is_the_recorded_run(tmp_path):
    """nudged_free_running: one unnudged start is exactly the free-running run the metrics record; unnudged
    copies in a batch agree with each other; nudged ones differ, here (no snap-through in 0.3 s) by little; open
    loop (``wrench``) steps with the recorded wrench of each frame."""
    from cmlearn.data import reference_rollout
    from cmlearn.data.windows import node_wrench
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.evaluate import from_rest
    from cmlearn.surrogate.magnetic import _case, nudged_free_running
    model, _ = load_checkpoint(ROOT / "checkpoints" / "magnetic_rod.pt", task="magnetic_rod")
    name, eta = TASK.heldout[0], model.config.eta
    scene = replace(TASK.scene_by_name(name), duration=0.3)
    p, W, _ = reference_rollout(TASK, name, 0.3, tmp_path)
    p, W = p.float(), W.float()
    ph, Wh = from_rest(p, node_wrench(W, TASK.wrench_nodes, TASK.modeled), eta)
    case = _case(model, TASK, scene, ph, Wh, eta, pad=eta, cosserat=False, nudged=3)
    free = case["orientation_deg"]["free_running"]
    recorded = sum(free[m][ax]["mean_deg"] for m in ("distal", "proximal") for ax in "xyz")
    assert recorded > 0.01
    one = nudged_free_running(model, TASK, scene, ph, eta, eta, n=1, sigma=0.0)
    assert one["sum_mean_deg"] == [pytest.approx(recorded, rel=1e-12)]
    assert one["distal"]["y"]["mean_deg"] == pytest.approx(free["distal"]["y"]["mean_deg"], rel=1e-12)
    same = nudged_free_running(model, TASK, scene, ph, eta, eta, n=3, sigma=0.0)["sum_mean_deg"]
    assert same[0] == same[1] == same[2]
    spread = case["free_running_nudged"]
    assert spread["n"] == 3 and spread["sigma_m"] == 1e-8 and len(set(spread["sum_mean_deg"])) == 3
    assert max(abs(s - recorded) for s in spread["sum_mean_deg"]) < 1e-3
    # open loop, fed the LGVI's wrench: its first step is the one-step prediction (same history and wrench) ...
    k = 12
    assert float((Wh[k + 1] - Wh[k]).abs().max()) > 0 and float((Wh[k] - Wh[k - 1]).abs().max()) > 0
    first = _case(model, TASK, scene, ph[:k + 2], Wh[:k + 1], k, pad=eta, cosserat=False, nudged=0)
    one_step = sum(first["orientation_deg"]["one_step"][m][ax]["mean_deg"] for m in ("distal", "proximal") for ax in "xyz")
    opened = nudged_free_running(model, TASK, scene, ph[:k + 2], k, eta, n=1, sigma=0.0, wrench=Wh[:k + 1])
    assert opened["sum_mean_deg"] == [pytest.approx(one_step, rel=1e-9)]
    # ... and over 0.3 s, with no snap-through, it stays near the closed loop without being it
    whole = nudged_free_running(model, TASK, scene, ph, eta, eta, n=1, sigma=0.0, wrench=Wh)["sum_mean_deg"][0]
    assert whole != recorded and abs(whole - recorded) < 0.1
    with pytest.raises(ValueError, match="wrench must hold"):
        nudged_free_running(model, TASK, scene, ph, eta, eta, wrench=Wh[:-1])
    with pytest.raises(ValueError, match="sigma"):
        nudged_free_running(model, TASK, scene, ph, eta, eta, sigma=-1.0)
    with pytest.raises(ValueError, match="n must"):
        nudged_free_running(model, TASK, scene, ph, eta, eta, n=0)


def test_closed_loop_training_rollout_computes_the_wrench_from_its_own_frames(tmp_path):
    """Closed-loop training (train_surrogate --closed-loop): the linearised field reproduces the stored wrench
    on the data and the exact one to second order off it; the training rollout with it follows the evaluation's
    closed loop (exact field); a dataset whose currents cannot be regenerated is refused."""
    from cmlearn.data.magnetic import equivalent_forces, field_samples, linearised_field
    from cmlearn.data.windows import RolloutWindows, node_wrench
    from cmlearn.models import NodeLSTMSurrogate
    from cmlearn.surrogate.magnetic import closed_loop, closed_loop_inputs, closed_loop_wrench
    from cmlearn.surrogate.training import SurrogateModule
    path = tmp_path / "mag.pt"
    generate_dataset("magnetic_rod", 2, seed=39, out=path, duration=0.4)  # seed 39: moves from 0.1 s
    d = load_dataset(path, task="magnetic_rod")
    inputs = closed_loop_inputs(TASK, d)
    end, H = int(round(0.4 / TASK.delta)), int(round(0.16 / TASK.delta))  # the last window below: H steps up to 0.4 s
    assert inputs.shape == (2, end, 2, 15) and float(inputs[1, -1, :, 3:6].norm(dim=-1).min()) > 1e-4  # tesla
    rod, pts = TASK.base_scene().rod, d["positions"][1, -2].double()
    I = torch.tensor([2.0, -1.0, 0.5, -2.0, 1.0, 1.5], dtype=torch.float64)
    field = linearised_field(field_samples(TASK, rod, eMNS(), pts, I))
    exact = lambda c: eMNS().field_and_gradient(c, I)  # noqa: E731
    assert torch.allclose(equivalent_forces(TASK, rod, pts, field), wrench_inputs(TASK, rod, eMNS(), pts, I), atol=1e-15)
    # the whole rod moved by 1 mm: only the field changes, and the expansion follows it (a wrong sign: twice off)
    moved = pts + torch.tensor([1e-3, -1e-3, 5e-4], dtype=torch.float64)
    w_exact = equivalent_forces(TASK, rod, moved, exact)
    err = float((equivalent_forces(TASK, rod, moved, field) - w_exact).abs().max())
    assert float((w_exact - equivalent_forces(TASK, rod, pts, exact)).abs().max()) > 10 * err, err
    torch.manual_seed(0)
    model = NodeLSTMSurrogate(TASK.model_config(eta=2, hidden=8))
    torch.nn.init.normal_(model.head[-1].weight, std=0.3)  # an untrained model that responds (its head starts at 0)
    model.set_scales([d["positions"][v] for v in range(2)], node_wrench(d["wrench"], TASK.wrench_nodes, TASK.modeled),
                     rod.length)
    wr = node_wrench(d["wrench"], TASK.wrench_nodes, TASK.modeled)
    batch = RolloutWindows(d["positions"], wr, [(1, 0, end)], eta=2, horizon=H, inputs=inputs)[-1]
    assert len(batch) == 5
    batch = [b[None] for b in batch]
    module = SurrogateModule(model, horizon=H, wrench_fn=closed_loop_wrench(TASK))
    open_loop = SurrogateModule(model, horizon=H)
    with torch.no_grad():
        _, pred = module.rollout_loss(batch, H)
        _, pred_open = open_loop.rollout_loss(batch, H)
        scene = replace(TASK.base_scene(), duration=0.4)
        currents = TASK.variants(scene, 2, 39)["currents"]
        ref = closed_loop(model, TASK, rod, eMNS(), batch[0], lambda t: currents(t)[1], end - H, H, batch[3])
    gap_open = float((pred_open - ref).abs().max())
    assert gap_open > 2e-7  # the untrained model's own frames give another wrench than the data's (float32: 1e-8 m)
    assert float((pred - ref).abs().max()) < 0.05 * gap_open
    # the selection rollout (val_rollout_mm) of a model trained open loop runs in closed loop when given the
    # wrench model: it scores the open-loop module as the closed-loop one, on fresh variants with their own inputs
    from cmlearn.surrogate.training import RolloutSelection, SurrogateDataModule
    dm = SurrogateDataModule(d, eta=2, horizon=8, inputs=inputs, val_dataset=d, val_inputs=inputs)
    closed = RolloutSelection(dm).score(module)
    assert RolloutSelection(dm, wrench_fn=closed_loop_wrench(TASK)).score(open_loop) == pytest.approx(closed, rel=1e-6)
    assert RolloutSelection(dm).score(open_loop) != closed
    with pytest.raises(ValueError, match="val_inputs"):
        SurrogateDataModule(d, eta=2, horizon=8, inputs=inputs, val_dataset=d)
    with pytest.raises(ValueError, match="val_inputs"):
        SurrogateDataModule(d, eta=2, horizon=8, val_inputs=inputs)
    with pytest.raises(ValueError, match="inputs"):
        RolloutWindows(d["positions"], wr, [(1, 0, 20)], eta=2, horizon=8, inputs=inputs[:, :5])
    with pytest.raises(ValueError, match="regenerated currents"):
        closed_loop_inputs(TASK, {**d, "meta": {**d["meta"], "seed": 40}})


def test_closed_loop_wrench_stays_on_the_device_of_its_frames():
    """A run on a GPU (``--accelerator gpu``) selects its epochs in closed loop with frames and field samples on
    the GPU: the node forces come back on that device (here the meta device, shapes only; found on an H200, where
    they came back on the CPU), the same shape as on the CPU."""
    from cmlearn.data.magnetic import field_samples
    from cmlearn.surrogate.magnetic import closed_loop_wrench, initial_points
    scene = TASK.base_scene()
    pts = initial_points(TASK, scene).double()[None]
    I = torch.tensor([[2.0, -1.0, 0.5, -2.0, 1.0, 1.5]], dtype=torch.float64)
    samples = field_samples(TASK, scene.rod, eMNS(), pts, I)
    fn = closed_loop_wrench(TASK)
    cpu = fn(pts, samples)
    meta = fn(pts.to("meta"), samples.to("meta"))
    assert meta.device.type == "meta" and meta.shape == cpu.shape == (1, len(TASK.modeled), 3)
    assert float(cpu.abs().max()) > 1e-6


def test_profiles_and_rod_validate_their_input():
    with pytest.raises(ValueError, match="moves"):
        MinJerkCurrents(torch.zeros(2, 6), (0.0,), (0.1, 0.1))
    with pytest.raises(ValueError, match="holds"):
        MinJerkCurrents(torch.zeros(2, 6), (1.0,), (0.1,))
    with pytest.raises(ValueError, match="frequencies"):
        SinusoidCurrents(torch.ones(2, 6), (0.1, -0.1), torch.zeros(2, 6))
    with pytest.raises(ValueError, match="tol"):
        CoilField(eMNS(), lambda t: torch.zeros(6), tol=0.0)
    with pytest.raises(TypeError, match="currents must be a function of time .* got Tensor"):
        CoilField(eMNS(), torch.zeros(6))
    with pytest.raises(ValueError, match="rigid_factor"):
        replace(get_scene("magnetic_rod").rod, rigid_factor=0.5)
    p = MinJerkCurrents(torch.tensor([[0.0] * 6, [1.0] * 6]), (2.0,), (1.0, 1.0))
    assert float(p(1.0)[0]) == 0.0 and float(p(2.0)[0]) == pytest.approx(0.5) and float(p(9.0)[0]) == 1.0


def test_damping_ratios_and_time_step():
    from physics.scenes_magnetic_rod import modal_damping
    scene = get_scene("magnetic_rod")
    rod = scene.rod
    assert isinstance(rod, MagnetBlockRod)
    (f1, z1), _, (ft, zt), (f2, z2) = modal_damping(rod, 4)
    assert f1 == pytest.approx(4.15, abs=0.01) and z1 == pytest.approx(0.25, abs=0.005)
    assert zt == pytest.approx(0.48, abs=0.01) and z2 == pytest.approx(0.078, abs=0.005)
    assert scene.chosen["damping_ratio_mode1"] == 0.25 and rod.stable_time_step().dt_max > scene.dt


def test_shipped_checkpoint_reproduces_its_check_and_compare_prints_degrees(tmp_path, capsys):
    from cmlearn.compare import run_compare
    from cmlearn.surrogate import Surrogate
    from cmlearn.surrogate.evaluate import short_check
    path = ROOT / "checkpoints" / "magnetic_rod.pt"
    engine = Surrogate.load(path, task="magnetic_rod")
    chk = engine.meta["check"]
    got = short_check(engine, chk["scene"], chk["duration"])
    assert got["max_err_mm"] == pytest.approx(chk["max_err_mm"], rel=1e-3, abs=1e-3)
    assert got["max_orientation_err_deg"] == pytest.approx(chk["max_orientation_err_deg"], rel=1e-3, abs=1e-3)
    m = engine.meta["metrics"]
    assert set(m) == {"seen_last40", "magnetic_rod_heldout"}
    for case in m.values():
        assert set(case["orientation_deg"]) == {"one_step", "free_running", "cosserat"}
    import matplotlib
    backend = matplotlib.get_backend()
    matplotlib.use("svg")  # the caller's backend (a notebook's inline one), which the plots must leave alone
    try:
        summary = run_compare("magnetic_rod_heldout", duration=0.1, out=tmp_path, compile=True)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(backend)
    out = capsys.readouterr().out
    assert "distal magnet orientation: about x max" in out and "deg" in out and "static Cosserat" in out
    assert "hybrid distal magnet orientation" in out and "quasi-static hybrid" in out  # the shipped hybrid too
    assert set(summary["orientation_deg"]) == {"surrogate", "cosserat", "hybrid"}
    # compiled: the surrogate and the LGVI (its coil field's maps inputs of the program), the LGVI within round-off
    # of the eager reference (measured 2e-17 mm)
    assert summary["surrogate_compiled"] and summary["lgvi_compile_s"] > 0 and "LGVI compiled:" in out
    assert summary["lgvi_compiled_diff_mm"] < 1e-9 and summary["speedup_vs_compiled_lgvi"] > 0


def test_real_time_closed_loop_runs_in_the_tabulated_field_and_compiles():
    """The engine's closed loop (run_scene) computes the magnets' wrench in the coil field tabulated over the
    workspace: its rollout equals the evaluation's closed loop in the exact field (float32 frames; the field
    differs by 1e-9 relative), and compiled it equals the eager one to round-off over 0.4 s (before any
    snap-through, where float rounding decides when the rod snaps). A magnet outside the tabulated ball ends
    the rollout with the step, time and magnet named."""
    from cmlearn.surrogate import Surrogate, SurrogateDivergence
    from cmlearn.surrogate.magnetic import check_workspace, closed_loop_latency, field_table, run_scene
    engine = Surrogate.load(ROOT / "checkpoints" / "magnetic_rod.pt", task="magnetic_rod")
    scene = replace(get_scene("magnetic_rod_heldout"), duration=0.4)
    tab, wall = engine.run_scene(scene)
    exact, _ = run_scene(engine, scene, exact_field=True)
    assert tab.shape == exact.shape == (21, len(TASK.tracked), 3) and wall > 0
    moved = float((tab - tab[:1]).abs().max())
    assert moved > 1e-3 and float((tab - exact).abs().max()) < 1e-6
    assert closed_loop_latency(engine, scene, n=5, warmup=1) > 0
    engine.compile(gemm_templates=False)  # the shipped path's matrix products as library calls: half the compile time
    compiled, _ = engine.run_scene(scene)
    assert float((compiled - tab).abs().max()) < 1e-6
    # the whole printed profile stays in the ball (its distal magnet reaches 50.1 mm, beyond the 50 mm workspace)
    assert engine.run_scene(get_scene("magnetic_rod"))[0].shape[0] == 1201
    field = field_table(scene.loads.field.emns)
    assert field is field_table(scene.loads.field.emns)  # built once per eMNS
    away = tab.clone()
    away[3:] += torch.tensor([0.0, 0.0, -0.07])
    with pytest.raises(SurrogateDivergence, match=r"workspace at step 3 \(t = 0.060 s\): the proximal magnet"):
        check_workspace(TASK, scene.rod, field, away)


def test_planar_setup_moves_the_rod_in_its_plane_and_the_cosserat_model_follows():
    """The experiment's set-up (magnetic_rod_planar): in-plane fields at the field point, the rod steered in
    the x-z plane, the Cosserat baseline clamped the same way."""
    from cmlearn.surrogate.magnetic import base_pose
    from physics.scenes_magnetic_rod import PLANAR_FIELD_POINT, planar_field_basis, planar_setpoints
    task = get_task("magnetic_rod_planar")
    U = planar_field_basis()
    pt = torch.tensor([PLANAR_FIELD_POINT], dtype=torch.float64)
    B = torch.cat([eMNS().field(pt, u) for u in U])
    assert torch.allclose(B, torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64), atol=1e-6)  # per tesla
    assert torch.allclose(U[:, 1], U[:, 2]) and torch.allclose(U[:, 4], U[:, 5])  # mirror-symmetric currents
    # the printed profile's first move (to 6 mT at 30 deg) in 0.5 s instead of 1.5, then a 0.4 s hold: quasi-static
    # at the end (measured: 0.11 deg from the static Cosserat pose)
    base = get_scene("magnetic_rod_planar")
    a = math.radians(30)
    move = MinJerkCurrents(planar_setpoints([[0.0, 0.0], [6e-3 * math.cos(a), 6e-3 * math.sin(a)]]), (0.5,), (0.05, 0.4))
    scene = replace(base, duration=0.95, loads=replace(base.loads, field=CoilField(eMNS(), move)))
    pts, _, _ = rollout(task, scene)
    assert float(pts[..., 1].abs().max()) < 1e-9  # nothing leaves the x-z plane
    _, R, _ = magnet_frames(task, scene.rod, pts[[0, -1]].double())
    e3 = R[..., 2]
    angle = torch.rad2deg(torch.atan2(e3[..., 2], e3[..., 0]))  # magnet axes from +x towards +z
    assert -30 < float(angle[0, 1]) < -25 and -26 < float(angle[0, 0]) < -20  # sagging at rest
    assert float((angle[1] - angle[0]).min()) > 3.0  # lifted towards the field
    R_cos, _ = cosserat_orientations(scene.loads.field.currents, [0.0, scene.duration], eMNS(), **base_pose(scene))
    err = orientation_errors(R_cos, R).abs()
    assert float(err[..., [0, 2]].max()) < 1e-6 and float(err[..., 1].max()) < 0.5, err  # a wrong clamp: > 20 deg


def test_the_closed_loop_names_a_scene_of_the_other_clamp_a_duration_short_of_a_frame_and_no_steps_to_time():
    """The hanging rod's surrogate in the planar set-up's horizontal clamp ran on silently; a duration shorter than
    one 20 ms frame (of the closed loop or the LGVI) failed deep in torch.stack; ``n=0`` timed steps in an
    IndexError."""
    from cmlearn.surrogate import Surrogate
    from cmlearn.surrogate.magnetic import closed_loop_latency, run_scene
    engine = Surrogate.load(ROOT / "checkpoints" / "magnetic_rod.pt", task="magnetic_rod")
    planar = replace(get_scene("magnetic_rod_planar"), duration=0.1)
    with pytest.raises(ValueError, match="scene 'magnetic_rod_planar': its rod is clamped otherwise .* 'magnetic_rod'"):
        engine.run_scene(planar)
    with pytest.raises(ValueError, match="clamped otherwise"):
        run_scene(engine, planar, exact_field=True)
    scene = get_scene("magnetic_rod_heldout")
    with pytest.raises(ValueError, match=r"duration must be a time of at least one surrogate step \(0\.02 s.*got 0\.005"):
        engine.run_scene(scene, duration=0.005)
    with pytest.raises(ValueError, match="n must be an integer >= 1 .* got n=0"):
        closed_loop_latency(engine, scene, n=0)
    with pytest.raises(ValueError, match=r"duration must be a time of at least one surrogate step \(0\.02 s.*got 0\.005"):
        rollout(TASK, scene, duration=0.005)  # the LGVI's frames: failed in torch.stack too
