"""Classical baselines: quadtree obstacle rectangles, ERRT, modulated attractor dynamics, and the
Sub-controller 2 wrappers on synthetic camera views."""
import math

import numpy as np
import pytest

from cmlearn.planning import (ERRT, AttractorController, AttractorDynamics, ERRTController, Superellipse,
                              covered_mask, direction_to_action, feedback_gain_G, fit_superellipses,
                              merge_rectangles, quadtree_rectangles, segment_hits)


def blobs(seed=0, size=84):
    rng = np.random.default_rng(seed)
    img = np.full((size, size), 230, np.uint8)
    for _ in range(6):
        r, c = rng.integers(0, size - 10, 2)
        h, w = rng.integers(3, 25, 2)
        img[r:r + h, c:c + w] = rng.integers(0, 51)
    img[rng.random((size, size)) < 0.01] = 10  # speckles
    img[5:15, 60:70] = 100  # gray but not an obstacle (> 50)
    return img


@pytest.mark.parametrize("min_size", [1, 3, 5, 8])
def test_quadtree_covers_every_obstacle_pixel_with_min_size(min_size):
    for seed in range(4):
        img = blobs(seed)
        rects = quadtree_rectangles(img, 50, min_size)
        cover = covered_mask(img.shape, rects)
        assert cover[img <= 50].all()
        assert all(r1 - r0 >= min_size and c1 - c0 >= min_size for r0, c0, r1, c1 in rects)
        if min_size == 1:  # exact at pixel resolution
            assert not cover[img > 50].any()
        unmerged = quadtree_rectangles(img, 50, min_size, merge=False)
        assert len(rects) <= len(unmerged)
        assert np.array_equal(covered_mask(img.shape, unmerged), cover)


def test_quadtree_edge_cases():
    assert quadtree_rectangles(np.full((16, 16), 255, np.uint8)) == []
    assert quadtree_rectangles(np.zeros((16, 16), np.uint8)) == [(0, 0, 16, 16)]
    assert merge_rectangles([(0, 0, 2, 4), (2, 0, 4, 4), (0, 4, 4, 6)]) == [(0, 0, 4, 6)]
    with pytest.raises(ValueError, match="min_size"):
        quadtree_rectangles(np.zeros((4, 4)), min_size=0)
    with pytest.raises(ValueError, match="gray"):
        quadtree_rectangles(np.zeros(4))


def test_segment_hits():
    rects = np.array([[0.4, 0.4, 0.6, 0.6]])
    assert segment_hits((0.0, 0.5), (1.0, 0.5), rects)
    assert not segment_hits((0.0, 0.0), (1.0, 0.0), rects)
    assert segment_hits((0.0, 0.35), (1.0, 0.35), rects, margin=0.06)
    assert segment_hits((0.5, 0.5), (0.5, 0.5), rects) and not segment_hits((0.1, 0.1), (0.1, 0.1), rects)


def path_ok(path, rects, margin=0.0):
    return all(not segment_hits(a, b, rects, margin) for a, b in zip(path[:-1], path[1:]))


def test_errt_finds_a_path_and_reuses_waypoints():
    rects = np.array([[0.3, 0.0, 0.35, 0.8], [0.6, 0.2, 0.65, 1.0]])  # a zig-zag
    planner = ERRT((0, 0, 1, 1), step=0.05, margin=0.01, seed=0)
    path = planner.plan((0.1, 0.1), (0.9, 0.9), rects)
    assert path is not None and path[0] == (0.1, 0.1) and path[-1] == (0.9, 0.9)
    assert path_ok(path, rects, 0.01)
    first = len(planner.tree)
    assert len(planner.waypoints) > 0
    again = planner.plan((0.1, 0.12), (0.9, 0.9), rects)  # replanning grows along the cache
    assert again is not None and path_ok(again, rects, 0.01) and len(planner.tree) <= 2 * first


