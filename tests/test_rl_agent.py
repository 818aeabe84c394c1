"""The Rainbow-IQN agent: network, IQN loss, replay priorities, noise, training, checkpoints, resume."""

import math

import numpy as np
import pytest

pytest.importorskip("torchrl")
pytest.importorskip("pybullet")
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torchrl.envs.utils import ExplorationType, set_exploration_type  # noqa: E402

from cmlearn.models.iqn import IQNConfig, IQNNetwork, find_iqn_network, make_iqn_actor  # noqa: E402
from cmlearn.rl import Map, MagneticParticleEnv, run_episode  # noqa: E402
from cmlearn.io import seal  # noqa: E402
from cmlearn.rl.agent import CheckpointError, IQNAgent, load_agent, save_agent  # noqa: E402
from cmlearn.rl.iqn_loss import IQNLoss, quantile_huber_loss  # noqa: E402
from cmlearn.rl.training import AgentTrainConfig, train_agent  # noqa: E402

# the unit tests build the loss alone and copy the target network by hand where they need it; training attaches
# torchrl's HardUpdate (cmlearn.rl.training)
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated")

SMALL = dict(stem_channels=4, widths=(4,), feature_dim=16, hidden_dim=16, num_cosines=8, num_policy_quantiles=8)


def batch(B=6, seed=0, gamma=None, terminated=None):
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({
        "observation": torch.randint(0, 256, (B, 2, 84, 84), dtype=torch.uint8, generator=g),
        "action": torch.nn.functional.one_hot(torch.randint(0, 4, (B,), generator=g), 4),
        "next": {"observation": torch.randint(0, 256, (B, 2, 84, 84), dtype=torch.uint8, generator=g),
                 "reward": torch.randn(B, 1, generator=g),
                 "terminated": torch.zeros(B, 1, dtype=torch.bool) if terminated is None else terminated}}, [B])
    if gamma is not None:
        td["gamma"] = gamma
    return td


def test_quantile_huber_loss_equals_hand_computation():
    pred = torch.tensor([[0.0, 2.0]])
    taus = torch.tensor([[0.25, 0.75]])
    target = torch.tensor([[0.5, 3.0]])
    # by hand, kappa = 1: delta_ij = y_j - z_i
    # i=0 (z=0, tau=.25): d=.5 -> .25*.125 = .03125 ; d=3 -> .25*(3-.5) = .625   -> mean .328125
    # i=1 (z=2, tau=.75): d=-1.5 -> |.75-1|*(1.5-.5) = .25 ; d=1 -> .75*.5 = .375 -> mean .3125
    assert quantile_huber_loss(pred, target, taus, 1.0).item() == pytest.approx(0.328125 + 0.3125, abs=1e-7)
    # kappa = 2: |delta| = 3 stays linear (2 (3 - 1)), the others are quadratic; all divided by kappa
    hand = (0.25 * 0.125 + 0.25 * (2 * (3 - 1))) / 2 / 2 + (0.25 * 1.125 + 0.75 * 0.5) / 2 / 2
    assert quantile_huber_loss(pred, target, taus, 2.0).item() == pytest.approx(hand, abs=1e-7)
    with pytest.raises(ValueError, match="kappa"):
        quantile_huber_loss(pred, target, taus, 0.0)
    with pytest.raises(ValueError, match=r"target \(B, N'\), got .*target \(1,\)"):  # was paired with every sample
        quantile_huber_loss(pred, target[:, 0], taus)


def test_loss_gradients_reach_every_parameter_and_priorities_are_written():
    actor = make_iqn_actor(IQNConfig(**SMALL))
    loss = IQNLoss(actor, num_quantiles=8, num_target_quantiles=8)
    td = batch()
    out = loss(td)
    out["loss"].backward()
    for name, p in loss.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert td["td_error"].shape == (6,) and (td["td_error"] > 0).all()


