"""Bad input to the robot, camera, maps, atlas, demonstrations, teacher, quadtree, error metrics, benchmark helpers
and sealed checkpoints: each gave a silently wrong result, NaN or a traceback from deep inside numpy/torch/pybullet,
and now gets an error naming the parameter."""
import json
import math

import numpy as np
import pytest
import torch

from cmlearn.eval.metrics import axis_errors, rmse_t
from cmlearn.eval.timing import json_line, lgvi_blocks
from cmlearn.io import save_sealed
from cmlearn.planning.quadtree import quadtree_rectangles

FREE, WALL = 235, 20


def corridor(length=0.1, height=0.06, width=0.04, res=0.002):
    """A straight corridor along x on a grid of 10 x 6 nodes (1 cm)."""
    from cmlearn.rl.maps import Map
    H, W = int(round(height / res)), int(round(length / res))
    img = np.full((H, W), WALL, np.uint8)
    y = (H - 0.5 - np.arange(H)) * res
    img[np.abs(y - height / 2) < width / 2, :] = FREE
    return Map(img, res, (-0.05, 0.40), name="corridor")


# --------------------------------------------------------------------------- eval.metrics
def test_error_metrics_need_matching_positions_and_a_length():
    """A transposed (3, T) pair or a (T, 6) pair was read as points of 3 coordinates, rmse_t broadcast a (1, 3) or
    (3,) reference, a zero length gave ZeroDivisionError and a NaN one a NaN percentage, no points a torch error."""
    p, r = torch.rand(10, 3, dtype=torch.float64), torch.rand(10, 3, dtype=torch.float64)
    for a, b in ((p.T, r.T), (torch.rand(10, 6), torch.rand(10, 6)), (torch.zeros(0, 3), torch.zeros(0, 3))):
        with pytest.raises(ValueError, match=r"positions \(\.\.\., 3\)"):
            axis_errors(a, b, 0.1)
        with pytest.raises(ValueError, match=r"positions \(\.\.\., 3\)"):
            rmse_t(a, b)
    for ref in (r[:1], r[0]):
        with pytest.raises(ValueError, match="must have the same shape"):
            rmse_t(p, ref)
    for length in (0.0, -0.1, math.nan):
        with pytest.raises(ValueError, match="length must be finite and > 0"):
            axis_errors(p, r, length)
    # numpy positions (e.g. from a peer simulator) are taken as they are
    assert axis_errors(p.numpy(), r.numpy(), 0.1) == axis_errors(p, r, 0.1)
    torch.testing.assert_close(rmse_t(p.numpy(), r.numpy()), rmse_t(p, r))


# --------------------------------------------------------------------------- eval.timing
def test_json_line_writes_numpy_and_torch_numbers():
    """A benchmark's last line failed ('Object of type float32 is not JSON serializable') after all its work."""
    line = json_line({"a": np.float32(1.25), "n": np.int64(3), "t": torch.tensor(0.5), "v": np.array([1.0, np.nan]),
                      "f": [np.float32("inf")], "ok": np.bool_(True)})
    assert json.loads(line) == {"a": 1.25, "n": 3, "t": 0.5, "v": [1.0, "nan"], "f": ["inf"], "ok": True}


def test_lgvi_blocks_needs_whole_step_counts():
    with pytest.raises(ValueError, match="steps_per_call must be an integer >= 1, got 0"):  # ZeroDivisionError
        lgvi_blocks(None, 8, False, steps_per_call=0)
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        lgvi_blocks(None, -8, False)


# --------------------------------------------------------------------------- io
def test_save_sealed_without_meta_writes_nothing(tmp_path):
    """A blob without 'meta' wrote the checkpoint, then raised KeyError: a checkpoint without its .json."""
    with pytest.raises(ValueError, match="blob must carry its metadata under 'meta'"):
        save_sealed(tmp_path / "a.pt", {"state_dict": {"w": torch.zeros(2)}})
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- planning.quadtree
def test_quadtree_refuses_a_nan_threshold_or_nan_pixels():
    """Both were silently free space: a NaN threshold found no obstacle at all, a NaN pixel was no obstacle."""
    img = np.full((20, 20), 255, np.uint8)
    img[5:10, 5:10] = 0
    with pytest.raises(ValueError, match="threshold"):
        quadtree_rectangles(img, math.nan)
    gray = np.where(img == 0, np.nan, 255.0)
    with pytest.raises(ValueError, match="gray must be finite"):
        quadtree_rectangles(gray)
    assert quadtree_rectangles(img.astype(float)) == [(5, 5, 10, 10)]


