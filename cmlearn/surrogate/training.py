"""Lightning wrappers around :class:`~cmlearn.models.NodeLSTMSurrogate` (imported only for training).

The loss is the free-running rollout error over a horizon that grows from 1 step (the one-step
fit) to ``horizon`` steps during training (a curriculum), with optional training noise on the
history (:meth:`SurrogateModule.noisy`), so that the model learns to stay accurate when it feeds
on its own predictions, not only one step ahead. With ``wrench_fn`` (closed-loop training, e.g. the
magnetic rod, whose wrench depends on the magnets' pose) the rollout also computes each step's input
wrench from its own last frame, as the free-running surrogate does. Errors are in units of the mean
second-difference scale, the same for every node, so the loss weighs millimetres equally along the rod.
"""
from __future__ import annotations

import atexit

import lightning as L
import torch
from torch.utils.data import DataLoader

from physics.checks import is_finite_real
from cmlearn.data.windows import RolloutWindows, node_wrench, split_ranges
from cmlearn.models import NodeLSTMSurrogate

__all__ = ["SeededDataModule", "SurrogateDataModule", "SurrogateModule", "RolloutSelection"]


class SeededDataModule(L.LightningDataModule):
    """A data module whose training shuffle draws from one generator seeded with ``seed`` (:attr:`shuffle`), which
    Lightning checkpoints with torch's global generator (the training noise): a run resumed from a checkpoint draws
    the batches and noise the uninterrupted run would have."""

    def __init__(self, seed: int = 0):
        super().__init__()
        self.seed = seed
        self.shuffle = torch.Generator().manual_seed(seed)

    def state_dict(self):
        return {"shuffle_rng": self.shuffle.get_state(), "torch_rng": torch.get_rng_state()}

    def load_state_dict(self, state):
        if "shuffle_rng" in state:  # checkpoints from before 2026-12-02 have none: the run restarts both
            self.shuffle.set_state(state["shuffle_rng"])
            torch.set_rng_state(state["torch_rng"])