def test_double_q_target_uses_the_online_argmax_and_the_data_discount():
    actor = make_iqn_actor(IQNConfig(**SMALL))
    loss = IQNLoss(actor, num_quantiles=8, num_target_quantiles=5, noisy=False)
    net = find_iqn_network(actor)
    key = ("module", "0", "module", "advantage", "2", "bias_mu")
    loss.value_network_params.get(key).data += torch.tensor([0.0, 10.0, 0.0, 0.0])   # online prefers action 1
    loss.target_value_network_params.get(key).data += torch.tensor([10.0, 0.0, 0.0, 0.0])  # target prefers 0
    term = torch.tensor([[False], [True], [False], [False]])
    td = batch(4, gamma=torch.tensor([0.99 ** 3, 0.99 ** 3, 0.99 ** 2, 0.99]), terminated=term)
    torch.manual_seed(3)
    a_star, y = loss.target_quantiles(td)
    torch.manual_seed(3)
    k = net.config.num_policy_quantiles
    taus_online, taus_target = torch.rand(4, k), torch.rand(4, 5)
    obs = td["next", "observation"]
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        with loss.value_network_params.to_module(loss.value_network):
            online = net.quantiles(obs, taus_online).mean(-2)
        with loss.target_value_network_params.to_module(loss.value_network):
            z_t = net.quantiles(obs, taus_target)
    assert torch.equal(a_star, online.argmax(-1)) and (a_star == 1).all()
    assert (z_t.mean(-2).argmax(-1) == 0).all()  # the target alone would have picked another action
    r = td["next", "reward"].reshape(4)
    expected = r[:, None] + (td["gamma"] * (~term.reshape(4)))[:, None] * z_t[:, :, 1]
    torch.testing.assert_close(y, expected)
    assert torch.allclose(y[1], r[1].expand(5))  # a terminal transition does not bootstrap


def test_priorities_change_after_an_update():
    from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer
    actor = make_iqn_actor(IQNConfig(**SMALL))
    loss = IQNLoss(actor, num_quantiles=8, num_target_quantiles=8)
    rb = TensorDictPrioritizedReplayBuffer(alpha=0.6, beta=0.4, storage=LazyTensorStorage(64), batch_size=8)
    rb.extend(batch(32, seed=1))
    sample = rb.sample()
    idx = sample["index"]
    before = torch.tensor([rb.sampler._sum_tree[int(i)] for i in idx])
    assert "priority_weight" in sample.keys()
    loss(sample)["loss"].backward()
    rb.update_tensordict_priority(sample)
    after = torch.tensor([rb.sampler._sum_tree[int(i)] for i in idx])
    assert not torch.allclose(before, after)
    expected = (sample["td_error"] + rb.sampler._eps) ** 0.6
    for i in range(len(idx)):  # an index drawn twice keeps one of its two new priorities
        same = idx == idx[i]
        assert torch.isclose(expected[same], after[i], rtol=1e-4).any()


def test_noise_is_resampled_and_off_in_deterministic_evaluation():
    net = IQNNetwork(IQNConfig(**SMALL))
    obs = batch(3)["observation"]
    taus = torch.rand(3, 4)
    with torch.no_grad():
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            d1 = net.quantiles(obs, taus)
            a1 = net(obs)
        with set_exploration_type(ExplorationType.RANDOM):
            r1 = net.quantiles(obs, taus)
        net.reset_noise()
        with set_exploration_type(ExplorationType.RANDOM):
            r2 = net.quantiles(obs, taus)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            d2 = net.quantiles(obs, taus)
            a2 = net(obs)
    assert torch.equal(d1, d2) and torch.equal(a1, a2)  # no noise, fixed quantile midpoints
    assert not torch.allclose(r1, d1) and not torch.allclose(r1, r2)


def test_network_shapes_and_bad_input():
    net = IQNNetwork(IQNConfig(**SMALL))
    assert net.quantiles(batch(2)["observation"], torch.rand(2, 7)).shape == (2, 7, 4)
    with pytest.raises(ValueError, match="observation"):
        net(torch.zeros(2, 3, 84, 84))
    with pytest.raises(ValueError, match="taus"):
        net.quantiles(batch(2)["observation"], torch.rand(3, 7))
    with pytest.raises(ValueError, match="widths"):
        IQNConfig(widths=())
    with pytest.raises(ValueError, match="frames_per_batch"):
        AgentTrainConfig(num_envs=4, frames_per_batch=30)


