"""A privileged teacher for Sub-controller 2: it reads the map, so it is not a controller the
robot could run, but it shows what the environment allows and it provides demonstrations for the
agent (``AgentTrainConfig.demo_episodes``, DQfD-style training, :mod:`cmlearn.rl.training`).

At each decision it tries the 4 moves and takes the one whose new end-effector position has the
smallest cost ``g_safe - clearance_weight * min(clearance, clearance_cap) + revisit_penalty * visits``:
``g_safe`` the geodesic distance to the goal through the nodes with the map's safe clearance (1.2 cm
from the walls), the clearance term keeping the magnet (and so the lagging particle) near the
middle of the channel, and a small penalty on the end-effector positions of the last
``memory`` decisions breaking ties that would cycle. Moves the camera's obstacle rule would end
the episode on (or that leave the safe free space) are taken only when nothing else is left.
"""
from __future__ import annotations

import numpy as np

from physics.checks import check_integer, real

from .env import ACTIONS

__all__ = ["GeodesicTeacher"]


class GeodesicTeacher:
    """Sub-controller 2 with privileged access to ``env`` (a :class:`~cmlearn.rl.env.MagneticParticleEnv`)."""

    def __init__(self, env, clearance_weight: float = 0.2, clearance_cap: float = 0.03,
                 revisit_penalty: float = 0.003, memory: int = 8):
        for name, v in (("clearance_weight", clearance_weight), ("clearance_cap", clearance_cap),
                        ("revisit_penalty", revisit_penalty)):
            if real(name, v) < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        memory = check_integer("memory", memory, lo=0)  # -1 kept all but the first position, 2.5 ran as 2
        self.env = env.unwrapped
        self.clearance_weight, self.clearance_cap = clearance_weight, clearance_cap
        self.revisit_penalty, self.memory = revisit_penalty, memory
        self._geo, self._goal, self._recent = None, None, []

    def reset(self, info=None) -> None:
        e = self.env
        self._goal = e.goal_node
        self._geo = e.map.geodesic(e.goal_node, "safe")
        self._recent = []

    def act(self, obs=None, info=None) -> int:
        e = self.env
        if self._geo is None or self._goal != e.goal_node:
            self.reset()
        m, step = e.map, e.config.action_step
        x, y = e.ee
        recent = self._recent[-self.memory:] if self.memory else []
        costs = []
        for dx, dy in ACTIONS:
            tx, ty = x + dx * step, y + dy * step
            node = m.nearest_node(tx, ty)
            g = float(self._geo[node])
            cost = g if np.isfinite(g) else 1e3
            cost -= self.clearance_weight * min(float(m.node_clear[node]), self.clearance_cap)
            if e.obstacle_detected(e.atlas.view(tx, ty)):
                cost += 1e6
            cost += self.revisit_penalty * recent.count((round(tx, 4), round(ty, 4)))
            costs.append(cost)
        self._recent.append((round(x, 4), round(y, 4)))
        return int(np.argmin(costs))
