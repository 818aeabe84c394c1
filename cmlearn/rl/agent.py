"""The trained Rainbow-IQN agent as Sub-controller 2: checkpoint save/load and deterministic acting.

A shipped agent checkpoint is a ``torch.save`` dict (loadable with ``weights_only=True``)::

    {"format": "cmlearn-iqn-agent/1", "config": IQNConfig fields, "state_dict": {...}, "meta": {...}}

with a JSON copy of ``meta`` (training command, wall time, frames, evaluation) next to it.
:meth:`IQNAgent.act` follows the ``SubController2`` protocol of :mod:`cmlearn.rl.switching`, so
the agent runs inside the switching controller through :func:`~cmlearn.rl.switching.run_episode`.
Acting is deterministic: mean weights (no noise) and the fixed quantile midpoints.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import torch

from cmlearn.io import CheckpointError, atomic_write, write_text_atomic
from cmlearn.models.iqn import IQNConfig, IQNNetwork

__all__ = ["AGENT_FORMAT", "IQNAgent", "save_agent", "load_agent", "CheckpointError"]

AGENT_FORMAT = "cmlearn-iqn-agent/1"


def save_agent(path: str | Path, network: IQNNetwork, meta: dict) -> Path:
    """Write the network's weights and plain-JSON ``meta`` atomically (plus ``<name>.json``)."""
    path = Path(path)
    meta = json.loads(json.dumps(meta, default=str))
    state = {k: v.detach().cpu().clone() for k, v in network.state_dict().items()}
    blob = {"format": AGENT_FORMAT, "config": network.config.to_dict(), "state_dict": state, "meta": meta}
    buf = io.BytesIO()
    torch.save(blob, buf)
    atomic_write(path, lambda f: f.write(buf.getvalue()))
    write_text_atomic(path.with_suffix(".json"), json.dumps(meta, indent=2) + "\n")
    return path


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
    try:
        net = IQNNetwork(IQNConfig.from_dict(blob["config"]))
        net.load_state_dict(blob["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: weights do not fit the stored IQN architecture "
                              f"({type(e).__name__}: {str(e)[:300]})") from None
    return net.eval(), blob.get("meta", {})


class IQNAgent:
    """Greedy, deterministic policy of a trained :class:`IQNNetwork`: ``act(obs, info) -> action``."""

    def __init__(self, network: IQNNetwork, meta: dict | None = None):
        self.network, self.meta = network.eval(), dict(meta or {})

    @classmethod
    def load(cls, path: str | Path) -> "IQNAgent":
        return cls(*load_agent(path))

    def q_values(self, obs) -> np.ndarray:
        """Mean-quantile action values (num_actions,) for one observation (2, 84, 84)."""
        from torchrl.envs.utils import ExplorationType, set_exploration_type
        x = torch.as_tensor(np.asarray(obs)).unsqueeze(0)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return self.network(x)[0].numpy()

    def act(self, obs, info=None) -> int:
        return int(np.argmax(self.q_values(obs)))

    def reset(self, info=None) -> None:
        pass