def test_checkpoint_acts_deterministically_and_bad_files_give_clear_errors(tmp_path):
    net = IQNNetwork(IQNConfig(**SMALL))
    path = save_agent(tmp_path / "a.pt", net, {"note": "test"})
    obs = batch(1)["observation"][0].numpy()
    a, b = IQNAgent.load(path), IQNAgent.load(path)
    assert np.array_equal(a.q_values(obs), a.q_values(obs)) and np.array_equal(a.q_values(obs), b.q_values(obs))
    assert a.act(obs, {}) == b.act(obs, {}) and a.meta["note"] == "test"
    blob = torch.load(path, weights_only=True)
    blob["config"]["widths"] = [8]  # another architecture, in a file sealed as written
    torch.save(seal(blob), tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="architecture"):
        load_agent(tmp_path / "other.pt")
    torch.save({"format": "cmlearn-surrogate/1"}, tmp_path / "surrogate.pt")
    with pytest.raises(CheckpointError, match="cmlearn-iqn-agent/1"):
        load_agent(tmp_path / "surrogate.pt")
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_agent(tmp_path / "cut.pt")
    blob = torch.load(path, weights_only=True)  # a weight changed where the archive still reads (bit rot)
    name = next(iter(blob["state_dict"]))
    blob["state_dict"][name].view(-1)[0] += 1e-6
    torch.save(blob, tmp_path / "rotten.pt")
    with pytest.raises(CheckpointError, match="weights do not match their stored SHA-256"):
        load_agent(tmp_path / "rotten.pt")
    blob = torch.load(path, weights_only=True)
    blob["config"]["widths"] = [8]  # the same change where the archive still reads: the header's digest catches it
    torch.save(blob, tmp_path / "rotten.pt")
    with pytest.raises(CheckpointError, match="configuration or metadata do not match their stored SHA-256"):
        load_agent(tmp_path / "rotten.pt")
    with pytest.raises(CheckpointError, match="no such"):
        load_agent(tmp_path / "missing.pt")


def corridor(length=0.3, width=0.05, height=0.1, res=0.002):
    H, W = int(round(height / res)), int(round(length / res))
    img = np.full((H, W), 20, np.uint8)
    y = (H - 0.5 - np.arange(H)) * res
    img[np.abs(y - height / 2) < width / 2, :] = 235
    return Map(img, res, (-0.15, 0.40), name="corridor")


def success_rate(env, controller, episodes, seed=500):
    return np.mean([run_episode(env, controller, seed=seed + i).success for i in range(episodes)])


class OneWayCorridor(Map):
    """The corridor with every start in one end third and every goal in the other: one action (+x or -x)
    is right everywhere, so a learner must turn the network's greedy action to it."""
    def __init__(self, east: bool):
        c = corridor()
        super().__init__(c.image, c.resolution, c.origin, name="east" if east else "west")
        self.east = east

    def sample_start_goal(self, rng, min_distance=0.1, tries=200):
        nodes = np.argwhere(self.safe)  # (i along x, j along y)
        third = self.nx // 3
        west, east = nodes[nodes[:, 0] < third], nodes[nodes[:, 0] >= self.nx - third]
        start, goal = (west, east) if self.east else (east, west)
        return tuple(int(v) for v in start[rng.integers(len(start))]), tuple(int(v) for v in goal[rng.integers(len(goal))])


def toward_goal(env, agent, episodes=20, seed=1000):
    """Fraction of fresh starts at which the agent's greedy action heads for the goal along x."""
    right = []
    for i in range(episodes):
        obs, info = env.reset(seed=seed + i)
        right.append(agent.act(obs, info) == (0 if env.unwrapped.map.east else 1))  # ACTIONS[0] = +x, [1] = -x
    return float(np.mean(right))


@pytest.mark.parametrize("east", [True, False])
def test_quick_training_turns_the_greedy_action_to_the_goal(tmp_path, east):
    maps = [OneWayCorridor(east)]
    env = MagneticParticleEnv(maps=maps, atlas_cache=None, max_steps=40)
    net = dict(stem_channels=8, widths=(8,), feature_dim=64, hidden_dim=64, num_cosines=32, num_policy_quantiles=16)
    cfg = dict(total_frames=2_048, init_random_frames=512, num_envs=4, frames_per_batch=32, updates_per_batch=8,
               target_update=100, buffer_size=4_096, lr=5e-4, max_steps=40, disturbance_probability=0.0,
               eval_every=10_000, eval_episodes=1, checkpoint_every=10_000, progress=False, network=net)
    for seed in range(1, 20):  # the first seed whose initial network (built as train_agent builds it) heads away
        torch.manual_seed(seed)
        initial = IQNAgent(find_iqn_network(make_iqn_actor(AgentTrainConfig(network=net).net_config)))
        heading = toward_goal(env, initial)
        if heading <= 0.2:
            break
    assert heading <= 0.2 and success_rate(env, initial, 10) <= 0.2
    res = train_agent(AgentTrainConfig(out=str(tmp_path / "run"), seed=seed, **cfg), maps=maps, log=lambda s: None)
    assert res.frames >= 2_048 and res.updates > 0
    trained = IQNAgent.load(res.agent_path)
    # measured at 2,048 frames, both directions, three processes: 0.0 -> 1.0 toward the goal and in success
    assert toward_goal(env, trained) >= 0.9, seed
    assert success_rate(env, trained, 10) >= 0.8, seed


