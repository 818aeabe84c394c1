"""On a CUDA device the physics and the surrogates give the CPU's answers (skipped where no GPU is seen).

Each test runs one computation on the CPU and on the GPU from the same inputs and compares them at
the dtype's precision: float64 solvers to ~1e-10 relative, float32 networks to ~1e-3 of their output
scale (cuDNN runs LSTMs in TF32 by torch's default; 1e-4 with it off), so that a tensor left on the wrong
device, a dropped dtype or a device-dependent branch fails.
"""
import math
import os
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from physics import LGVI, Loads, Magnet, SolverError, UniformField
from problems import pdms_rod

# CMLEARN_GPU_TEST_DEVICE=cpu runs the same code on the CPU twice: a check of the tests themselves
CUDA = torch.device(os.environ.get("CMLEARN_GPU_TEST_DEVICE", "cuda"))
pytestmark = [pytest.mark.gpu, pytest.mark.skipif(CUDA.type == "cuda" and not torch.cuda.is_available(),
                                                  reason="no CUDA device")]
D = torch.float64
ROOT = Path(__file__).resolve().parents[1]


def rel(a, b):
    return float((a.cpu() - b.cpu()).norm() / b.cpu().norm().clamp_min(1e-300))


# ------------------------------------------------------------------------------------------ LGVI
ROD = pdms_rod(10, magnets=(Magnet(s=0.06055, mass=9.6e-5, moment=(0.0, 0.0, 0.0109)),))


def swung_rods(dev):
    """A batch of four tip-magnet rods, each swung differently, under gravity in a field turning at 1 Hz."""
    w, Bm = 2 * math.pi, 0.01

    def field(t):
        return torch.stack((Bm * torch.sin(w * t), torch.zeros_like(t), Bm * torch.cos(w * t)))

    v = torch.zeros(4, ROD.n_nodes, 3, dtype=D)
    v[:, :, 0] = torch.linspace(-0.02, 0.02, 4, dtype=D)[:, None] * ROD.arclength / ROD.length
    sim = LGVI(ROD, dt=0.8 * ROD.stable_time_step().dt_max, device=dev,
               loads=Loads(gravity=(0.0, -9.81, 0.0), field=UniformField(field)))
    s0 = sim.initial_state()
    return sim, sim.initial_state(p=s0.p.expand(4, -1, -1), R=s0.R.expand(4, -1, -1, -1), v=v.to(dev))


def test_lgvi_batch_on_cuda_equals_cpu_with_gravity_and_a_rotating_field():
    out = {}
    for side, dev in (("cpu", torch.device("cpu")), ("gpu", CUDA)):
        sim, s0 = swung_rods(dev)
        out[side], traj = sim.simulate(s0, n_steps=400, record_every=100, record_R=True)
        assert traj.p.device.type == dev.type
    cpu, gpu = out["cpu"], out["gpu"]
    assert float((gpu.p.cpu() - cpu.p).abs().max()) < 1e-12 * ROD.length + 1e-14
    assert float((gpu.R.cpu() - cpu.R).abs().max()) < 1e-10
    assert float((cpu.p[:, -1] - cpu.p[:, 0]).norm(dim=-1).min()) > 0.5 * ROD.length  # it moved, not a rest state