class SurrogateDataModule(SeededDataModule):
    """Training windows from ``dataset`` (see :func:`split_ranges`). Validation: the dataset's last
    ``val_variants`` variants, or, where ``val_dataset`` is given (fresh variants of the same scene from
    another seed), its variants but the first (the printed scene, trained on), while all of ``dataset``
    trains; validation windows start every ``val_stride`` frames. ``val_tail``: the printed scene's last
    part before the cut validates too (see :func:`split_ranges`). ``inputs`` (and ``val_inputs`` for a
    ``val_dataset``): the per-step inputs of a closed-loop ``wrench_fn``, in every window. ``time_reversal``:
    the training windows also play backwards (undamped scenes; :class:`RolloutWindows`), validation does not.
    ``printed_repeat``: the printed scene's training windows appear this many times in each training epoch, so
    that the one trajectory the thesis trains on keeps its share of the training as variants are added (the
    scales, computed from :meth:`train_positions`, count it once)."""

    def __init__(self, dataset: dict, eta: int, horizon: int, batch_size: int = 64, val_variants: int = 1,
                 num_workers: int = 0, seed: int = 0, inputs: torch.Tensor | None = None,
                 val_dataset: dict | None = None, val_stride: int = 1, val_inputs: torch.Tensor | None = None,
                 val_tail: float = 0.0, time_reversal: bool = False, printed_repeat: int = 1):
        super().__init__(seed)
        if printed_repeat < 1:
            raise ValueError(f"printed_repeat must be >= 1, got {printed_repeat}")
        if val_dataset is not None and val_tail:
            raise ValueError("val_tail and val_dataset: validate on the printed scene's tail or on fresh variants, "
                             "not both")
        if val_dataset is not None and (inputs is None) != (val_inputs is None):
            raise ValueError("inputs and val_inputs: closed-loop inputs must be given for both datasets or neither")
        if val_dataset is None and val_inputs is not None:
            raise ValueError("val_inputs belong to a val_dataset, and none is given")
        if val_stride < 1:
            raise ValueError(f"val_stride must be >= 1, got {val_stride}")
        self.inputs = inputs  # (V, T-1, ...) per-step inputs of a closed-loop wrench_fn
        meta = dataset["meta"]
        self.positions = dataset["positions"]
        self.wrench = node_wrench(dataset["wrench"], meta["wrench_nodes"], meta["modeled"])
        self.ranges = split_ranges(meta["n_variants"], self.positions.shape[1],
                                   val_variants=val_variants if val_dataset is None else 0, val_tail=val_tail)
        self.val_positions, self.val_wrench, self.val_inputs = self.positions, self.wrench, inputs
        if val_dataset is not None:
            vm = val_dataset["meta"]
            if vm["n_variants"] < 2:
                raise ValueError("val_dataset must hold variants besides its first (the printed scene)")
            self.val_positions = val_dataset["positions"]
            self.val_wrench = node_wrench(val_dataset["wrench"], vm["wrench_nodes"], vm["modeled"])
            self.val_inputs = val_inputs
            self.ranges["val"] = [(v, 0, self.val_positions.shape[1] - 1) for v in range(1, vm["n_variants"])]
        self.eta, self.horizon, self.batch_size = eta, horizon, batch_size
        self.num_workers, self.val_stride = num_workers, val_stride
        self.time_reversal, self.printed_repeat = time_reversal, printed_repeat

    def train_positions(self, fresh_validation: bool | None = None, val_tail: float = 0.0):
        """Trajectories the scales may be computed from (training ranges only): this module's, or those of
        a run with (``fresh_validation=True``: every variant trains) or without fresh validation variants
        and with the given ``val_tail``."""
        return [self.positions[v, a:b + 1] for v, a, b in self._train_ranges(fresh_validation, val_tail)]

    def train_wrench(self, fresh_validation: bool | None = None, val_tail: float = 0.0) -> torch.Tensor:
        """The node forces (N, K, 3) of the transitions in :meth:`train_positions`' trajectories (their force
        scale: none from the validation or test ranges)."""
        ranges = self._train_ranges(fresh_validation, val_tail)
        return torch.cat([self.wrench[v, a:b] for v, a, b in ranges]) if self.wrench.numel() else self.wrench

    def _train_ranges(self, fresh_validation: bool | None, val_tail: float) -> list:
        if fresh_validation is None:
            return self.ranges["train"]
        return split_ranges(len(self.positions), self.positions.shape[1],
                            val_variants=0 if fresh_validation else 1, val_tail=val_tail)["train"]

    def _val_ranges(self):
        """The validation ranges; an error where there are none of their own (:func:`split_ranges` then gives the
        test range, and selecting on it would grade the model on what it was selected by)."""
        if self.ranges["val"] == self.ranges["test"]:
            raise ValueError("SurrogateDataModule: nothing to validate on but the test range (the printed scene's "
                             "last 40 %): give more variants than val_variants, val_tail > 0 or a val_dataset")
        return self.ranges["val"]

    def _loader(self, split: str, shuffle: bool):
        if split == "val":
            ds = RolloutWindows(self.val_positions, self.val_wrench, self._val_ranges(), self.eta, self.horizon,
                                self.val_inputs, stride=self.val_stride)
        else:  # training: the printed scene's range (variant 0, always the first) printed_repeat times
            train = self.ranges["train"]
            ds = RolloutWindows(self.positions, self.wrench, [train[0]] * (self.printed_repeat - 1) + train, self.eta,
                                self.horizon, self.inputs, time_reversal=self.time_reversal)
        return DataLoader(ds, batch_size=self.batch_size, shuffle=shuffle, generator=self.shuffle if shuffle else None,
                          num_workers=self.num_workers, drop_last=shuffle and len(ds) > self.batch_size)

    def train_dataloader(self):
        return self._loader("train", True)

    def val_dataloader(self):
        return self._loader("val", False)

    def long_rollout_batch(self, steps: int = 0):
        """The validation trajectories as one batch of free-running windows from their first frame:
        ``steps`` steps each (0: as many as the shortest range holds)."""
        W = self.eta + 1
        n = min(b - a - W + 1 for _, a, b in self._val_ranges())
        n = min(n, steps) if steps > 0 else n
        windows = [RolloutWindows(self.val_positions, self.val_wrench, [(v, a, a + W - 1 + n)], self.eta, n,
                                  self.val_inputs)[0]
                   for v, a, _ in self.ranges["val"]]
        return tuple(torch.stack(parts) for parts in zip(*windows))


