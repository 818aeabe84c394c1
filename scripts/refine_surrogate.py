"""Refine a trained surrogate checkpoint by full-batch L-BFGS on a fixed set of its training windows.

    python scripts/refine_surrogate.py checkpoints/semicircle.pt --variants 96 --windows 1024 --max-time 72 \
        --out runs/semi_lbfgs.pt

Training (``train_surrogate.py``) draws a new mini-batch of windows at every Adam step. This instead takes the
model's own free-running rollout loss (``SurrogateModule.rollout_loss``: ``--horizon`` steps, no training noise)
over ``--windows`` fixed windows of the checkpoint's training ranges (every window of the printed scene, the rest
drawn with ``--window-seed``; ``--printed-weight`` weighs the printed scene's windows in the mean, ``--node-weight``
the scene's node of interest among the modelled nodes) and minimises it with ``torch.optim.LBFGS`` (strong Wolfe
line search), the gradient summed over chunks of ``--chunk`` windows on ``--device``. The weights with the lowest
loss seen are kept (``--max-time`` may stop the run inside a line search); with ``--val-seed``, those with the
lowest score on ``--val-variants`` fresh variants of the scene instead (``rank_checkpoints.py``'s score: the mean
over the variants of the node of interest's largest free-running error, from rest), scored at the first evaluation,
every ``--val-every``-th and the ``--max-evals``-th (``loss_best``: the kept weights' loss; a run stopped sooner, by
``--max-time`` or by L-BFGS, leaves its evaluations after the last scored one unscored). The checkpoint's scales
are kept. The data must be the checkpoint's own: the same hash, or, with ``--keep-scales``, any data of its task. The
refined model is evaluated as ``train_surrogate.py`` evaluates (the printed scene's last 40 % and the held-out
scenes) and written with the checkpoint's metadata, its new metrics, this command and ``init_from`` (the starting
file's path, SHA-256, command and data hash). Position tasks only. Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import copy
import json
import shlex
import sys
import time

import torch
from torch.utils.data import default_collate

from cmlearn.args import bounded, readable, writable
from cmlearn.data import cached_dataset, get_task
from cmlearn.data.windows import RolloutWindows
from cmlearn.surrogate import load_checkpoint, save_checkpoint
from cmlearn.surrogate.checkpoint import provenance
from cmlearn.surrogate.evaluate import (evaluate_scenes, fresh_errors, fresh_score, interest_slots, metric_lines,
                                       recorded_check)


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("checkpoint", type=readable(), help="the surrogate checkpoint (.pt) to refine")
    ap.add_argument("--variants", type=bounded(int, at_least=1), default=96,
                    help="variants of the checkpoint's training data")
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=0, help="the data's seed")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data", help="where the LGVI runs are cached")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (0: the scene's own)")
    ap.add_argument("--keep-scales", action="store_true", help="accept data other than the checkpoint's own")
    ap.add_argument("--windows", type=bounded(int, at_least=1), default=1024,
                    help="fixed training windows the loss sums over")
    ap.add_argument("--window-seed", type=bounded(int, at_least=0), default=1, help="seed of the windows' draw")
    ap.add_argument("--printed-weight", type=bounded(float, above=0), default=1.0,
                    help="weight of each printed-scene window in the loss's mean (the others weigh 1)")
    ap.add_argument("--node-weight", type=bounded(float, above=0), default=1.0,
                    help="weight of the printed scene's node of interest in the loss's mean over the modelled nodes "
                         "(the others weigh 1)")
    ap.add_argument("--horizon", type=bounded(int, at_least=1), default=96, help="rollout steps of each window")
    ap.add_argument("--max-evals", type=bounded(int, at_least=1), default=200, help="loss evaluations at most")
    ap.add_argument("--history", type=bounded(int, at_least=1), default=20, help="L-BFGS history size")
    ap.add_argument("--chunk", type=bounded(int, at_least=1), default=128, help="windows per forward and backward pass")
    ap.add_argument("--max-time", type=bounded(float, at_least=0), default=0.0,
                    help="minutes of refinement at most (0: no limit)")
    ap.add_argument("--val-seed", type=bounded(int, at_least=0), default=None,
                    help="select the weights by the fresh variants of this seed (default: by the loss)")
    ap.add_argument("--val-variants", type=bounded(int, at_least=1), default=16, help="fresh variants --val-seed draws")
    ap.add_argument("--val-every", type=bounded(int, at_least=1), default=5,
                    help="score the fresh variants at every n-th evaluation")
    ap.add_argument("--device", default="cpu", help="torch device of the refinement (cpu, cuda, cuda:1, ...)")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1, help="torch CPU threads")
    ap.add_argument("--out", type=writable(checkpoint=True), required=True, help="the refined checkpoint (.pt)")
    a = ap.parse_args(argv)
    if a.val_seed is not None and a.val_seed == a.seed:
        ap.error(f"--val-seed {a.val_seed} is the data's --seed: its variants are trained on")
    try:
        dev = torch.device(a.device)
    except RuntimeError as e:
        ap.error(f"--device {a.device!r}: {e}")
    if dev.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"--device {a.device}: no CUDA device is available")
    return a


def fixed_windows(ds: RolloutWindows, printed: int, n: int, seed: int) -> list[int]:
    """Every one of the first ``printed`` windows (the printed scene's) and ``n - printed`` others drawn without
    replacement (all the windows where ``n`` covers them)."""
    g = torch.Generator().manual_seed(seed)
    others = (torch.randperm(len(ds) - printed, generator=g)[:max(0, n - printed)] + printed).tolist()
    return list(range(min(printed, n))) + others


class _Budget(Exception):
    pass


def main(argv=None) -> dict:
    a = parse(argv)
    from cmlearn.surrogate.training import SurrogateDataModule, SurrogateModule
    torch.set_num_threads(a.threads)
    model, meta = load_checkpoint(a.checkpoint)
    task = get_task(meta["task"])
    if task.custom:
        raise SystemExit(f"{a.checkpoint}: task {task.name!r} has its own evaluation; refine_surrogate.py takes "
                         "position tasks only")
    data = cached_dataset(task, a.variants, a.seed, a.data_dir, a.duration or None)
    if data["meta"]["data_hash"] != meta.get("data_hash") and not a.keep_scales:
        raise SystemExit(f"--variants/--seed: {a.checkpoint} was trained on data {meta.get('data_hash')}, these are "
                         f"{data['meta']['data_hash']} (--keep-scales refines on them all the same)")
    eta = model.config.eta
    dm = SurrogateDataModule(data, eta=eta, horizon=a.horizon)
    ds = RolloutWindows(dm.positions, dm.wrench, dm.ranges["train"], eta, a.horizon)
    printed = sum(v == 0 for v, _, _ in ds.index)  # the printed scene's windows (variant 0, the first range)
    idx = fixed_windows(ds, printed, a.windows, a.window_seed)
    n_printed = min(printed, len(idx))
    dev = torch.device(a.device)
    batch = [t.to(dev) for t in default_collate([ds[i] for i in idx])]
    # the printed windows (the first n_printed) in chunks of their own, so that each chunk has one weight
    bounds = [(i, min(i + a.chunk, n_printed)) for i in range(0, n_printed, a.chunk)]
    bounds += [(i, min(i + a.chunk, len(idx))) for i in range(n_printed, len(idx), a.chunk)]
    chunks = [(tuple(t[i:j] for t in batch), (j - i) * (a.printed_weight if i < n_printed else 1.0))
              for i, j in bounds]
    total_weight = n_printed * a.printed_weight + len(idx) - n_printed
    node_weights = torch.ones(len(model.config.modeled), device=dev)
    node_weights[list(model.config.modeled).index(interest_slots(task, task.base_scene())[0])] = a.node_weight
    val = None if a.val_seed is None else cached_dataset(task, a.val_variants + 1, a.val_seed, a.data_dir,
                                                         a.duration or None)
    model.to(dev).train()
    module = SurrogateModule(model, horizon=a.horizon)

    def val_score() -> float:
        model.eval()
        try:
            return fresh_score(fresh_errors(model, task, val))
        finally:
            model.train()

    def loss_and_grad() -> float:
        total = 0.0
        for c, weight in chunks:
            loss = module.rollout_loss(c, a.horizon, node_weights=node_weights)[0] * (weight / total_weight)
            loss.backward()
            total += float(loss.detach())
        return total

    # the closure stops the run at --max-evals (or --max-time), so that a run is reproduced evaluation for evaluation
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=10 * a.max_evals, max_eval=10 * a.max_evals,
                            history_size=a.history, line_search_fn="strong_wolfe", tolerance_grad=0.0,
                            tolerance_change=0.0)
    t0 = time.perf_counter()
    trace, scores = [], []  # scores: (evaluation, loss, fresh score) where scored
    best = {"loss": float("inf"), "score": float("inf"), "eval": 0, "state": None}

    def closure():
        opt.zero_grad()
        loss = loss_and_grad()
        trace.append(loss)
        n, note = len(trace), ""
        if val is None and loss < best["loss"]:
            best.update(loss=loss, eval=n, state=copy.deepcopy(model.state_dict()))
        if val is not None and (n == 1 or n % a.val_every == 0 or n >= a.max_evals):
            score = val_score()
            scores.append((n, loss, score))
            if score < best["score"]:
                best.update(loss=loss, score=score, eval=n, state=copy.deepcopy(model.state_dict()))
            note = f", fresh {score:.3f} mm (best {best['score']:.3f} at {best['eval']})"
        print(f"eval {n}: loss {loss:.4g} (kept {best['loss']:.4g}){note}, {time.perf_counter() - t0:.0f} s",
              flush=True)
        if not torch.isfinite(torch.tensor(loss)):
            raise _Budget(f"the rollout ran away at evaluation {len(trace)}")
        if len(trace) >= a.max_evals:
            raise _Budget(f"--max-evals {a.max_evals} reached")
        if a.max_time and time.perf_counter() - t0 > a.max_time * 60:
            raise _Budget(f"--max-time {a.max_time} min reached at evaluation {len(trace)}")
        return torch.tensor(loss)

    stop = "L-BFGS stopped on its own"
    try:
        opt.step(closure)
    except _Budget as e:
        stop = str(e)
    if best["state"] is None:
        raise SystemExit(f"{a.checkpoint}: the starting rollout loss is not finite on these windows")
    model.load_state_dict(best["state"])
    wall = time.perf_counter() - t0
    model.cpu().eval()  # evaluated and written on the CPU, as load_checkpoint gave it
    metrics = evaluate_scenes(model, task, data, a.duration or None, a.data_dir)
    cmd = "python scripts/refine_surrogate.py " + " ".join(
        shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    out = dict(meta)
    out.update(metrics=metrics, command=cmd, data_hash=data["meta"]["data_hash"], train_wall_s=wall,
               init_from=provenance(a.checkpoint, meta),
               refine={"windows": len(idx), "printed_windows": n_printed,
                       "printed_weight": a.printed_weight, "node_weight": a.node_weight, "horizon": a.horizon,
                       "evaluations": len(trace), "loss_start": trace[0], "loss_best": best["loss"],
                       "kept_evaluation": best["eval"], "stop": stop, "device": str(dev),
                       "select": "loss" if val is None else {
                           "seed": a.val_seed, "variants": a.val_variants, "every": a.val_every,
                           "score_start_mm": scores[0][2], "score_best_mm": best["score"], "scored": scores}})
    out["check"] = recorded_check(model, out, a.duration, a.data_dir)
    save_checkpoint(a.out, model, out)
    print(f"wrote {a.out}: loss {trace[0]:.4g} -> {best['loss']:.4g} (evaluation {best['eval']} of {len(trace)}), "
          f"{wall:.0f} s ({stop})")
    print("\n".join(metric_lines(metrics, ("free_running",))))
    res = {"checkpoint": a.out, "loss_start": trace[0], "loss_best": best["loss"], "evaluations": len(trace),
           "kept_evaluation": best["eval"], "select": out["refine"]["select"], "wall_s": wall, "stop": stop,
           "metrics": metrics}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
