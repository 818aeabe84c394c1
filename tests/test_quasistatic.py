"""The quasi-static hybrid surrogate of the magnetic rod: the static track's coordinates, the correction's
linear fit and rollout, Lightning training, the checkpoint and the shipped model's recorded check."""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pytest
import torch

from cmlearn.data.quasistatic import StaticTrack, compose, deviation, static_state
from cmlearn.io import CheckpointError
from cmlearn.models.quasistatic import QuasiStaticConfig, QuasiStaticCorrection
from cmlearn.surrogate import load_checkpoint, surrogate_checkpoints
from cmlearn.surrogate.magnetic import orientation_errors
from cmlearn.surrogate.quasistatic import (QuasiStaticSurrogate, deviation_errors, profile_scores, rollout_from,
                                           save_quasistatic, short_check)
from physics.lie import so3_exp

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "checkpoints" / "magnetic_rod_quasistatic.pt"


def _rotations(g, *shape):
    return so3_exp(torch.randn(*shape, 3, generator=g, dtype=torch.float64) * 0.8)


def test_deviation_and_compose_invert_each_other_and_give_the_orientation_errors():
    g = torch.Generator().manual_seed(0)
    P, c = torch.randn(5, 2, 3, generator=g, dtype=torch.float64) * 0.03, torch.randn(5, 2, 3, generator=g,
                                                                                          dtype=torch.float64) * 0.03
    Rs, R = _rotations(g, 5, 2), _rotations(g, 5, 2)
    d = deviation(c, R, P, Rs)
    c2, R2 = compose(d, P, Rs)
    assert torch.allclose(c2, c, atol=1e-15) and torch.allclose(R2, R, atol=1e-12)
    # millimetres and degrees: a 1 mm shift and a 2 deg turn about z read as such
    d1 = deviation(P + torch.tensor([1e-3, 0, 0], dtype=torch.float64), so3_exp(
        torch.tensor([0, 0, math.radians(2.0)], dtype=torch.float64)) @ Rs, P, Rs)
    assert torch.allclose(d1[:, 0], torch.ones(5, dtype=torch.float64))
    assert torch.allclose(d1[:, 8], torch.full((5,), 2.0, dtype=torch.float64))
    # the errors between two deviations from one static rod are those of the composed rotations
    d_other = deviation(c, _rotations(g, 5, 2), P, Rs)
    assert torch.allclose(deviation_errors(d_other, d), orientation_errors(compose(d_other, P, Rs)[1], R), atol=1e-9)
    assert deviation_errors(d, d).abs().max() < 1e-9
    # the static state is relative to the rest rotations: zero turn at rest
    assert static_state(P, Rs, Rs[0])[0, 6:].abs().max() < 1e-12


def _linear_system(cfg, V=4, T=120, seed=0, kick=0.0, bias=0.0):
    """Static tracks of random smooth motions and deviations from a known stable linear step, plus random kicks
    of size ``kick`` (without them the deviations are linear in the inputs and L is not identifiable) and a
    term ``bias |s(k+1) - s(k)|`` (no linear map has it)."""
    g = torch.Generator().manual_seed(seed)
    s = 3 * torch.sin(torch.cumsum(torch.randn(V, T, 12, generator=g, dtype=torch.float64) * 0.4, 1))  # bounded
    s[:, 1:4] = s[:, :1]  # at rest at first, as a profile from zero current
    n_reg = 12 * (cfg.eta + 1 + cfg.increments)
    L = torch.zeros(n_reg, 12, dtype=torch.float64)
    L[12 * cfg.eta:12 * (cfg.eta + 1)] = 0.6 * torch.eye(12)  # d(k) -> d(k+1): a decaying lag
    L[12 * cfg.eta - 12:12 * cfg.eta] = 0.2 * torch.eye(12)  # d(k-1)
    L[-12:] = -0.5 * torch.eye(12)  # the newest static increment drives it
    d = torch.zeros(V, T, 12, dtype=torch.float64)
    for k in range(max(cfg.eta, cfg.increments - 1), T - 1):
        x = torch.cat([d[:, k - cfg.eta:k + 1].flatten(1), (s[:, k + 2 - cfg.increments:k + 2] -
                                                           s[:, k + 1 - cfg.increments:k + 1]).flatten(1)], -1)
        d[:, k + 1] = (x @ L + kick * torch.randn(V, 12, generator=g, dtype=torch.float64)
                       + bias * (s[:, k + 1] - s[:, k]).abs())
    return s, d, L


