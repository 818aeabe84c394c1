"""The magnetic-particle environment on hand-built maps: observation, obstacle rule, termination and
rewards, disturbances and the switching controller, determinism, checkers and bad input."""
import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("gymnasium")
import gymnasium as gym  # noqa: E402

import cmlearn.rl as rl  # noqa: E402
from cmlearn.rl import DisturbanceConfig, Map, MagneticParticleEnv, load_map, procedural_map  # noqa: E402
from cmlearn.rl.atlas import Atlas  # noqa: E402

FREE, WALL = 235, 20


def corridor(origin=(-0.1, 0.40), length=0.2, width=0.05, height=0.1, res=0.002, name="corridor"):
    """A straight corridor along x, centred in a map of ``length`` x ``height``."""
    H, W = int(round(height / res)), int(round(length / res))
    img = np.full((H, W), WALL, np.uint8)
    y = (H - 0.5 - np.arange(H)) * res
    img[np.abs(y - height / 2) < width / 2, :] = FREE
    return Map(img, res, origin, name=name)


def open_square(origin=(-0.15, 0.30), size=0.3, res=0.002):
    n = int(round(size / res))
    return Map(np.full((n, n), FREE, np.uint8), res, origin, name="square")


def make(maps, **kw):
    kw.setdefault("atlas_cache", None)
    return MagneticParticleEnv(maps=maps, **kw)


def run(env, actions):
    out = []
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append((r, term, trunc, info))
        if term or trunc:
            break
    return out


def test_observation_layout_and_markers():
    env = make([corridor()])
    obs, info = env.reset(seed=0, options={"start": (-0.055, 0.445), "goal": (0.045, 0.445)})
    assert obs.shape == (2, 84, 84) and obs.dtype == np.uint8 and env.observation_space.contains(obs)
    top, bottom = obs[1, :42], obs[1, 42:]
    assert (top == 255).sum() == 9 and (bottom == 255).sum() == 9
    (rg, cg), (re, ce) = np.argwhere(top == 255).mean(0), np.argwhere(bottom == 255).mean(0)
    assert cg > ce and abs(rg - re) < 1e-9  # goal to the right (+x) of the end-effector, same y
    assert obs[0, 42, 42] > 150 and obs[0, 0, 42] < 50  # corridor in the middle, wall above
    assert info["ee_xy"] == info["particle_xy"] == pytest.approx((-0.055, 0.445))


def test_obstacle_rule_on_views():
    env = make([corridor()])
    v = np.full((84, 84), 255, np.uint8)
    assert not env.obstacle_detected(v)
    v[34:49, 34:49] = 0
    assert env.obstacle_detected(v)
    v = np.full((84, 84), 255, np.uint8)
    v[34:40, 34:49] = 0  # 6/15 of the window dark: mean 153 >= 150
    assert not env.obstacle_detected(v)
    v[34:41, 34:49] = 0  # 7/15: mean 136 < 150
    assert env.obstacle_detected(v)


def test_success_gives_positive_reward():
    env = make([corridor()])
    env.reset(seed=0, options={"start": (-0.055, 0.445), "goal": (-0.015, 0.445)})
    out = run(env, [0] * 10)
    r, term, trunc, info = out[-1]
    assert info["reason"] == "success" and term and not trunc
    assert math.dist(info["particle_xy"], info["goal_xy"]) < 0.02 and r > 0.9
    assert sum(o[0] for o in out[:-1]) > 0 and all(-0.02 < o[0] < 0.2 for o in out[:-1])  # shaping


def test_obstacle_terminates_with_negative_reward():
    env = make([corridor()])
    env.reset(seed=0, options={"start": (0.005, 0.445), "goal": (0.045, 0.445)})
    r, term, trunc, info = run(env, [2] * 10)[-1]  # +y, into the wall
    assert info["reason"] == "obstacle" and term and r < -0.9
    assert info["ee_xy"][1] > 0.46


def test_particle_into_wall_is_a_collision():
    env = make([corridor()], obstacle_threshold=0.0)  # camera rule off: the physics decides
    env.reset(seed=0, options={"start": (0.005, 0.445), "goal": (0.045, 0.445)})
    r, term, trunc, info = run(env, [2] * 15)[-1]
    assert info["reason"] == "collision" and term and r < -0.9
    assert info["particle_xy"][1] > 0.475 - 0.0025 - 1e-9


