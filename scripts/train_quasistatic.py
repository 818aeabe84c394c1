"""Train the quasi-static hybrid surrogate of the magnetic rod (static Cosserat rod + learned dynamics).

    python scripts/train_quasistatic.py [--variants 32] [--epochs 30] [--quick]

Generates the LGVI dataset (``data/<task>_v<V>_s<seed>.pt``) and the static Cosserat rod along its profiles
(``..._static.pt``) where missing, fits the correction's linear part by least squares, trains its network on
free-running rollouts with Lightning (progress bar, CSV logs, early stopping and selection on the validation
profile's rollout loss, ``--resume`` from a Lightning checkpoint), evaluates the orientation errors of the
hybrid and of the static rod alone on the printed profile's last 40 % and the held-out profile, and writes
``checkpoints/<task>_quasistatic.pt`` + ``.json`` with the metrics and this exact command. Prints one JSON
line last.
"""
from __future__ import annotations

import json
import shlex
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

import cmlearn
from cmlearn.args import dataclass_parser, opt
from cmlearn.data import cached_dataset, get_task

MAGNETIC_TASKS = ("magnetic_rod", "magnetic_rod_planar")


@dataclass
class Args:
    task: str = opt("magnetic_rod", "the magnetic-rod task", MAGNETIC_TASKS)
    variants: int = opt(32, "LGVI current profiles in the dataset (the printed one and random ones)")
    seed: int = opt(0, "the dataset's seed", at_least=0)
    train_seed: int = opt(0, "seeds the initial weights and the batch order", at_least=0)
    eta: int = opt(2, "deviation history beyond the current frame (the LSTM's eta, >= 2)", at_least=2)
    increments: int = opt(3, "static-state increments the step sees", at_least=1)
    hidden: int = opt(32, "LSTM units", at_least=1)
    width: int = opt(64, "dense widths", at_least=1)
    margin: bool = opt(False, "the network also sees the static solutions' stability margins (they fall to zero "
                              "as the rod nears a snap-through)")
    fold_clock: float = opt(0.0, "with --margin: the network also sees the frames since the static track last "
                                 "jumped over a fold (the fold's time within its frame from the margins before it), "
                                 "capped at this many (0: off)", at_least=0)
    horizon: int = opt(32, "free-running steps per training window", at_least=1)
    val_horizon: int = opt(128, "free-running steps per validation window", at_least=1)
    val_stride: int = opt(8, "frames between validation windows", at_least=1)
    batch_size: int = opt(64, "training windows per batch", at_least=1)
    train_batches: int = opt(100, "batches per epoch", at_least=1)
    epochs: int = opt(30, "training epochs (cosine learning-rate schedule over them)", at_least=1)
    lr: float = opt(1e-3, "Adam learning rate (0: the weights stay)", at_least=0)
    loss: str = opt("l1", "rollout loss: mean absolute or mean squared deviation error (l2 weighs the large "
                          "errors of the snap-throughs more)", ("l1", "l2"))
    patience: int = opt(10, "epochs without a better validation loss before stopping", at_least=1)
    threads: int = opt(1, "torch CPU threads", at_least=1)
    data_dir: str = opt("data", "where datasets and static tracks are cached", path="folder")
    log_dir: str = opt("logs", "Lightning CSV logs", path="folder")
    fresh: int = opt(0, "also score the model from rest on this many random profiles of --fresh-seed, never trained "
                        "on (0: none)", at_least=0)
    fresh_seed: int = opt(1, "the seed of the --fresh profiles (must differ from --seed)", at_least=0)
    out: str = opt("", "checkpoint path (default checkpoints/<task>_quasistatic.pt; with --quick "
                       "runs/quick/<task>_quasistatic.pt, so a smoke test never replaces a shipped model)", path="checkpoint")
    resume: str = opt("", "a Lightning checkpoint to resume", path="input")
    init_from: str = opt("", "a hybrid checkpoint whose network (LSTM, dense layers, head) starts the training; its "
                             "--increments, --hidden, --width, --margin and --fold-clock must match, --eta may "
                             "differ (the LSTM reads any history); the linear part is fitted anew", path="input")
    quick: bool = opt(False, "smoke-test budget: 3 profiles of 1 s, two epochs of 4 batches, no evaluation")


def parse(argv=None) -> Args:
    ap = dataclass_parser(Args, __doc__.splitlines()[0])
    a = Args(**vars(ap.parse_args(argv)))
    if a.variants < 3:
        ap.error(f"--variants must be >= 3 (the printed profile, training profiles and a validation one), "
                 f"got {a.variants}")
    if a.fresh and a.fresh_seed == a.seed:
        ap.error(f"--fresh-seed must differ from --seed {a.seed} (the --fresh profiles would be training ones)")
    if a.fold_clock and not a.margin:
        ap.error("--fold-clock needs --margin (the clock is read from the margins before a fold)")
    if a.quick:
        a.variants, a.epochs, a.train_batches, a.horizon, a.val_horizon = 3, 2, 4, 4, 8
    return a


