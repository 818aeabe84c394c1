"""Gymnasium environment of Chapter 4.1: a UR5 carries a block magnet 10 cm above a table and
steers a 5 mm magnetic sphere through an intestine-like map, seeing only its camera.

Interface (thesis lines 700-735):

* Observation ``uint8 (2, 84, 84)``. Channel 0: the grayscale end-effector camera view, looked up
  in an image atlas rendered with pybullet on the map's 1 cm grid (:mod:`cmlearn.rl.atlas`).
  Channel 1: two 42x84 halves, the top one marking the goal, the bottom one the end-effector,
  each as a 3x3 block of 255 at the position scaled from the map's extent to 42 rows x 84
  columns (row 0 = largest y), zeros elsewhere.
* Actions ``Discrete(4)``: move the end-effector by ``action_step`` (1 cm) in +x, -x, +y, -y.
* One step is one control period (``control_period`` = 0.1 s): IK for the new set-point, the
  particle simulated under the moving magnet (:mod:`cmlearn.rl.particle`), then disturbances and
  the switching controller (:mod:`cmlearn.rl.switching`): when the particle is farther than 5 cm,
  Sub-controller 1 runs (inside the same ``step``) until it is recaptured; those periods are
  counted in ``info["sc1_steps"]`` and recorded in ``env.trajectory`` but not in ``max_steps``.
* Termination (reward ``reward_failure`` = -1): no IK solution (``"ik_failure"``), the particle
  touching a wall (``"collision"``), the obstacle rule -- mean of the central 15x15 pixels of the
  camera view < 150 while Sub-controller 2 acts (``"obstacle"``) --, or no recapture within
  ``sc1_max_steps`` (``"recapture_failed"``). Truncation after ``max_steps`` (150) decisions
  (``"max_steps"``, also -1, as the thesis ends such an episode with a negative reward). Success
  (``reward_success`` = +1): the particle within ``goal_radius`` (2 cm) of the goal.
* Shaping (documented, optional): ``-step_penalty`` per decision plus the potential-based term
  ``shaping * (g_prev - g_new) / action_step`` with ``g`` the free-space (geodesic, 4-neighbour
  grid) distance of the particle to the goal; potential-based shaping does not change the
  optimal policy (Ng, Harada & Russell 1999). ``shaping=0, step_penalty=0`` gives the thesis's
  sparse reward.
* Disturbances (:class:`DisturbanceConfig`): with a given probability per decision (or at given
  steps), the particle is dragged ``magnitude`` metres (uniform in the range) in a random
  direction along a straight line inside the free space to a spot connected to the goal, as when
  the experimenter drew it away; at most ``max_count`` per episode, not before ``min_step``.

* Waypoints (``waypoint_lookahead`` > 0; off by default, the thesis's observation): the goal
  half of channel 1 marks, instead of the goal, the waypoint ``waypoint_lookahead`` moves down the
  optimistic plan of a :class:`~cmlearn.planning.memory.MemoryPlanner` that remembers every
  observed view of the episode (``info["waypoint_xy"]``). Only what the robot has goes into it:
  its views, where they were taken, its end-effector and the goal. It gives a memoryless policy
  the map memory it lacks in unseen maps; rewards and success still refer to the goal. The
  planning time is ``info["waypoint_s"]``, counted in the decision time by
  :func:`~cmlearn.rl.switching.run_episode`. With ``waypoint_prior`` the memory starts from every
  view of the map's image atlas, i.e. from a camera sweep of the map as the thesis recorded its
  workspace: a map the robot has swept before (the training maps); without it, it starts empty.

All randomness flows from ``reset(seed=...)`` (``self.np_random``).
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from dataclasses import dataclass, field, fields, replace

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .atlas import Atlas, default_cache_dir
from .camera import CameraSpec
from .maps import Map, load_map, map_seeds, procedural_map
from .particle import ParticleParams, ParticleSim
from .switching import SubController1, SwitchingConfig, SwitchingLaw
from .ur5 import JOINT_SPEED, UR5, IKError

__all__ = ["EnvConfig", "DisturbanceConfig", "MagneticParticleEnv", "ACTIONS"]

ACTIONS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))  # +x, -x, +y, -y


def _count(v) -> bool:
    """``v`` is an integer >= 0 (a bool is not)."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0