def test_training_with_one_seed_gives_one_agent(tmp_path):
    """Two runs of one seed train the same weights: the collector's environments start from their seeded reset (the
    collector resets them once unseeded when it is built). Also: pre-training with no margin loss
    (``margin_weight=0``) logs and runs."""
    cfg = dict(num_envs=2, frames_per_batch=10, total_frames=40, init_random_frames=10, n_steps=3, network=dict(SMALL),
               max_steps=30, updates_per_batch=2, progress=False, eval_episodes=1, eval_every=10**6,
               checkpoint_every=10**6, seed=0, demo_episodes=2, pretrain_updates=2, margin_weight=0.0)
    weights = []
    for k in range(2):
        res = train_agent(AgentTrainConfig(out=str(tmp_path / f"run{k}"), **cfg), maps=[corridor()], log=lambda s: None)
        weights.append(load_agent(res.agent_path)[0].state_dict())
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_interrupted_run_resumes_and_states_the_replay_buffer(tmp_path):
    maps = [corridor()]
    base = dict(total_frames=384, init_random_frames=64, num_envs=2, frames_per_batch=16, updates_per_batch=2,
                buffer_size=1_024, max_steps=20, eval_every=10_000, eval_episodes=1, checkpoint_every=128,
                progress=False, disturbance_probability=0.0, network=dict(SMALL))
    for save_buffer, expected in ((False, "NOT restored"), (True, "restored")):
        out = tmp_path / f"run{save_buffer}"
        cfg = AgentTrainConfig(out=str(out), save_buffer=save_buffer, **base)
        first = train_agent(cfg, maps=maps, log=lambda s: None, stop_after_frames=192)
        assert first.frames == 192 and first.resumed_from is None
        lines = []
        cfg = AgentTrainConfig(out=str(out), save_buffer=save_buffer, resume=True, **base)
        second = train_agent(cfg, maps=maps, log=lines.append)
        assert second.resumed_from == 192 and second.frames == 384 and second.buffer_restored is save_buffer
        assert second.updates > first.updates
        assert any(expected in s and "resumed from frame 192" in s for s in lines), lines
    with pytest.raises(FileNotFoundError, match="resume"):
        train_agent(AgentTrainConfig(out=str(tmp_path / "none"), resume=True, **base), maps=maps)


def test_agent_runs_as_sub_controller_2_of_the_switching_controller():
    n = 150  # a 0.3 m open square at 2 mm/px
    square = Map(np.full((n, n), 235, np.uint8), 0.002, (-0.15, 0.30), name="square")
    from cmlearn.rl import DisturbanceConfig
    env = MagneticParticleEnv(maps=[square], atlas_cache=None, max_steps=3,
                              disturbance=DisturbanceConfig(at_steps=(1,), magnitude=(0.11, 0.12), min_step=0))
    agent = IQNAgent(IQNNetwork(IQNConfig(**SMALL)))
    res = run_episode(env, agent, seed=1, options={"start": (0.005, 0.455), "goal": (0.085, 0.455)})
    assert res.disturbances == 1 and res.sc1_steps > 0  # Sub-controller 1 recaptured the dragged particle
    assert set(res.trajectory[:, 4]) >= {0, 1, 2} and res.decision_time_s > 0