class SurrogateModule(L.LightningModule):
    def __init__(self, model: NodeLSTMSurrogate, horizon: int = 32, warmup_epochs: int = 10, lr: float = 2e-3,
                 weight_decay: float = 0.0, max_epochs: int = 100, noise: float = 0.0,
                 step_weighting: str = "uniform", one_step_weight: float = 0.0, wrench_fn=None,
                 noise_shape: str = "walk", window_weighting: str = "uniform", motion_floor: float = 1e-3):
        super().__init__()
        if noise_shape not in ("walk", "offset"):
            raise ValueError(f"noise_shape must be 'walk' or 'offset', got {noise_shape!r}")
        if step_weighting not in ("uniform", "inverse_square"):
            raise ValueError(f"step_weighting must be 'uniform' or 'inverse_square', got {step_weighting!r}")
        if window_weighting not in ("uniform", "inverse_motion"):
            raise ValueError(f"window_weighting must be 'uniform' or 'inverse_motion', got {window_weighting!r}")
        if not motion_floor > 0:
            raise ValueError(f"motion_floor must be > 0 metres, got {motion_floor!r}")
        if not one_step_weight >= 0:
            raise ValueError(f"one_step_weight must be >= 0, got {one_step_weight!r}")
        if not (is_finite_real(noise) and noise >= 0):  # NaN skipped every batch
            raise ValueError(f"noise must be a finite number >= 0 (metres; 0 for none), got {noise!r}")
        if not (is_finite_real(lr) and lr >= 0):
            raise ValueError(f"lr must be a finite number >= 0 (0: the weights stay), got {lr!r}")
        if not (isinstance(horizon, int) and horizon >= 1):
            raise ValueError(f"horizon must be an integer >= 1 (steps), got {horizon!r}")
        self.model, self.wrench_fn = model, wrench_fn  # wrench_fn(frame, inputs_h) -> (B, K, 3): closed loop
        self.noise, self.step_weighting, self.one_step_weight = noise, step_weighting, one_step_weight
        self.noise_shape, self.window_weighting, self.motion_floor = noise_shape, window_weighting, motion_floor
        self.horizon, self.warmup_epochs, self.lr = horizon, warmup_epochs, lr
        self.weight_decay, self.max_epochs = weight_decay, max_epochs
        self.save_hyperparameters(ignore=["model"])
        self.skipped_batches = 0

    def current_horizon(self) -> int:
        frac = min(1.0, (self.current_epoch + 1) / max(1, self.warmup_epochs))
        return max(1, int(round(frac * self.horizon)))

    def rollout_loss(self, batch, horizon: int, weighting: str = "uniform", wrench_fn=None,
                     window_weighting: str = "uniform", node_weights: torch.Tensor | None = None):
        """Mean squared rollout error over ``horizon`` steps. ``inverse_square`` divides the error at
        step h by h: a bias in the predicted second difference grows as h^2 along a rollout, so
        uniform weights let the last steps' drift dominate the loss and the fit of each single step
        (what the rollout is made of) hardly counts; divided by h, every step weighs about alike.
        ``window_weighting="inverse_motion"`` weighs each window's squared error by 1 / (d^2 + floor^2), d the RMS
        displacement of its modelled nodes from the reference shape over the window (``motion_floor`` metres),
        the weights scaled to mean 1 over the batch: an absolute loss is ruled by the largest motions (its
        weight grows as the load squared), so a small load's vibration, the printed Simulation III pulse's,
        hardly counts; relative to its motion, every window weighs about alike.
        Closed loop (the module's ``wrench_fn``, or the ``wrench_fn`` given here, and a batch with inputs):
        each step's wrench from the last frame. ``node_weights`` (one per modelled node) weigh the nodes' squared
        errors in the mean (divided by their mean, so that weights of one give the plain mean)."""
        hist, future, wrench, ref = batch[:4]
        if horizon > future.shape[1]:
            raise ValueError(f"horizon {horizon} exceeds the batch's {future.shape[1]} future frames (give the data "
                             "module a horizon at least the module's)")
        m = self.model
        idx = m.idx_modeled
        fn, wrench_fn = None, wrench_fn or self.wrench_fn
        if wrench_fn is not None:
            if len(batch) <= 4:  # it ran open loop, silently
                raise ValueError("wrench_fn: a closed-loop rollout needs batches with the loop's inputs "
                                 "(SurrogateDataModule(inputs=...))")
            inputs = batch[4]
            fn = lambda h, frame: wrench_fn(frame, inputs[:, h])  # noqa: E731
        pred = m.rollout(hist, wrench[:, :horizon], ref, anchors=future[:, :horizon], wrench_fn=fn)
        err = self.scaled_error(pred[:, :, idx], future[:, :horizon, idx])
        if weighting == "inverse_square":
            err = err / torch.arange(1, horizon + 1, dtype=err.dtype, device=err.device)[:, None, None]
        if node_weights is not None:
            err = err * (node_weights / node_weights.mean()).sqrt()[:, None]
        if window_weighting == "inverse_motion":
            frames = torch.cat([hist, future[:, :horizon]], 1)[:, :, idx]
            d2 = (frames - ref[:, None, idx]).pow(2).mean((1, 2, 3))
            w = 1.0 / (d2 + self.motion_floor ** 2)
            return (err.pow(2).mean((1, 2, 3)) * (w / w.mean())).mean(), pred
        return err.pow(2).mean(), pred

    def scaled_error(self, pred, target):
        """Position error in units of the mean second-difference scale (the losses' unit)."""
        return (pred - target) / self.model.a_scale.mean()

    def one_step_loss(self, batch, horizon: int):
        """Mean squared one-step (teacher-forced) error over the window's first ``horizon`` frames: each
        predicted from the true history, in the rollout loss's units."""
        hist, future, wrench, ref = batch[:4]
        m = self.model
        frames = torch.cat([hist, future[:, :horizon]], 1)
        windows = frames.unfold(1, hist.shape[1], 1)[:, :horizon].movedim(-1, 2)  # (B, horizon, W, n_tracked, 3)
        pred = m(windows.flatten(0, 1), wrench[:, :horizon].flatten(0, 1), ref.repeat_interleave(horizon, 0))
        err = self.scaled_error(pred.unflatten(0, (hist.shape[0], horizon)), future[:, :horizon, m.idx_modeled])
        return err.pow(2).mean()

    def noisy(self, batch):
        """Training noise on the modelled nodes' history, so that the model learns to correct its own rollout
        errors: ``walk``, a random walk (std ``noise`` x the node's step scale per frame), which also perturbs
        the history's velocities; ``offset``, one shift of that std per node and window, the same in every
        frame (a free-running rollout's slow drift: its positions err, its steps hardly), which leaves the
        velocities exact, so the model learns to pull a displaced node back without learning to distrust
        the motion it sees."""
        if self.noise <= 0:
            return batch
        hist = batch[0]
        idx = self.model.idx_modeled
        if self.noise_shape == "offset":
            shift = torch.randn_like(hist[:, :1, idx]) * self.noise * self.model.v_scale
            return (hist.index_add(2, idx, shift.expand_as(hist[:, :, idx])), *batch[1:])
        walk = (torch.randn_like(hist[:, :, idx]) * self.noise * self.model.v_scale).cumsum(1)
        return (hist.index_add(2, idx, walk), *batch[1:])

    def training_step(self, batch, batch_idx):
        loss, _ = self.rollout_loss(self.noisy(batch), self.current_horizon(), self.step_weighting,
                                    window_weighting=self.window_weighting)
        if self.one_step_weight > 0:
            loss = loss + self.one_step_weight * self.one_step_loss(batch, self.current_horizon())
        # a rollout that ran away (on any process, under DDP): skip the batch rather than poison the weights
        if not self.trainer.strategy.reduce_boolean_decision(bool(torch.isfinite(loss)), all=True):
            if self.trainer.world_size > 1:
                # DDP all-reduces the gradients, so every process must run the backward pass (returning None
                # would leave the others waiting): NaN gradients make all of them drop the step together,
                # and none logs this batch's loss (every logged metric is synchronised)
                return loss * float("nan")
            self._skip()
            return None
        self.log("train_loss", loss, prog_bar=True, on_epoch=True, on_step=False, sync_dist=True)
        self.log("horizon", float(self.current_horizon()), on_epoch=True, on_step=False, sync_dist=True)
        return loss

    def validation_step(self, batch, batch_idx):
        loss, pred = self.rollout_loss(batch, self.horizon)
        future = batch[1]
        idx = self.model.idx_modeled
        mm = (pred[:, :, idx] - future[:, :self.horizon, idx]).abs().amax() * 1e3
        # sync_dist: under DDP each process validates its share of the windows; every process must select the
        # same epoch (and name its checkpoint file alike)
        self.log("val_loss", loss, prog_bar=True, sync_dist=True)
        self.log("val_max_err_mm", mm, reduce_fx="max", sync_dist=True)

    def _skip(self):
        """Count a skipped batch (under DDP every process skips the same ones)."""
        self.skipped_batches += 1
        self.log("skipped_batches", float(self.skipped_batches), on_epoch=True, on_step=False, reduce_fx="max",
                 sync_dist=True)

    def on_before_optimizer_step(self, optimizer):
        """A finite loss can still overflow in the backward pass: drop such a step's gradients (the
        optimiser then leaves the weights as they are) instead of letting clipping spread the NaN."""
        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        if grads and not all(torch.isfinite(g).all() for g in grads):
            self._skip()
            for p in self.model.parameters():
                p.grad = None

    def setup(self, stage: str):
        """Under DDP on CPU (gloo) close the process group when the process exits. Lightning closes only
        NCCL groups; a gloo group left open can abort the process at exit ("terminate called without an
        active exception", SIGABRT) after training has finished."""
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized() and dist.get_backend() == "gloo":
            atexit.register(_close_process_group)

    def configure_optimizers(self):
        opt = torch.optim.AdamW(self.model.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, self.max_epochs), eta_min=self.lr * 0.05)
        return {"optimizer": opt, "lr_scheduler": sched}