def test_errt_reports_failure_on_a_sealed_map():
    box = np.array([[0.7, 0.7, 1.0, 0.72], [0.7, 0.7, 0.72, 1.0], [0.7, 0.98, 1.0, 1.0], [0.98, 0.7, 1.0, 1.0]])
    planner = ERRT((0, 0, 1, 1), step=0.05, max_nodes=300, seed=0)  # the default margin, 0
    assert planner.plan((0.1, 0.1), (0.85, 0.85), box) is None
    assert len(planner.tree) > 300  # it searched the whole node budget before it gave up
    assert planner.plan((0.1, 0.1), (0.9, 0.9), np.zeros((0, 4))) == [(0.1, 0.1), (0.9, 0.9)]  # straight across
    wall = np.array([[0.4, 0.0, 0.5, 0.6]])
    path = planner.plan((0.1, 0.1), (0.9, 0.9), wall)
    assert path is not None and len(path) > 2 and path_ok(path, wall)
    assert planner.plan((0.45, 0.3), (0.9, 0.9), wall) is None  # a start inside an obstacle
    for bounds in ((1, 0, 0, 1), ((0, 1), (0, 1))):
        with pytest.raises(ValueError, match=r"bounds must be \(xmin, ymin, xmax, ymax\)"):
            ERRT(bounds)
    for kw in ({"margin": -0.01}, {"cache_size": -1}):
        with pytest.raises(ValueError, match="margin .* and cache_size .* must be >= 0"):
            ERRT((0, 0, 1, 1), **kw)


def test_feedback_gain_and_nominal_convergence():
    K = np.diag([2.0, 3.0])
    assert np.allclose(feedback_gain_G(K), K - np.eye(2))  # A = B = I
    dyn = AttractorDynamics(K)
    p, goal = np.array([0.0, 0.0]), np.array([0.3, -0.2])
    for _ in range(1200):
        p = dyn.step(p, goal, [], 0.02)
    assert np.abs(p - goal).max() < 1e-6
    with pytest.raises(ValueError, match="stabilise"):
        AttractorDynamics(0.5)


@pytest.mark.parametrize("obstacle", [Superellipse((0.5, 0.5), 0.1, 0.05, 0.0, 4.0),
                                      Superellipse((0.5, 0.45), 0.12, 0.04, 0.6, 4.0),
                                      Superellipse((0.5, 0.5), 0.08, 0.08, 0.0, 2.0)])
def test_modulated_attractor_never_enters_a_convex_obstacle(obstacle):
    dyn = AttractorDynamics(2.0)
    goal = np.array([1.0, 0.5])
    rng = np.random.default_rng(0)
    for y0 in np.concatenate([np.linspace(0.3, 0.7, 15), rng.uniform(0.3, 0.7, 5)]):
        p = np.array([0.0, y0])
        gmin = math.inf
        for _ in range(3000):
            p = dyn.step(p, goal, [obstacle], 0.002)
            gmin = min(gmin, obstacle.gamma(p))
        assert gmin > 1.0 - 1e-9  # never inside (a head-on start stops on the boundary: KB12's saddle)
        if abs(y0 - obstacle.center[1]) > 0.01:
            assert gmin > 1.0 and np.linalg.norm(p - goal) < 0.05  # and gets past it


def test_superellipses_cover_what_the_camera_sees():
    pytest.importorskip("cv2")
    view = np.full((84, 84), 230, np.uint8)
    view[10:30, 50:80] = 0
    view[60:70, 5:12] = 30
    mpp, at = 0.12 / 84, (0.0, 0.5)
    obs = fit_superellipses(view, at, mpp, margin=0.0)
    assert obs
    for r, c in np.argwhere(view <= 50)[::7]:
        x, y = at[0] + (c + 0.5 - 42) * mpp, at[1] - (r + 0.5 - 42) * mpp
        assert min(o.gamma((x, y)) for o in obs) <= 1.0 + 1e-9
    assert all(o.gamma(at) > 1.0 for o in obs)  # the free centre is outside every obstacle


