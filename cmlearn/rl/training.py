"""Training the Rainbow-IQN-ResNet agent with TorchRL (thesis Chapter 4.1; ``scripts/train_agent.py``).

Pieces, all TorchRL: a ``Collector`` over a ``SerialEnv`` of ``num_envs`` environments (or a
``MultiSyncCollector`` with ``workers`` processes, one ``SerialEnv`` each; TorchRL's distributed
collectors are the path beyond one machine), a ``TensorDictPrioritizedReplayBuffer`` over a
``LazyTensorStorage`` with a ``MultiStepTransform`` (n-step returns), the :class:`IQNLoss`, a
``HardUpdate`` target network, Adam, noisy-net exploration (the collector runs the policy under
``ExplorationType.RANDOM``; noise is resampled after every update), CSV (and TensorBoard when
installed) logs through ``torchrl.record.loggers``, periodic greedy evaluation inside the
switching controller, and atomic checkpoints with resume.

Learning from demonstrations (DQfD, Hester et al. 2018; off by default): ``demo_episodes``
episodes of the privileged :class:`~cmlearn.rl.teacher.GeodesicTeacher` become a second, fixed
replay of n-step transitions (:mod:`cmlearn.rl.demos`); ``pretrain_updates`` updates on them
alone come first, then every update adds ``demo_batch`` of them to the 32 own transitions, and
the loss adds the large-margin term on them (:class:`IQNLoss`). The pre-training is not
checkpointed on its own: a run interrupted during it starts again.

Hyper-parameters start from the IQN paper (Dabney et al. 2018) and Rainbow (Hessel et al. 2018)
as used in Rainbow-IQN (Toromanoff et al. 2019), changed for a 2-core CPU and a short, sparse task
(see :class:`AgentTrainConfig`): N = N' = K = 32 quantiles (paper: 64, 64, 32), replay of 100k
transitions (paper: 1M), target update every 1,000 updates (Rainbow: 8,000 frames = 2,000 updates
at one update per 4 frames), learning rate 1e-4 (Rainbow 6.25e-5) with Adam eps 1.5e-4, n = 3,
gamma = 0.99, priority exponent 0.5, importance exponent annealed 0.4 -> 1, noisy sigma_0 0.5,
gradient-norm clip 10, and a small network (:mod:`cmlearn.models.iqn`).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cmlearn.io import save_torch_atomic, write_text_atomic
from cmlearn.models.iqn import IQNConfig, find_iqn_network, make_iqn_actor

from .agent import IQNAgent, save_agent
from .iqn_loss import IQNLoss

__all__ = ["AgentTrainConfig", "TrainResult", "train_agent", "evaluate_agent", "make_replay_buffer", "target_updater",
           "TRAIN_CHECKPOINT_FORMAT"]

TRAIN_CHECKPOINT_FORMAT = "cmlearn-iqn-train/1"


@dataclass
class AgentTrainConfig:
    # environment
    train_maps: int = 8
    max_steps: int = 150
    disturbance_probability: float = 0.02
    waypoint_lookahead: int = 0  # > 0: the goal marker shows the map-memory planner's waypoint (cmlearn.rl.env)
    num_envs: int = 4
    workers: int = 1
    # collection and replay
    total_frames: int = 300_000
    frames_per_batch: int = 32
    init_random_frames: int = 5_000
    buffer_size: int = 100_000
    batch_size: int = 32
    updates_per_batch: int = 8
    n_steps: int = 3
    gamma: float = 0.99
    priority_alpha: float = 0.5
    priority_beta: float = 0.4
    # optimisation
    lr: float = 1e-4
    adam_eps: float = 1.5e-4
    grad_clip: float = 10.0
    target_update: int = 1_000
    num_quantiles: int = 32
    num_target_quantiles: int = 32
    kappa: float = 1.0
    network: dict = field(default_factory=dict)
    # learning from demonstrations (DQfD; 0 episodes = plain Rainbow-IQN)
    demo_episodes: int = 0
    demo_batch: int = 8
    pretrain_updates: int = 0
    margin: float = 0.8
    margin_weight: float = 1.0
    # bookkeeping
    seed: int = 0
    eval_every: int = 25_000
    eval_episodes: int = 20
    checkpoint_every: int = 25_000
    out: str = "runs/agent"
    resume: bool = False
    save_buffer: bool = False
    threads: int = 1
    progress: bool = True

    def __post_init__(self):
        for name in ("num_envs", "workers", "total_frames", "frames_per_batch", "buffer_size", "batch_size",
                     "updates_per_batch", "n_steps", "target_update", "eval_every", "eval_episodes",
                     "checkpoint_every", "threads", "max_steps", "train_maps"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        if self.frames_per_batch % (self.num_envs * self.workers):
            raise ValueError(f"frames_per_batch={self.frames_per_batch} must be a multiple of num_envs*workers="
                             f"{self.num_envs * self.workers}")
        if self.frames_per_batch // (self.num_envs * self.workers) < self.n_steps + 2:
            raise ValueError(f"frames_per_batch={self.frames_per_batch} gives fewer than n_steps + 2 = "
                             f"{self.n_steps + 2} steps per environment per batch (the n-step transform needs them)")
        for name, lo, hi in (("gamma", 0, 1), ("priority_alpha", 0, 1), ("priority_beta", 0, 1),
                             ("disturbance_probability", 0, 1)):
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise ValueError(f"{name} must be in [{lo}, {hi}], got {v}")
        for name in ("lr", "adam_eps", "grad_clip", "kappa"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name in ("init_random_frames", "demo_episodes", "pretrain_updates"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be an int >= 0, got {getattr(self, name)!r}")
        if not (isinstance(self.demo_batch, int) and 1 <= self.demo_batch):
            raise ValueError(f"demo_batch must be an int >= 1, got {self.demo_batch!r}")
        if self.batch_size > self.buffer_size:  # the replay would never hold a batch: a run without updates
            raise ValueError(f"batch_size={self.batch_size} must be <= buffer_size={self.buffer_size}")
        if self.init_random_frames > self.total_frames and not self.pretrain_updates:
            raise ValueError(f"init_random_frames={self.init_random_frames} > total_frames={self.total_frames}: "
                             "the run would end before its first update")
        if self.pretrain_updates and not self.demo_episodes:
            raise ValueError("pretrain_updates > 0 needs demonstrations (demo_episodes > 0)")
        for name in ("margin", "margin_weight"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        IQNConfig(**self.network)  # validate early

    @property
    def net_config(self) -> IQNConfig:
        return IQNConfig(**self.network)


@dataclass
class TrainResult:
    frames: int
    updates: int
    wall_s: float
    evaluations: list = field(default_factory=list)
    resumed_from: int | None = None
    buffer_restored: bool | None = None
    agent_path: str = ""
    best_agent_path: str = ""


def _env_kwargs(cfg: AgentTrainConfig, maps) -> dict:
    from .env import DisturbanceConfig
    from .maps import map_seeds
    kw = dict(max_steps=cfg.max_steps, atlas_cache="default", waypoint_lookahead=cfg.waypoint_lookahead,
              disturbance=DisturbanceConfig(probability=cfg.disturbance_probability))
    if maps is not None:
        kw["maps"] = list(maps)
        kw["atlas_cache"] = None
    else:
        kw["map_seeds"] = map_seeds("train", cfg.train_maps)
    return kw


def evaluate_agent(agent: IQNAgent, env_kwargs: dict, episodes: int, seed: int = 10_000) -> dict:
    """Greedy episodes of the switching controller with ``agent`` as Sub-controller 2."""
    from .env import MagneticParticleEnv, _count
    from .switching import run_episode
    if not (_count(episodes) and episodes >= 1):  # none gave NaN metrics
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    env = MagneticParticleEnv(**env_kwargs)
    try:
        res = [run_episode(env, agent, seed=seed + i) for i in range(episodes)]
    finally:
        env.close()
    return {"success_rate": float(np.mean([r.success for r in res])),
            "mean_steps": float(np.mean([r.steps for r in res])),
            "return": float(np.mean([r.return_ for r in res])),
            "decision_ms": 1e3 * float(np.mean([r.decision_time_s for r in res]))}


def _make_collector(cfg: AgentTrainConfig, actor, env_kwargs: dict, start_seed: int, init_random: int):
    from torchrl.collectors import Collector, MultiSyncCollector

    from .torchrl_env import make_batched_env
    # the agent is feed-forward: no recurrent state to prime, so the collector leaves the env as it is (TorchRL 0.15
    # would otherwise append an InitTracker by default, and 0.14 warns that it will)
    common = dict(frames_per_batch=cfg.frames_per_batch, total_frames=-1, init_random_frames=init_random or None,
                  auto_register_policy_transforms=False)
    if cfg.workers == 1:
        col = Collector(make_batched_env(cfg.num_envs, seed=None, **env_kwargs), actor, **common)
    else:
        make = _BatchedFactory(cfg.num_envs, env_kwargs)
        col = MultiSyncCollector([make] * cfg.workers, actor, cat_results="stack", **common)
    col.set_seed(start_seed)
    col.reset()  # the constructor reset the env before it was seeded: start every env from its seeded reset
    return col


class _BatchedFactory:
    """Picklable env factory for collector worker processes."""

    def __init__(self, num_envs: int, env_kwargs: dict):
        self.num_envs, self.env_kwargs = num_envs, env_kwargs

    def __call__(self):
        import torch as _torch
        _torch.set_num_threads(1)
        from .torchrl_env import make_batched_env
        return make_batched_env(self.num_envs, seed=None, **self.env_kwargs)


def make_replay_buffer(cfg: AgentTrainConfig):
    """Prioritized replay of n-step transitions (``LazyTensorStorage`` of (envs, time) frames).

    ``MultiStepTransform`` leaves its ``done_keys`` at step t; only ``done`` and ``truncated``
    are declared as such here, so that ``("next", "terminated")`` is gathered like the next
    observation, from the last step of the window: a window that ends in a terminal state then
    does not bootstrap from the terminal observation (with the default keys it would)."""
    from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer
    from torchrl.envs.transforms import MultiStepTransform
    return TensorDictPrioritizedReplayBuffer(
        alpha=cfg.priority_alpha, beta=cfg.priority_beta, batch_size=cfg.batch_size,
        storage=LazyTensorStorage(cfg.buffer_size, ndim=2),
        transform=MultiStepTransform(cfg.n_steps, cfg.gamma, done_keys=["done", "truncated"]))


def target_updater(loss: IQNLoss, every: int):
    """torchrl's ``HardUpdate`` that copies the online weights into the target network after every ``every``-th
    update (its ``counter`` is the number of updates done modulo ``every``). ``HardUpdate`` copies when its counter,
    stepped from 0, equals its interval, i.e. every interval + 1 steps: the interval is ``every - 1``."""
    from torchrl.objectives import HardUpdate
    return HardUpdate(loss, value_network_update_interval=every - 1)


def _save_train_state(path: Path, state: dict) -> None:
    save_torch_atomic(path, state)


def train_agent(cfg: AgentTrainConfig, maps=None, command: str = "", log: Callable[[str], None] = print,
                stop_after_frames: int | None = None) -> TrainResult:
    """Train (or resume) and write ``<out>/train_state.pt`` (full state), ``<out>/agent.pt`` (weights),
    ``<out>/best_agent.pt`` (the best periodic evaluation so far, its result under ``"selected"``) and logs.

    ``maps`` (a list of :class:`~cmlearn.rl.maps.Map`) replaces the procedural training maps.
    ``stop_after_frames`` ends the run early (as an interruption would) after writing a checkpoint."""
    from torchrl.record.loggers.csv import CSVLogger

    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    state_path, buffer_dir = out / "train_state.pt", out / "replay_buffer"
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    env_kwargs = _env_kwargs(cfg, maps)

    actor = make_iqn_actor(cfg.net_config)
    net = find_iqn_network(actor)
    loss = IQNLoss(actor, gamma=cfg.gamma, num_quantiles=cfg.num_quantiles,
                   num_target_quantiles=cfg.num_target_quantiles, kappa=cfg.kappa, margin=cfg.margin,
                   margin_weight=cfg.margin_weight)
    updater = target_updater(loss, cfg.target_update)
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    rb = make_replay_buffer(cfg)
    demo_rb = None
    if cfg.demo_episodes:  # regenerated from the seed on resume: the teacher is deterministic
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        from .demos import collect_demonstrations
        demos = collect_demonstrations(env_kwargs, cfg.demo_episodes, cfg.n_steps, cfg.gamma,
                                       seed=1_000_000 + 1_000 * cfg.seed, log=log)
        demo_rb = TensorDictReplayBuffer(storage=LazyTensorStorage(demos.numel()))
        demo_rb.extend(demos)

    frames = updates = 0
    wall_before = 0.0
    evaluations: list = []
    result = TrainResult(0, 0, 0.0)
    if cfg.resume:
        if not state_path.is_file():
            raise FileNotFoundError(f"resume: no checkpoint {state_path} (run without --resume first)")
        st = torch.load(state_path, map_location="cpu", weights_only=False)
        if st.get("format") != TRAIN_CHECKPOINT_FORMAT:
            raise ValueError(f"{state_path}: not a {TRAIN_CHECKPOINT_FORMAT} training checkpoint")
        if IQNConfig(**st["config"]["network"]).to_dict() != cfg.net_config.to_dict():  # not its spelling
            raise ValueError(f"resume: the checkpoint's network {st['config']['network']} differs from {cfg.network}")
        loss.load_state_dict(st["loss"])
        optim.load_state_dict(st["optim"])
        frames, updates, wall_before = st["frames"], st["updates"], st["wall_s"]
        evaluations = st.get("evaluations", [])
        torch.set_rng_state(st["torch_rng"])
        np.random.set_state(st["numpy_rng"])
        result.resumed_from = frames
        if (buffer_dir / "done").is_file():
            rb.loads(buffer_dir)
            result.buffer_restored = True
            log(f"resumed from frame {frames} (update {updates}); replay buffer restored ({len(rb)} transitions)")
        else:
            result.buffer_restored = False
            log(f"resumed from frame {frames} (update {updates}); replay buffer NOT restored (it was not saved): "
                f"refilling {cfg.init_random_frames} frames with the current policy before updates resume")
    updater.counter = updates % cfg.target_update  # keep the target-update phase across a resume

    csv = CSVLogger(exp_name="log", log_dir=str(out))
    tb = None
    try:
        from torchrl.record.loggers.tensorboard import TensorboardLogger
        tb = TensorboardLogger(exp_name="tb", log_dir=str(out))
    except (ImportError, ModuleNotFoundError):  # tensorboard is optional
        pass

    def log_scalar(name, value, step):
        csv.log_scalar(name, value, step=step)
        if tb is not None:
            tb.log_scalar(name, value, step=step)

    keys = ["observation", "action", "gamma", ("next", "observation"), ("next", "reward"), ("next", "terminated")]

    def update(sample, demo):
        """One gradient step on a replay sample (priorities updated) plus, if given, demonstrations."""
        batch = sample
        if demo is not None:
            batch = demo = demo.select(*keys, "expert")
            demo.set("priority_weight", torch.ones(demo.shape[0]))
            if sample is not None:
                own = sample.select(*keys, "priority_weight")
                own.set("expert", torch.zeros(own.shape[0], dtype=torch.bool))
                batch = torch.cat([own, demo], 0)
        out_td = loss(batch)
        optim.zero_grad(set_to_none=True)
        out_td["loss"].backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), cfg.grad_clip)
        optim.step()
        if sample is not None:
            sample.set("td_error", batch["td_error"][:sample.shape[0]])
            rb.update_tensordict_priority(sample)
        updater.step()
        loss.reset_noise()
        return out_td

    def agent_meta(wall):
        return {"frames": frames, "updates": updates, "wall_s": round(wall, 1), "command": command,
                "train_config": asdict(cfg), "evaluations": evaluations,
                "threads": cfg.threads, "workers": cfg.workers, "num_envs": cfg.num_envs}

    best = max((e["success_rate"] for e in evaluations), default=-1.0)

    def evaluate(wall, **extra):
        """Greedy evaluation, logged; the best one so far is kept as ``best_agent.pt``."""
        nonlocal best
        ev = evaluate_agent(IQNAgent(net), env_kwargs, cfg.eval_episodes, seed=cfg.seed * 1_000 + 10_000)
        net.train()
        ev.update(frames=frames, updates=updates, wall_s=round(wall, 1), **extra)
        evaluations.append(ev)
        for k in ("success_rate", "mean_steps", "return"):
            log_scalar(f"eval/{k}", ev[k], frames)
        if ev["success_rate"] > best:
            best = ev["success_rate"]
            save_agent(out / "best_agent.pt", net, {**agent_meta(wall), "selected": ev})
        return ev

    if demo_rb is not None and frames == 0 and cfg.pretrain_updates:
        t_pre = time.perf_counter()
        for i in range(cfg.pretrain_updates):  # DQfD pre-training: demonstrations only
            out_td = update(None, demo_rb.sample(cfg.batch_size))
            updates += 1
            if (i + 1) % 500 == 0 or i + 1 == cfg.pretrain_updates:
                log_scalar("pretrain/loss", out_td["loss"].item(), updates)
                log_scalar("pretrain/margin_loss", float(out_td.get("margin_loss", 0.0)), updates)
        log(f"pre-trained on demonstrations: {cfg.pretrain_updates} updates in {time.perf_counter() - t_pre:.1f} s, "
            f"loss {out_td['loss'].item():.4f}, margin loss {float(out_td.get('margin_loss', 0.0)):.4f}")
        wall_before += time.perf_counter() - t_pre
        ev = evaluate(wall_before, phase="pretrain")
        log(f"after pre-training: eval success {ev['success_rate']:.3f} steps {ev['mean_steps']:.1f}")

    init_random = cfg.init_random_frames if frames == 0 else 0
    learn_start = frames + (cfg.init_random_frames if not result.buffer_restored else 0)
    collector = _make_collector(cfg, actor, env_kwargs, cfg.seed + 7919 * (frames // cfg.frames_per_batch + 1),
                                init_random)
    bar = None
    if cfg.progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.total_frames, initial=frames, unit="frame", dynamic_ncols=True)
    t0 = time.perf_counter()
    next_eval = (frames // cfg.eval_every + 1) * cfg.eval_every
    next_ckpt = (frames // cfg.checkpoint_every + 1) * cfg.checkpoint_every
    last_loss = float("nan")

    def checkpoint():
        wall = wall_before + time.perf_counter() - t0
        st = {"format": TRAIN_CHECKPOINT_FORMAT, "config": asdict(cfg), "loss": loss.state_dict(),
              "optim": optim.state_dict(), "frames": frames, "updates": updates, "wall_s": wall,
              "evaluations": evaluations, "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state()}
        if cfg.save_buffer:
            (buffer_dir / "done").unlink(missing_ok=True)
            rb.dumps(buffer_dir)
            (buffer_dir / "done").write_text(str(frames))
        _save_train_state(state_path, st)
        save_agent(out / "agent.pt", net, agent_meta(wall))
        return wall

    try:
        for batch in collector:
            batch = batch.reshape(-1, batch.shape[-1]) if batch.ndim > 2 else batch
            n = batch.numel()
            frames += n
            rb.extend(batch)
            if frames >= learn_start and len(rb) >= cfg.batch_size:
                frac = min(1.0, frames / cfg.total_frames)
                rb.sampler.beta = cfg.priority_beta + (1.0 - cfg.priority_beta) * frac
                for _ in range(cfg.updates_per_batch):
                    out_td = update(rb.sample(), demo_rb.sample(cfg.demo_batch) if demo_rb is not None else None)
                    updates += 1
                    last_loss = out_td["loss"].item()
                collector.update_policy_weights_()
                if updates % 50 < cfg.updates_per_batch:
                    log_scalar("loss", last_loss, frames)
                    log_scalar("q_mean", float(out_td["q_mean"]), frames)
            if bar is not None:
                bar.update(n)
                bar.set_postfix(loss=f"{last_loss:.3f}", updates=updates, rb=len(rb))
            if frames >= next_eval or frames >= cfg.total_frames:
                next_eval += cfg.eval_every
                ev = evaluate(wall_before + time.perf_counter() - t0)
                log(f"frames {frames} updates {updates} eval success {ev['success_rate']:.3f} "
                    f"steps {ev['mean_steps']:.1f} return {ev['return']:.3f} loss {last_loss:.4f}")
            stop = frames >= cfg.total_frames or (stop_after_frames is not None and frames >= stop_after_frames)
            if frames >= next_ckpt or stop:
                next_ckpt += cfg.checkpoint_every
                checkpoint()
            if stop:
                break
    finally:
        collector.shutdown()
        if bar is not None:
            bar.close()
    result.frames, result.updates = frames, updates
    result.wall_s = wall_before + time.perf_counter() - t0
    result.evaluations = evaluations
    result.agent_path = str(out / "agent.pt")
    result.best_agent_path = str(out / "best_agent.pt") if (out / "best_agent.pt").is_file() else ""
    write_text_atomic(out / "summary.json", json.dumps(asdict(result), indent=2))
    return result


def config_from_args(ns) -> AgentTrainConfig:
    names = {f.name for f in fields(AgentTrainConfig)}
    return AgentTrainConfig(**{k: v for k, v in vars(ns).items() if k in names})
