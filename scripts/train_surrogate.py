"""Train a distributed LSTM node surrogate on LGVI data and ship it as a checkpoint.

    python scripts/train_surrogate.py --task semicircle [--variants 24] [--epochs 60] [--quick]

Generates the dataset with the physics if ``data/<task>_v<V>_s<seed>.pt`` is missing, trains with
Lightning (progress bar, CSV and, when installed, TensorBoard logs under ``logs/``, checkpoint selection
and early stopping on the validation windows' rollout loss or, with ``--select-by rollout``, on a
free-running rollout of the whole validation trajectories, ``--resume`` from a Lightning checkpoint, ``--init-from``
a shipped checkpoint's weights (fine-tuning with a fresh schedule), ``--ema`` to validate and ship an
exponential moving average of the weights, ``--ddp`` for
multi-process data parallel, ``--accelerator gpu`` to train on a GPU; the checkpoint is always written for
the CPU), evaluates one-step and free-running errors on the printed scene's unseen last 40 % and on the
held-out scenes, and writes ``checkpoints/<task>.pt`` + ``.json`` with
the metrics and this exact command. Prints one JSON line last.
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
from cmlearn.data import TASKS, cached_dataset, get_task
from cmlearn.models import NodeLSTMSurrogate
from cmlearn.surrogate import save_checkpoint
from cmlearn.surrogate.checkpoint import provenance
from cmlearn.surrogate.evaluate import evaluate_scenes, metric_lines, recorded_check


SELECT_METRICS = {"val_loss": "val_loss", "rollout": "val_rollout_mm"}


@dataclass
class Args:
    task: str = opt("semicircle", "the scene to learn", sorted(TASKS))
    variants: int = opt(24, "LGVI trajectories generated for the dataset (random load/shape variants)", at_least=1)
    seed: int = opt(0, "the dataset's seed (its random variants); also the training seed unless --train-seed",
                    at_least=0)
    train_seed: int = opt(-1, "seeds the initial weights and the batch order (-1: --seed), for runs on the same data",
                          at_least=-1)
    eta: int = opt(2, "pose-history length each node's LSTM sees (the thesis's eta, >= 2)", at_least=2)
    hidden: int = opt(48, "LSTM hidden size per modelled node", at_least=1)
    head_hidden: int = opt(64, "width of the two hidden layers of the dense head after the LSTM (with --init-from: "
                            "at least the checkpoint's; a wider head's added units start without effect)", at_least=1)
    stencil: int = opt(1, "rings of neighbours each node sees: 1 (left, right), 2 (also their outer neighbours: a "
                          "five-node stencil, as bending needs) or 3 (seven nodes); with --init-from at least the "
                          "checkpoint's, an added ring's weights starting at zero", (1, 2, 3))
    mix: int = opt(0, "rings of neighbouring modelled nodes whose LSTM outputs each node's dense head also sees: 0 "
                      "(none), 1 (left and right: a second local layer, five nodes in view with --stencil 1) or 2 "
                      "(seven); with --init-from at least the checkpoint's, the added inputs' weights starting at zero",
                   (0, 1, 2))
    mix_width: int = opt(0, "with --mix: each neighbour's LSTM output reaches the head through a shared linear "
                            "projection to this many numbers (0: the whole output), a cheaper step; with --init-from "
                            "any, the checkpoint's weights on the neighbours' outputs taken to their best "
                            "approximation of that rank (exact at its own width or more)", at_least=0)
    rest_anchor: bool = opt(False, "subtract the model's output at rest: in the task's equilibrium where it names one "
                                   "(Simulation I's circle), else in the initial shape (scenes that start at rest); "
                                   "no weights, so --init-from may add it")
    chord_projection: bool = opt(False, "after every rollout step move the modelled nodes (to the nearest frame, to "
                                        "second order) so that each chord between consecutive tracked nodes keeps "
                                        "its reference length, for rods that hardly stretch; no weights, so "
                                        "--init-from may add it (no shipped model uses it: docs/surrogates.md)")
    mirror: str = opt("", "axis letters (x, y, z; e.g. zx): make the step equivariant under those reflections "
                          "of the task; no weights, so --init-from may add or drop them")
    horizon: int = opt(32, "free-running steps of the training rollout loss after the warm-up epochs", at_least=1)
    warmup_epochs: int = opt(15, "epochs over which the rollout horizon grows linearly up to --horizon", at_least=0)
    epochs: int = opt(60, "maximum number of epochs", at_least=1)
    max_time: float = opt(0.0, "wall-time budget of the training in minutes (0: none); Lightning checks it after "
                               "each batch and validation, then the run keeps its selected epoch and evaluates",
                               at_least=0)
    batch_size: int = opt(64, "windows per optimiser step", at_least=1)
    train_batches: int = opt(0, "batches per epoch (0: all windows)", at_least=0)
    lr: float = opt(3e-3, "AdamW learning rate, cosine-annealed to 5 %% of it over --epochs (0: the weights stay)",
                    at_least=0)
    weight_decay: float = opt(1e-4, "AdamW weight decay", at_least=0)
    ema: float = opt(0.0, "decay of an exponential moving average of the weights, updated every optimiser step, "
                          "that validation scores and the checkpoint ships (0: off; e.g. 0.995)", at_least=0)
    noise: float = opt(0.0, "training-noise std on the history, in units of each node's step scale", at_least=0)
    noise_shape: str = opt("walk", "the training noise in time: a random walk over the history frames (walk), or "
                                   "one shift per node and window (offset: the velocities left exact)",
                           ["walk", "offset"])
    time_reversal: bool = opt(False, "also train on every window played backwards (undamped scenes with "
                                     "time-dependent forces only, whose motion is time-reversible), which "
                                     "penalises a step that dissipates energy")
    printed_repeat: int = opt(1, "the printed scene's training windows (its first 60 %%) appear this many times in "
                                 "each epoch, so that it keeps its share of the training as --variants grows (the "
                                 "scales count it once)", at_least=1)
    step_weighting: str = opt("uniform", "rollout-loss weights per step (inverse_square: 1/h^2)",
                              ["uniform", "inverse_square"])
    window_weighting: str = opt("uniform", "rollout-loss weights per training window (inverse_motion: 1 / (d^2 + "
                                           "floor^2), d the window's RMS displacement from the reference shape)",
                                ["uniform", "inverse_motion"])
    motion_floor: float = opt(1e-3, "the floor of --window-weighting inverse_motion, metres", above=0)
    one_step_weight: float = opt(0.0, "weight of a teacher-forced one-step loss term beside the rollout loss",
                                 at_least=0)
    closed_loop: bool = opt(False, "training rollouts compute their own wrench (tasks whose custom module can; "
                                   "their validation rollout, val_rollout_mm, always does)")
    patience: int = opt(15, "early stopping: epochs without improvement of the selection metric", at_least=1)
    select_by: str = opt("val_loss", "checkpoint selection and early stopping (rollout: val_rollout_mm)",
                         sorted(SELECT_METRICS))
    val_fresh: int = opt(0, "validate on this many fresh variants of the scene (--val-seed, LGVI runs cached) "
                            "instead of the dataset's last variant, which then trains (0: off)", at_least=0)
    val_seed: int = opt(-1, "the fresh validation variants' seed, with --val-fresh (-1: --seed + 1)", at_least=-1)
    val_tail: float = opt(0.0, "this fraction of the printed scene's trajectory, just before the 60 %% cut, "
                               "validates instead of training (the thesis's protocol: --variants 1 --val-tail 0.15)",
                               at_least=0)
    val_stride: int = opt(1, "validation windows start every this many frames", at_least=1)
    select_steps: int = opt(0, "steps of the validation rollout behind val_rollout_mm (0: the whole trajectory)",
                            at_least=0)
    keep_top_k: int = opt(1, "Lightning checkpoints kept by the selection metric (-1: every epoch)", at_least=-1)
    threads: int = opt(2, "torch CPU threads", at_least=1)
    data_dir: str = opt("data", "where datasets and the LGVI runs of the evaluated scenes are generated and cached",
                        path="folder")
    compile_data: bool = opt(False, "generate a missing dataset with the LGVI's compiled rollout (its program compiled "
                                    "ahead of time; equal to the eager LGVI to round-off; not for the magnetic rod)")
    out: str = opt("", "the shipped checkpoint to write (empty: checkpoints/<task>.pt; with --quick runs/quick/<task>.pt, "
                       "so a smoke test never replaces a shipped model)", path="checkpoint")
    log_dir: str = opt("logs", "CSV / TensorBoard logs and Lightning checkpoints", path="folder")
    resume: str = opt("", "a Lightning checkpoint (.ckpt) whose run (weights, optimiser, schedule) continues",
                      path="input")
    init_from: str = opt("", "a cmlearn surrogate checkpoint (.pt) whose weights start a new run (fine-tuning)",
                         path="input")
    keep_scales: bool = opt(False, "with --init-from, keep the checkpoint's input and output scales where this run's "
                                   "data gives others (e.g. more variants of the same scene: the scales only "
                                   "normalise, so the weights keep their meaning); the difference is recorded")
    accelerator: str = opt("cpu", "Lightning's accelerator; off the CPU, ops without a deterministic kernel warn",
                           ["cpu", "gpu", "auto"])
    ddp: bool = opt(False, "multi-process data parallel (Lightning's DDP strategy) over --devices; --batch-size "
                          "and --train-batches are per process, and only the first process evaluates and writes")
    devices: int = opt(1, "processes / devices for --ddp", at_least=1)
    quick: bool = opt(False, "smoke-test budget: a short scene, at most 3 variants, two epochs")
    duration: float = opt(0.0, "simulated seconds per trajectory (0: the scene's own)", at_least=0)


def parse(argv=None) -> Args:
    ap = dataclass_parser(Args, __doc__.splitlines()[0])
    a = Args(**vars(ap.parse_args(argv)))
    try:
        get_task(a.task).reflections(a.mirror)
    except ValueError as e:
        ap.error(f"--mirror must name task {a.task!r}'s reflections: {e}")
    if not a.val_tail < 0.6:
        ap.error(f"--val-tail must lie in [0, 0.6) of the trajectory (the printed scene's cut), got {a.val_tail}")
    if a.val_tail and a.val_fresh:
        ap.error("--val-tail and --val-fresh exclude each other: validate on the printed scene's tail or on fresh "
                 "variants")
    if a.variants < 2 and not (a.val_tail or a.val_fresh):
        ap.error(f"--variants {a.variants} leaves no variant to validate on (the printed scene's last 40 % is the "
                 "test): give --val-tail F (the thesis's one-trajectory protocol), --val-fresh N or more variants")
    if a.val_seed >= 0 and not a.val_fresh:
        ap.error(f"--val-seed {a.val_seed} seeds the --val-fresh variants, and none are asked for")
    if a.motion_floor != Args.motion_floor and a.window_weighting != "inverse_motion":
        ap.error(f"--motion-floor {a.motion_floor} is the floor of --window-weighting inverse_motion, which is off")
    if a.noise_shape != Args.noise_shape and not a.noise:
        ap.error(f"--noise-shape {a.noise_shape} shapes the training noise, and --noise is 0")
    if a.val_seed < 0:
        a.val_seed = a.seed + 1
    if a.val_fresh and a.val_seed == a.seed:
        ap.error(f"--val-seed must differ from --seed {a.seed}: the fresh variants would be the training ones")
    if a.mix_width and not (a.mix and 1 <= a.mix_width <= a.hidden):
        ap.error(f"--mix-width must be 0, or in 1..--hidden ({a.hidden}) with --mix 1 or 2, got {a.mix_width} with "
                 f"--mix {a.mix}")
    if not a.ema < 1.0:
        ap.error(f"--ema must lie in [0, 1) (0: off), got {a.ema}")
    if a.time_reversal:
        task = get_task(a.task)
        rod = task.base_scene().rod
        if task.custom or rod.damping or rod.rotational_damping:
            ap.error(f"--time-reversal: task {a.task!r} is not time-reversible (damped, or its wrench depends on the "
                     "rod's own state)")
    if a.chord_projection and get_task(a.task).custom:
        ap.error(f"--chord-projection: task {a.task!r} tracks points that are not a chain along the rod (markers)")
    if a.resume:
        try:
            resumed = torch.load(a.resume, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001 (any unpickling failure)
            ap.error(f"--resume: {a.resume} is not a readable Lightning checkpoint ({type(e).__name__}: {e})")
    if a.resume and not a.ema and isinstance(resumed, dict) and "current_model_state" in resumed:
        ap.error(f"--resume: {a.resume} comes from a run with --ema (its state_dict holds the averaged weights, "
                 "the optimiser's own are beside them): resume it with the same --ema")
    if a.keep_scales and not a.init_from:
        ap.error("--keep-scales needs --init-from (the checkpoint whose scales it keeps)")
    if a.init_from and a.resume:
        ap.error("--init-from and --resume exclude each other: --resume restores a Lightning run (weights, "
                 "optimiser and schedule), --init-from only the weights of a cmlearn checkpoint")
    if a.keep_top_k == 0:
        ap.error("--keep-top-k must be >= 1 or -1 (every epoch), got 0: with none kept no epoch is selected, and the "
                 "last one would ship")
    if a.devices > 1 and not a.ddp:
        ap.error(f"--devices must be 1, or more with --ddp (one training process each), got {a.devices}")
    if a.quick:  # smoke-test budget: a short scene, few variants, two epochs
        a.variants, a.epochs, a.warmup_epochs, a.horizon = min(a.variants, 3), min(a.epochs, 2), 1, min(a.horizon, 4)
        a.duration = a.duration or 0.3
    return a


def model_config(task, a: Args):
    return task.model_config(eta=a.eta, hidden=a.hidden, head_hidden=a.head_hidden, rest_anchor=a.rest_anchor,
                             chord_projection=a.chord_projection, mirror=a.mirror, stencil=a.stencil, mix=a.mix,
                             mix_width=a.mix_width)


def build_model(task, a: Args) -> NodeLSTMSurrogate:
    return NodeLSTMSurrogate(model_config(task, a))


def load_init(task, a: Args) -> tuple[NodeLSTMSurrogate, dict]:
    """The ``--init-from`` checkpoint, checked for this run's task and architecture before any data is
    generated (:func:`start_from` widens it); SystemExit naming --init-from otherwise."""
    from cmlearn.surrogate.checkpoint import CheckpointError, load_checkpoint
    try:
        init, meta = load_checkpoint(a.init_from, task=task.name)
    except CheckpointError as e:
        raise SystemExit(f"--init-from: {e}") from None
    # the chord projection, the rest anchor and the mirrors have no weights: a run may add or drop them; a wider
    # head, stencil or mix is added as weights that start without effect (NodeLSTMSurrogate.widened_to)
    try:
        init.widened_to(model_config(task, a))
    except ValueError as e:
        raise SystemExit(f"--init-from: {a.init_from}: {e}; pass the same --eta and --hidden, and a --head-hidden, "
                         "--stencil and --mix at least its own") from None
    return init, meta


SCALES = ("length_scale", "disp_scale", "rel_scale", "v_scale", "a_scale", "f_scale")


def start_from(model: NodeLSTMSurrogate, init: NodeLSTMSurrogate, meta: dict, data: dict, dm, path: str,
               keep_scales: bool = False) -> dict:
    """Fine-tuning: ``model`` takes ``init``'s weights, scales included, and starts a run with its own
    schedule; ``init`` is first grown into ``model``'s architecture (:meth:`NodeLSTMSurrogate.widened_to`: a wider
    head, stencil or mix, the neighbours' outputs projected to its ``mix_width``), an added ring's offset scales
    from the data. The checkpoint's scales must fit this run's data: the same data
    hash, or (regenerated data can differ in its last bits, for example on another machine) the scales this
    data gives within 1e-5, over the variants the checkpoint's own run trained on (with or without
    --val-fresh, with its --val-tail), unless ``keep_scales``. Returns the provenance the new checkpoint records
    (the file's path and SHA-256, the command and data hash that made it, and ``scales_off``, the largest relative
    difference of those scales: 0 on the same data)."""
    run = meta.get("args", {})
    trained = dm.train_positions(fresh_validation=bool(run.get("val_fresh")), val_tail=run.get("val_tail", 0.0))
    fresh = NodeLSTMSurrogate(model.config)  # the scales this run's data gives
    forces = dm.train_wrench(fresh_validation=bool(run.get("val_fresh")), val_tail=run.get("val_tail", 0.0))
    fresh.set_scales(trained, forces, float(init.length_scale))
    ring = 6 * init.config.stencil  # the offset scales the checkpoint holds; those of a ring it adds are new
    off = 0.0
    if meta.get("data_hash") != data["meta"]["data_hash"]:
        held = lambda m, k: getattr(m, k)[:, :ring] if k == "rel_scale" else getattr(m, k)  # noqa: E731
        off = max(float(((held(fresh, k) - held(init, k)).abs() / held(init, k).abs()).max()) for k in SCALES)
        if off > 1e-5 and not keep_scales:
            raise SystemExit(f"--init-from: {path} was trained on data {meta.get('data_hash')}, this run's data is "
                             f"{data['meta']['data_hash']} and its scales differ by up to {off:.1e} (relative; "
                             "--keep-scales keeps the checkpoint's)")
    model.load_state_dict(init.widened_to(model.config, ring_scales=fresh.rel_scale).state_dict())
    return {**provenance(path, meta), "scales_off": off}


def evaluate_all(model, task, data: dict, a: Args) -> dict:
    """Seen scene (variant 0, last 40 %) and the held-out scenes from rest, both modes."""
    if task.custom:  # e.g. the magnetic rod: closed-loop rollout, orientation errors, the Cosserat baseline
        return task.hook("evaluate")(model, task, data, a)
    return evaluate_scenes(model, task, data, a.duration, a.data_dir)


def ema_callback(decay: float):
    """Lightning's weight averaging as an exponential moving average of the parameters (the buffers, the
    model's fixed scales and index maps, are not averaged)."""
    from lightning.pytorch.callbacks import WeightAveraging
    from torch.optim.swa_utils import get_ema_multi_avg_fn
    return WeightAveraging(multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=False)


