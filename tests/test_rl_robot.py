"""UR5 kinematics from DH parameters: FK/IK round trips, unreachable targets, the generated URDF."""
import math

import numpy as np
import pytest

pytest.importorskip("pybullet")
from cmlearn.rl.ur5 import DOWN, UR5, IKError, ur5_urdf, write_urdf  # noqa: E402


@pytest.fixture(scope="module")
def robot():
    r = UR5(tool_length=0.06)
    yield r
    r.close()


def test_fk_ik_round_trip_random_joints(robot):
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.uniform(-math.pi, math.pi, 6)
        T = robot.fk(q)
        sols = robot.ik_all(T)
        assert 1 <= len(sols) <= 8
        for s in sols:  # every candidate reproduces the pose
            assert np.abs(robot.fk(s) - T).max() < 1e-8
        wrapped = [np.abs((s - q + math.pi) % (2 * math.pi) - math.pi).max() for s in sols]
        assert min(wrapped) < 1e-6  # the generating configuration is among them


def test_ik_positions_on_the_table_plane(robot):
    rng = np.random.default_rng(1)
    for _ in range(40):
        p = np.array([rng.uniform(-0.3, 0.3), rng.uniform(0.25, 0.65), 0.105])
        q_new = robot.ik(p)
        T = robot.fk(q_new)
        assert np.abs(T[:3, 3] - p).max() < 1e-9 and np.abs(T[:3, :3] - DOWN).max() < 1e-9
        assert ((q_new >= robot.limits[:, 0]) & (q_new <= robot.limits[:, 1])).all()


def test_small_moves_keep_the_branch(robot):
    q = robot.ik([0.0, 0.4, 0.105])
    for k in range(1, 30):
        q2 = robot.ik([0.01 * k, 0.4, 0.105], q)
        assert np.abs(q2 - q).max() < 0.2
        q = q2


@pytest.mark.parametrize("p", [[0.0, 1.2, 0.105], [0.95, 0.0, 0.105], [0.02, 0.03, 0.105], [0.0, 0.4, 1.5]])
def test_unreachable_targets_are_flagged(robot, p):
    with pytest.raises(IKError, match="no inverse-kinematics solution"):
        robot.ik(p)
    assert not robot.reachable(p)


def test_bad_inputs(robot):
    with pytest.raises(ValueError, match="position"):
        robot.ik([0.1, 0.2])
    with pytest.raises(ValueError, match="q must be 6"):
        robot.fk([0.0] * 5)
    with pytest.raises(ValueError, match="tool_length"):
        UR5(tool_length=-0.1)


def test_generated_urdf_matches_dh_fk(robot, tmp_path):
    path = write_urdf(0.06, tmp_path)
    assert path.exists() and path.read_text() == ur5_urdf(0.06)
    assert write_urdf(0.06, tmp_path) == path  # cached, same name
    assert not list(tmp_path.glob(".*.tmp"))  # atomic: no temp left behind
    rng = np.random.default_rng(2)
    for _ in range(10):
        q = rng.uniform(-math.pi, math.pi, 6)
        assert np.abs(robot.pybullet_fk(q) - robot.fk(q)).max() < 1e-6


def test_pybullet_fallback_is_verified(robot):
    T = robot.tool_pose([0.1, 0.45, 0.105])
    q = robot._pybullet_ik(T, robot.ik([0.11, 0.45, 0.105]))
    assert q is not None and np.abs(robot.fk(q)[:3, 3] - [0.1, 0.45, 0.105]).max() < 1e-4
    assert robot._error(q, T) < robot.tol  # the user's tolerance, not a looser floor
    assert robot._pybullet_ik(robot.tool_pose([0.0, 1.5, 0.105]), np.zeros(6)) is None