def test_n_step_windows_that_end_in_a_terminal_state_do_not_bootstrap():
    from cmlearn.rl.training import make_replay_buffer
    T = 12
    term = torch.zeros(1, T, 1, dtype=torch.bool)
    term[0, 5] = True
    trunc = torch.zeros(1, T, 1, dtype=torch.bool)
    trunc[0, 9] = True
    g = torch.Generator().manual_seed(0)
    obs = torch.randint(0, 256, (1, T + 1, 2, 84, 84), dtype=torch.uint8, generator=g)
    td = TensorDict({"observation": obs[:, :-1], "action": torch.nn.functional.one_hot(torch.zeros(1, T).long(), 4),
                     "next": {"observation": obs[:, 1:], "reward": torch.ones(1, T, 1), "terminated": term,
                              "truncated": trunc, "done": term | trunc}}, [1, T])
    rb = make_replay_buffer(AgentTrainConfig(n_steps=3, gamma=0.9, buffer_size=64, network=dict(SMALL)))
    rb.extend(td)
    d = rb[:][0]  # one env, the first T - n_steps windows
    # windows starting at 3, 4, 5 end at the terminal step 5: no bootstrap
    assert d["next", "terminated"].flatten().tolist()[3:6] == [True, True, True]
    assert not d["next", "terminated"].flatten()[:3].any() and not d["next", "terminated"].flatten()[6:].any()
    assert torch.allclose(d["next", "reward"].flatten()[3:6], torch.tensor([2.71, 1.9, 1.0]))
    loss = IQNLoss(make_iqn_actor(IQNConfig(**SMALL)), num_target_quantiles=4)
    _, y = loss.target_quantiles(d)
    torch.testing.assert_close(y[3:6], d["next", "reward"][3:6].expand(3, 4))  # exactly the summed rewards
    assert not torch.allclose(y[:3], d["next", "reward"][:3].expand(3, 4))     # the others bootstrap
    # a window cut by truncation (step 9) bootstraps from the observation after the truncated step
    assert torch.equal(d["next", "observation"][8], obs[0, 10]) and not d["next", "terminated"][8]


def test_shipped_agent_checkpoint_loads_acts_deterministically_and_records_its_training():
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "checkpoints" / "iqn_agent.pt"
    a, b = IQNAgent.load(path), IQNAgent.load(path)
    meta = a.meta
    assert meta["command"].startswith("python scripts/train_agent.py") and meta["updates"] >= 10_000
    assert meta["wall_s"] > 0 and meta["evaluations"] and path.stat().st_size < 5e6
    import cmlearn.rl as rl
    from cmlearn.rl.agent import ActingGuard
    look = meta["train_config"]["waypoint_lookahead"]  # it was trained to follow the map memory's waypoints
    assert look > 0
    env = MagneticParticleEnv(map_seeds=rl.map_seeds("train", 8), waypoint_lookahead=look, waypoint_prior=True)
    obs, info = env.reset(seed=0)
    assert np.array_equal(a.q_values(obs), b.q_values(obs)) and a.act(obs, info) == b.act(obs, info)
    r1, r2 = run_episode(env, a, seed=3), run_episode(env, b, seed=3)
    assert r1.reason == r2.reason and r1.steps == r2.steps and np.array_equal(r1.trajectory, r2.trajectory)
    # as shipped (inside its guard) it reaches the goal on the training maps (100 % over 200 in the README)
    guarded = IQNAgent.load(path, guard=ActingGuard())
    wins = [run_episode(env, guarded, seed=100 + i).success for i in range(10)]
    assert sum(wins) >= 9, wins
    # and on maps it never saw, with the memory starting empty (100 % over 200 in the README)
    env = MagneticParticleEnv(map_seeds=rl.map_seeds("unseen", 2), waypoint_lookahead=look)
    wins = [run_episode(env, guarded, seed=100 + i).success for i in range(10)]
    assert sum(wins) >= 8, wins


# ---------------------------------------------------------------- learning from demonstrations (DQfD)

def test_margin_loss_equals_hand_computation_and_is_added_on_expert_samples_only():
    actor = make_iqn_actor(IQNConfig(**SMALL))
    loss = IQNLoss(actor, num_quantiles=8, num_target_quantiles=8, margin=0.8, margin_weight=0.5)
    q = torch.tensor([[1.0, 2.0, 0.5, 0.0], [1.0, 2.0, 0.5, 0.0]])
    # expert action 0: max(1 + 0, 2 + .8, .5 + .8, 0 + .8) - 1 = 1.8; expert action 1: max(1.8, 2, 1.3, .8) - 2 = 0
    torch.testing.assert_close(loss.margin_loss(q, torch.tensor([0, 1])), torch.tensor([1.8, 0.0]))
    td = batch(B=4)
    torch.manual_seed(3)
    plain = loss(td.clone())["loss"]
    td["expert"] = torch.tensor([True, False, True, False])
    torch.manual_seed(3)
    out = loss(td)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM), \
            loss.value_network_params.to_module(loss.value_network):
        torch.manual_seed(3)
        _ = loss.target_quantiles(td)                      # same random stream as inside forward
        z = find_iqn_network(actor).quantiles(td["observation"], torch.rand(4, 8))
    m = loss.margin_loss(z.mean(-2), td["action"].argmax(-1))
    expected = plain + 0.5 * (m[0] + m[2]) / 4
    torch.testing.assert_close(out["loss"], expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["margin_loss"], (m[0] + m[2]) / 2, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="margin"):
        IQNLoss(actor, margin=-1.0)