def test_ik_failure_terminates():
    m = corridor(origin=(0.6, -0.05), length=0.4)
    env = make([m])
    env.reset(seed=0, options={"start": (0.705, -0.005), "goal": (0.655, -0.005)})
    r, term, trunc, info = run(env, [0] * 40)[-1]
    assert info["reason"] == "ik_failure" and term and r < -0.9
    assert not env.robot.reachable([info["ee_xy"][0] + 0.01, info["ee_xy"][1], 0.105])


def test_max_steps_truncates_with_negative_reward():
    env = make([corridor()], max_steps=3)
    env.reset(seed=0, options={"start": (-0.055, 0.445), "goal": (0.045, 0.445)})
    out = run(env, [0, 1, 0, 1])
    r, term, trunc, info = out[-1]
    assert len(out) == 3 and trunc and not term and info["reason"] == "max_steps" and r < -0.9
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_disturbance_and_switching_controller_recapture():
    env = make([open_square()], disturbance=DisturbanceConfig(at_steps=(1,), magnitude=(0.11, 0.12), min_step=0))
    env.reset(seed=1, options={"start": (0.005, 0.455), "goal": (0.085, 0.455)})
    # camera images that tell the grid nodes apart (all bright enough for the obstacle rule)
    env.atlas.view = lambda x, y: np.full((84, 84), 150 + sum(env.map.nearest_node(x, y)) % 100, np.uint8)
    obs, r, term, trunc, info = env.step(3)
    assert info["disturbances"] == 1 and info["sc1_steps"] > 0 and info["controller"] == 1
    assert info["reason"] == "running"
    assert math.dist(info["ee_xy"], info["particle_xy"]) < 0.02  # handed back after recapture
    assert np.array_equal(obs[0], env.atlas.view(*env.ee))  # the camera where Sub-controller 1 left it
    traj = np.asarray(env.trajectory)
    assert (traj[:, 4] == 1).sum() == info["sc1_steps"] and (traj[:, 4] == 0).sum() == 1


def test_each_recapture_starts_without_the_last_ones_velocity_estimate():
    """Sub-controller 1 estimates the particle's velocity from its last call; a new recapture (after Sub-controller 2
    steps and a new drag) starts without one, not from where the particle was when the last recapture ended."""
    env = make([open_square()], disturbance=DisturbanceConfig(at_steps=(1, 4), magnitude=(0.11, 0.12), min_step=0))
    env.reset(seed=2, options={"start": (0.005, 0.455), "goal": (0.085, 0.455)})
    env.atlas.view = lambda x, y: np.full((84, 84), 200, np.uint8)
    phases, first_calls = [], []
    recapture, sc1 = env._recapture, type(env.sc1).__call__

    def counted():
        phases.append(len(phases))
        return recapture()

    def spied(self, *args):
        if len(first_calls) < len(phases):
            first_calls.append(self._last)
        return sc1(self, *args)
    env._recapture = counted
    type(env.sc1).__call__ = spied
    try:
        for a in (3, 0, 0, 0, 0):
            info = env.step(a)[-1]
    finally:
        type(env.sc1).__call__ = sc1
    assert info["disturbances"] == 2 and len(phases) == 2 and first_calls == [None, None]


def test_switching_distance_decides_who_brings_a_dragged_particle_back():
    """A particle dragged 7 cm: past the default 5 cm Sub-controller 1 recaptures it; under the
    thesis's 10 cm nobody does (the magnet's pull alone acts on it while Sub-controller 2 goes on)."""
    for switch, recaptured in ((None, True), (0.10, False)):
        kw = {} if switch is None else {"switching": rl.SwitchingConfig(switch_distance=switch)}
        env = make([open_square()], disturbance=DisturbanceConfig(at_steps=(1,), magnitude=(0.07, 0.07), min_step=0),
                   **kw)
        env.reset(seed=1, options={"start": (0.005, 0.455), "goal": (0.085, 0.455)})
        info = env.step(3)[-1]
        assert info["disturbances"] == 1 and (info["sc1_steps"] > 0) == recaptured
        assert (math.dist(info["ee_xy"], info["particle_xy"]) < 0.02) == recaptured


