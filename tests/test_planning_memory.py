"""Explored-map memory and optimistic planner: plans on synthetic views, a dead end in the
environment, and the environment's waypoint marker."""
import numpy as np
import pytest

from cmlearn.planning import MemoryPlanner, MemoryPlannerController

MPP = 0.12 / 84
BOUNDS = (0.0, 0.0, 0.3, 0.3)


def wall_view(col0, col1, size=84):
    """A free view with a dark vertical band over columns [col0, col1)."""
    v = np.full((size, size), 230, np.uint8)
    v[:, col0:col1] = 10
    return v


def walk(planner, start, max_moves=80):
    """Follow the planner's cheapest move from ``start`` without new views; the visited positions."""
    p, path = np.array(start, float), [tuple(start)]
    for _ in range(max_moves):
        if np.linalg.norm(p - planner.goal) < 1e-6:
            break
        moves, _ = planner.plan(p)
        p = p + 0.01 * np.array([(1, 0), (-1, 0), (0, 1), (0, -1)][int(np.argmin(moves))])
        path.append(tuple(p))
    return np.array(path)


def test_unknown_space_is_free_and_a_seen_wall_is_avoided():
    pl = MemoryPlanner(MPP, lookahead=8)
    pl.reset(BOUNDS, (0.25, 0.15))
    moves, wp = pl.plan((0.05, 0.15))
    assert np.argmin(moves) == 0 and moves[0] == pytest.approx(20.0)  # straight +x, 20 moves, no soft cost
    assert moves[1] == pytest.approx(22.0) and wp == pytest.approx((0.13, 0.15))
    # a view centred at (0.12, 0.15) shows a 12 cm wall across x = 0.132..0.146
    pl.add_view(wall_view(50, 60), (0.12, 0.15))
    assert (pl.occ == 1).sum() > 0 and (pl.occ == 0).sum() > 0 and (pl.occ == -1).sum() > 0
    moves2, wp2 = pl.plan((0.05, 0.15))
    assert moves2.min() > 20.0 + 2 * 6  # around the wall's end: at least 6 cm up and 6 cm back down
    path = walk(pl, (0.05, 0.15))
    assert np.allclose(path[-1], (0.25, 0.15)) and len(path) < 60
    xs, ys = path[:, 0], path[:, 1]
    crossing = (xs > 0.125) & (xs < 0.155)
    assert crossing.any() and np.all(np.abs(ys[crossing] - 0.15) > 0.06 + 0.012 - 1e-9)  # past the wall's end


def test_goal_within_lookahead_is_the_waypoint_and_bad_input():
    pl = MemoryPlanner(MPP, lookahead=8)
    pl.reset(BOUNDS, (0.104, 0.15))
    assert pl.plan((0.05, 0.15))[1] == (0.104, 0.15)
    moves, wp = pl.plan((-0.01, 0.15))  # an end-effector off the map: every move is blocked, no crash
    assert np.isinf(moves).all() and wp == (0.104, 0.15)
    with pytest.raises(ValueError, match="lookahead"):
        MemoryPlanner(MPP, lookahead=0)
    with pytest.raises(ValueError, match="metres_per_pixel"):
        MemoryPlanner(0.0)
    with pytest.raises(ValueError, match="bounds"):
        pl.reset((0.0, 0.0, 0.0, 0.3), (0.1, 0.1))
    with pytest.raises(RuntimeError, match="reset"):
        MemoryPlanner(MPP).plan((0.1, 0.1))
    for goal in ((0.5, 0.15), (float("nan"), 0.15)):  # a goal off the map was clipped to its edge: every move inf
        with pytest.raises(ValueError, match="goal_xy must be a finite point inside bounds"):
            pl.reset(BOUNDS, goal)
    with pytest.raises(ValueError, match="bounds must be finite"):
        pl.reset((0.0, 0.0, float("inf"), 0.3), (0.1, 0.1))
    pl.reset(BOUNDS, (0.25, 0.15))
    with pytest.raises(ValueError, match="ee_xy must be 2 finite coordinates"):
        pl.plan((float("nan"), 0.15))
    with pytest.raises(ValueError, match=r"view must be a square \(n, n\)"):
        pl.add_view(np.full((84, 40), 230, np.uint8), (0.12, 0.15))
    with pytest.raises(ValueError, match="view_xy must be a finite"):  # NaN: the view was dropped without a word
        pl.add_view(np.full((84, 84), 230, np.uint8), (float("nan"), 0.15))