# --------------------------------------------------------------------------- rl.ur5
def test_ur5_settings_and_ik_inputs_are_checked():
    from cmlearn.rl.ur5 import UR5, ur5_urdf
    pos = [0.0, 0.45, 0.16]
    for kw in ({"tol": math.nan}, {"tol": 0.0}, {"tol": -1e-6}, {"max_joint_step": math.nan},
               {"max_joint_step": -1.0}):
        # NaN passed every check (an unverified solution); 0 or < 0 gave "no inverse-kinematics solution"
        with pytest.raises(ValueError, match=f"{next(iter(kw))} must be finite and > 0"):
            UR5(**kw)
    robot = UR5()
    q = robot.ik(pos)
    with pytest.raises(ValueError, match="q_current must be 6 finite joint angles"):  # numpy broadcast error
        robot.ik(pos, q[:5])
    with pytest.raises(ValueError, match="q_current must be 6 finite joint angles"):  # "no IK solution"
        robot.ik(pos, np.full(6, np.nan))
    with pytest.raises(ValueError, match=r"q_current must be joint angles \(rad\) inside the joint limits"):
        robot.ik(pos, np.degrees(q))  # degrees: "no inverse-kinematics solution"
    for R in (np.array([0.0, 0.0, -1.0]), 2 * np.eye(3), np.diag([1.0, 1.0, -1.0])):
        with pytest.raises(ValueError, match="R must be a (finite 3x3|proper) rotation matrix"):  # "no IK solution"
            robot.ik(pos, None, R)
        with pytest.raises(ValueError, match="R must be a (finite 3x3|proper) rotation matrix"):  # False: "unreachable"
            robot.reachable(pos, R)
    with pytest.raises(ValueError, match="T_tool must be a finite 4x4 pose"):  # numpy matmul error
        robot.ik_all(np.eye(3))
    with pytest.raises(ValueError, match="q must be 6 finite joint angles"):  # IndexError
        robot.pybullet_fk([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="tool_length"):  # NaN in the URDF
        ur5_urdf(math.nan)
    np.testing.assert_allclose(robot.fk(robot.ik(pos, q))[:3, 3], pos, atol=1e-9)  # valid input unchanged


# --------------------------------------------------------------------------- rl.camera
def test_camera_height_must_put_the_table_inside_the_clipping_planes():
    """At 1.5 m (or 105: millimetres) the table lay past the far plane and every view was blank (255): no walls."""
    from cmlearn.rl.camera import CameraSpec
    for h in (1.5, 105.0, 0.005):
        with pytest.raises(ValueError, match=r"height must be in \(0.01, 0.99\) m"):
            CameraSpec(height=h)
    with pytest.raises(ValueError, match="table_level must be in"):  # a TypeError from '<='
        CameraSpec(table_level="25")
    assert CameraSpec(height=0.5).height == 0.5


def test_camera_refuses_a_nan_position():
    """render(nan, y) gave a blank (255) view: free space where the map is unknown."""
    pytest.importorskip("pybullet")
    pytest.importorskip("cv2")
    from cmlearn.rl.camera import CameraSpec, PybulletCamera
    cam = PybulletCamera(corridor(), CameraSpec(size=16))
    try:
        with pytest.raises(ValueError, match="x and y must be finite"):
            cam.render(math.nan, 0.43)
    finally:
        cam.close()


# --------------------------------------------------------------------------- rl.maps
def test_map_nodes_must_be_inside_the_grid():
    """A negative node wrapped round (the goal became a node at the other side, or nothing was reachable) and a
    fractional one was truncated."""
    m = corridor()
    g = tuple(int(v) for v in np.argwhere(m.safe)[0])
    for node in ((-1, -1), (g[0] + 0.5, g[1]), (m.nx, 0), (1, 2, 3)):
        with pytest.raises(ValueError, match="goal_node must be a grid node"):
            m.geodesic(node)
    with pytest.raises(ValueError, match="start_node must be a grid node"):
        m.check_reachable((-1, -1), g)
    with pytest.raises(ValueError, match="node must be a grid node"):
        m.sample_partner(np.random.default_rng(0), (-1, g[1]))
    assert m.geodesic(np.array(g))[g] == 0.0 and m.geodesic(list(g)) is m.geodesic(g)


def test_procedural_map_settings_are_checked():
    from cmlearn.rl.maps import map_seeds, procedural_map
    for kw, msg in (({"lattice": 0.0}, "lattice must be finite and > 0"),  # ZeroDivisionError
                    ({"lattice": math.nan}, "lattice must be finite and > 0"),  # cannot convert NaN to integer
                    ({"resolution": -0.002}, "resolution must be finite and > 0"),  # negative dimensions
                    ({"size": (-0.4, 0.4)}, "size must be two finite lengths > 0"),
                    ({"width": (0.04,)}, "width must be two finite lengths > 0"),  # IndexError
                    ({"width": (0.04, math.inf)}, "width must be two finite lengths > 0"),  # OverflowError
                    ({"p_narrow": 30}, r"p_narrow \(a probability\) must be in \[0, 1\]"),  # every edge narrowed
                    ({"p_narrow": math.nan}, r"p_narrow \(a probability\) must be in \[0, 1\]"),  # none
                    ({"dead_ends": -1}, "dead_ends must be an integer >= 0"),  # silently none
                    ({"dead_ends": 1.5}, "dead_ends must be an integer >= 0")):
        with pytest.raises(ValueError, match=msg):
            procedural_map(0, **kw)
    with pytest.raises(ValueError, match="count must be an integer >= 0"):  # () silently
        map_seeds("train", -2)


# --------------------------------------------------------------------------- rl.atlas
def test_atlas_node_view_outside_the_grid_is_refused():
    """node_view(-1, j) rendered a view off the map into the slot of node (nx - 1, j), kept by the saved atlas."""
    from cmlearn.rl.atlas import Atlas
    from cmlearn.rl.camera import CameraSpec
    atlas = Atlas(corridor(), CameraSpec(size=16))
    for i, j in ((-1, 0), (0, atlas.map.ny), (0.5, 0)):
        with pytest.raises(ValueError, match=r"\(i, j\) must be a grid node"):
            atlas.node_view(i, j)
    assert atlas.renders == 0 and not atlas.filled.any()


def test_atlas_file_that_cannot_be_read_gets_a_clear_error(tmp_path):
    """A truncated, empty or foreign cache file raised numpy's BadZipFile/EOFError/KeyError/pickle errors."""
    from cmlearn.rl.atlas import Atlas
    from cmlearn.rl.camera import CameraSpec
    m, spec = corridor(), CameraSpec(size=16)
    path = Atlas(m, spec, tmp_path).path
    for content in (b"", b"garbage", b"PK\x03\x04truncated"):
        path.write_bytes(content)
        with pytest.raises(ValueError, match="unreadable or not an atlas.*delete the file to rebuild it"):
            Atlas(m, spec, tmp_path)
    with open(path, "wb") as f:
        np.savez(f, other=np.zeros(3))
    with pytest.raises(ValueError, match="unreadable or not an atlas.*delete the file to rebuild it"):
        Atlas(m, spec, tmp_path)


def test_atlas_cache_dir_that_is_a_file_is_refused_up_front(tmp_path):
    """The FileExistsError came only at the save, after every view had been rendered."""
    from cmlearn.rl.atlas import Atlas
    from cmlearn.rl.camera import CameraSpec
    f = tmp_path / "cache"
    f.write_text("x")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        Atlas(corridor(), CameraSpec(size=16), f)


# --------------------------------------------------------------------------- rl.demos
def test_episode_transitions_inputs():
    from cmlearn.rl.demos import collect_demonstrations, episode_transitions
    T = 5
    obs, a, r = np.zeros((T + 1, 2, 4, 4), np.uint8), np.array([0, 1, 2, 3, 0]), np.ones(T)
    for g in (math.nan, 1.5, -0.5):  # NaN returns (and > 1 returns that grow)
        with pytest.raises(ValueError, match=r"gamma \(the discount\) must be in \[0, 1\]"):
            episode_transitions(obs, a, r, True, 3, g)
    with pytest.raises(ValueError, match="n_steps must be an integer >= 1, got 2.5"):  # numpy slicing error
        episode_transitions(obs, a, r, True, 2.5, 0.9)
    want = episode_transitions(obs, a, r, True, 3, 0.9)
    assert torch.equal(episode_transitions(obs, a, r, True, 3.0, 0.9)["next", "reward"], want["next", "reward"])
    # (T, 1) or one-hot actions came out one-hot again as (T, 1, 4) / (T, 4, 4); 0.7 more ran as the action below
    for bad in (a[:, None], np.eye(4)[a], a + 0.7):
        with pytest.raises(ValueError, match=r"actions must be T action indices \(integers in \[0, 4\)\)"):
            episode_transitions(obs, bad, r, True, 3, 0.9)
    with pytest.raises(ValueError, match="rewards must be T finite numbers, got shape"):  # TorchRL's (T, 1)
        episode_transitions(obs, a, r[:, None], True, 3, 0.9)
    with pytest.raises(ValueError, match="rewards must be T finite numbers"):  # NaN returns
        episode_transitions(obs, a, r * np.nan, True, 3, 0.9)
    # checked before the teacher's episodes run (an unknown env setting would fail first)
    with pytest.raises(ValueError, match="gamma"):
        collect_demonstrations({"no_such_setting": 1}, 1, 3, math.nan, seed=0)


# --------------------------------------------------------------------------- rl.teacher
def test_teacher_memory_and_weights_are_checked():
    """memory=-1 kept all but the first position (recent[1:]), 2.5 ran as 2; a string weight gave numpy's
    'ufunc isfinite not supported'."""
    from cmlearn.rl.teacher import GeodesicTeacher
    for m in (-1, 2.5, math.nan):
        with pytest.raises(ValueError, match="memory must be an integer >= 0"):
            GeodesicTeacher(None, memory=m)
    with pytest.raises(TypeError, match="clearance_weight must be a real number"):
        GeodesicTeacher(None, clearance_weight="0.2")