def _close_process_group():
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


class RolloutSelection(L.Callback):
    """Logs ``val_rollout_mm`` after every validation epoch: the mean absolute error (mm) of the modelled
    nodes over a free-running rollout of the validation trajectories from their first frame (``steps``
    steps; 0: the whole trajectory), in closed loop where the module has a ``wrench_fn`` or one is given
    here (a model trained open loop but used in closed loop, selected as it is used). The short
    windows of ``val_loss`` do not rank models by how long their rollouts stay on the physics; monitor
    this instead to select and early-stop on it. A rollout that runs away scores ``cap_mm``."""

    def __init__(self, datamodule: SurrogateDataModule, steps: int = 0, cap_mm: float = 1e5, wrench_fn=None):
        self.dm, self.steps, self.cap_mm, self.wrench_fn = datamodule, steps, cap_mm, wrench_fn
        self._batch = None

    @torch.no_grad()
    def score(self, module: SurrogateModule) -> float:
        if self._batch is None:
            self._batch = self.dm.long_rollout_batch(self.steps)
        batch = tuple(t.to(module.device, module.dtype if t.is_floating_point() else t.dtype) for t in self._batch)
        _, pred = module.rollout_loss(batch, batch[1].shape[1], wrench_fn=self.wrench_fn)
        idx = module.model.idx_modeled
        err = (pred[:, :, idx] - batch[1][:, :, idx]).abs().mean() * 1e3
        return float(err) if torch.isfinite(err) and err < self.cap_mm else self.cap_mm

    def on_validation_epoch_end(self, trainer, pl_module):
        if trainer.sanity_checking:
            return
        pl_module.log("val_rollout_mm", self.score(pl_module), prog_bar=True, sync_dist=True)  # alike on every process
