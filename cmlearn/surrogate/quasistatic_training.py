"""Lightning training of the quasi-static hybrid's correction (:class:`~cmlearn.models.QuasiStaticCorrection`),
imported only for training.

Data: a task's dataset (the LGVI's runs of its current profiles) and the static Cosserat rod along the same
profiles (:func:`~cmlearn.surrogate.quasistatic.static_tracks`, cached next to the dataset), as static states
and deviations (V, T, 12) (:mod:`cmlearn.data.quasistatic`). Splits are
:func:`~cmlearn.data.windows.split_ranges`' (the printed profile's first 60 % and all other profiles but the
last train; the last validates). The linear part is
fitted on the training frames first (:meth:`QuasiStaticCorrection.fit_linear`); the loss is then the mean
absolute (``loss="l1"``) or squared (``"l2"``: the large errors of the snap-throughs weigh more) deviation error,
in units of ``dev_scale``, of free-running rollouts of ``horizon`` steps from the true history at random frames;
validation rolls out ``val_horizon`` steps from every ``val_stride``-th frame.
"""
from __future__ import annotations


import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from cmlearn.data.windows import split_ranges
from cmlearn.models.quasistatic import QuasiStaticCorrection
from cmlearn.surrogate.training import SeededDataModule
from physics.checks import check_integer

__all__ = ["track_ends", "training_ranges", "fit_scales", "DeviationWindows", "QuasiStaticDataModule", "QuasiStaticModule"]


def track_ends(s: torch.Tensor) -> dict[int, int]:
    """{profile: the first frame with no static solution} of static states ``s`` (V, T, 13), for the profiles whose
    track ended at a fold (:func:`~cmlearn.data.quasistatic.static_track`'s ``truncate``: NaN from there on)."""
    n = torch.isfinite(s).all(-1).long().cumprod(-1).sum(-1)
    return {v: int(k) for v, k in enumerate(n) if k < s.shape[1]}


def training_ranges(s: torch.Tensor) -> dict:
    """:func:`~cmlearn.data.windows.split_ranges` of static states ``s`` (V, T, 13), each range cut before its
    profile's :func:`track_ends` (a range left with no step is dropped)."""
    ends = track_ends(s)
    out = {}
    for split, ranges in split_ranges(s.shape[0], s.shape[1]).items():
        cut = [(v, a, min(b, ends.get(v, b + 1) - 1)) for v, a, b in ranges]
        out[split] = [(v, a, b) for v, a, b in cut if b > a]
    return out


def fit_scales(s: torch.Tensor, d: torch.Tensor, ranges) -> dict:
    """:class:`~cmlearn.models.QuasiStaticConfig` keywords: per-coordinate scales of the deviations, the static
    increments and the static states on the frame ranges [(variant, first, last)] (and of the margins, a 13th
    column of ``s``, where there)."""
    S = torch.cat([s[v, a:b + 1] for v, a, b in ranges])
    D = torch.cat([d[v, a:b + 1] for v, a, b in ranges])
    inc = torch.cat([s[v, a + 1:b + 1] - s[v, a:b] for v, a, b in ranges])[:, :12]
    floor = 1e-3
    out = {"dev_scale": tuple((D.std(0) + floor).tolist()), "inc_scale": tuple((inc.std(0) + floor).tolist()),
           "state_mean": tuple(S[:, :12].mean(0).tolist()), "state_scale": tuple((S[:, :12].std(0) + floor).tolist())}
    if S.shape[1] > 12:
        out["margin_scale"] = float(S[:, 12].std() + floor)
    return out


class DeviationWindows(Dataset):
    """Windows of ``horizon`` steps from every ``stride``-th frame k0 of the ranges [(variant, first, last)]:
    (deviations k0-eta..k0, static states k0+1-increments..k0+horizon, deviations k0+1..k0+horizon)."""

    def __init__(self, s: torch.Tensor, d: torch.Tensor, ranges, eta: int, increments: int, horizon: int,
                 stride: int = 1):
        # horizon 0 gave empty targets (a NaN loss), eta -1 an empty history, stride 0 range()'s error
        eta, increments, horizon, stride = (check_integer(f"DeviationWindows: {name}", v, lo) for name, v, lo in (
            ("eta", eta, 0), ("increments", increments, 1), ("horizon", horizon, 1), ("stride", stride, 1)))
        self.s, self.d, self.eta, self.n, self.H = s.float(), d.float(), eta, increments, horizon
        lead = max(eta, increments - 1)
        self.starts = [(v, k) for v, a, b in ranges for k in range(max(a, lead), b - horizon + 1, stride)]
        if not self.starts:
            raise ValueError(f"no window of {horizon} steps fits the ranges {ranges}")

    def __len__(self):
        return len(self.starts)

    def __getitem__(self, i):
        v, k = self.starts[i]
        return (self.d[v, k - self.eta:k + 1], self.s[v, k + 1 - self.n:k + self.H + 1],
                self.d[v, k + 1:k + self.H + 1])


class QuasiStaticDataModule(SeededDataModule):
    def __init__(self, s: torch.Tensor, d: torch.Tensor, eta: int, increments: int, horizon: int,
                 val_horizon: int, batch_size: int = 64, val_stride: int = 8, seed: int = 0):
        super().__init__(seed)
        ranges = training_ranges(s)
        self.train_set = DeviationWindows(s, d, ranges["train"], eta, increments, horizon)
        self.val_set = DeviationWindows(s, d, ranges["val"], eta, increments, val_horizon, val_stride)
        if batch_size > len(self.train_set):  # the loader drops the last partial batch: no training at all
            raise ValueError(f"batch_size {batch_size} exceeds the {len(self.train_set)} training windows of "
                             f"{horizon} steps")
        self.batch_size = batch_size

    def train_dataloader(self):
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, drop_last=True,
                          generator=self.shuffle)

    def val_dataloader(self):
        return DataLoader(self.val_set, batch_size=256)


LOSSES = ("l1", "l2")


class QuasiStaticModule(L.LightningModule):
    def __init__(self, model: QuasiStaticCorrection, lr: float = 1e-3, epochs: int = 30, loss: str = "l1"):
        super().__init__()
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
        self.model, self.lr, self.epochs, self.kind = model, lr, epochs, loss

    def loss(self, batch) -> torch.Tensor:
        dev, s, target = batch
        e = (self.model.rollout(dev, s) - target) / self.model.dev_scale
        return e.abs().mean() if self.kind == "l1" else e.pow(2).mean()

    def training_step(self, batch, _):
        loss = self.loss(batch)
        self.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True)
        return loss

    def validation_step(self, batch, _):
        self.log("val_loss", self.loss(batch), prog_bar=True, on_epoch=True)

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.model.parameters(), lr=self.lr)
        return {"optimizer": opt, "lr_scheduler": torch.optim.lr_scheduler.CosineAnnealingLR(opt, self.epochs)}