def main(argv=None):
    a = parse(argv)
    import lightning as L
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    from cmlearn.surrogate.training import RolloutSelection, SurrogateDataModule, SurrogateModule

    torch.set_num_threads(a.threads)
    train_seed = a.seed if a.train_seed < 0 else a.train_seed
    L.seed_everything(train_seed, workers=True)
    task = get_task(a.task)
    if a.closed_loop and not task.custom:
        raise SystemExit(f"--closed-loop: task {task.name!r} has no wrench model of its own (its node forces are "
                         "given, not computed from the pose)")
    init = load_init(task, a) if a.init_from else None
    t0 = time.perf_counter()
    data = cached_dataset(task, a.variants, a.seed, a.data_dir, a.duration or None, compile=a.compile_data)
    # fresh validation variants: the generator's first variant is the printed scene, left out of validation
    val_data = cached_dataset(task, a.val_fresh + 1, a.val_seed, a.data_dir, a.duration or None,
                              compile=a.compile_data) if a.val_fresh else None
    t_data = time.perf_counter() - t0
    # a task with a wrench model of its own (the magnetic rod) is evaluated in closed loop, so its selection
    # rollout (val_rollout_mm) runs in closed loop too, whether or not training does (--closed-loop)
    inputs = val_inputs = wrench_fn = None
    if task.custom:
        inputs_of, wrench_fn = task.hook("closed_loop_inputs"), task.hook("closed_loop_wrench")(task)
        inputs, val_inputs = inputs_of(task, data), inputs_of(task, val_data) if val_data else None
    dm = SurrogateDataModule(data, eta=a.eta, horizon=a.horizon, batch_size=a.batch_size, seed=train_seed,
                             inputs=inputs, val_dataset=val_data, val_stride=a.val_stride, val_inputs=val_inputs,
                             val_tail=a.val_tail, time_reversal=a.time_reversal, printed_repeat=a.printed_repeat)
    model = build_model(task, a)
    init_from = None
    if init is None:
        model.set_scales(dm.train_positions(), dm.train_wrench(), task.base_scene().rod.length)
    else:  # the starting checkpoint's weights and scales
        init_from = start_from(model, *init, data, dm, a.init_from, a.keep_scales)
    module = SurrogateModule(model, horizon=a.horizon, warmup_epochs=a.warmup_epochs, lr=a.lr,
                             weight_decay=a.weight_decay, max_epochs=a.epochs, noise=a.noise,
                             step_weighting=a.step_weighting, one_step_weight=a.one_step_weight,
                             wrench_fn=wrench_fn if a.closed_loop else None, noise_shape=a.noise_shape,
                             window_weighting=a.window_weighting, motion_floor=a.motion_floor)
    loggers = [CSVLogger(a.log_dir, name=task.name)]
    try:
        from lightning.pytorch.loggers import TensorBoardLogger
        import tensorboard  # noqa: F401
        loggers.append(TensorBoardLogger(a.log_dir, name=task.name))
    except ImportError:
        pass
    monitor = SELECT_METRICS[a.select_by]
    # the average must come after RolloutSelection: it swaps its weights in for the validation epoch and back
    # out at the epoch's end, where val_rollout_mm is scored; checkpoints hold the averaged weights
    averaging = [ema_callback(a.ema)] if a.ema else []
    ckpt_cb = ModelCheckpoint(dirpath=Path(loggers[0].log_dir) / "ckpt", monitor=monitor, save_last=True,
                              save_top_k=a.keep_top_k, filename="{epoch}-{val_loss:.1f}-{val_rollout_mm:.1f}")
    trainer = L.Trainer(
        max_epochs=a.epochs, max_time={"seconds": a.max_time * 60} if a.max_time else None, logger=loggers,
        enable_progress_bar=True,
        deterministic=True if a.accelerator == "cpu" else "warn",
        callbacks=[RolloutSelection(dm, a.select_steps, wrench_fn=wrench_fn), *averaging,
                   EarlyStopping(monitor, patience=a.patience), ckpt_cb],
        gradient_clip_val=1.0, limit_train_batches=a.train_batches or 1.0, accelerator=a.accelerator,
        devices=a.devices, strategy="ddp" if a.ddp else "auto", log_every_n_steps=10, num_sanity_val_steps=0)
    if init_from is not None:  # the starting weights' validation metrics (not logged): did fine-tuning beat them?
        start = L.Trainer(accelerator=a.accelerator, devices=1, logger=False, enable_checkpointing=False,
                          enable_progress_bar=False, callbacks=[RolloutSelection(dm, a.select_steps, wrench_fn=wrench_fn)]
                          ).validate(module, datamodule=dm, verbose=False)[0]
        init_from["val"] = {k: float(start[k]) for k in SELECT_METRICS.values() if k in start}
    trainer.fit(module, datamodule=dm, ckpt_path=a.resume or None)
    if trainer.global_rank != 0:  # --ddp: the other processes only trained; rank 0 evaluates and writes
        return None
    if init_from is not None and ckpt_cb.best_model_score is not None:
        best = float(ckpt_cb.best_model_score)
        init_from["selected_beats_start"] = bool(best < init_from["val"][monitor])
        if not init_from["selected_beats_start"]:
            print(f"warning: no epoch beat the starting weights on {monitor} ({best:.4g} against "
                  f"{init_from['val'][monitor]:.4g}): the fine-tuned model is the selected epoch all the same",
                  file=sys.stderr)
    if ckpt_cb.best_model_path:
        state = torch.load(ckpt_cb.best_model_path, map_location="cpu", weights_only=False)["state_dict"]
        module.load_state_dict(state)
    model = module.model.cpu().float().eval()
    t_train = time.perf_counter() - t0 - t_data
    metrics = evaluate_all(model, task, data, a)
    cmd = "python scripts/train_surrogate.py " + " ".join(shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    meta = {"task": task.name, "scene": task.scene, "heldout": list(task.heldout), "delta": task.delta,
            "tracked": list(task.tracked), "modeled": list(task.modeled), "wrench_nodes": list(task.wrench_nodes),
            "architecture": model.config.to_dict(), "n_parameters": sum(p.numel() for p in model.parameters()),
            "data_hash": data["meta"]["data_hash"], "data_seed": a.seed,
            "val_data_hash": val_data["meta"]["data_hash"] if val_data else None, "n_variants": a.variants,
            "metrics": metrics, "command": cmd.strip(), "args": asdict(a), "cmlearn_version": cmlearn.__version__,
            "torch": str(torch.__version__), "epochs_run": trainer.current_epoch, "world_size": trainer.world_size,
            "train_wall_s": t_train, "data_wall_s": t_data, "init_from": init_from}
    meta["check"] = recorded_check(model, meta, a.duration, a.data_dir)
    out = Path(a.out or f"{'runs/quick' if a.quick else 'checkpoints'}/{task.name}.pt")
    save_checkpoint(out, model, meta)
    print(f"wrote {out}")
    print("\n".join(metric_lines(metrics)))
    print(json.dumps({"checkpoint": str(out), "metrics": metrics, "train_wall_s": t_train}))
    return meta


if __name__ == "__main__":
    main()