def test_compiled_lgvi_rollout_on_cuda_equals_the_eager_cpu_steps():
    """``compiled_rollout`` on the device (``torch.compile``, Triton kernels; the CPU's program is the C++ one) from
    the swung batch of the test above: frames and end state equal the eager CPU steps, and no block is replayed."""
    sim, s0 = swung_rods(torch.device("cpu"))
    cpu, traj = sim.simulate(s0, n_steps=400, record_every=100)
    sim, s0 = swung_rods(CUDA)
    gpu, frames = sim.compiled_rollout(s0, n_steps=400, steps_per_call=4, record_every=25)
    assert frames.device.type == CUDA.type and sim.eager_blocks == 0
    assert frames.shape == traj.p.shape == (4, 5, ROD.n_nodes, 3)
    assert float((frames.cpu() - traj.p).abs().max()) < 1e-12 * ROD.length
    assert float((gpu.p.cpu() - cpu.p).abs().max()) < 1e-12 * ROD.length
    assert float((gpu.R.cpu() - cpu.R).abs().max()) < 1e-10
    assert abs(float(gpu.t) - float(cpu.t)) < 1e-12 and gpu.step == cpu.step == 400
    assert float((cpu.p[:, -1] - cpu.p[:, 0]).norm(dim=-1).min()) > 0.5 * ROD.length


def test_lgvi_float32_on_cuda_tracks_float64_and_divergence_names_the_step():
    rod = pdms_rod(8)
    g = (0.0, -9.81, 0.0)
    ref, _ = (sim := LGVI(rod, dt=0.8 * rod.stable_time_step().dt_max, loads=Loads(gravity=g))).simulate(
        sim.initial_state(), n_steps=1000, record_every=10**9)
    f32 = LGVI(rod, dt=sim.dt, loads=Loads(gravity=g), dtype=torch.float32, device=CUDA)
    st, _ = f32.simulate(f32.initial_state(), n_steps=1000, record_every=10**9)
    assert st.p.dtype == torch.float32 and st.p.device.type == CUDA.type
    sag = float(ref.p[-1, 1].abs())
    assert sag > 1e-3 and float((st.p.cpu().double() - ref.p).abs().max()) < 1e-3 * sag
    fast = LGVI(rod, dt=3 * rod.stable_time_step().dt_max, bc="free-free", stability="off", check_every=50,
                device=CUDA)
    s0 = fast.initial_state()
    v = torch.zeros(rod.n_nodes, 3, dtype=D, device=CUDA)
    v[:, 0] = torch.linspace(-1.0, 1.0, rod.n_nodes, dtype=D, device=CUDA)
    with pytest.raises(SolverError, match=r"step=\d+, time=.*node=\d+"):
        fast.simulate(fast.initial_state(p=s0.p, R=s0.R, v=v), n_steps=5000)


# ------------------------------------------------------------------------------- static Cosserat
def test_cosserat_shooting_on_cuda_equals_cpu_with_jacobian():
    from physics import CircularSection, Material
    from physics.cosserat import CosseratRod, MagnetDipole
    from physics.cosserat_shooting import CosseratSolver

    rod = CosseratRod.uniform(0.06, CircularSection(3e-3), Material(E=2e6, density=1100.0, nu=0.5), n_nodes=13,
                              magnets=(MagnetDipole(0.06, (0.0, 0.0, 2e-3), mass=2e-4),))
    Bs = torch.tensor([[0.0, 0.004, 0.001], [0.003, -0.002, 0.0], [0.0, 0.0, -0.005]], dtype=D)
    F = torch.tensor([[1e-4, 0, 0], [0, 0, 0], [0, -2e-4, 1e-4]], dtype=D)
    sol = {}
    for side, dev in (("cpu", torch.device("cpu")), ("gpu", CUDA)):
        s = CosseratSolver(rod, device=dev).solve(field=UniformField(Bs[:, None, :].to(dev)), tip_force=F.to(dev),
                                                  gravity=(0.0, -9.81, 0.0))
        assert s.y.device.type == dev.type
        sol[side] = s
    assert rel(sol["gpu"].y, sol["cpu"].y) < 1e-10
    assert rel(sol["gpu"].jacobian, sol["cpu"].jacobian) < 1e-8
    assert torch.equal(sol["gpu"].iterations.cpu(), sol["cpu"].iterations)