def test_demonstration_windows_match_the_replay_buffers_n_step_transform():
    from cmlearn.rl.demos import episode_transitions
    from cmlearn.rl.training import make_replay_buffer
    T, n, gamma = 9, 3, 0.9
    g = torch.Generator().manual_seed(1)
    obs = torch.randint(0, 256, (T + 1, 2, 84, 84), dtype=torch.uint8, generator=g)
    actions, rewards = torch.randint(0, 4, (T,), generator=g), torch.randn(T, generator=g)
    for terminated in (True, False):
        demo = episode_transitions(obs.numpy(), actions.numpy(), rewards.numpy(), terminated, n, gamma)
        # the last windows by hand: reward r7 + .9 r8 (2 steps) and r8 (1 step), ending at the last observation
        torch.testing.assert_close(demo["next", "reward"][T - 2, 0], rewards[7] + 0.9 * rewards[8])
        assert demo["gamma"][T - 1].item() == pytest.approx(0.9) and torch.equal(demo["next", "observation"][T - 1],
                                                                                 obs[T])
        assert demo["next", "terminated"].flatten().tolist() == [False] * (T - n) + [terminated] * n
        done = torch.zeros(1, T, 1, dtype=torch.bool)
        done[0, -1] = True
        td = TensorDict({"observation": obs[None, :-1], "action": torch.nn.functional.one_hot(actions, 4)[None],
                         "next": {"observation": obs[None, 1:], "reward": rewards.view(1, T, 1),
                                  "terminated": done & terminated, "truncated": done & (not terminated),
                                  "done": done}}, [1, T])
        rb = make_replay_buffer(AgentTrainConfig(n_steps=n, gamma=gamma, buffer_size=64, network=dict(SMALL)))
        rb.extend(td)
        ref = rb[:][0]  # the first T - n windows, written by torchrl's MultiStepTransform
        k = ref.shape[0]
        assert k == T - n and demo["expert"].all()
        torch.testing.assert_close(demo["next", "reward"][:k], ref["next", "reward"])
        torch.testing.assert_close(demo["gamma"][:k], ref["gamma"].float())
        assert torch.equal(demo["next", "observation"][:k], ref["next", "observation"])
        assert torch.equal(demo["action"][:k], ref["action"])
        assert torch.equal(demo["next", "terminated"][:k], ref["next", "terminated"])


def test_teacher_reaches_the_goal_and_rejects_bad_parameters():
    from cmlearn.rl.teacher import GeodesicTeacher
    import cmlearn.rl as rl
    env = MagneticParticleEnv(map_seeds=rl.map_seeds("train", 2))
    teacher = GeodesicTeacher(env)
    res = [run_episode(env, teacher, seed=i) for i in range(6)]
    assert all(r.success for r in res), [r.reason for r in res]
    with pytest.raises(ValueError, match="clearance_weight"):
        GeodesicTeacher(env, clearance_weight=-1.0)


def test_pretraining_on_demonstrations_imitates_the_teacher(tmp_path):
    from cmlearn.rl.demos import collect_demonstrations
    maps = [corridor()]
    net = dict(stem_channels=8, widths=(8,), feature_dim=64, hidden_dim=64, num_cosines=32, num_policy_quantiles=16)
    cfg = AgentTrainConfig(total_frames=64, init_random_frames=0, num_envs=2, frames_per_batch=32, updates_per_batch=1,
                           buffer_size=1_024, max_steps=40, disturbance_probability=0.0, eval_every=10_000,
                           eval_episodes=4, checkpoint_every=10_000, out=str(tmp_path / "run"), progress=False,
                           seed=2, network=net, demo_episodes=6, pretrain_updates=1_000, lr=1e-3)
    lines = []
    res = train_agent(cfg, maps=maps, log=lines.append)
    assert any(s.startswith("demonstrations: ") for s in lines) and any("pre-trained on demonstrations" in s
                                                                        for s in lines), lines
    assert res.evaluations[0]["phase"] == "pretrain" and res.updates >= 1_000
    best_meta = load_agent(res.best_agent_path)[1]   # the best periodic evaluation is kept
    assert best_meta["selected"]["success_rate"] == max(e["success_rate"] for e in res.evaluations)
    env_kw = dict(maps=maps, atlas_cache=None, max_steps=40)
    demos = collect_demonstrations(env_kw, 6, cfg.n_steps, cfg.gamma, seed=1_000_000 + 1_000 * cfg.seed,
                                   log=lambda s: None)
    expert = demos["action"].argmax(-1)

    def agreement(net):
        with torch.no_grad():
            return (net(demos["observation"]).argmax(-1) == expert).float().mean().item()

    majority = torch.bincount(expert).max().item() / len(expert)   # the best state-blind imitation
    trained = agreement(load_agent(res.agent_path)[0].eval())
    assert trained >= 0.9 and trained >= majority + 0.2, (trained, majority)
    with pytest.raises(ValueError, match="pretrain_updates"):
        AgentTrainConfig(pretrain_updates=10, network=dict(SMALL))