def test_the_linear_fit_recovers_a_known_step_and_the_rollout_follows_it():
    cfg = QuasiStaticConfig(eta=2, increments=3, hidden=4, width=8)
    model = QuasiStaticCorrection(cfg).double()
    s, d, L = _linear_system(cfg, V=8, T=600, kick=0.3)
    ranges = [(v, 0, s.shape[1] - 1) for v in range(s.shape[0])]
    kick_share = 0.3 / float(d[:, 3:].pow(2).mean().sqrt())  # what the residual cannot explain
    assert model.fit_linear(d, s, ranges) == pytest.approx(kick_share, rel=0.05)
    assert (model.linear - L).abs().max() < 0.06  # of coefficients 0.2, 0.6 and -0.5
    s, d, L = _linear_system(cfg)
    assert model.fit_linear(d, s, [(v, 0, s.shape[1] - 1) for v in range(s.shape[0])]) < 1e-9
    # the network starts at zero: free-running from the true history at frame 10 reproduces the trajectory,
    # and so does the batched rollout from rest (zero history) of a system that starts at rest
    model = model.float()
    dev = rollout_from(model, s, d, 10)
    assert torch.allclose(dev, d[:, 11:], atol=1e-3 * d.abs().max())
    assert profile_scores(model, s, d).max() < 1e-2
    # a step is the forward call on the shifted windows
    c = cfg
    one = model(d[:, 10 - c.eta:11].float(), s[:, 11 - c.increments:12].float())
    assert torch.allclose(one.double(), dev[:, 0], atol=1e-6)


def test_the_config_and_the_step_name_bad_input():
    for kw, msg in (({"eta": -1}, "eta"), ({"increments": 0}, "increments"), ({"dev_scale": (1.0,) * 11}, "dev_scale"),
                    ({"state_scale": (0.0,) * 12}, "state_scale")):
        with pytest.raises(ValueError, match=msg):
            QuasiStaticConfig(**kw)
    model = QuasiStaticCorrection(QuasiStaticConfig(eta=2, increments=3))
    with pytest.raises(ValueError, match="dev must be"):
        model(torch.zeros(2, 2, 12), torch.zeros(2, 4, 12))
    with pytest.raises(ValueError, match="static must be"):
        model(torch.zeros(2, 3, 12), torch.zeros(2, 3, 12))
    with pytest.raises(ValueError, match="no step with a full history"):
        model.fit_linear(torch.zeros(1, 3, 12), torch.zeros(1, 3, 12), [(0, 0, 2)])


def test_lightning_training_lowers_the_rollout_loss_and_the_checkpoint_round_trips(tmp_path):
    import lightning as L

    from cmlearn.surrogate.quasistatic_training import QuasiStaticDataModule, QuasiStaticModule, fit_scales
    torch.manual_seed(0)
    cfg = QuasiStaticConfig(eta=2, increments=3, hidden=8, width=16)
    s, d, _ = _linear_system(cfg, V=6, T=100, bias=1.0)
    train = [(v, 0, 99) for v in range(5)]
    cfg = QuasiStaticConfig(eta=2, increments=3, hidden=8, width=16, **fit_scales(s, d, train))
    model = QuasiStaticCorrection(cfg)
    model.fit_linear(d, s, train)
    dm = QuasiStaticDataModule(s, d, cfg.eta, cfg.increments, horizon=8, val_horizon=16, batch_size=32)
    module = QuasiStaticModule(model, lr=1e-2, epochs=20)
    trainer = L.Trainer(max_epochs=20, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        limit_train_batches=20, num_sanity_val_steps=0)
    everything = next(iter(torch.utils.data.DataLoader(dm.train_set, batch_size=len(dm.train_set))))
    before = float(module.loss(everything).detach())
    trainer.fit(module, datamodule=dm)
    after = float(module.loss(everything).detach())  # the rollout loss over every training window
    assert after < 0.8 * before, (before, after)
    dev, st, target = everything  # the squared loss: the mean square of the same scaled errors
    e = (model.rollout(dev, st) - target) / model.dev_scale
    l2 = QuasiStaticModule(model, loss="l2")
    torch.testing.assert_close(l2.loss(everything), e.pow(2).mean())
    torch.testing.assert_close(module.loss(everything), e.abs().mean())
    with pytest.raises(ValueError, match="loss must be one of"):
        QuasiStaticModule(model, loss="huber")
    path = save_quasistatic(tmp_path / "q.pt", model.eval(), {"task": "magnetic_rod", "command": "test"})
    engine = QuasiStaticSurrogate.load(path, task="magnetic_rod")
    assert torch.equal(rollout_from(engine.model, s, d, 5), rollout_from(model, s, d, 5))
    assert json.loads(path.with_suffix(".json").read_text())["format"] == "cmlearn-quasistatic/1"
    # not a node-surrogate checkpoint, nor listed with them
    assert path not in surrogate_checkpoints(tmp_path)
    with pytest.raises(CheckpointError, match="not a cmlearn-surrogate/1 checkpoint"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match="not 'semicircle'"):
        QuasiStaticSurrogate.load(path, task="semicircle")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(path.read_bytes()[:200])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        QuasiStaticSurrogate.load(bad)
    with pytest.raises(CheckpointError, match="not a cmlearn-quasistatic/1 checkpoint"):
        QuasiStaticSurrogate.load(ROOT / "checkpoints" / "magnetic_rod.pt")