# ------------------------------------------------------------------------------------ magnetics
def test_dipoles_coils_and_emns_allocation_on_cuda_equal_cpu():
    from physics.magnetics import CircularLoop
    from physics.magnetics.emns import allocate_currents, six_coil_emns
    from physics.magnetics.sources import DipoleSet

    g = torch.Generator().manual_seed(3)
    pos = 0.01 * torch.randn(40, 3, generator=g, dtype=D)
    mom = torch.randn(40, 3, generator=g, dtype=D)
    pts = 0.1 + 0.05 * torch.randn(2, 5, 3, generator=g, dtype=D)
    mt = torch.randn(2, 5, 3, generator=g, dtype=D)
    cpu = DipoleSet(pos, mom).force_torque(pts, mt)
    gpu = DipoleSet(pos, mom).to(device=CUDA).force_torque(pts.to(CUDA), mt.to(CUDA))
    for a, b in zip(gpu, cpu):
        assert a.device.type == CUDA.type and rel(a, b) < 1e-12
    loop = CircularLoop(centre=(0.0, 0.0, 0.01), axis=(0.0, 0.3, 1.0), radius=0.02, current=2.0)
    for a, b in zip(loop.field_and_gradient(pts.to(CUDA)), loop.field_and_gradient(pts)):
        assert a.device.type == CUDA.type and rel(a, b) < 1e-12
    emns = six_coil_emns()
    x = torch.tensor([[0.01, -0.02, 0.015]], dtype=D)
    I = torch.linspace(-3.0, 3.0, 6, dtype=D)
    for a, b in zip(emns.field_and_gradient(x.to(CUDA), I.to(CUDA)), emns.field_and_gradient(x, I)):
        assert a.device.type == CUDA.type and rel(a, b) < 1e-12
    A = emns.actuation_matrix(x)
    target = A @ I
    cur_cpu, _ = allocate_currents(A, target)
    cur_gpu, _ = allocate_currents(A.to(CUDA), target.to(CUDA))
    assert rel(cur_gpu, cur_cpu) < 1e-9 and rel(cur_cpu, I) < 1e-8


# ------------------------------------------------------------------------------------ surrogates
def test_shipped_surrogate_rollout_on_cuda_equals_cpu():
    from cmlearn.data.windows import node_wrench
    from cmlearn.surrogate import Surrogate

    engine = Surrogate.load(ROOT / "checkpoints" / "semicircle_fast.pt")
    task, model, W = engine.task, engine.model, engine.eta + 1
    scene = replace(task.scene_by_name(task.scene), duration=0.05)
    rolled, _ = engine.run_scene(scene)  # CPU: frames (T, n_tracked, 3), the history to start from
    n = rolled.shape[0] - 1
    wk = node_wrench(engine.scene_wrench(scene, n), task.wrench_nodes, task.modeled)[None, W - 1:n]
    hist, ref = rolled[:W][None], rolled[0][None]
    with torch.no_grad():
        cpu = model.rollout(hist, wk, ref)
        gpu = model.to(CUDA).rollout(hist.to(CUDA), wk.to(CUDA), ref.to(CUDA))
    model.cpu()
    swing = float((cpu - rolled[None, :1]).abs().max())
    assert gpu.device.type == CUDA.type and swing > 1e-5
    assert float((gpu.cpu() - cpu).abs().max()) < 1e-3 * swing + 1e-7


