"""The trained Rainbow-IQN agent as Sub-controller 2: checkpoint save/load and deterministic acting.

A shipped agent checkpoint is a ``torch.save`` dict (loadable with ``weights_only=True``)::

    {"format": "cmlearn-iqn-agent/1", "config": IQNConfig fields, "state_dict": {...}, "meta": {...},
     "weights_sha256": "...", "header_sha256": "..."}

(the digests of :func:`cmlearn.io.seal`, checked on load)

with a JSON copy of ``meta`` (training command, wall time, frames, evaluation) next to it.
:meth:`IQNAgent.act` follows the ``SubController2`` protocol of :mod:`cmlearn.rl.switching`, so
the agent runs inside the switching controller through :func:`~cmlearn.rl.switching.run_episode`.
Acting is deterministic: mean weights (no noise) and the fixed quantile midpoints.

:class:`ActingGuard` (optional, used for the deployed Sub-controller 2 in
``scripts/eval_controllers.py``) wraps the greedy choice in two rules that use only the
observation: (1) moves whose next camera window the obstacle rule would call an obstacle are
masked -- the next window is the current view shifted by one move (``shift_px`` = action step /
metres per pixel = 7 px), the same mean-below-threshold test the environment applies; (2) a
revisit tie-break: the values of the moves already taken from an identical observation in this
episode are lowered by ``revisit_penalty`` per time taken, which breaks the two-state cycles a
memoryless greedy policy can fall into.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cmlearn.io import CheckpointError, check_digests, save_sealed
from cmlearn.models.iqn import IQNConfig, IQNNetwork

from .env import ACTIONS

__all__ = ["AGENT_FORMAT", "IQNAgent", "ActingGuard", "save_agent", "load_agent", "CheckpointError"]

AGENT_FORMAT = "cmlearn-iqn-agent/1"


def save_agent(path: str | Path, network: IQNNetwork, meta: dict) -> Path:
    """Write the network's weights and plain-JSON ``meta`` atomically (plus ``<name>.json``)."""
    meta = json.loads(json.dumps(meta, default=str))
    state = {k: v.detach().cpu().clone() for k, v in network.state_dict().items()}
    return save_sealed(path, {"format": AGENT_FORMAT, "config": network.config.to_dict(), "state_dict": state,
                              "meta": meta})


def load_agent(path: str | Path) -> tuple[IQNNetwork, dict]:
    """The network (eval mode, CPU) and its metadata; :class:`CheckpointError` on any problem."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such agent checkpoint")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means an unusable (e.g. truncated) file
        raise CheckpointError(f"{path}: not a readable checkpoint, truncated or corrupt "
                              f"({type(e).__name__}: {str(e)[:160]})") from None
    if not isinstance(blob, dict) or blob.get("format") != AGENT_FORMAT:
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise CheckpointError(f"{path}: not a {AGENT_FORMAT} checkpoint (format {got!r})")
    check_digests(path, blob)
    try:
        net = IQNNetwork(IQNConfig.from_dict(blob["config"]))
        net.load_state_dict(blob["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: weights do not fit the stored IQN architecture "
                              f"({type(e).__name__}: {str(e)[:300]})") from None
    return net.eval(), blob.get("meta", {})


@dataclass(frozen=True)
class ActingGuard:
    """Obstacle mask and revisit tie-break around the greedy action (see the module docstring).

    Defaults match the environment's defaults: 1 cm moves, 84 px over 12 cm, threshold 150 over
    the central 15 x 15 pixels, actions +x, -x, +y, -y (image rows grow toward -y)."""
    obstacle_mask: bool = True
    shift_px: int = 7
    threshold: float = 150.0
    window: int = 15
    revisit_penalty: float = 1.0
    actions: tuple = ACTIONS

    def __post_init__(self):
        if not (isinstance(self.shift_px, int) and self.shift_px >= 0):
            raise ValueError(f"shift_px must be an int >= 0, got {self.shift_px!r}")
        if not (isinstance(self.window, int) and self.window >= 1):
            raise ValueError(f"window must be an int >= 1, got {self.window!r}")
        if not (np.isfinite(self.revisit_penalty) and self.revisit_penalty >= 0):
            raise ValueError(f"revisit_penalty must be finite and >= 0, got {self.revisit_penalty}")
        if not 0 <= self.threshold <= 255:  # NaN blocked no move
            raise ValueError(f"threshold (a grey level: a darker window is an obstacle) must be in [0, 255], got "
                             f"{self.threshold}")

    def blocked(self, view: np.ndarray) -> np.ndarray:
        """(num_actions,) bool: the obstacle rule on the window each move would bring under the camera."""
        n = view.shape[-1]
        s0 = (n - self.window) // 2
        out = np.zeros(len(self.actions), bool)
        for a, (dx, dy) in enumerate(self.actions):
            r0, c0 = s0 - int(round(dy * self.shift_px)), s0 + int(round(dx * self.shift_px))
            if min(r0, c0) < 0 or max(r0, c0) + self.window > n:
                raise ValueError(f"shift_px={self.shift_px} and window={self.window} leave the {n} px view")
            out[a] = float(view[r0:r0 + self.window, c0:c0 + self.window].mean()) < self.threshold
        return out


class IQNAgent:
    """Greedy, deterministic policy of a trained :class:`IQNNetwork`: ``act(obs, info) -> action``,
    optionally inside an :class:`ActingGuard`."""

    def __init__(self, network: IQNNetwork, meta: dict | None = None, guard: ActingGuard | None = None):
        self.network, self.meta, self.guard = network.eval(), dict(meta or {}), guard
        self._taken: dict = {}

    @classmethod
    def load(cls, path: str | Path, guard: ActingGuard | None = None) -> "IQNAgent":
        return cls(*load_agent(path), guard=guard)

    def q_values(self, obs) -> np.ndarray:
        """Mean-quantile action values (num_actions,) for one observation (2, 84, 84)."""
        from torchrl.envs.utils import ExplorationType, set_exploration_type
        x = torch.as_tensor(np.asarray(obs)).unsqueeze(0)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.network(x)[0].numpy()

    def act(self, obs, info=None) -> int:
        q = self.q_values(obs).astype(np.float64)
        if not np.isfinite(q).all():  # the argmax of NaN is the first action
            raise ValueError(f"obs: the network's action values are not finite ({q.tolist()}); the observation "
                             "holds a NaN or infinite pixel")
        g = self.guard
        if g is None:
            return int(np.argmax(q))
        obs = np.asarray(obs)
        if g.obstacle_mask:
            blocked = g.blocked(obs[0])
            if not blocked.all():
                q[blocked] = -np.inf
        taken = self._taken.setdefault(obs.tobytes(), np.zeros(len(q)))
        a = int(np.argmax(q - g.revisit_penalty * taken))
        taken[a] += 1
        return a

    def reset(self, info=None) -> None:
        self._taken = {}