def test_acting_guard_predicts_the_obstacle_rule_and_breaks_cycles():
    from cmlearn.rl.agent import ActingGuard
    from cmlearn.rl.env import ACTIONS
    import cmlearn.rl as rl
    env = MagneticParticleEnv(map_seeds=rl.map_seeds("train", 1))
    env.reset(seed=0)
    m, guard = env.map, ActingGuard()
    rng = np.random.default_rng(0)
    agree, total, positives = 0, 0, 0
    for _ in range(150):   # nodes near the channels: the rule's answer for each move, from the current view only
        i, j = int(rng.integers(2, m.nx - 2)), int(rng.integers(2, m.ny - 2))
        x, y = m.node_xy(i, j)
        pred = guard.blocked(env.atlas.view(x, y))
        for a, (dx, dy) in enumerate(ACTIONS):
            truth = env.obstacle_detected(env.atlas.view(x + 0.01 * dx, y + 0.01 * dy))
            agree += pred[a] == truth
            positives += truth
            total += 1
    assert agree / total >= 0.97 and 0.05 < positives / total < 0.95, (agree / total, positives / total)
    # a wrong sign on the shift would mispredict most moves along the walls
    flipped = ActingGuard(actions=tuple((-dx, -dy) for dx, dy in ACTIONS))
    i, j = next((i, j) for i in range(m.nx) for j in range(m.ny)
                if m.safe[i, j] and guard.blocked(env.atlas.view(*m.node_xy(i, j))).any())
    v = env.atlas.view(*m.node_xy(i, j))
    assert not np.array_equal(guard.blocked(v), flipped.blocked(v))
    # revisit tie-break: the same observation twice gets the second-best move the second time
    agent = IQNAgent(IQNNetwork(IQNConfig(**SMALL)), guard=ActingGuard(obstacle_mask=False))
    obs = np.zeros((2, 84, 84), np.uint8)
    order = np.argsort(-agent.q_values(obs))
    assert [agent.act(obs) for _ in range(2)] == [order[0], order[1]]
    agent.reset()
    assert agent.act(obs) == order[0]
    with pytest.raises(ValueError, match="revisit_penalty"):
        ActingGuard(revisit_penalty=-1.0)
    for t in (math.nan, -5.0, 1e9):  # NaN blocked no move, even on an all-dark view
        with pytest.raises(ValueError, match=r"threshold \(a grey level"):
            ActingGuard(threshold=t)
    with pytest.raises(ValueError, match="obs: the network's action values are not finite"):  # was action 0
        IQNAgent(IQNNetwork(IQNConfig(**SMALL))).act(np.full((2, 84, 84), np.nan, np.float32))


def test_target_network_is_copied_after_every_target_update_th_update():
    """``target_update`` updates between copies (torchrl's HardUpdate copies every interval + 1 steps), and the
    target's weights stay plain tensors after a forward pass, so an updater can still be built then."""
    from cmlearn.rl.training import target_updater
    loss = IQNLoss(make_iqn_actor(IQNConfig(**SMALL)), num_quantiles=8, num_target_quantiles=8)
    loss(batch())  # a forward pass (the target quantiles) before the updater is built, as on a resume
    online, target = loss.value_network_params, loss.target_value_network_params
    assert not any(p.requires_grad for p in target.values(True, True))
    weights = [k for k, p in online.items(True, True) if p.requires_grad]  # the buffers (noise) are the nets' own
    assert len(weights) > 10
    updater = target_updater(loss, 3)
    synced = []
    for _ in range(9):
        for k in weights:
            online[k].data.add_(1.0)  # an optimiser step
        updater.step()
        synced.append(all(torch.equal(online[k], target[k]) for k in weights))
    assert synced == [False, False, True] * 3