def test_chord_projected_mirrored_rollout_on_cuda_equals_cpu():
    """The shipped mirrored model with the chord projection (its batched tridiagonal solves) on both devices, with
    every mirror image and with the one image the printed push's symmetry leaves."""
    from cmlearn.models import NodeLSTMSurrogate
    from cmlearn.surrogate import Surrogate

    engine = Surrogate.load(ROOT / "checkpoints" / "semicircle.pt")
    task = engine.task
    model = NodeLSTMSurrogate(replace(engine.model.config, chord_projection=True))
    model.load_state_dict(engine.model.state_dict())
    model.eval()
    scene = replace(task.scene_by_name(task.scene), duration=0.3)
    W = engine.scene_wrench(scene, 30)[None]
    ref = scene.initial_configuration()["p"][list(task.tracked)].float()[None]
    hist = ref[:, None].expand(-1, model.config.eta + 1, -1, -1)
    with torch.no_grad():
        cpu = model.rollout(hist, W, ref)
        gpu = model.to(CUDA).rollout(hist.to(CUDA), W.to(CUDA), ref.to(CUDA))
    model.cpu()
    chords = lambda x: (x[..., 1:, :] - x[..., :-1, :]).norm(dim=-1)  # noqa: E731
    swing = float((cpu - ref[:, None]).abs().max())
    assert gpu.device.type == CUDA.type and swing > 1e-4
    assert float((gpu.cpu() - cpu).abs().max()) < 1e-3 * swing
    assert float((chords(gpu.cpu()) - chords(ref)).abs().max()) < 2e-6
    # the printed push is symmetric under both mirrors: one image per step on the GPU, the same rollout
    axes = model.invariant_axes(hist, W)
    with torch.no_grad():
        one = model.to(CUDA).use_symmetry(axes).rollout(hist.to(CUDA), W.to(CUDA), ref.to(CUDA))
    model.use_symmetry(()).cpu()
    assert axes == (0, 2) and one.device.type == CUDA.type
    assert float((one.cpu() - cpu).abs().max()) < 1e-3 * swing


def test_loop_model_anchored_at_its_circle_on_cuda_equals_cpu():
    """The shipped Simulation I model, rest-anchored at the circle (``rest_shape``, a buffer from the config):
    the circle at rest stays put exactly on the GPU too, and a swing from the printed ellipse matches the CPU's."""
    from cmlearn.surrogate import Surrogate

    engine = Surrogate.load(ROOT / "checkpoints" / "ellipse.pt")
    task, model = engine.task, engine.model
    rest = task.model_config(rest_anchor=True).rest_shape
    assert model.config.rest_anchor and model.config.rest_shape == rest
    W = model.config.eta + 1
    ref = task.base_scene().initial_configuration()["p"][list(task.tracked)].float()[None]
    still = torch.tensor(rest)[None]
    wrench = torch.zeros(1, 40, len(task.modeled), 3)
    with torch.no_grad():
        cpu = model.rollout(ref[:, None].expand(-1, W, -1, -1), wrench, ref)
        model.to(CUDA)
        held = model.rollout(still[:, None].expand(-1, W, -1, -1).to(CUDA), wrench.to(CUDA), ref.to(CUDA))
        gpu = model.rollout(ref[:, None].expand(-1, W, -1, -1).to(CUDA), wrench.to(CUDA), ref.to(CUDA))
    model.cpu()
    assert held.device.type == CUDA.type and torch.equal(held.cpu(), still[:, None].expand_as(held.cpu()))
    swing = float((cpu - ref[:, None]).abs().max())
    assert swing > 1e-4 and float((gpu.cpu() - cpu).abs().max()) < 1e-3 * swing


def graph_rollouts(engine, scene, n: int, ref: torch.Tensor) -> dict:
    """``n`` steps of ``scene``'s forces from rest in ``ref`` (1, n_tracked, 3) through the engine's stepper: on the
    CPU, on the device eagerly and as CUDA-graph replays (two graphed steppers stepped in turn, which must not share
    buffers), each (n, n_tracked, 3) on the CPU."""
    W = engine.eta + 1
    wrench = engine.scene_wrench(scene, n)[:, None]
    hist = ref[:, None].expand(-1, W, -1, -1)
    out = {}
    with torch.no_grad():
        st = engine.stepper(hist, ref)
        out["cpu"] = torch.cat([st.step(w) for w in wrench])
        engine.model.to(CUDA)
        h, r, wd = hist.to(CUDA), ref.to(CUDA), wrench.to(CUDA)
        st = engine.stepper(h, r)
        out["eager"] = torch.cat([st.step(w) for w in wd]).cpu()
        if CUDA.type == "cuda":  # CMLEARN_GPU_TEST_DEVICE=cpu: no graph to record
            a, b = engine.stepper(h, r, graph=True), engine.stepper(h, r, graph=True)
            steps = [(a.step(w), b.step(w)) for w in wrench]  # from the host, the graph copies them in
            out["graph"], out["graph_b"] = (torch.cat(x).cpu() for x in zip(*steps))
    engine.model.cpu()
    return out


