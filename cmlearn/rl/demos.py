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

__all__ = ["collect_demonstrations", "episode_transitions"]


def episode_transitions(obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, terminated: bool,
                        n_steps: int, gamma: float, num_actions: int = 4) -> TensorDict:
    """n-step transitions of one episode: ``obs`` (T + 1, ...), ``actions`` and ``rewards`` (T,)."""
    T = len(actions)
    if len(obs) != T + 1 or len(rewards) != T or T < 1:
        raise ValueError(f"an episode of T >= 1 steps needs T + 1 observations and T rewards, got "
                         f"{len(obs)}, {len(actions)}, {len(rewards)}")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    k = np.minimum(n_steps, T - np.arange(T))                      # steps in each window
    disc = gamma ** np.arange(n_steps)
    padded = np.concatenate([np.asarray(rewards, dtype=np.float64), np.zeros(n_steps)])
    ret = np.array([(padded[t:t + n_steps] * disc * (np.arange(n_steps) < k[t])).sum() for t in range(T)])
    end = np.arange(T) + k
    term = (end == T) & bool(terminated)
    a = torch.as_tensor(np.asarray(actions), dtype=torch.long)
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
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
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