def test_controllers_choose_valid_actions():
    pytest.importorskip("cv2")
    assert [direction_to_action(v) for v in ((1, 0.2), (-1, 0), (0.1, 1), (0, -1))] == [0, 1, 2, 3]
    obs = np.zeros((2, 84, 84), np.uint8)
    obs[0] = 230
    obs[0, :, 60:] = 0  # a wall to the right (+x)
    info = {"ee_xy": (0.0, 0.5), "view_xy": (0.0, 0.5), "goal_xy": (0.3, 0.5), "bounds": (-0.2, 0.3, 0.4, 0.7)}
    att = AttractorController(0.12 / 84)
    a = att.act(obs, info)
    assert att.obstacles and a in (0, 1, 2, 3)
    p = np.asarray(info["ee_xy"])
    nominal = att.dyn.nominal(p, info["goal_xy"])
    v = att.dyn.velocity(p, info["goal_xy"], att.obstacles)
    assert v[0] < nominal[0]  # the modulation brakes the motion toward the wall
    nxt = p + 0.01 * np.array([(1, 0), (-1, 0), (0, 1), (0, -1)][a])
    assert min(o.gamma(nxt) for o in att.obstacles) > 1.0  # the chosen move stays outside
    errt = ERRTController(0.12 / 84, seed=0)
    errt.reset(info)
    a = errt.act(obs, info)
    assert a in (0, 1, 2, 3) and errt.replans == 1 and len(errt.rects) > 0


def test_planners_reject_bad_input_instead_of_a_silent_result():
    planner = ERRT((0, 0, 1, 1), step=0.05, seed=0)
    with pytest.raises(ValueError, match=r"rects must be \(n, 4\)"):  # was silently reshaped into 3 rectangles
        planner.plan((0.1, 0.1), (0.9, 0.9), np.zeros((2, 6)))
    for start in ((math.nan, 0.1), (0.1, 0.1, 0.0)):
        with pytest.raises(ValueError, match="start must be 2 finite coordinates"):
            planner.plan(start, (0.9, 0.9), np.zeros((0, 4)))
    with pytest.raises(ValueError, match="goal must be 2 finite coordinates"):
        planner.plan((0.1, 0.1), (0.9, math.inf), np.zeros((0, 4)))
    with pytest.raises(ValueError, match="max_nodes an int >= 1"):
        ERRT((0, 0, 1, 1), max_nodes=2.5)
    with pytest.raises(ValueError, match="bounds must be"):
        ERRT((0, 0, math.inf, 1))
    dyn = AttractorDynamics(2.0)
    for h in (0.0, -0.1, math.nan):  # a negative step walked away from the goal, NaN gave NaN
        with pytest.raises(ValueError, match="h .*must be finite and > 0"):
            dyn.step((0.0, 0.0), (1.0, 0.0), [], h)
    with pytest.raises(ValueError, match="p must be 2 finite coordinates"):
        dyn.velocity((math.nan, 0.0), (1.0, 0.0), [Superellipse((0.5, 0.5), 0.1, 0.1)])
    with pytest.raises(ValueError, match="goal must be 2 finite coordinates"):
        dyn.velocity((0.0, 0.0), (1.0, 0.0, 0.0), [])
    with pytest.raises(ValueError, match="A and B must be 2x2"):
        AttractorDynamics(2.0, A=np.eye(3))
    with pytest.raises(ValueError, match="center, a, b, angle and n must be finite"):
        Superellipse((math.nan, 0.0), 0.1, 0.1)
    with pytest.raises(ValueError, match="v must be a finite 2-D direction"):  # was the move +x
        direction_to_action((math.nan, 0.0))
    for cls in (AttractorController, ERRTController):
        with pytest.raises(ValueError, match="mpp"):
            cls(0.0)
        # a NaN threshold saw no obstacle (the controllers steered into walls), a negative margin failed later
        for kw, msg in ((dict(threshold=math.nan), r"threshold \(a grey level"), (dict(threshold=300), "threshold"),
                        (dict(margin=-0.05), "margin must be finite and >= 0")):
            with pytest.raises(ValueError, match=msg):
                cls(0.002, **kw)
    with pytest.raises(ValueError, match="tile must be an integer >= 1"):
        AttractorController(0.002, tile=0)
    with pytest.raises(ValueError, match="K must be a finite scalar or 2x2"):
        AttractorController(0.002, K=math.nan)
    with pytest.raises(ValueError, match="move must be finite and > 0"):
        ERRTController(0.002, move=0.0)