@dataclass(frozen=True)
class DisturbanceConfig:
    probability: float = 0.0
    magnitude: tuple[float, float] = (0.06, 0.15)
    max_count: int = 2
    min_step: int = 5
    at_steps: tuple[int, ...] = ()

    def __post_init__(self):
        if not 0.0 <= self.probability <= 1.0:
            raise ValueError(f"probability must be in [0, 1], got {self.probability}")
        m = self.magnitude
        if not (len(m) == 2 and all(math.isfinite(v) for v in m) and 0 < m[0] <= m[1]):
            raise ValueError(f"magnitude must be (min, max) with 0 < min <= max (m), got {m}")
        for name in ("max_count", "min_step"):
            if not _count(getattr(self, name)):
                raise ValueError(f"{name} must be an integer >= 0, got {getattr(self, name)!r}")
        if not all(_count(k) for k in self.at_steps):
            raise ValueError(f"at_steps must be step numbers (integers >= 0), got {self.at_steps!r}")
        # a step that can never disturb was dropped silently: the first step is 1, none comes before min_step, and
        # no more than max_count come in an episode
        first = max(1, self.min_step)
        if any(k < first for k in self.at_steps) or len(set(self.at_steps)) > self.max_count:
            raise ValueError(f"at_steps must be at most max_count ({self.max_count}) steps, each >= 1 and >= "
                             f"min_step ({self.min_step}), got {self.at_steps!r}")

    @property
    def active(self) -> bool:
        return self.probability > 0 or bool(self.at_steps)


