"""UR5 (CB3) from its published DH parameters: URDF generation, forward and inverse kinematics.

Standard DH, ``A_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, with the CB3 values of Universal
Robots: ``d = (0.089159, 0, 0, 0.10915, 0.09465, 0.0823)``, ``a = (0, -0.425, -0.39225, 0, 0, 0)``,
``alpha = (pi/2, 0, 0, pi/2, -pi/2, 0)`` (m, rad). The base frame is the world frame (base on the
table, z up). A tool (gripper + block magnet) of length ``tool_length`` sits on the flange along
its z axis; the *tool point* is the magnet's centre.

Inverse kinematics is the closed-form UR solution (shoulder, elbow and wrist branches: up to 8
solutions), every candidate verified by forward kinematics; the one inside the joint limits
closest to the current joints wins. :meth:`UR5.ik` raises :class:`IKError` when no candidate
reaches the target within ``tol`` (unreachable, too close to the base column, outside the joint
limits, or a branch jump larger than ``max_joint_step``). ``fallback="pybullet"`` retries with
pybullet's damped-least-squares IK on the generated URDF (verified by the same FK check).
The URDF uses primitive geometry (cylinders) and is written atomically into a cache directory.
"""
from __future__ import annotations

import hashlib
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from physics.checks import check_rotations, is_finite_real

from ..io import write_text_atomic

__all__ = ["UR5", "IKError", "DH_D", "DH_A", "DH_ALPHA", "DOWN", "JOINT_SPEED", "TOOL_SPEED", "ur5_urdf", "write_urdf"]