def test_graphed_steppers_on_cuda_equal_the_eager_steps():
    """``Surrogate.stepper(..., graph=True)`` with the shipped mirrored Simulation III model (all four mirror images),
    the same weights with the chord projection after each replay, and the Simulation I model anchored at its circle:
    one replay a step gives the device's eager steps (the same kernels, to 1e-6 of the swing) and so the CPU's to 1e-3
    of it; two graphed steppers keep apart; ``run_scene`` steps on the model's device, graphed or not; the loop at rest
    in its circle stays there exactly."""
    from cmlearn.models import NodeLSTMSurrogate
    from cmlearn.surrogate import Surrogate

    engine = Surrogate.load(ROOT / "checkpoints" / "semicircle.pt")
    task = engine.task
    chords = Surrogate(NodeLSTMSurrogate(replace(engine.model.config, chord_projection=True)), engine.meta)
    chords.model.load_state_dict(engine.model.state_dict())
    chords.model.freeze_features()
    scene = replace(task.scene_by_name(task.scene), duration=0.3)
    ref = scene.initial_configuration()["p"][list(task.tracked)].float()[None]
    loop = Surrogate.load(ROOT / "checkpoints" / "ellipse.pt")
    circle = torch.tensor(loop.model.config.rest_shape)[None]
    loop_scene = loop.task.base_scene()
    loop_ref = loop_scene.initial_configuration()["p"][list(loop.task.tracked)].float()[None]
    for eng, sc, r, n in ((engine, scene, ref, 30), (chords, scene, ref, 30), (loop, loop_scene, loop_ref, 40)):
        out = graph_rollouts(eng, sc, n, r)
        swing = float((out["cpu"] - r).abs().max())
        assert swing > 1e-4
        assert float((out["eager"] - out["cpu"]).abs().max()) < 1e-3 * swing
        if CUDA.type == "cuda":
            assert float((out["graph"] - out["eager"]).abs().max()) < 1e-6 * swing
            assert torch.equal(out["graph"], out["graph_b"])
    # run_scene on the model's device (the printed push: one mirror image), graphed and eager
    cpu, _ = engine.run_scene(scene)
    engine.model.to(CUDA)
    eager, _ = engine.run_scene(scene)
    graphed, wall = engine.run_scene(scene, graph=CUDA.type == "cuda")
    engine.model.cpu()
    swing = float((cpu - cpu[:1]).abs().max())
    assert eager.device.type == graphed.device.type == CUDA.type and wall > 0 and swing > 1e-4
    assert float((eager.cpu() - cpu).abs().max()) < 1e-3 * swing
    assert float((graphed - eager).abs().max()) < 1e-6 * swing
    if CUDA.type == "cuda":
        held = graph_rollouts(loop, replace(loop_scene, loads=replace(loop_scene.loads, force=None)), 20, circle)
        assert torch.equal(held["graph"], circle.expand_as(held["graph"]))
        with pytest.raises(ValueError, match="graph: a CUDA graph needs the model"):
            engine.stepper(ref[:, None].expand(-1, 3, -1, -1), ref, graph=True)
        engine.model.to(CUDA)
        st = engine.stepper(ref[:, None].expand(-1, 3, -1, -1).to(CUDA), ref.to(CUDA), graph=True)
        with pytest.raises(ValueError, match=r"wrench must be torch.float32 \(the model's dtype\), got torch.float64"):
            st.step(torch.zeros(1, len(task.modeled), 3, dtype=D, device=CUDA))
        engine.model.cpu()