def corner_map(res=0.002):
    """An open square whose lower-left quarter (x < 0, y < 0.42) is a wall block."""
    n = int(round(0.3 / res))
    img = np.full((n, n), FREE, np.uint8)
    y, x = 0.30 + (n - 0.5 - np.arange(n)) * res, -0.15 + (np.arange(n) + 0.5) * res
    img[np.ix_(y < 0.42, x < 0.0)] = WALL
    return Map(img, res, (-0.15, 0.30), name="corner")


def test_fast_recapture_does_not_pull_the_particle_across_a_wall_corner():
    """The particle lies 2 cm right of the block's edge, the magnet 10.6 cm away above the block: the
    straight line between them crosses the corner. Approaching at 0.15 m/s the magnet drags the
    particle into the corner; at the UR5's tool speed (the default) it is over it in one period."""
    for speed, reason, sc1 in ((0.15, "collision", 5), (None, "running", 1)):
        kw = {} if speed is None else {"switching": rl.SwitchingConfig(max_speed=speed)}
        env = make([corner_map()], **kw)
        env.reset(seed=0, options={"start": (-0.065, 0.465), "goal": (0.105, 0.545)})
        env.atlas.view = lambda x, y: np.full((84, 84), 200, np.uint8)
        env.sim.reset(0.02, 0.39)  # dragged there
        info = env.step(0)[-1]
        assert (info["reason"], info["sc1_steps"]) == (reason, sc1)


def test_sub_controller_1_moves_respect_the_joint_speed_limit():
    from cmlearn.rl.ur5 import JOINT_SPEED
    env = make([open_square()])
    env.reset(seed=0, options={"start": (0.005, 0.455), "goal": (0.085, 0.455)})
    q0, cap = env.q.copy(), JOINT_SPEED * env.config.control_period
    near = (0.015, 0.455)  # 1 cm: untouched
    assert env._joint_limited(near)[0] == near
    far = (-0.145, 0.305)  # 21 cm in one period: shortened along the same line until the joints keep up
    (x, y), q = env._joint_limited(far)
    assert q is not None and cap * 0.9 < np.abs(q - q0).max() <= cap
    assert np.allclose(env.robot.fk(q)[:2, 3], (x, y), atol=1e-6)
    t = (x - 0.005) / (far[0] - 0.005)
    assert 0.05 < t < 0.95 and math.isclose(y, 0.455 + t * (far[1] - 0.455), abs_tol=1e-9)


def test_seeded_determinism():
    def rollout():
        env = MagneticParticleEnv(map_seeds=(3, 4), map_size=(0.24, 0.24), atlas_cache=None,
                                  disturbance=DisturbanceConfig(probability=0.2, magnitude=(0.03, 0.06), min_step=1))
        obs, info = env.reset(seed=7)
        rng, out = np.random.default_rng(0), [(obs.copy(), 0.0, info)]
        for _ in range(25):
            obs, r, term, trunc, info = env.step(int(rng.integers(4)))
            out.append((obs.copy(), r, info))
            if term or trunc:
                obs, info = env.reset()
                out.append((obs.copy(), 0.0, info))
        return out
    a, b = rollout(), rollout()
    assert len(a) == len(b)
    for (oa, ra, ia), (ob, rb, ib) in zip(a, b):
        assert np.array_equal(oa, ob) and ra == rb and ia == ib


def test_gymnasium_checker_registered_id_and_vector_env():
    from gymnasium.utils.env_checker import check_env
    env = gym.make(rl.ENV_ID, map_seeds=(0,), map_size=(0.24, 0.24), atlas_cache=None)
    check_env(env.unwrapped, skip_render_check=True)
    venv = rl.make_vector_env(2, map_seeds=(0,), map_size=(0.24, 0.24), atlas_cache=None)
    obs, _ = venv.reset(seed=0)
    obs, r, term, trunc, _ = venv.step(np.array([0, 2]))
    assert obs.shape == (2, 2, 84, 84) and r.shape == (2,)
    venv.close()