pytest.importorskip("pybullet")
pytest.importorskip("gymnasium")
from cmlearn.rl import Map, MagneticParticleEnv  # noqa: E402
from cmlearn.rl.switching import run_episode  # noqa: E402


def hook_map(res=0.002):
    """A blind spur: the start faces the goal across a wall; the way round is up, across and down."""
    W, H = 0.36, 0.30
    img = np.full((int(round(H / res)), int(round(W / res))), 20, np.uint8)
    x = (np.arange(img.shape[1]) + 0.5) * res
    y = (img.shape[0] - 0.5 - np.arange(img.shape[0])) * res
    X, Y = np.meshgrid(x, y)
    free = (((Y > 0.02) & (Y < 0.08) & (X > 0.02) & (X < 0.16))      # the spur toward the goal
            | ((X > 0.02) & (X < 0.08) & (Y > 0.02) & (Y < 0.28))     # up
            | ((Y > 0.22) & (Y < 0.28) & (X > 0.02) & (X < 0.34))     # across
            | ((X > 0.28) & (X < 0.34) & (Y > 0.02) & (Y < 0.28)))    # down to the goal
    img[free] = 235
    return Map(img, res, (-0.18, 0.30), name="hook")


@pytest.fixture(scope="module")
def hook_env():
    env = MagneticParticleEnv(maps=[hook_map()], atlas_cache=None, waypoint_lookahead=8)
    yield env
    env.close()


START, GOAL = {"start": (-0.055, 0.345)}, {"goal": (0.125, 0.345)}


def test_memory_controller_leaves_the_blind_spur(hook_env):
    res = run_episode(hook_env, MemoryPlannerController(MPP), options={**START, **GOAL})
    assert res.success, res.reason
    assert 40 <= res.steps <= 100  # the way round is about 64 moves; the spur costs a few more
    xs = np.array([p[0] for p in res.trajectory])
    assert xs.min() < -0.11  # it went back through the vertical corridor


def test_env_marks_the_waypoint_instead_of_the_goal(hook_env):
    obs, info = hook_env.reset(seed=0, options={**START, **GOAL})
    wx, wy = info["waypoint_xy"]
    assert info["goal_xy"] == pytest.approx((0.125, 0.345))
    assert abs(wx - info["ee_xy"][0]) + abs(wy - info["ee_xy"][1]) == pytest.approx(0.08)  # 8 moves
    top = np.argwhere(obs[1, :42] == 255).mean(0)
    assert top == pytest.approx(hook_env._marker(wx, wy, 42, 84), abs=1e-9)
    assert np.abs(top - hook_env._marker(*info["goal_xy"], 42, 84)).max() >= 2  # not the goal's marker
    plain = MagneticParticleEnv(maps=[hook_env.get_map(0)], atlas_cache=None)
    obs0, info0 = plain.reset(seed=0, options={**START, **GOAL})
    assert info0["waypoint_xy"] == info0["goal_xy"]
    assert np.argwhere(obs0[1, :42] == 255).mean(0) == pytest.approx(plain._marker(*info0["goal_xy"], 42, 84))
    plain.close()
    with pytest.raises(ValueError, match="waypoint_lookahead"):
        MagneticParticleEnv(maps=[hook_env.get_map(0)], atlas_cache=None, waypoint_lookahead=-1)
    with pytest.raises(ValueError, match="waypoint_prior"):
        MagneticParticleEnv(maps=[hook_env.get_map(0)], atlas_cache=None, waypoint_prior=True)


def test_sweep_prior_starts_the_memory_from_the_whole_map(hook_env):
    swept = MagneticParticleEnv(maps=[hook_env.get_map(0)], atlas_cache=None, waypoint_lookahead=8,
                                waypoint_prior=True)
    obs, info = swept.reset(seed=0, options={**START, **GOAL})
    assert (swept.planner.occ != -1).all()  # every cell seen in the sweep
    (wx, _), (ex, _) = info["waypoint_xy"], info["ee_xy"]
    assert wx <= ex - 0.05  # back along the spur toward the way round, never into the blind end
    res = run_episode(swept, MemoryPlannerController(MPP), options={**START, **GOAL})
    assert res.success and res.steps <= 80  # straight round, without a look into the blind spur
    swept.close()
    with pytest.raises(ValueError, match="prior"):
        MemoryPlanner(MPP).reset(BOUNDS, (0.1, 0.1), prior=np.zeros((3, 3), np.int8))