DH_D = (0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823)
DH_A = (0.0, -0.425, -0.39225, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
LIMITS = np.array([[-2 * math.pi, 2 * math.pi]] * 2 + [[-math.pi, math.pi]] + [[-2 * math.pi, 2 * math.pi]] * 3)
DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # tool z pointing at the table
JOINT_SPEED = math.pi  # rad/s, every joint (UR5 CB3 data sheet: 180 deg/s)
TOOL_SPEED = 1.0  # m/s, the data sheet's typical tool speed
HOME = np.array([math.pi / 2, -1.9, 1.9, -math.pi / 2, -math.pi / 2, 0.0])


class IKError(RuntimeError):
    """The inverse kinematics has no valid solution for the requested pose."""


def _dh(q: float, d: float, a: float, alpha: float) -> np.ndarray:
    cq, sq, ca, sa = math.cos(q), math.sin(q), math.cos(alpha), math.sin(alpha)
    return np.array([[cq, -sq * ca, sq * sa, a * cq], [sq, cq * ca, -cq * sa, a * sq], [0.0, sa, ca, d],
                     [0.0, 0.0, 0.0, 1.0]])


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def _check_tool_length(tool_length) -> float:
    if not (is_finite_real(tool_length) and 0 <= tool_length < 0.5):
        raise ValueError(f"tool_length must be in [0, 0.5) m, got {tool_length!r}")
    return float(tool_length)


def _joints(name: str, q) -> np.ndarray:
    """``q`` as 6 joint angles (rad); ValueError naming ``name`` unless it is 6 finite numbers."""
    q = np.asarray(q, dtype=float)
    if q.shape != (6,) or not np.isfinite(q).all():
        raise ValueError(f"{name} must be 6 finite joint angles (rad), got shape {q.shape}")
    return q


def _rotation(R) -> np.ndarray:
    """``R`` as a 3x3 array; ValueError unless it is a proper rotation matrix to 1e-6 (the IK reported a valid but
    unreachable pose as "no inverse-kinematics solution", and :meth:`UR5.reachable` answered False)."""
    if R is DOWN:
        return R
    check_rotations("R", R, tol=1e-6, single=True)
    return np.asarray(R, dtype=float)


def ur5_urdf(tool_length: float = 0.06) -> str:
    """URDF text of the UR5 with primitive geometry; joint ``i`` origin = the DH transform of link ``i-1``."""
    tool_length = _check_tool_length(tool_length)
    masses = (3.7, 8.393, 2.275, 1.219, 1.219, 0.1879)
    lines = ['<?xml version="1.0"?>', '<robot name="ur5_dh">']

    def link(name, mass, length, radius=0.05):
        iz = 0.5 * mass * radius ** 2
        ix = mass * (3 * radius ** 2 + length ** 2) / 12
        lines.append(f'  <link name="{name}"><inertial><mass value="{mass}"/><origin xyz="0 0 0"/>'
                     f'<inertia ixx="{ix:.6g}" ixy="0" ixz="0" iyy="{ix:.6g}" iyz="0" izz="{iz:.6g}"/></inertial>'
                     f'<visual><geometry><cylinder radius="{radius}" length="{max(length, 0.02):.4f}"/></geometry>'
                     f'</visual></link>')

    link("base_link", 4.0, 0.05)
    parent, origin = "base_link", (0.0, 0.0, 0.0, 0.0)
    for i in range(6):
        name = f"link{i + 1}"
        link(name, masses[i], abs(DH_A[i]) + DH_D[i], 0.045)
        x, z, roll = origin[0], origin[1], origin[2]
        lo, hi = LIMITS[i]
        lines.append(f'  <joint name="joint{i + 1}" type="revolute"><parent link="{parent}"/><child link="{name}"/>'
                     f'<origin xyz="{x} 0 {z}" rpy="{roll} 0 0"/><axis xyz="0 0 1"/>'
                     f'<limit lower="{lo}" upper="{hi}" effort="150" velocity="{JOINT_SPEED:.4f}"/></joint>')
        parent, origin = name, (DH_A[i], DH_D[i], DH_ALPHA[i], 0.0)
    link("flange", 0.01, 0.01, 0.03)
    lines.append(f'  <joint name="flange_joint" type="fixed"><parent link="{parent}"/><child link="flange"/>'
                 f'<origin xyz="{origin[0]} 0 {origin[1]}" rpy="{origin[2]} 0 0"/></joint>')
    link("tool", 0.2, tool_length, 0.02)
    lines.append(f'  <joint name="tool_joint" type="fixed"><parent link="flange"/><child link="tool"/>'
                 f'<origin xyz="0 0 {tool_length}" rpy="0 0 0"/></joint>')
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def write_urdf(tool_length: float = 0.06, cache_dir: str | Path | None = None) -> Path:
    """Write the URDF (atomically) into ``cache_dir`` (default: a per-user temp folder) and return its path."""
    text = ur5_urdf(tool_length)
    key = hashlib.sha256(text.encode()).hexdigest()[:16]
    folder = Path(cache_dir) if cache_dir is not None else Path(tempfile.gettempdir()) / f"cmlearn-{os.getuid()}"
    path = folder / f"ur5_dh_{key}.urdf"
    if not path.exists():
        write_text_atomic(path, text)
    return path


class UR5:
    """Kinematics of the UR5 with a tool of ``tool_length`` (m) along the flange z axis."""

    def __init__(self, tool_length: float = 0.06, tol: float = 1e-6, max_joint_step: float = 1.0,
                 fallback: str | None = None):
        tool_length = _check_tool_length(tool_length)
        for name, v in (("tol", tol), ("max_joint_step", max_joint_step)):
            if not (is_finite_real(v) and v > 0):  # NaN passed every check
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        if fallback not in (None, "pybullet"):
            raise ValueError(f"fallback must be None or 'pybullet', got {fallback!r}")
        self.tool_length, self.tol, self.max_joint_step, self.fallback = tool_length, tol, max_joint_step, fallback
        self.limits = LIMITS.copy()
        self._tool = np.eye(4)
        self._tool[2, 3] = tool_length
        self._pb = None

    # ------------------------------------------------------------------ forward kinematics
    def fk(self, q) -> np.ndarray:
        """4x4 pose of the tool point in the base frame for joints ``q`` (6,)."""
        q = _joints("q", q)
        T = self._tool
        for i in range(5, -1, -1):
            T = _dh(q[i], DH_D[i], DH_A[i], DH_ALPHA[i]) @ T
        return T

    def flange_from_tool(self, T_tool: np.ndarray) -> np.ndarray:
        return T_tool @ _inv(self._tool)

    def tool_pose(self, position, R: np.ndarray = DOWN) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.asarray(position, dtype=float)
        return T

    # ------------------------------------------------------------------ inverse kinematics
    def _candidates(self, T_tool: np.ndarray, ref: np.ndarray | None):
        """Closed-form candidates (wrapped to (-pi, pi]), branches ordered by closeness to ``ref``."""
        T = self.flange_from_tool(T_tool)
        d1, d4, d5, d6 = DH_D[0], DH_D[3], DH_D[4], DH_D[5]
        a2, a3 = DH_A[1], DH_A[2]
        R, p = T[:3, :3], T[:3, 3]
        p5 = p - d6 * R[:, 2]
        r = math.hypot(p5[0], p5[1])
        if r < d4 + 1e-12:
            return
        near = (lambda vals, i: vals) if ref is None else (
            lambda vals, i: sorted(vals, key=lambda v: abs((v - ref[i] + math.pi) % (2 * math.pi) - math.pi)))
        phi, psi = math.atan2(p5[1], p5[0]), math.asin(d4 / r)
        for q1 in near((phi + psi, phi + math.pi - psi), 0):
            s1, c1 = math.sin(q1), math.cos(q1)
            c5 = (p[0] * s1 - p[1] * c1 - d4) / d6
            if abs(c5) > 1 + 1e-9:
                continue
            a5 = math.acos(max(-1.0, min(1.0, c5)))
            for q5 in near((a5, -a5), 4):
                s5 = math.sin(q5)
                if abs(s5) < 1e-9:
                    q6 = 0.0 if ref is None else float(ref[5])  # wrist singularity: q6 is free
                else:
                    q6 = math.atan2((-R[0, 1] * s1 + R[1, 1] * c1) / s5, (R[0, 0] * s1 - R[1, 0] * c1) / s5)
                T14 = _inv(_dh(q1, d1, 0.0, DH_ALPHA[0])) @ T @ _inv(_dh(q5, d5, 0.0, DH_ALPHA[4]) @ _dh(q6, d6, 0.0, 0.0))
                p13 = T14 @ np.array([0.0, -d4, 0.0, 1.0])
                n13 = math.hypot(p13[0], p13[1])
                c3 = (n13 ** 2 - a2 ** 2 - a3 ** 2) / (2 * a2 * a3)
                if abs(c3) > 1 + 1e-9:
                    continue
                a3c = math.acos(max(-1.0, min(1.0, c3)))
                for q3 in near((a3c, -a3c), 2):
                    q2 = -math.atan2(p13[1], -p13[0]) + math.asin(max(-1.0, min(1.0, a3 * math.sin(q3) / n13)))
                    T34 = _inv(_dh(q2, 0.0, a2, 0.0) @ _dh(q3, 0.0, a3, 0.0)) @ T14
                    q4 = math.atan2(T34[1, 0], T34[0, 0])
                    yield (np.array([q1, q2, q3, q4, q5, q6]) + math.pi) % (2 * math.pi) - math.pi

    def ik_all(self, T_tool: np.ndarray) -> list[np.ndarray]:
        """All closed-form solutions (wrapped to (-pi, pi]) that reproduce ``T_tool`` within ``tol``."""
        T_tool = np.asarray(T_tool, dtype=float)
        if T_tool.shape != (4, 4) or not np.isfinite(T_tool).all():
            raise ValueError(f"T_tool must be a finite 4x4 pose, got shape {T_tool.shape}")
        check_rotations("T_tool[:3, :3]", T_tool[:3, :3], tol=1e-6, single=True)
        return [q for q in self._candidates(T_tool, None) if self._error(q, T_tool) < self.tol]

    def _error(self, q, T_tool) -> float:
        F = self.fk(q)
        return float(np.abs(F[:3, 3] - T_tool[:3, 3]).max() + np.abs(F[:3, :3] - T_tool[:3, :3]).max())

    def _nearest(self, q: np.ndarray, ref: np.ndarray) -> np.ndarray | None:
        """The 2 pi shift of each joint closest to ``ref`` inside the limits (None if none fits)."""
        k = np.round((ref - q) / (2 * math.pi))
        q = q + 2 * math.pi * k
        q = np.where(q > self.limits[:, 1], q - 2 * math.pi, q)
        q = np.where(q < self.limits[:, 0], q + 2 * math.pi, q)
        return q if bool(((q >= self.limits[:, 0]) & (q <= self.limits[:, 1])).all()) else None

    def ik(self, position, q_current=None, R: np.ndarray = DOWN) -> np.ndarray:
        """Joints placing the tool point at ``position`` with orientation ``R``; raises :class:`IKError`.

        With ``q_current`` the branch closest to it is tried first and the first verified candidate
        within ``max_joint_step`` of it is returned; without it, the verified candidate closest to a
        home posture."""
        position = np.asarray(position, dtype=float)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise ValueError(f"position must be 3 finite numbers (m), got {position!r}")
        if q_current is None:
            ref = HOME
        else:
            ref = _joints("q_current", q_current)
            if ((ref < self.limits[:, 0]) | (ref > self.limits[:, 1])).any():  # degrees: "no IK solution"
                raise ValueError(f"q_current must be joint angles (rad) inside the joint limits "
                                 f"{self.limits.round(4).tolist()}, got {ref.round(4).tolist()}")
        T = self.tool_pose(position, _rotation(R))
        best, dist = None, math.inf
        for q in self._candidates(T, ref):
            q = self._nearest(q, ref)
            if q is None or (d := float(np.abs(q - ref).max())) >= dist or self._error(q, T) >= self.tol:
                continue
            best, dist = q, d
            if q_current is not None and d <= self.max_joint_step:
                break
        if best is None and self.fallback == "pybullet":
            best = self._pybullet_ik(T, ref)
            dist = math.inf if best is None else float(np.abs(best - ref).max())
        if best is None:
            raise IKError(f"position {position.round(4).tolist()}: no inverse-kinematics solution within the joint "
                          f"limits (reach of the UR5 with a {self.tool_length} m tool)")
        if q_current is not None and dist > self.max_joint_step:
            raise IKError(f"position {position.round(4).tolist()}: the nearest IK solution is {dist:.3f} rad away "
                          f"(> max_joint_step={self.max_joint_step}); a branch switch near a singularity")
        return best

    def reachable(self, position, R: np.ndarray = DOWN) -> bool:
        try:
            self.ik(position, None, R)
            return True
        except IKError:
            return False

    # ------------------------------------------------------------------ pybullet
    def pybullet(self, cache_dir=None):
        """(client, body, tool link index) of the generated URDF loaded in a pybullet DIRECT client."""
        if self._pb is None:
            import pybullet as p
            cid = p.connect(p.DIRECT)
            body = p.loadURDF(str(write_urdf(self.tool_length, cache_dir)), useFixedBase=True, physicsClientId=cid)
            names = [p.getJointInfo(body, j, physicsClientId=cid)[12].decode() for j in
                     range(p.getNumJoints(body, physicsClientId=cid))]
            self._pb = (cid, body, names.index("tool"))
        return self._pb

    def pybullet_fk(self, q) -> np.ndarray:
        """Tool pose computed by pybullet from the generated URDF (a check on the URDF)."""
        import pybullet as p
        q = _joints("q", q)
        cid, body, tool = self.pybullet()
        for j in range(6):
            p.resetJointState(body, j, float(q[j]), physicsClientId=cid)
        pos, quat = p.getLinkState(body, tool, computeForwardKinematics=True, physicsClientId=cid)[4:6]
        T = np.eye(4)
        T[:3, :3] = np.asarray(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        T[:3, 3] = pos
        return T

    def _pybullet_ik(self, T_tool, ref) -> np.ndarray | None:
        import pybullet as p
        from scipy.spatial.transform import Rotation
        cid, body, tool = self.pybullet()
        quat = Rotation.from_matrix(T_tool[:3, :3]).as_quat().tolist()
        q = ref
        for _ in range(5):  # re-seeded refinements of pybullet's damped least squares
            for j in range(6):
                p.resetJointState(body, j, float(q[j]), physicsClientId=cid)
            q = np.asarray(p.calculateInverseKinematics(
                body, tool, T_tool[:3, 3].tolist(), quat, maxNumIterations=200, residualThreshold=1e-10,
                physicsClientId=cid))[:6]
            if self._error(q, T_tool) < self.tol:
                break
        if self._error(q, T_tool) >= self.tol:  # verified as the closed form is (pybullet's FK is float32-close)
            return None
        return self._nearest(q, ref)  # None when no 2 pi shift fits the joint limits

    def close(self):
        if self._pb is not None:
            import pybullet as p
            p.disconnect(self._pb[0])
            self._pb = None