def test_torchrl_wrapper_and_batched_env_specs():
    pytest.importorskip("torchrl")
    from torchrl.envs.utils import check_env_specs

    from cmlearn.rl.torchrl_env import make_batched_env, make_torchrl_env
    kw = dict(map_seeds=(0,), map_size=(0.24, 0.24), atlas_cache=None)
    env = make_torchrl_env(**kw)
    check_env_specs(env, seed=0)
    td = env.rollout(5)
    assert td["observation"].shape[-3:] == (2, 84, 84)
    batched = make_batched_env(2, seed=0, categorical_action_encoding=True, **kw)
    check_env_specs(batched)
    assert batched.rollout(3, break_when_any_done=False)["next", "reward"].shape == (2, 3, 1)
    batched.close()


def test_procedural_maps_are_seeded_and_connected():
    a, b, c = procedural_map(5), procedural_map(5), procedural_map(6)
    assert np.array_equal(a.image, b.image) and not np.array_equal(a.image, c.image)
    for m in (a, c):
        s, g = m.sample_start_goal(np.random.default_rng(0), 0.1)
        assert np.isfinite(m.geodesic(g, "safe")[s]) and m.geodesic(g, "safe")[s] >= 0.1
    with pytest.raises(TypeError, match="seed"):
        procedural_map(1.5)
    assert rl.map_seeds("train", 3) == (0, 1, 2) and not set(rl.map_seeds("unseen", 50)) & set(rl.map_seeds("train", 50))


def test_atlas_cache_is_atomic_and_keyed(tmp_path):
    m = corridor(length=0.06, height=0.05, width=0.03)
    atlas = Atlas(m, rl.CameraSpec(), tmp_path).precompute()
    files = list(tmp_path.iterdir())
    assert [f.name for f in files] == [atlas.path.name] and atlas.renders == m.nx * m.ny
    again = Atlas(m, rl.CameraSpec(), tmp_path)
    assert again.renders == 0 and np.array_equal(again.images, atlas.images)
    assert Atlas(m, rl.CameraSpec(extent=0.1), tmp_path).key != atlas.key
    # the rendered view is the map under the camera
    x, y = m.node_xy(2, 2)
    r, c = m.to_pixel(x, y)
    view = atlas.node_view(2, 2)
    assert view[42, 42] > 200 and view[0, 42] < 50 and view[83, 42] < 50 and m.image[r, c] == FREE


def test_bad_inputs(tmp_path):
    bad = tmp_path / "not_an_image.png"
    bad.write_text("hello")
    with pytest.raises(ValueError, match="cannot read a map image"):
        load_map(bad)
    with pytest.raises(ValueError, match="cannot read a map image"):
        load_map(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="no free cell"):
        Map(np.full((50, 50), WALL, np.uint8))
    with pytest.raises(ValueError, match="no free cell"):
        corridor(width=0.015)  # free pixels, but narrower than the clearance
    env = make([corridor()])
    with pytest.raises(ValueError, match="start"):
        env.reset(seed=0, options={"start": (0.005, 0.49), "goal": (0.045, 0.445)})
    with pytest.raises(ValueError, match="goal"):
        env.reset(seed=0, options={"start": (0.005, 0.445), "goal": (0.2, 0.445)})
    two = corridor().image.copy()
    two[:, 45:55] = WALL  # a wall across the corridor
    env2 = make([Map(two, 0.002, (-0.1, 0.40))])
    with pytest.raises(ValueError, match="not reachable"):
        env2.reset(seed=0, options={"start": (-0.055, 0.445), "goal": (0.045, 0.445)})
    env.reset(seed=0)
    for a in (4, -1, 1.5, "0", None, True):
        with pytest.raises(ValueError, match="action"):
            env.step(a)
    env.step(np.int64(0))
    with pytest.raises(TypeError, match="unknown EnvConfig"):
        MagneticParticleEnv(colour="red")
    for kw, msg in (({"map_size": (0.4, 0.0)}, "map_size must be two finite lengths > 0"),
                    ({"obstacle_threshold": 300.0}, r"obstacle_threshold .* must be in \[0, 255\]"),
                    ({"min_start_goal_distance": -0.1}, "min_start_goal_distance must be finite and >= 0"),
                    ({"tool_length": -0.06}, "tool_length must be finite and > 0"),
                    ({"step_penalty": float("nan")}, "step_penalty must be finite"),
                    ({"max_steps": 2.5}, "max_steps must be an integer >= 1, got 2.5"),
                    ({"sc1_max_steps": 0}, "sc1_max_steps must be an integer >= 1")):
        with pytest.raises(ValueError, match=msg):
            MagneticParticleEnv(**kw)
    for kw, msg in (({"disturbance": 0.03}, "disturbance must be a DisturbanceConfig, got 0.03"),
                    ({"camera": None}, "camera must be a CameraSpec"),
                    ({"switching": 1}, "switching must be a SwitchingConfig or None, got 1")):
        with pytest.raises(TypeError, match=msg):
            MagneticParticleEnv(**kw)
    for kw, msg in (({"probability": 2.0}, "probability"), ({"magnitude": (0.1,)}, "magnitude must be"),
                    ({"max_count": -1}, "max_count must be an integer >= 0"),
                    ({"min_step": 1.5}, "min_step must be an integer >= 0"),
                    ({"at_steps": (3, -1)}, r"at_steps must be step numbers")):
        with pytest.raises(ValueError, match=msg):
            DisturbanceConfig(**kw)