@pytest.mark.skipif(not SHIPPED.is_file(), reason="no shipped quasi-static checkpoint")
def test_the_shipped_hybrid_reproduces_its_recorded_check_and_beats_the_static_rod():
    torch.set_num_threads(1)
    engine = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod")
    rec = engine.meta["check"]
    got = short_check(engine, rec["duration"])
    for key in ("sum_mean_deg", "max_deg", "static_sum_mean_deg"):
        assert got[key] == pytest.approx(rec[key], rel=1e-3, abs=1e-3), key
    metrics = dict(engine.meta["metrics"])
    fresh = metrics.pop("fresh")  # profiles of another seed, from rest: the median sum of six means
    assert fresh["profiles"] == 8 and fresh["hybrid"]["median"] < 0.6 * fresh["static"]["median"]
    for case, res in metrics.items():  # the recorded figures the README prints
        assert res["hybrid"]["sum_mean_deg"] < 0.6 * res["static"]["sum_mean_deg"], case
    from dataclasses import replace

    from cmlearn.data import get_task
    with pytest.raises(ValueError, match="scene 'semicircle': its rod .* task 'magnetic_rod'"):
        engine.run(get_task("semicircle").base_scene())
    scene = get_task("magnetic_rod").base_scene()
    with pytest.raises(ValueError, match="has no coil field"):
        engine.stepper(replace(scene, loads=replace(scene.loads, field=None)))
    # the LGVI's node positions (11 of them, as many as the tracked points) ran to NaN frames; 40 frames for a
    # 6-frame scene ran past its duration; a given track was ignored and solved again
    from cmlearn.data.magnetic import tracked_points
    short = replace(scene, duration=0.1)
    cfg = short.initial_configuration()
    good = tracked_points(engine.task, short.rod, cfg["p"], cfg["R"]).expand(6, -1, -1)
    with pytest.raises(ValueError, match=r"positions are not tracked points .* off its 20 mm lever arm"):
        engine.run(short, positions=cfg["p"].expand(6, -1, -1), start=2)
    with pytest.raises(ValueError, match=r"positions must hold the scene's 6 frames .*got \(40, 11, 3\)"):
        engine.run(short, positions=good[:1].expand(40, -1, -1), start=2)
    with pytest.raises(ValueError, match="track must be the scene's StaticTrack at its 6 frames"):
        engine.run(short, positions=good, start=2, track="a track")
    cp, Rp, P, R = engine.run(short, positions=good, start=2)
    again = engine.run(short, positions=good, start=2, track=StaticTrack(P.new_zeros(6, 2, 3), R[:1].expand(6, -1, -1, -1),
                                                                        torch.ones(6, dtype=P.dtype), 0.0))
    assert cp.shape == (3, 2, 3) and bool(torch.isfinite(cp).all())
    assert float((again[2] - 0).abs().max()) == 0.0  # the given track is the one composed with


def test_the_field_hook_gives_a_diverging_trial_position_a_nan_field():
    """A shooting step that diverges puts nodes at non-finite or absurd positions (1e239 m was seen at 400 A): they
    get a NaN field, which the solver rejects, instead of the coil model's overflow error; the rest are exact."""
    from cmlearn.data.quasistatic import FAR, field_hook
    from cmlearn.data.tasks import get_task
    emns = get_task("magnetic_rod").base_scene().loads.field.emns
    I = torch.tensor([3.0, -1.0, 0.5, 0.0, 2.0, -4.0], dtype=torch.float64)
    x = torch.tensor([[0.01, 0.0, -0.02], [math.nan, 0.0, 0.0], [1e239, 0.0, 0.0], [0.0, -2 * FAR, 0.0]],
                     dtype=torch.float64)
    B, dB = field_hook(emns, I)(0.0, x)
    B0, dB0 = emns.field_and_gradient(x[:1], I)
    assert torch.equal(B[:1], B0) and torch.equal(dB[:1], dB0)
    assert B[1:].isnan().all() and dB[1:].isnan().all()
    with pytest.raises(ValueError, match="too far"):
        emns.field_and_gradient(x[2:3], I)


def test_the_stability_margin_falls_to_zero_at_a_snap_through():
    """The held-out profile's first snap-through (frame 108, 2.16 s): the smallest singular value of the static
    solution's shooting Jacobian falls like the square root of the distance to the fold (its square about
    linearly), to a fraction of its value, and recovers on the new branch, where the magnets have turned."""
    from cmlearn.data.quasistatic import static_track
    from cmlearn.data.tasks import get_task
    from cmlearn.surrogate.magnetic import base_pose
    torch.set_num_threads(1)
    scene = get_task("magnetic_rod").scene_by_name("magnetic_rod_heldout")
    tr = static_track(scene.loads.field.currents, scene.loads.field.emns, [0.02 * k for k in range(111)],
                      **base_pose(scene))
    m = tr.margin
    jump = int((tr.R[1:] - tr.R[:-1]).abs().amax((-1, -2, -3)).argmax()) + 1  # the frame the track jumps to
    assert jump == 108
    before = m[jump - 8:jump]
    assert bool((before[1:] < before[:-1]).all()) and m[jump - 1] < 0.3 * m[:jump - 20].median()
    sq = before.pow(2)  # about linear in time towards the fold: equal steps within a factor of two
    steps = sq[:-1] - sq[1:]
    assert steps.max() < 2.5 * steps.min()
    assert m[jump] > 2 * m[jump - 1]


