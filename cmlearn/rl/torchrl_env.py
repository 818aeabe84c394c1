"""TorchRL versions of the environment: one wrapped env, and batches for fast collection.

* :func:`make_torchrl_env`: ``torchrl.envs.GymWrapper`` around a
  :class:`~cmlearn.rl.env.MagneticParticleEnv` (observation ``"observation"``: uint8 (2, 84, 84);
  action: one-hot over 4 by default, or an integer with ``categorical_action_encoding=True``).
* :func:`make_batched_env`: ``num_envs`` copies in a ``SerialEnv`` (one process) or a
  ``ParallelEnv`` (one worker process each, ``parallel=True``), with per-worker seeds.

The extra ``info`` entries (positions, the termination reason) are not put in the tensordict;
use the gymnasium env directly when you need them.
"""
from __future__ import annotations

from .env import MagneticParticleEnv

__all__ = ["make_torchrl_env", "make_batched_env"]


def make_torchrl_env(categorical_action_encoding: bool = False, device: str = "cpu", **env_kwargs):
    from torchrl.envs import GymWrapper
    env = MagneticParticleEnv(**env_kwargs)
    return GymWrapper(env, categorical_action_encoding=categorical_action_encoding, device=device)


def _factory(categorical: bool, device: str, env_kwargs: dict):
    def make():
        return make_torchrl_env(categorical, device, **env_kwargs)
    return make


def make_batched_env(num_envs: int, parallel: bool = False, seed: int | None = 0,
                     categorical_action_encoding: bool = False, device: str = "cpu", **env_kwargs):
    """``num_envs`` environments stepping as one batch (``SerialEnv`` or ``ParallelEnv``)."""
    from torchrl.envs import ParallelEnv, SerialEnv
    if not (isinstance(num_envs, int) and num_envs >= 1):
        raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
    cls = ParallelEnv if parallel else SerialEnv
    env = cls(num_envs, _factory(categorical_action_encoding, device, env_kwargs))
    if seed is not None:
        env.set_seed(seed)
    return env