def test_quasistatic_hybrid_rollout_with_a_fold_clock_on_cuda_equals_cpu():
    """The magnetic rod's hybrid along the held-out profile's static track (solved once on the CPU) through its first
    snap-through (frame 108): the shipped correction, and a model that reads the fold clock (random weights), run from
    rest on both devices; the clock itself, counted on the device, equals the CPU's. With TF32 off the device's
    float32 rollout equals the CPU's to 1e-4 of its swing; with torch's default (cuDNN's LSTM in TF32) to 1e-3."""
    from cmlearn.data.quasistatic import fold_clock, static_state
    from cmlearn.models.quasistatic import QuasiStaticCorrection
    from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate, rollout_from, scene_track

    engine = QuasiStaticSurrogate.load(ROOT / "checkpoints" / "magnetic_rod_quasistatic.pt", task="magnetic_rod")
    scene = replace(engine.task.scene_by_name("magnetic_rod_heldout"), duration=2.3)
    track = scene_track(engine.task, scene, 116)
    s = static_state(track.P, track.R, engine.rest, track.margin)
    d = torch.zeros(s.shape[0], 12, dtype=D)
    tau = {side: fold_clock(s.to(dev), 6.0) for side, dev in (("cpu", torch.device("cpu")), ("gpu", CUDA))}
    assert tau["gpu"].device.type == CUDA.type and torch.allclose(tau["gpu"].cpu(), tau["cpu"], atol=1e-12)
    assert float(tau["cpu"][100]) == 6.0 and float(tau["cpu"][110]) < 6.0  # the clock restarted at the fold
    torch.manual_seed(1)
    clocked = QuasiStaticCorrection(replace(engine.model.config, hidden=8, width=16, fold_clock=6.0,
                                            margin=True)).eval()
    for p in clocked.parameters():
        torch.nn.init.normal_(p, std=0.3)
    for model in (engine.model, clocked):
        cpu = rollout_from(model, s, d, 0)
        swing = float(cpu.abs().max())
        assert swing > 0.1
        for tf32, tol in ((False, 1e-4), (True, 1e-3)):
            with torch.backends.cudnn.flags(enabled=True, allow_tf32=tf32):
                gpu = rollout_from(model.to(CUDA), s.to(CUDA), d.to(CUDA), 0)
            model.cpu()
            assert gpu.device.type == CUDA.type
            assert float((gpu.cpu() - cpu).abs().max()) < tol * swing + 1e-6, (tf32, swing)


# the magnetic rod selects its epochs in closed loop: its wrench model runs on the GPU too (before 2026-11-29 the
# node forces came back on the CPU and the run stopped at its first validation)
@pytest.mark.parametrize("task, flags", [("semicircle", ["--rest-anchor", "--mirror", "zx"]),
                                         ("magnetic_rod", ["--mix", "2", "--mix-width", "8"])])
def test_train_surrogate_quick_on_gpu(tmp_path, task, flags):
    pytest.importorskip("lightning")
    sys.path.insert(0, str(ROOT / "scripts"))
    import train_surrogate
    from cmlearn.surrogate import Surrogate

    out = tmp_path / f"{task}_gpu.pt"
    acc = "gpu" if CUDA.type == "cuda" else "cpu"
    meta = train_surrogate.main(["--task", task, "--quick", "--accelerator", acc, *flags,
                                 "--data-dir", str(tmp_path / "data"), "--out", str(out),
                                 "--log-dir", str(tmp_path / "logs")])
    assert out.exists() and meta["args"]["accelerator"] == acc
    assert "diverged" not in meta["check"]
    eng = Surrogate.load(out)
    assert next(eng.model.parameters()).device.type == "cpu"