def test_the_margin_option_reads_the_thirteenth_column_and_keeps_the_rest_anchor():
    torch.manual_seed(0)
    cfg = QuasiStaticConfig(eta=2, increments=3, hidden=8, width=16, margin=True, margin_scale=0.3, rest_margin=0.7,
                            rest_state=tuple(torch.randn(12).tolist()))
    model = QuasiStaticCorrection(cfg)
    for p in model.parameters():  # a trained network is not zero
        torch.nn.init.normal_(p, std=0.3)
    rest = torch.tensor(cfg.rest_state + (cfg.rest_margin,)).expand(1, 4, 13)
    assert model(torch.zeros(1, 3, 12), rest).abs().max() == 0  # at rest it stays at rest
    lower = rest.clone()
    lower[..., 12] = 0.1  # near a fold
    assert model(torch.zeros(1, 3, 12), lower).abs().max() > 1e-3
    with pytest.raises(ValueError, match="static must be"):
        model(torch.zeros(1, 3, 12), rest[..., :12])
    with pytest.raises(ValueError, match="margin_scale"):
        QuasiStaticConfig(margin_scale=0.0)


def test_the_fold_clock_restarts_at_a_jump_from_the_margins_before_it_and_the_option_reads_a_fourteenth_column():
    from cmlearn.data.quasistatic import fold_clock, with_fold_clock
    s = torch.zeros(2, 12, 13, dtype=torch.float64)
    s[..., 12] = torch.tensor([1.0, 1.0, 0.9, 0.5, 0.3, 0.8, 0.9, 1.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    s[0, 5:, 7] = 30.0  # profile 0: the distal magnet turns by 30 deg between frames 4 and 5
    s[1, 5:, 7] = 9.0  # profile 1: by less than a fold's jump
    tau = fold_clock(s, 5.0)
    # the squared margin falls 0.25 -> 0.09 from frame 3 to 4: zero at 4 + 0.09 / 0.16 = 4.5625
    want = [5.0] * 5 + [0.4375, 1.4375, 2.4375, 3.4375, 4.4375, 5.0, 5.0]
    torch.testing.assert_close(tau[0], torch.tensor(want, dtype=torch.float64))
    assert bool((tau[1] == 5.0).all())
    s[0, 3, 12] = 0.2  # margins that do not fall before the jump: the fold halfway through the frame
    assert float(fold_clock(s, 5.0)[0, 5]) == 0.5
    s[0, 8:, 7] = float("nan")  # a track that ended: no jump, the clock counts on
    assert fold_clock(s, 5.0)[0, 8:].tolist() == [3.5, 4.5, 5.0, 5.0]
    assert with_fold_clock(s, 5.0).shape == (2, 12, 14)
    with pytest.raises(ValueError, match="cap"):
        fold_clock(s, 0.0)
    # the model reads the clock of frame k+1 (the 14th column), and at its cap at rest it stays at rest
    torch.manual_seed(0)
    cfg = QuasiStaticConfig(eta=2, increments=3, hidden=8, width=16, margin=True, margin_scale=0.3, rest_margin=0.7,
                            rest_state=tuple(torch.randn(12).tolist()), fold_clock=5.0)
    model = QuasiStaticCorrection(cfg)
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.3)
    rest = torch.tensor(cfg.rest_state + (cfg.rest_margin, 5.0)).expand(1, 4, 14).clone()
    assert model(torch.zeros(1, 3, 12), rest).abs().max() == 0
    after = rest.clone()
    after[:, :-1, 13] = 0.0  # the older frames' clocks are not read
    assert model(torch.zeros(1, 3, 12), after).abs().max() == 0
    after[:, -1, 13] = 0.5  # half a frame after a fold
    assert model(torch.zeros(1, 3, 12), after).abs().max() > 1e-3
    with pytest.raises(ValueError, match=r"static must be \(1, 4, 14\)"):
        model(torch.zeros(1, 3, 12), rest[..., :13])
    with pytest.raises(ValueError, match="fold_clock needs margin"):
        QuasiStaticConfig(fold_clock=5.0)
    with pytest.raises(ValueError, match="fold_clock must be"):
        QuasiStaticConfig(margin=True, fold_clock=-1.0)


def test_a_warm_step_too_far_is_split_in_time_a_fold_restarts_its_problem_cold_and_a_failure_names_it():
    import cmlearn.data.quasistatic as q
    from physics.cosserat_shooting import StaticSolution
    from physics.errors import SolverError

    asked = []

    def currents(t):
        asked.append(float(t))
        return torch.zeros(2, 6, dtype=torch.float64)

    def solution(t, ok):
        return StaticSolution(torch.zeros(1), torch.full((2, 1, 1), t), torch.zeros(2, 6), ok, torch.zeros(2),
                              (~ok).double(), torch.zeros(2, 6, 6))

    class Folds:  # problem 0 reaches 0.3 s past its warm start; problem 1's branch ends at 0.6 s
        def __init__(self, cold: bool):
            self.cold, self.cold_at = cold, []

        def solve(self, solver, field, init=None, load_steps=1, raise_on_failure=True, **pose):
            t = asked[-1]
            if init is None:
                self.cold_at.append(t)
                return solution(t, torch.tensor([self.cold, self.cold]))
            t0 = init.y[:, 0, 0]
            return solution(t, torch.stack([t - t0[0] <= 0.3, ~((t0[1] < 0.6) & (t >= 0.6))]))

    f = Folds(cold=True)
    start, no_field = solution(0.0, torch.ones(2, dtype=torch.bool)), lambda I: None  # noqa: E731
    out = q._warm_step(f, None, no_field, currents, {}, start, 0.0, 1.0, 4)
    assert out.converged.all() and out.y.flatten().tolist() == [1.0, 1.0]
    assert f.cold_at == [0.625]  # one problem restarted cold, once, in the sub-step of 1/16 that crosses the fold
    assert asked[:3] == [1.0, 0.5, 0.25]  # halved until within the warm start's reach
    with pytest.raises(SolverError, match=r"from t = 0\.5625 s in 16 warm-started sub-steps nor from the unloaded "
                                          r"rod.*time=0\.625, node=1"):
        q._warm_step(Folds(cold=False), None, no_field, currents, {}, start, 0.0, 1.0, 4)


def test_truncate_ends_a_profile_whose_track_fails_and_its_training_ranges_stop_before_it(monkeypatch):
    import cmlearn.data.quasistatic as q
    from cmlearn.data.tasks import get_task
    from cmlearn.surrogate.magnetic import base_pose
    from cmlearn.surrogate.quasistatic_training import track_ends, training_ranges
    from physics.errors import SolverError
    torch.set_num_threads(1)
    scene = get_task("magnetic_rod").scene_by_name("magnetic_rod_heldout")
    own = scene.loads.field.currents
    currents = lambda t: torch.stack([own(t), 2 * own(t)])  # noqa: E731 - two profiles, one batch
    times = [0.02 * k for k in range(6)]
    whole = q.static_track(currents, scene.loads.field.emns, times, **base_pose(scene))
    warm = q._warm_step

    def fold(sc, solver, field_of, cur, pose, sol, t_prev, t, halvings):  # profile 1 finds no equilibrium from 0.05 s
        if t >= 0.05 and bool(cur(torch.tensor(t)).abs()[1].sum() > 0):
            raise SolverError("no equilibrium", time=t, node=1)
        return warm(sc, solver, field_of, cur, pose, sol, t_prev, t, halvings)
    monkeypatch.setattr(q, "_warm_step", fold)
    with pytest.raises(SolverError, match="node=1"):
        q.static_track(currents, scene.loads.field.emns, times, **base_pose(scene))
    with pytest.warns(UserWarning, match=r"profile 1 has no equilibrium at t = 0\.06 s; its track ends there"):
        cut = q.static_track(currents, scene.loads.field.emns, times, truncate=True, **base_pose(scene))
    assert torch.equal(cut.P[0], whole.P[0]) and torch.equal(cut.margin[0], whole.margin[0])
    assert torch.equal(cut.P[1, :3], whole.P[1, :3]) and cut.P[1, 3:].isnan().all() and cut.R[1, 3:].isnan().all()
    s = torch.zeros(4, 11, 13)
    s[2, 7:] = math.nan  # a training profile whose track ended at frame 7
    s[3, 0:] = math.nan  # the validation profile's ended at once
    r = training_ranges(s)
    assert track_ends(s) == {2: 7, 3: 0}
    assert r["train"] == [(0, 0, 6), (1, 0, 10), (2, 0, 6)] and r["val"] == [] and r["test"] == [(0, 6, 10)]


def test_the_real_time_stepper_follows_the_offline_rollout_and_names_bad_input_and_a_failed_step(monkeypatch):
    import cmlearn.surrogate.quasistatic_stepper as qs
    from dataclasses import replace
    from physics.errors import SolverError
    from physics.programs import compile_program
    torch.set_num_threads(1)
    engine = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod")
    scene = replace(engine.task.scene_by_name("magnetic_rod_heldout"), duration=0.6)
    cp, Rp, _, Rs = engine.run(scene)
    currents = scene.loads.field.currents
    its = {}
    for predictor, chord in ((False, False), (True, False), (True, True)):
        st = engine.stepper(scene, predictor=predictor, chord=chord)
        frames, its[predictor, chord] = [], 0
        for k in range(1, 31):
            frames.append(st.step(currents(torch.tensor(0.02 * k, dtype=torch.float64))))
            its[predictor, chord] += st.iterations
        c, R = torch.stack([f[0] for f in frames]), torch.stack([f[1] for f in frames])
        assert (c - cp).abs().max() < 1e-8 and orientation_errors(R, Rp).abs().max() < 1e-4  # m, deg
    assert orientation_errors(Rp, Rs).abs().max() > 0.3  # the correction moves the magnets off the static rod
    assert its[True, False] < its[False, False]  # the secant predictor saves Levenberg-Marquardt iterations
    assert st.k == 30 and st.static.shape == (1, engine.model.config.increments + 1, 13)
    # the frame's program traces (the compiled stepper compiles it) and equals the eager frame
    args = (st.solution.y.contiguous(), st.solution.jacobian.contiguous(), st.dev, st.static)
    prog = compile_program(st._frame, args, direct=True)
    for a, b in zip(prog(*args), st._frame(*args)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    # where every try from the predicted start fails (the stages, then the solver's escalation), the frame is
    # solved from the last solution (the static track's recovery)
    Scene = type(st.sc)
    solve, calls, tries = Scene.solve, [], len(qs.STAGES) + 1
    (its, frame_solve), = st._frame_solves.items()  # the first stage's solve (physics.cosserat_frames)

    def failed(out, init):
        calls.append(init)
        return out._replace(converged=torch.zeros_like(out.converged)) if len(calls) <= tries else out

    def first_fail(self, *a, **k):
        return failed(solve(self, *a, **k), k.get("init"))
    last, I = st.solution, currents(torch.tensor(0.62, dtype=torch.float64))
    monkeypatch.setattr(Scene, "solve", first_fail)
    monkeypatch.setitem(st._frame_solves, its, lambda field, init, chord: failed(frame_solve(field, init, chord), init))
    got = st.solve(I)
    monkeypatch.setattr(Scene, "solve", solve)
    monkeypatch.setitem(st._frame_solves, its, frame_solve)
    assert len(calls) == tries + 1 and calls[tries] is last and bool(got.converged)  # the fallback: the last frame
    ref = st.sc.solve(st.solver, field=st.field_of(I), init=last, **st.pose)
    assert (got.p - ref.p).abs().max() < 1e-9
    with pytest.raises(ValueError, match=r"currents must be 6 numbers \(A\), got shape \(5,\)"):
        st.step(torch.zeros(5))
    with pytest.raises(ValueError, match="currents must be finite"):
        st.step(torch.full((6,), math.nan))

    def no_equilibrium(*a, **k):
        raise SolverError("no equilibrium", time=1.0, node=0)
    monkeypatch.setattr(qs, "_warm_step", no_equilibrium)
    st.reset()
    st.solver.max_iter, st.stages = 1, ((1, 1),)  # no try can converge: the fallback runs and fails
    with pytest.raises(SolverError, match=r"no static equilibrium at the new currents.*step=1, time=0\.02"):
        st.step(torch.full((6,), 3.0, dtype=torch.float64))
    # currents beyond the training profiles' 4 A per coil warn, once per stepper
    with pytest.warns(UserWarning, match=r"exceed the \+-4 A per coil.*the correction extrapolates"):
        with pytest.raises(SolverError):
            st.step(torch.tensor([0.0, 0.0, -4.5, 0.0, 0.0, 0.0], dtype=torch.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SolverError):
            st.step(torch.full((6,), 5.0, dtype=torch.float64))


def test_the_stepper_gives_up_past_max_seconds_and_stays_at_its_last_frame():
    """Far outside the training currents the fallback's sub-steps searched for over 14 minutes (1e4 A, eager): with
    ``max_seconds`` the step ends in a SolverError naming it soon after, and the next step goes on from the last
    frame as if the failed one had not been asked for."""
    import time
    from physics.errors import SolverError
    torch.set_num_threads(1)
    engine = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod")
    scene = engine.task.scene_by_name("magnetic_rod_heldout")
    for bad in (0.0, math.inf, "1", True):
        with pytest.raises(ValueError, match="max_seconds must be a finite number of seconds > 0 or None"):
            engine.stepper(scene, max_seconds=bad)
    currents = lambda k: scene.loads.field.currents(torch.tensor(0.02 * k, dtype=torch.float64))  # noqa: E731
    st, ref = engine.stepper(scene, max_seconds=1.5), engine.stepper(scene)
    st.step(currents(1))
    ref.step(currents(1))
    last, t0 = st.solution, time.perf_counter()
    with pytest.warns(UserWarning, match="exceed"):
        with pytest.raises(SolverError, match=r"no static equilibrium within max_seconds=1\.5 s.*step=2, time=0\.04"):
            st.step(torch.tensor([1e4, -1e4, 1e4, 0.0, 0.0, 0.0], dtype=torch.float64))
    assert time.perf_counter() - t0 < 4.5 and st.solution is last and st.k == 1
    c, R = st.step(currents(2))
    c_ref, R_ref = ref.step(currents(2))
    assert (c - c_ref).abs().max() < 1e-9 and (R - R_ref).abs().max() < 1e-9


def test_the_staged_solve_crosses_a_snap_through_onto_the_branch_the_escalation_finds():
    """The held-out profile's first snap-through (frame 108): the predictor's first try (10 iterations) fails, the
    loads stepped up in 12 steps land on the equilibrium that the solver's own escalation (4, 16, 64 load steps of
    up to 50 iterations) finds, on the new branch (the magnets turned)."""
    from dataclasses import replace
    from cmlearn.surrogate.quasistatic_stepper import STAGES
    torch.set_num_threads(1)
    engine = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod")
    scene = replace(engine.task.scene_by_name("magnetic_rod_heldout"), duration=2.2)
    currents = lambda k: scene.loads.field.currents(torch.tensor(0.02 * k, dtype=torch.float64))  # noqa: E731
    st = engine.stepper(scene)
    for k in range(1, 108):  # the static rod alone up to the frame before the fold
        st.solve(currents(k))
    before = st.solution, st._prev_wrench, st.currents
    staged, its = st.solve(currents(108)), st.iterations
    st.solution, st._prev_wrench, st.currents = before
    st.stages = ()
    escalated = st.solve(currents(108))
    assert STAGES[0][1] < its <= STAGES[0][1] + STAGES[1][0] * STAGES[1][1]  # the first try failed, the second held
    assert bool(staged.converged) and (staged.p - escalated.p).abs().max() < 1e-9
    turned = (staged.R[st.nodes] - before[0].R[st.nodes]).abs().max()
    assert turned > 0.1 and (escalated.R - staged.R).abs().max() < 1e-9


def test_the_stepper_counts_the_fold_clock_as_the_offline_rollout_does_through_a_snap_through():
    """A model that reads the fold clock (random weights): the real-time stepper, which counts the clock frame by frame
    inside its frame program, follows the offline rollout (the clock of the whole static track) through the held-out
    profile's first snap-through (frame 108) and two frames after it."""
    from dataclasses import replace
    from physics.programs import compile_program
    torch.set_num_threads(1)
    torch.manual_seed(1)
    shipped = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod").model.config
    cfg = replace(shipped, hidden=8, width=16, fold_clock=4.0)
    model = QuasiStaticCorrection(cfg)
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.3)
    engine = QuasiStaticSurrogate(model, {"task": "magnetic_rod"})
    scene = replace(engine.task.scene_by_name("magnetic_rod_heldout"), duration=2.2)
    cp, Rp = engine.run(scene)[:2]
    st = engine.stepper(scene)
    for k in range(1, 111):
        c, R = st.step(scene.loads.field.currents(torch.tensor(0.02 * k, dtype=torch.float64)))
    assert (c - cp[-1]).abs().max() < 1e-8 and orientation_errors(R[None], Rp[-1:]).abs().max() < 1e-4  # m, deg
    tau = st.static[0, :, 13]  # frames 107-110: the cap, then 1 - (the fold's time within frame 107-108), +1, +2
    assert float(tau[0]) == 4.0 and 0.0 < float(tau[1]) < 1.0 and torch.allclose(tau[1:] - tau[1], torch.arange(3.0))
    # the clock changes the step: the same frame with the clock still at its cap
    args = (st.solution.y.contiguous(), st.solution.jacobian.contiguous(), st.dev, st.static)
    capped = st.static.clone()
    capped[0, -1, 13] = 4.0
    assert (st._frame(*args[:3], capped)[0] - st._frame(*args)[0]).abs().max() > 1e-3
    for a, b in zip(compile_program(st._frame, args, direct=True)(*args), st._frame(*args)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_a_cached_static_track_is_served_only_for_the_same_times_clamp_truncation_and_physics(tmp_path, monkeypatch):
    """The cache of static solves is keyed on what changes them: a track cut short by ``truncate`` (NaN frames) is not
    served to a caller that wants a SolverError, nor one of another clamp or physics version."""
    import physics
    from cmlearn.data import quasistatic as qs
    calls = []

    def fake(currents, emns, times, **kw):
        calls.append(kw)
        n = len(times)
        return qs.StaticTrack(torch.zeros(n, 2, 3), torch.eye(3).expand(n, 2, 3, 3), torch.ones(n), 0.5)
    monkeypatch.setattr(qs, "static_track", fake)
    path, pose = tmp_path / "track.pt", {"base_quaternion": torch.tensor([0.0, 1.0, 0.0, 0.0])}
    track = qs.cached_static_track(path, None, None, [0.0, 0.02], **pose)
    assert qs.cached_static_track(path, None, None, [0.0, 0.02], **pose).wall_s == track.wall_s and len(calls) == 1
    for kw in ({**pose, "truncate": True}, {}, {"base_quaternion": torch.tensor([1.0, 0.0, 0.0, 0.0])}):
        qs.cached_static_track(path, None, None, [0.0, 0.02], **kw)
    qs.cached_static_track(path, None, None, [0.0, 0.04])
    monkeypatch.setattr(physics, "__version__", "9.9.9")
    qs.cached_static_track(path, None, None, [0.0, 0.04])
    assert len(calls) == 6
    # another profile's currents (or coils) were served the first one's track (26.6 mm off at 4 A)
    amps = [torch.zeros(6, dtype=torch.float64), torch.full((6,), 4.0, dtype=torch.float64)]
    for I in amps + amps[-1:]:
        qs.cached_static_track(path, lambda t, I=I: I, None, [0.0, 0.04])
    qs.cached_static_track(path, lambda t: amps[1], "other coils", [0.0, 0.04])
    assert len(calls) == 9


def test_a_batch_mates_failed_warm_step_leaves_the_converged_problems_solution_alone():
    """Where one problem of a batch needs its step split in halves, the others keep the solution their one warm
    step gave (the static track of a profile is the same in any batch), and the split one reaches the time."""
    from cmlearn.data import quasistatic as qs
    from physics.cosserat_shooting import StaticSolution
    asked = []

    def solution(y, ok):
        return StaticSolution(torch.zeros(1), y, torch.zeros(2, 6), ok, torch.zeros(2), (~ok).double(),
                              torch.zeros(2, 6, 6))

    class Solver:  # y[..., 0]: the time reached; y[..., 1]: the warm solves along the path to it
        def solve(self, solver, field, init=None, **kw):
            t, t0 = asked[-1], init.y[:, 0, 0]
            ok = torch.stack([torch.tensor(True), t - t0[1] <= 0.25])  # problem 1 moves a quarter at most
            return solution(torch.stack([torch.full((2,), t), init.y[:, 0, 1] + 1], -1)[:, None, :], ok)

    def currents(t):
        asked.append(float(t))
        return torch.zeros(2, 6, dtype=torch.float64)
    start = solution(torch.zeros(2, 1, 2, dtype=torch.float64), torch.ones(2, dtype=torch.bool))
    out = qs._warm_step(Solver(), None, lambda current: None, currents, {}, start, 0.0, 1.0, 4)
    assert out.y[:, 0, 0].tolist() == [1.0, 1.0] and bool(out.converged.all())
    assert out.y[:, 0, 1].tolist() == [1.0, 4.0]  # one warm solve for problem 0; four quarter steps for problem 1


def test_the_hybrid_names_a_scene_of_the_other_clamp_a_duration_short_of_a_frame_a_start_past_the_end_and_n_0():
    """The hanging rod's hybrid in the planar set-up's clamp ran on silently (its rest rotations are the hanging
    rod's: at zero current the magnets drifted 6 deg in three frames); a duration shorter than a frame, a start at or
    past the last frame and ``latency(n=0)`` failed with internal messages (or, a negative start, returned the wrong
    frames)."""
    from dataclasses import replace

    from cmlearn.data import get_task
    engine = QuasiStaticSurrogate.load(SHIPPED, task="magnetic_rod")
    planar = get_task("magnetic_rod_planar").base_scene()
    for call in (engine.run, engine.stepper):
        with pytest.raises(ValueError, match="scene 'magnetic_rod_planar': its rod is clamped otherwise"):
            call(planar)
    scene = engine.task.scene_by_name("magnetic_rod_heldout")
    with pytest.raises(ValueError, match=r"duration must be a time of at least one surrogate step \(0\.02 s.*got 0\.01"):
        engine.run(replace(scene, duration=0.01))
    with pytest.raises(ValueError, match="n must be an integer >= 1"):
        engine.latency(scene, n=0)
    s, d = torch.zeros(10, 13, dtype=torch.float64), torch.zeros(10, 12, dtype=torch.float64)
    assert rollout_from(engine.model, s, d, 8).shape == (1, 12)
    for start in (9, 10, -1):
        with pytest.raises(ValueError, match=rf"start must be a frame 0\.\.8 of the 10 frames, got {start}"):
            rollout_from(engine.model, s, d, start)


def test_a_batch_larger_than_the_training_windows_is_named_instead_of_training_nothing():
    """The loader drops the last partial batch: a batch_size above the training windows left Lightning with no batch
    and the script wrote the untrained model."""
    from cmlearn.surrogate.quasistatic_training import QuasiStaticDataModule
    s, d = torch.zeros(3, 51, 13), torch.zeros(3, 51, 12)
    n = len(QuasiStaticDataModule(s, d, 2, 3, 4, 8, batch_size=1).train_set)
    assert len(QuasiStaticDataModule(s, d, 2, 3, 4, 8, batch_size=n).train_dataloader()) == 1
    with pytest.raises(ValueError, match=f"batch_size {n + 1} exceeds the {n} training windows of 4 steps"):
        QuasiStaticDataModule(s, d, 2, 3, 4, 8, batch_size=n + 1)