def main(argv=None):
    a = parse(argv)
    import lightning as L
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    from cmlearn.data.quasistatic import with_fold_clock
    from cmlearn.models.quasistatic import QuasiStaticConfig, QuasiStaticCorrection
    from cmlearn.surrogate.quasistatic import (QuasiStaticSurrogate, evaluate_quasistatic, fresh_scores,
                                              rest_rotations, save_quasistatic, short_check, static_tracks)
    from cmlearn.surrogate.quasistatic_training import (QuasiStaticDataModule, QuasiStaticModule, fit_scales,
                                                        track_ends, training_ranges)

    torch.set_num_threads(a.threads)
    L.seed_everything(a.train_seed, workers=True)
    task = get_task(a.task)
    t0 = time.perf_counter()
    data = cached_dataset(task, a.variants, a.seed, a.data_dir, 1.0 if a.quick else None)
    s, d = static_tracks(task, data, None if a.quick else a.data_dir, rest_rotations(task), truncate=True)
    t_data = time.perf_counter() - t0
    ranges, ended = training_ranges(s), track_ends(s)
    for v, k in ended.items():
        print(f"profile {v}: the static rod has no equilibrium at frame {k} (t = {k * task.delta:.3g} s); "
              f"it trains on frames 0-{k - 1} only")
    cfg = QuasiStaticConfig(eta=a.eta, increments=a.increments, hidden=a.hidden, width=a.width,
                            rest_state=tuple(s[0, 0, :12].tolist()), margin=a.margin, rest_margin=float(s[0, 0, 12]),
                            fold_clock=a.fold_clock, **fit_scales(s, d, ranges["train"]))
    if a.fold_clock:
        s = with_fold_clock(s, a.fold_clock)
    model = QuasiStaticCorrection(cfg)
    residual = model.fit_linear(d, s, ranges["train"])
    if a.init_from:
        src = QuasiStaticSurrogate.load(a.init_from, task=task.name).model
        differ = [k for k in ("increments", "hidden", "width", "margin", "fold_clock")
                  if getattr(src.config, k) != getattr(cfg, k)]
        if differ:
            raise SystemExit(f"--init-from {a.init_from}: its {', '.join(differ)} differ from this run's")
        model.load_state_dict({k: v for k, v in src.state_dict().items() if k.split(".")[0] in ("lstm", "dense", "head")},
                              strict=False)
    dm = QuasiStaticDataModule(s, d, a.eta, a.increments, a.horizon, a.val_horizon, a.batch_size, a.val_stride,
                               a.train_seed)
    module = QuasiStaticModule(model, lr=a.lr, epochs=a.epochs, loss=a.loss)
    logger = CSVLogger(a.log_dir, name=f"{task.name}_quasistatic")
    ckpt = ModelCheckpoint(dirpath=Path(logger.log_dir) / "ckpt", monitor="val_loss", save_last=True)
    trainer = L.Trainer(max_epochs=a.epochs, logger=logger, enable_progress_bar=True, deterministic=True,
                        callbacks=[EarlyStopping("val_loss", patience=a.patience), ckpt], gradient_clip_val=1.0,
                        limit_train_batches=a.train_batches, log_every_n_steps=10, num_sanity_val_steps=0)
    start = trainer.validate(module, datamodule=dm, verbose=False)[0]["val_loss"]
    trainer.fit(module, datamodule=dm, ckpt_path=a.resume or None)
    if ckpt.best_model_path:
        module.load_state_dict(torch.load(ckpt.best_model_path, map_location="cpu", weights_only=False)["state_dict"])
    model = module.model.cpu().float().eval()
    t_train = time.perf_counter() - t0 - t_data
    cmd = "python scripts/train_quasistatic.py " + " ".join(
        shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    meta = {"task": task.name, "scene": task.scene, "heldout": list(task.heldout), "delta": task.delta,
            "model": "static Cosserat rod (13 nodes) + QuasiStaticCorrection", "architecture": cfg.to_dict(),
            "n_parameters": sum(p.numel() for p in model.parameters()), "linear_fit_residual": residual,
            "val_loss_start": float(start), "val_loss_best": float(ckpt.best_model_score or start),
            "data_hash": data["meta"]["data_hash"], "data_seed": a.seed, "n_variants": a.variants,
            "static_track_ends": {str(v): k for v, k in ended.items()},
            "command": cmd.strip(), "args": asdict(a), "cmlearn_version": cmlearn.__version__,
            "torch": str(torch.__version__), "epochs_run": trainer.current_epoch, "train_wall_s": t_train,
            "data_wall_s": t_data}
    if not a.quick:
        engine = QuasiStaticSurrogate(model, meta)
        meta["metrics"] = evaluate_quasistatic(engine, a.data_dir)
        meta["check"] = short_check(engine, data_dir=a.data_dir)
        if a.fresh:
            meta["metrics"]["fresh"] = fresh_scores(model, task, a.fresh + 1, a.fresh_seed, a.data_dir)
    out = Path(a.out or f"{'runs/quick' if a.quick else 'checkpoints'}/{task.name}_quasistatic.pt")
    save_quasistatic(out, model, meta)
    print(f"wrote {out}")
    for case, res in meta.get("metrics", {}).items():
        if case == "fresh":
            print(f"{res['profiles']} fresh profiles of seed {res['seed']}: median sum of the six mean orientation "
                  f"errors {res['hybrid']['median']:.2f} deg (static rod alone {res['static']['median']:.2f})")
            continue
        print(f"{case}: sum of the six mean orientation errors {res['hybrid']['sum_mean_deg']:.2f} deg "
              f"(static rod alone {res['static']['sum_mean_deg']:.2f})")
    print(json.dumps({"checkpoint": str(out), "metrics": meta.get("metrics"), "train_wall_s": t_train}))
    return meta


if __name__ == "__main__":
    main()