def test_loss_rejects_non_finite_kappa_bad_policy_quantiles_and_non_finite_batches():
    """A NaN or infinite kappa, or a NaN reward or observation, made a silent NaN (or zero) loss that the optimiser
    wrote into every weight and the replay into every priority; ``num_policy_quantiles=0`` silently meant the
    network's default."""
    actor = make_iqn_actor(IQNConfig(**SMALL))
    for kappa in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="kappa"):
            IQNLoss(actor, kappa=kappa)
        with pytest.raises(ValueError, match="kappa"):
            quantile_huber_loss(torch.zeros(1, 2), torch.ones(1, 2), torch.full((1, 2), 0.5), kappa)
    for k in (0, -1):
        with pytest.raises(ValueError, match="num_policy_quantiles"):
            IQNLoss(actor, num_policy_quantiles=k)
    loss = IQNLoss(actor, num_quantiles=8, num_target_quantiles=8)
    td = batch()
    td["next", "reward"][2] = float("nan")
    with pytest.raises(ValueError, match="reward"):
        loss(td)
    td = batch()
    td["observation"] = td["observation"].float() / 255
    td["observation"][1, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="observation"):
        loss(td)
    td = batch()
    td["priority_weight"] = torch.tensor([1.0, float("nan"), 1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="priority_weight"):
        loss(td)
    assert torch.isfinite(loss(batch())["loss"])


def test_train_config_rejects_runs_that_would_never_update():
    """A batch larger than the replay, or more random frames than the whole run, trained nothing and shipped the
    untrained network without a word."""
    with pytest.raises(ValueError, match="batch_size=64 must be <= buffer_size=32"):
        AgentTrainConfig(batch_size=64, buffer_size=32, network=dict(SMALL))
    with pytest.raises(ValueError, match="init_random_frames=5000 > total_frames=1000"):
        AgentTrainConfig(total_frames=1_000, network=dict(SMALL))
    AgentTrainConfig(total_frames=1_000, demo_episodes=2, pretrain_updates=10, network=dict(SMALL))  # pre-training


def test_resume_accepts_the_same_network_spelled_differently(tmp_path):
    """A run started from Python (``widths`` a tuple) resumed from the command line (JSON: a list), or with the
    defaults written out, is the same architecture; only a different one is refused."""
    base = dict(num_envs=2, frames_per_batch=10, total_frames=20, init_random_frames=10, n_steps=3, max_steps=20,
                updates_per_batch=1, buffer_size=64, progress=False, eval_episodes=1, eval_every=10**6,
                checkpoint_every=10**6, disturbance_probability=0.0, out=str(tmp_path / "run"))
    first = train_agent(AgentTrainConfig(network=dict(SMALL), **base), maps=[corridor()], log=lambda s: None,
                        stop_after_frames=10)
    assert first.frames == 10
    as_json = {**SMALL, "widths": list(SMALL["widths"]), "noisy_std": 0.5}
    res = train_agent(AgentTrainConfig(network=as_json, resume=True, **base), maps=[corridor()], log=lambda s: None)
    assert res.resumed_from == 10 and res.frames == 20
    with pytest.raises(ValueError, match="differs"):
        train_agent(AgentTrainConfig(network={**SMALL, "hidden_dim": 8}, resume=True, **base), maps=[corridor()],
                    log=lambda s: None)


def test_save_agent_refuses_a_json_path(tmp_path):
    """``save_agent("agent.json")`` wrote the checkpoint and then overwrote it with its own metadata copy."""
    with pytest.raises(ValueError, match=r"path must not end in \.json"):
        save_agent(tmp_path / "agent.json", IQNNetwork(IQNConfig(**SMALL)), {})
    assert not (tmp_path / "agent.json").exists()


def test_evaluate_agent_refuses_no_episodes():
    """``episodes=0`` returned NaN for every metric (the mean of no episodes)."""
    from cmlearn.rl.training import evaluate_agent
    for n in (0, -3, 2.0):
        with pytest.raises(ValueError, match=f"episodes must be an integer >= 1, got {n}"):
            evaluate_agent(IQNAgent(IQNNetwork(IQNConfig(**SMALL))), {}, n)