@dataclass(frozen=True)
class EnvConfig:
    map_seeds: tuple[int, ...] = map_seeds("train", 8)
    map_path: str | None = None
    map_size: tuple[float, float] = (0.4, 0.4)
    map_resolution: float = 0.002
    action_step: float = 0.01
    control_period: float = 0.1
    max_steps: int = 150
    goal_radius: float = 0.02
    obstacle_threshold: float = 150.0
    obstacle_window: int = 15
    min_start_goal_distance: float = 0.1
    reward_success: float = 1.0
    reward_failure: float = -1.0
    step_penalty: float = 0.01
    shaping: float = 0.05
    sc1_max_steps: int = 100
    tool_length: float = 0.06
    waypoint_lookahead: int = 0
    waypoint_prior: bool = False
    atlas_cache: str | None = "default"
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    switching: SwitchingConfig | None = field(default_factory=SwitchingConfig)
    particle: ParticleParams = field(default_factory=ParticleParams)
    camera: CameraSpec = field(default_factory=CameraSpec)

    def __post_init__(self):
        for name, kind in (("disturbance", DisturbanceConfig), ("particle", ParticleParams), ("camera", CameraSpec),
                           ("switching", (SwitchingConfig, type(None)))):
            if not isinstance(getattr(self, name), kind):
                want = kind.__name__ if isinstance(kind, type) else f"{kind[0].__name__} or None"
                raise TypeError(f"{name} must be a {want}, got {getattr(self, name)!r}")
        for name in ("action_step", "control_period", "goal_radius", "map_resolution", "tool_length"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name in ("reward_success", "reward_failure", "step_penalty", "shaping"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)}")
        for name in ("max_steps", "sc1_max_steps"):
            if not (_count(getattr(self, name)) and getattr(self, name) >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {getattr(self, name)!r}")
        if len(self.map_size) != 2 or not all(math.isfinite(v) and v > 0 for v in self.map_size):
            raise ValueError(f"map_size must be two finite lengths > 0 (m), got {self.map_size!r}")
        if not 0 <= self.obstacle_threshold <= 255:
            raise ValueError(f"obstacle_threshold (a grey level: a darker view is an obstacle; 0: the rule off) must "
                             f"be in [0, 255], got {self.obstacle_threshold}")
        if not (math.isfinite(self.min_start_goal_distance) and self.min_start_goal_distance >= 0):
            raise ValueError(f"min_start_goal_distance must be finite and >= 0 (m), got {self.min_start_goal_distance}")
        if not (0 < self.obstacle_window <= self.camera.size):
            raise ValueError(f"obstacle_window must be in [1, {self.camera.size}], got {self.obstacle_window}")
        if not (isinstance(self.waypoint_lookahead, int) and self.waypoint_lookahead >= 0):
            raise ValueError(f"waypoint_lookahead must be an int >= 0, got {self.waypoint_lookahead!r}")
        if self.waypoint_prior and not self.waypoint_lookahead:
            raise ValueError("waypoint_prior=True needs waypoint_lookahead > 0 (the prior is the waypoint planner's memory)")
        if not self.map_seeds and self.map_path is None:
            raise ValueError("map_seeds is empty and map_path is None: the environment has no map")
        if self.map_path is not None:  # it was ignored beside the default map_seeds
            if self.map_seeds:
                raise ValueError(f"map_path {self.map_path!r} and map_seeds {self.map_seeds!r}: the environment "
                                 f"draws its maps from one of them (give map_seeds=() with map_path)")
            if not Path(self.map_path).is_file():
                raise ValueError(f"map_path: no such map image {self.map_path!r}")


_MAPS: dict = {}
_ATLASES: dict = {}
_SWEEPS: dict = {}


def _cached_map(cfg: EnvConfig, seed: int | None) -> Map:
    key = (seed, cfg.map_path, cfg.map_size, cfg.map_resolution)
    if key not in _MAPS:
        _MAPS[key] = (load_map(cfg.map_path, cfg.map_resolution) if seed is None else
                      procedural_map(seed, cfg.map_size, cfg.map_resolution))
    return _MAPS[key]


def _cached_atlas(map_: Map, cfg: EnvConfig) -> Atlas:
    cache = None if cfg.atlas_cache is None else (default_cache_dir() if cfg.atlas_cache == "default"
                                                  else cfg.atlas_cache)
    key = (id(map_), cfg.camera, str(cache))
    if key not in _ATLASES or _ATLASES[key][0] is not map_:
        _ATLASES[key] = (map_, Atlas(map_, cfg.camera, cache))
    return _ATLASES[key][1]


class MagneticParticleEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, config: EnvConfig | None = None, maps: list[Map] | None = None, render_mode=None, **overrides):
        cfg = config or EnvConfig()
        names = {f.name for f in fields(EnvConfig)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise TypeError(f"unknown EnvConfig field(s) {bad}; valid: {sorted(names)}")
        self.config = cfg = replace(cfg, **overrides) if overrides else cfg
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._maps = None if maps is None else list(maps)
        if self._maps is not None and not (self._maps and all(isinstance(m, Map) for m in self._maps)):
            raise TypeError(f"maps must be a non-empty list of cmlearn.rl.maps.Map (None: the config's), got {maps!r}")
        n = cfg.camera.size
        self.observation_space = spaces.Box(0, 255, (2, n, n), np.uint8)
        self.action_space = spaces.Discrete(4)
        self.robot = UR5(cfg.tool_length)
        self.sim = ParticleSim(cfg.particle)
        self.height = cfg.particle.magnet_height
        self.radius = cfg.particle.particle_diameter / 2
        self.law = SwitchingLaw(cfg.switching) if cfg.switching else None
        self.sc1 = SubController1(cfg.switching) if cfg.switching else None
        start = (n - cfg.obstacle_window) // 2
        self._win = slice(start, start + cfg.obstacle_window)
        self._wall = lambda x, y: self.map.touches_wall(x, y, self.radius)
        self.planner = None
        if cfg.waypoint_lookahead:
            from cmlearn.planning.memory import MemoryPlanner
            self.planner = MemoryPlanner(cfg.camera.metres_per_pixel, step=cfg.action_step,
                                         lookahead=cfg.waypoint_lookahead)
        self.map = None
        self._done = True
        self.trajectory: list[tuple[float, float, float, float, int]] = []

    # ------------------------------------------------------------------ maps
    def map_count(self) -> int:
        return len(self._maps) if self._maps is not None else (len(self.config.map_seeds) or 1)

    def get_map(self, index: int) -> Map:
        if self._maps is not None:
            return self._maps[index]
        seeds = self.config.map_seeds
        return _cached_map(self.config, seeds[index] if seeds else None)

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = sorted(set(options) - {"map_index", "start", "goal"})
        if unknown:  # a misspelt key drew a random map and goal
            raise ValueError(f"options: unknown key(s) {unknown}; valid: ['goal', 'map_index', 'start']")
        rng = self.np_random
        idx = options.get("map_index", int(rng.integers(self.map_count())))
        if not (_count(idx) and idx < self.map_count()):
            raise ValueError(f"options['map_index'] must be an int in [0, {self.map_count()}), got {idx!r}")
        self.map = self.get_map(idx)
        self.atlas = _cached_atlas(self.map, self.config)
        m = self.map
        if "start" in options or "goal" in options:
            start = m.check_point("start", options["start"]) if "start" in options else None
            goal = m.check_point("goal", options["goal"]) if "goal" in options else None
            if start is None:  # the other one: connected to the given one and as far away as a sampled pair
                start = m.sample_partner(rng, goal, self.config.min_start_goal_distance)
            elif goal is None:
                goal = m.sample_partner(rng, start, self.config.min_start_goal_distance)
            m.check_reachable(start, goal)
            self._place(m.node_xy(*start), user=True)
        else:
            for _ in range(50):
                start, goal = m.sample_start_goal(rng, self.config.min_start_goal_distance)
                if self._place(m.node_xy(*start), user=False) and self.robot.reachable([*m.node_xy(*goal), self.height]):
                    break
            else:
                raise ValueError(f"map {m.name!r}: no start/goal pair reachable by the UR5 (check the map origin)")
        self.goal_node, self.goal_xy = goal, m.node_xy(*goal)
        self.start_xy = self.ee
        self._geo = m.geodesic(goal, "free")
        self._g = self._geodist()
        self.steps = self.sc1_steps = self.disturbances = 0
        self.controller, self.reason, self._done = 2, "running", False
        if self.law:
            self.law.reset()
            self.sc1.reset()
        self.trajectory = [(*self.ee, *self.sim.position, 2)]
        if self.planner is not None:
            self.planner.reset(self._bounds(), self.goal_xy, self.sweep_memory() if self.config.waypoint_prior else None)
        return self._obs(), self._info()

    def _place(self, xy, user: bool) -> bool:
        try:
            self.q = self.robot.ik([xy[0], xy[1], self.height])
        except IKError as e:
            if user:
                raise ValueError(f"start={list(xy)} is not reachable by the UR5: {e}") from None
            return False
        self.ee = (float(xy[0]), float(xy[1]))
        self.sim.reset(*xy)
        return True

    def step(self, action):
        if self._done:
            raise RuntimeError("step() called after the episode ended; call reset() first")
        if isinstance(action, np.ndarray) and action.shape == ():
            action = action.item()
        if isinstance(action, bool) or not isinstance(action, (int, np.integer)) or not 0 <= int(action) < 4:
            raise ValueError(f"action must be an int in [0, 4) (+x, -x, +y, -y), got {action!r}")
        cfg = self.config
        dx, dy = ACTIONS[int(action)]
        self.controller = 2
        self.reason = self._move((self.ee[0] + dx * cfg.action_step, self.ee[1] + dy * cfg.action_step), 2)
        self.steps += 1
        view = self.atlas.view(*self.ee)
        if self.reason == "running" and float(view[self._win, self._win].mean()) < cfg.obstacle_threshold:
            self.reason = "obstacle"
        if self.reason == "running":
            self._maybe_disturb()
            if self.law is not None and self.law(self.ee, self.sim.position) == 1:
                self._recapture()
                view = self.atlas.view(*self.ee)  # the observation shows where Sub-controller 1 left the camera
        if self.reason == "running" and math.dist(self.sim.position, self.goal_xy) < cfg.goal_radius:
            self.reason = "success"
        truncated = self.reason == "running" and self.steps >= cfg.max_steps
        if truncated:
            self.reason = "max_steps"
        terminated = self.reason not in ("running", "max_steps")
        g = self._geodist()
        reward = -cfg.step_penalty + cfg.shaping * (self._g - g) / cfg.action_step
        self._g = g
        if self.reason == "success":
            reward += cfg.reward_success
        elif terminated or truncated:
            reward += cfg.reward_failure
        self._done = terminated or truncated
        return self._obs(view), float(reward), terminated, truncated, self._info()

    # ------------------------------------------------------------------ internals
    def _move(self, target, controller: int, q=None) -> str:
        """Move the end-effector to ``target`` (joints ``q`` if known) over one control period; returns the outcome."""
        try:
            self.q = self.robot.ik([target[0], target[1], self.height], self.q) if q is None else q
        except IKError:
            return "ik_failure"
        hit = self.sim.advance(self.ee, target, self.config.control_period, self._wall)
        self.ee = (float(target[0]), float(target[1]))
        self.trajectory.append((*self.ee, *self.sim.position, controller))
        return "collision" if hit else "running"

    def _recapture(self):
        self.controller = 1
        self.sc1.reset()  # a new tracking phase: no velocity estimate from the particle of an earlier one
        for _ in range(self.config.sc1_max_steps):
            target, q = self._joint_limited(self.sc1(self.ee, self.sim.position, self.config.control_period))
            self.sc1_steps += 1
            self.reason = self._move(target, 1, q)
            if self.reason != "running" or self.law(self.ee, self.sim.position) == 2:
                return
        self.reason = "recapture_failed"

    def _joint_limited(self, target):
        """Shorten a Sub-controller 1 move so that no joint turns faster than the UR5's
        ``JOINT_SPEED`` in one control period; returns the target and its joints (None: no IK, which
        :meth:`_move` reports)."""
        x0, y0 = self.ee
        for _ in range(8):
            try:
                q = self.robot.ik([target[0], target[1], self.height], self.q)
            except IKError:
                return target, None
            ratio = float(np.abs(q - self.q).max()) / (JOINT_SPEED * self.config.control_period)
            if ratio <= 1.0:
                return target, q
            f = 0.98 / ratio  # the joints move nearly linearly with the tool over one period
            target = (x0 + f * (target[0] - x0), y0 + f * (target[1] - y0))
        return target, None

    def _maybe_disturb(self):
        d = self.config.disturbance
        if not d.active or self.disturbances >= d.max_count or self.steps < d.min_step:
            return
        rng = self.np_random
        if not (self.steps in d.at_steps or (d.probability > 0 and rng.random() < d.probability)):
            return
        m, (px, py) = self.map, self.sim.position
        for _ in range(30):
            r, th = rng.uniform(*d.magnitude), rng.uniform(0, 2 * math.pi)
            x, y = px + r * math.cos(th), py + r * math.sin(th)
            if m.clearance_at(x, y) < m.clearance or not np.isfinite(self._geo[m.nearest_node(x, y)]):
                continue
            k = max(2, int(r / 0.002))  # dragged along a straight line inside the free space
            if all(m.clearance_at(px + (x - px) * t / k, py + (y - py) * t / k) >= self.radius for t in range(k + 1)):
                self.sim.reset(x, y)
                self.disturbances += 1
                self.trajectory.append((*self.ee, x, y, 0))
                return

    def _geodist(self) -> float:
        g = float(self._geo[self.map.nearest_node(*self.sim.position)])
        return g if math.isfinite(g) else getattr(self, "_g", 0.0)

    def _obs(self, view=None) -> np.ndarray:
        n = self.config.camera.size
        obs = np.zeros((2, n, n), dtype=np.uint8)
        obs[0] = self.atlas.view(*self.ee) if view is None else view
        self.view_xy = self.map.node_xy(*self.map.nearest_node(*self.ee))  # where the view was taken
        self.waypoint_xy, self.waypoint_s = self.goal_xy, 0.0
        if self.planner is not None:
            t0 = time.perf_counter()
            self.planner.add_view(obs[0], self.view_xy)
            self.waypoint_xy = self.planner.plan(self.ee)[1]
            self.waypoint_s = time.perf_counter() - t0
        h = n // 2
        for row0, (x, y) in ((0, self.waypoint_xy), (h, self.ee)):
            r, c = self._marker(x, y, h, n)
            obs[1, row0 + max(r - 1, 0):row0 + min(r + 2, h), max(c - 1, 0):c + 2] = 255
        return obs

    def _marker(self, x, y, rows, cols) -> tuple[int, int]:
        m = self.map
        W, H = m.size
        u = min(max((x - m.origin[0]) / W, 0.0), 1.0)
        v = min(max((m.origin[1] + H - y) / H, 0.0), 1.0)
        return int(round(v * (rows - 1))), int(round(u * (cols - 1)))

    def _info(self) -> dict:
        return {"ee_xy": self.ee, "particle_xy": self.sim.position, "goal_xy": self.goal_xy,
                "waypoint_xy": self.waypoint_xy, "waypoint_s": self.waypoint_s,
                "view_xy": self.view_xy, "reason": self.reason,
                "steps": self.steps, "sc1_steps": self.sc1_steps, "disturbances": self.disturbances,
                "controller": self.controller, "map": self.map.name, "bounds": self._bounds()}

    def sweep_memory(self) -> np.ndarray:
        """A :class:`~cmlearn.planning.memory.MemoryPlanner` memory after pasting every view of the
        current map's image atlas, i.e. after a camera sweep of the map (cached per map)."""
        from cmlearn.planning.memory import MemoryPlanner
        key = (id(self.map), self.config.camera)
        if key not in _SWEEPS or _SWEEPS[key][0] is not self.map:
            planner = MemoryPlanner(self.config.camera.metres_per_pixel)
            planner.reset(self._bounds(), self.goal_xy)
            for i in range(self.map.nx):
                for j in range(self.map.ny):
                    planner.add_view(self.atlas.node_view(i, j), self.map.node_xy(i, j))
            _SWEEPS[key] = (self.map, planner.occ.copy())
        return _SWEEPS[key][1]

    def _bounds(self) -> tuple[float, float, float, float]:
        m = self.map
        return m.origin[0], m.origin[1], m.origin[0] + m.size[0], m.origin[1] + m.size[1]

    def obstacle_detected(self, view: np.ndarray) -> bool:
        """The thesis's rule: mean of the central window of a camera view below the threshold."""
        return float(np.asarray(view)[self._win, self._win].mean()) < self.config.obstacle_threshold

    def render(self):
        if self.render_mode != "rgb_array" or self.map is None:
            return None
        img = np.repeat(self.map.image[:, :, None], 3, axis=2).copy()
        for (x, y), color in ((self.goal_xy, (0, 200, 0)), (self.ee, (0, 0, 255)), (self.sim.position, (255, 0, 0))):
            r, c = self.map.to_pixel(x, y)
            img[max(r - 3, 0):r + 4, max(c - 3, 0):c + 4] = color
        return img

    def close(self):
        self.robot.close()
