"""The switching controller of the thesis (Figure 4.2): Sub-controller 1, the switching law, and
a driver that runs any Sub-controller 2 (a policy or a classical planner) in the environment.

* **Sub-controller 1** (IK-based proportional tracking, eq. 4.4): from the tracked particle
  position ``P_p`` (optical tracking) and its finite-difference velocity (the derivative filter
  ``s``), the end-effector set-point moves by ``dt (dP_p/dt + K1 (P_p - P_ee))``, clipped to
  ``max_speed``; the inverse kinematics turns it into joint positions (IK failure ends the episode)
  and the environment shortens a move whose joints would turn faster than the UR5's 180 deg/s
  (:data:`~cmlearn.rl.ur5.JOINT_SPEED`). The thesis gives no value for the gain ``K1``; the default
  10 1/s makes ``dt K1 = 1`` in the 0.1 s control period (the set-point reaches the tracked
  position in one period, speed allowing): a slower approach lets the magnet pull a dragged
  particle sideways into a wall (with a 0.15 m/s cap the agent lost 16 of 200 disturbed episodes
  with 2 1/s, 9 with 5 and 4 with 10). The same holds for the speed: the thesis sets no limit
  ("no need to have a collision avoidance strategy when the manipulator is moving to the location
  of the disturbed particle", line 800), and the default ``max_speed`` is the UR5's typical tool
  speed, 1 m/s (:data:`~cmlearn.rl.ur5.TOOL_SPEED`). A slow magnet passing beside a wall corner
  pulls the particle it approaches across the corner: the privileged teacher hit a wall in 12 of
  400 disturbed training-map episodes with 0.15 m/s (6 during a recapture), and at most once, never
  during a recapture, with 0.3, 0.5 or 1 m/s (episode seeds ``11 * 1_000_003 + k``, apart from the
  evaluation's; ``docs/controllers.md``).
* **Switching law**: Sub-controller 1 takes over when ``|P_p - P_ee| > switch_distance`` and hands
  back to Sub-controller 2 when the distance falls below ``release_distance``. With
  ``release_distance == switch_distance`` this is exactly the thesis's law; the default 2 cm adds
  hysteresis so that Sub-controller 2 starts with the particle captured. The thesis calls its
  threshold "an arbitrary value, chosen to be 10 cm" (line 695); the default here is 5 cm, about
  three times the following lag (1.7 cm) and below the capture radius of the default physics
  (9.1 cm): with 10 cm a particle dragged 6-10 cm away is never handed to Sub-controller 1 but is
  pulled straight back through the walls while Sub-controller 2, which does not see it, carries on
  (the privileged teacher then lost 9 of 100 disturbed episodes, 8 of them that way; with 4, 5 or
  6 cm, 1 of 100). ``switch_distance=0.10`` gives the thesis's value.
* **Sub-controller 2** is any object with ``act(obs, info) -> int`` (and optionally
  ``reset(info)``); plain callables ``f(obs, info)`` are accepted too.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from .ur5 import TOOL_SPEED

__all__ = ["SwitchingConfig", "SubController1", "SwitchingLaw", "SubController2", "EpisodeResult", "run_episode",
           "RandomPolicy"]


@dataclass(frozen=True)
class SwitchingConfig:
    k1: float = 10.0
    switch_distance: float = 0.05
    release_distance: float = 0.02
    max_speed: float = TOOL_SPEED

    def __post_init__(self):
        for name in ("k1", "switch_distance", "release_distance", "max_speed"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if self.release_distance > self.switch_distance:
            raise ValueError(f"release_distance={self.release_distance} must be <= switch_distance="
                             f"{self.switch_distance}")


class SwitchingLaw:
    """Supervisor S: which sub-controller acts, from the end-effector-to-particle distance."""

    def __init__(self, config: SwitchingConfig):
        self.config, self.active = config, 2

    def reset(self):
        self.active = 2

    def __call__(self, ee_xy, particle_xy) -> int:
        d = math.dist(ee_xy, particle_xy)
        if self.active == 2 and d > self.config.switch_distance:
            self.active = 1
        elif self.active == 1 and d < self.config.release_distance:
            self.active = 2
        return self.active


class SubController1:
    """Proportional tracking of the particle with velocity feed-forward (eq. 4.4, discretised)."""

    def __init__(self, config: SwitchingConfig):
        self.config = config
        self._last = None

    def reset(self):
        self._last = None

    def __call__(self, ee_xy, particle_xy, dt: float) -> tuple[float, float]:
        """Next end-effector set-point (x, y)."""
        px, py = particle_xy
        vx = vy = 0.0
        if self._last is not None:
            vx, vy = (px - self._last[0]) / dt, (py - self._last[1]) / dt
        self._last = (px, py)
        k = min(self.config.k1 * dt, 1.0)
        dx, dy = vx * dt + k * (px - ee_xy[0]), vy * dt + k * (py - ee_xy[1])
        n, cap = math.hypot(dx, dy), self.config.max_speed * dt
        if n > cap:
            dx, dy = dx * cap / n, dy * cap / n
        return ee_xy[0] + dx, ee_xy[1] + dy


class SubController2(Protocol):
    def act(self, obs: np.ndarray, info: dict) -> int: ...


class RandomPolicy:
    """Uniformly random actions (a reference Sub-controller 2)."""

    def __init__(self, seed: int = 0, n: int = 4):
        self.rng, self.n = np.random.default_rng(seed), n

    def act(self, obs, info) -> int:
        return int(self.rng.integers(self.n))


@dataclass
class EpisodeResult:
    success: bool
    reason: str
    steps: int
    sc1_steps: int
    return_: float
    path_length: float
    tracking_error_mean: tuple[float, float]
    tracking_error_max: tuple[float, float]
    decision_time_s: float
    disturbances: int
    trajectory: np.ndarray = field(repr=False)
    start: tuple[float, float] = (0.0, 0.0)
    goal: tuple[float, float] = (0.0, 0.0)
    map_name: str = ""
    extra: dict[str, Any] = field(default_factory=dict, repr=False)


def run_episode(env, controller: SubController2 | Callable, seed: int | None = None, options=None) -> EpisodeResult:
    """Run one episode of the switching controller with ``controller`` as Sub-controller 2.

    ``env`` is a :class:`~cmlearn.rl.env.MagneticParticleEnv` (or a wrapper of it); Sub-controller 1
    and the switching law run inside its ``step``."""
    act = controller.act if hasattr(controller, "act") else controller
    obs, info = env.reset(seed=seed, options=options)
    if hasattr(controller, "reset"):
        controller.reset(info)
    total, times, done = 0.0, [], False
    while not done:
        t0 = time.perf_counter()
        a = act(obs, info)
        times.append(time.perf_counter() - t0 + info.get("waypoint_s", 0.0))  # the observation's planning too
        obs, r, term, trunc, info = env.step(a)
        total += float(r)
        done = term or trunc
    base = env.unwrapped
    traj = np.asarray(base.trajectory, dtype=float)  # (T, 5): ee x, ee y, particle x, particle y, controller
    err = np.abs(traj[:, 2:4] - traj[:, 0:2])
    path = float(np.linalg.norm(np.diff(traj[:, 2:4], axis=0), axis=1).sum()) if len(traj) > 1 else 0.0
    return EpisodeResult(
        success=info["reason"] == "success", reason=info["reason"], steps=info["steps"], sc1_steps=info["sc1_steps"],
        return_=total, path_length=path, tracking_error_mean=tuple(err.mean(0).tolist()),
        tracking_error_max=tuple(err.max(0).tolist()), decision_time_s=float(np.mean(times)) if times else 0.0,
        disturbances=info["disturbances"], trajectory=traj, start=base.start_xy, goal=tuple(info["goal_xy"]),
        map_name=base.map.name)
