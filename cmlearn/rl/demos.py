"""Demonstrations for DQfD-style training of the agent (Hester et al. 2018): successful episodes of
the privileged :class:`~cmlearn.rl.teacher.GeodesicTeacher` in the training environment, stored as
n-step transitions in the layout the replay buffer samples (``observation``, one-hot ``action``,
``("next", "reward")`` = the discounted n-step return, ``("next", "observation")``,
``("next", "terminated")`` at the end of the window, ``gamma`` = gamma^steps) plus ``expert = True``.

The windows follow the replay buffer's ``MultiStepTransform`` convention: a window cut short by the
end of the episode bootstraps from the last observation unless the episode terminated there
(a truncated episode, at ``max_steps``, still bootstraps).
"""
from __future__ import annotations

import time

import numpy as np
import torch
from tensordict import TensorDict

from physics.checks import as_real, check_integer

__all__ = ["collect_demonstrations", "episode_transitions"]


def _check_return(n_steps, gamma) -> tuple[int, float]:
    """``(n_steps, gamma)``; ValueError unless ``n_steps`` is an integer >= 1 and ``gamma`` a discount in [0, 1] (NaN
    made every return NaN; 3.0 steps failed in numpy's slicing)."""
    gamma = as_real("gamma", gamma)
    if not 0 <= gamma <= 1:
        raise ValueError(f"gamma (the discount) must be in [0, 1], got {gamma!r}")
    return check_integer("n_steps", n_steps), gamma


def episode_transitions(obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, terminated: bool,
                        n_steps: int, gamma: float, num_actions: int = 4) -> TensorDict:
    """n-step transitions of one episode: ``obs`` (T + 1, ...), ``actions`` and ``rewards`` (T,)."""
    T = len(actions)
    if len(obs) != T + 1 or len(rewards) != T or T < 1:
        raise ValueError(f"an episode of T >= 1 steps needs T + 1 observations and T rewards, got "
                         f"{len(obs)}, {len(actions)}, {len(rewards)}")
    n_steps, gamma = _check_return(n_steps, gamma)
    num_actions = check_integer("num_actions", num_actions)
    actions = np.asarray(actions)
    # (T, 1) actions, or one-hot ones, came out one-hot again as (T, 1, 4) or (T, 4, 4); 1.7 ran as action 1
    if actions.shape != (T,) or not (np.issubdtype(actions.dtype, np.integer) or (
            np.issubdtype(actions.dtype, np.floating) and (actions == np.round(actions)).all())) \
            or actions.min() < 0 or actions.max() >= num_actions:
        raise ValueError(f"actions must be T action indices (integers in [0, {num_actions})), got "
                         f"{actions.dtype}{actions.shape}")
    rewards = np.asarray(rewards, dtype=np.float64)
    if rewards.shape != (T,) or not np.isfinite(rewards).all():  # (T, 1) failed in numpy, NaN became the return
        raise ValueError(f"rewards must be T finite numbers, got shape {rewards.shape}"
                         f"{'' if rewards.shape != (T,) else ' with non-finite values'}")
    k = np.minimum(n_steps, T - np.arange(T))                      # steps in each window
    disc = gamma ** np.arange(n_steps)
    padded = np.concatenate([rewards, np.zeros(n_steps)])
    ret = np.array([(padded[t:t + n_steps] * disc * (np.arange(n_steps) < k[t])).sum() for t in range(T)])
    end = np.arange(T) + k
    term = (end == T) & bool(terminated)
    a = torch.as_tensor(actions, dtype=torch.long)
    obs_t = torch.as_tensor(np.asarray(obs))
    return TensorDict({
        "observation": obs_t[:T],
        "action": torch.nn.functional.one_hot(a, num_actions),
        "gamma": torch.as_tensor(gamma ** k, dtype=torch.float32),
        "expert": torch.ones(T, dtype=torch.bool),
        "next": TensorDict({"observation": obs_t[torch.as_tensor(end)],
                            "reward": torch.as_tensor(ret, dtype=torch.float32).unsqueeze(-1),
                            "terminated": torch.as_tensor(term).unsqueeze(-1)}, batch_size=[T]),
    }, batch_size=[T])


def collect_demonstrations(env_kwargs: dict, episodes: int, n_steps: int, gamma: float, seed: int,
                           log=print) -> TensorDict:
    """Run the teacher for ``episodes`` seeded episodes and keep the successful ones as transitions."""
    from .env import MagneticParticleEnv
    from .teacher import GeodesicTeacher
    episodes = check_integer("episodes", episodes)
    n_steps, gamma = _check_return(n_steps, gamma)  # checked before the episodes run, not after
    env = MagneticParticleEnv(**env_kwargs)
    teacher = GeodesicTeacher(env)
    parts, kept, t0 = [], 0, time.perf_counter()
    try:
        for i in range(episodes):
            obs, info = env.reset(seed=seed + i)
            teacher.reset(info)
            observations, actions, rewards, done = [obs], [], [], False
            while not done:
                a = teacher.act(obs, info)
                obs, r, terminated, truncated, info = env.step(a)
                observations.append(obs)
                actions.append(a)
                rewards.append(r)
                done = terminated or truncated
            if info["reason"] == "success":
                kept += 1
                parts.append(episode_transitions(np.stack(observations), np.array(actions), np.array(rewards),
                                                 terminated, n_steps, gamma, env.action_space.n))
    finally:
        env.close()
    if not parts:
        raise RuntimeError(f"the teacher succeeded in none of {episodes} episodes: no demonstrations")
    demos = torch.cat(parts, 0)
    log(f"demonstrations: {kept} of {episodes} teacher episodes succeeded, {demos.numel()} transitions, "
        f"{time.perf_counter() - t0:.1f} s")
    return demos