def test_a_given_start_or_goal_gets_a_connected_partner():
    """Two parallel corridors: the sampled goal of a given start (and start of a given goal) is in its corridor,
    at least ``min_start_goal_distance`` away (it was drawn anywhere: 'not reachable' in about half the seeds)."""
    img = np.full((75, 150), WALL, np.uint8)
    img[5:30, 5:145] = img[45:70, 5:145] = FREE
    env = make([Map(img, 0.002, (-0.15, 0.35), name="two")])
    given = (-0.105, 0.465)
    for seed in range(8):
        for key, other in (("start", "goal_xy"), ("goal", "ee_xy")):
            _, info = env.reset(seed=seed, options={key: given})
            assert abs(info[other][1] - given[1]) < 0.03 and math.dist(info[other], given) >= 0.1 - 1e-9
    for idx in (1.5, "0", True):
        with pytest.raises(ValueError, match=r"options\['map_index'\] must be an int"):
            env.reset(seed=0, options={"map_index": idx})
    with pytest.raises(ValueError, match="start must be 2 finite coordinates"):
        env.reset(seed=0, options={"start": (-0.105, 0.465, 0.0)})
    with pytest.raises(ValueError, match="origin must be 2 finite coordinates"):
        Map(img, 0.002, (math.nan, 0.35))
    env.close()


def test_settings_that_did_nothing_are_refused(tmp_path):
    """A map_path beside the default map_seeds was ignored (the procedural maps ran), maps=[] fell back to them,
    a misspelt reset option drew a random map and goal, and disturbance steps that can never come (0, before
    min_step, past max_count) were dropped."""
    import cv2
    cv2.imwrite(str(tmp_path / "hall.png"), corridor().image)
    with pytest.raises(ValueError, match=r"map_path .*hall.png' and map_seeds .*give map_seeds=\(\) with map_path"):
        MagneticParticleEnv(map_path=str(tmp_path / "hall.png"))
    with pytest.raises(ValueError, match="map_path: no such map image"):
        MagneticParticleEnv(map_seeds=(), map_path=str(tmp_path / "none.png"))
    env = MagneticParticleEnv(map_seeds=(), map_path=str(tmp_path / "hall.png"), atlas_cache=None)
    assert env.reset(seed=0)[1]["map"] == "hall"
    with pytest.raises(TypeError, match=r"maps must be a non-empty list .*got \[\]"):
        MagneticParticleEnv(maps=[])
    with pytest.raises(ValueError, match=r"options: unknown key\(s\) \['map_idx'\]"):
        env.reset(seed=0, options={"map_idx": 0})
    for kw in ({"at_steps": (0,), "min_step": 0}, {"at_steps": (3,)}, {"at_steps": (5, 6, 7)}):
        with pytest.raises(ValueError, match=r"at_steps must be at most max_count \(2\) steps, each >= 1 and >= "):
            DisturbanceConfig(**kw)
    assert DisturbanceConfig(at_steps=(5, 9)).at_steps == (5, 9)
    with pytest.raises(TypeError, match="max_steps"):  # validated and never read: the recapture limit is
        rl.SwitchingConfig(max_steps=1)                # EnvConfig.sc1_max_steps
