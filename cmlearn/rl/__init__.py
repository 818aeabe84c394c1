"""Magnetic-particle steering (thesis Chapter 4.1): UR5 kinematics, particle physics, maps,
camera atlas, the gymnasium environment ``cmlearn/MagneticParticle-v0``, its TorchRL wrappers,
the switching controller, and the Rainbow-IQN agent (:mod:`.agent`, :mod:`.iqn_loss`,
:mod:`.training`). Importing this package loads gymnasium (the ``rl`` extra); the rest (pybullet,
cv2, torchrl) loads when first used."""
import gymnasium as _gym

from .switching import RandomPolicy, SubController1, SwitchingConfig, SwitchingLaw, run_episode
from .ur5 import UR5, IKError
from .particle import ParticleParams, ParticleSim
from .maps import Map, load_map, map_seeds, procedural_map
from .camera import CameraSpec
from .atlas import Atlas
from .env import ACTIONS, DisturbanceConfig, EnvConfig, MagneticParticleEnv

ENV_ID = "cmlearn/MagneticParticle-v0"
if ENV_ID not in _gym.registry:
    _gym.register(id=ENV_ID, entry_point="cmlearn.rl.env:MagneticParticleEnv")

__all__ = ["ENV_ID", "UR5", "IKError", "ParticleParams", "ParticleSim", "Map", "load_map", "map_seeds",
           "procedural_map", "CameraSpec", "Atlas", "EnvConfig", "DisturbanceConfig", "MagneticParticleEnv",
           "ACTIONS", "SwitchingConfig", "SwitchingLaw", "SubController1", "RandomPolicy", "run_episode",
           "make_env", "make_vector_env", "IQNAgent", "IQNLoss", "AgentTrainConfig", "train_agent"]

_LAZY = {"IQNAgent": ".agent", "IQNLoss": ".iqn_loss", "AgentTrainConfig": ".training", "train_agent": ".training"}


def __getattr__(name):  # the agent's modules load torchrl, so only on first use
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_env(**kwargs):
    """``gymnasium.make(ENV_ID, **kwargs)`` (EnvConfig fields as keywords, or ``config=``)."""
    return _gym.make(ENV_ID, **kwargs)


def make_vector_env(num_envs: int, asynchronous: bool = False, **kwargs):
    """``num_envs`` copies as a gymnasium vector env (sync, or async in subprocesses)."""
    if int(num_envs) < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    fns = [lambda: _gym.make(ENV_ID, **kwargs) for _ in range(int(num_envs))]
    return _gym.vector.AsyncVectorEnv(fns) if asynchronous else _gym.vector.SyncVectorEnv(fns)
