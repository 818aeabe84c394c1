"""Blend two surrogate checkpoints of one architecture: the weights (1 - alpha) A + alpha B.

    python scripts/blend_checkpoints.py checkpoints/semicircle.pt runs/semi_lbfgs.pt --alpha 0.6 --val-seed 1 \
        --out runs/semi_blend.pt

A refinement (``refine_surrogate.py``) or fine-tuning (``train_surrogate.py --init-from``) of A ends at B; the models
on the straight line between them trade what B gained on its training windows against what A did better elsewhere.
A and B must be of one task with the same scales (as a refinement or fine-tuning on A's data keeps them), and B of
A's architecture or a widening of it (a wider head, stencil or mix): then A is first widened as the fine-tuning
started (``NodeLSTMSurrogate.widened_to``; an added ring's offset scales B's), and the blend has B's architecture.
The blend is evaluated as ``train_surrogate.py`` evaluates (the printed scene's last 40 % and the held-out scenes, on
``--variants`` variants of seed ``--seed``: by default A's own data) and, with ``--val-seed``, scored with A and B on
``--val-variants`` fresh variants (``rank_checkpoints.py``'s score). It is written with A's metadata, its new
metrics, this command, ``init_from`` (A's provenance) and ``blend`` (alpha, A's and B's provenance, the fresh
scores). Position tasks only. Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import copy
import json
import shlex
import sys

import torch

from cmlearn.args import bounded, readable, writable
from cmlearn.data import cached_dataset, get_task
from cmlearn.surrogate import load_checkpoint, save_checkpoint
from cmlearn.surrogate.checkpoint import provenance
from cmlearn.surrogate.evaluate import evaluate_scenes, fresh_errors, fresh_score, metric_lines, recorded_check


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("start", type=readable(), help="checkpoint A (.pt): alpha 0")
    ap.add_argument("end", type=readable(), help="checkpoint B (.pt): alpha 1")
    ap.add_argument("--alpha", type=bounded(float), required=True, help="the blend's place between A (0) and B (1)")
    ap.add_argument("--variants", type=bounded(int, at_least=0), default=0,
                    help="variants of the evaluation data (0: A's own)")
    ap.add_argument("--seed", type=bounded(int, at_least=0), default=None,
                    help="the evaluation data's seed (default: A's own)")
    ap.add_argument("--data-dir", type=writable(folder=True), default="data", help="where the LGVI runs are cached")
    ap.add_argument("--duration", type=bounded(float, at_least=0), default=0.0,
                    help="simulated seconds (0: the scene's own)")
    ap.add_argument("--val-seed", type=bounded(int, at_least=0), default=None,
                    help="also score A, B and the blend on fresh variants")
    ap.add_argument("--val-variants", type=bounded(int, at_least=1), default=16, help="fresh variants --val-seed draws")
    ap.add_argument("--threads", type=bounded(int, at_least=1), default=1, help="torch CPU threads")
    ap.add_argument("--out", type=writable(checkpoint=True), required=True, help="the blended checkpoint (.pt)")
    a = ap.parse_args(argv)
    if not 0.0 <= a.alpha <= 1.0:
        ap.error(f"--alpha must be in [0, 1], got {a.alpha}")
    return a


def blend_state(start, end, alpha: float) -> dict:
    """The state of ``(1 - alpha) start + alpha end`` (two models of one architecture) over the parameters; the
    buffers (the scales) must be equal in both and are kept."""
    params = {k for k, _ in start.named_parameters()}
    sa, sb = start.state_dict(), end.state_dict()
    if sa.keys() != sb.keys():
        raise ValueError(f"the checkpoints hold other weights: {sorted(sa.keys() ^ sb.keys())[:4]}")
    for k in sa.keys() - params:
        if not torch.equal(sa[k], sb[k]):
            raise ValueError(f"buffer {k!r} differs between the checkpoints (blend a refinement of the start, which "
                             "keeps its scales)")
    return {k: torch.lerp(v, sb[k], alpha) if k in params else v for k, v in sa.items()}


def main(argv=None) -> dict:
    a = parse(argv)
    torch.set_num_threads(a.threads)
    start, meta = load_checkpoint(a.start)
    end, end_meta = load_checkpoint(a.end)
    if end_meta["task"] != meta["task"]:
        raise SystemExit(f"end: {a.end} is of task {end_meta['task']!r}, {a.start} of {meta['task']!r}")
    if end_meta["architecture"] != meta["architecture"]:
        try:  # an added ring's offset scales B's, as its fine-tuning set them from its data
            start = start.widened_to(end.config, ring_scales=end.rel_scale)
        except ValueError as e:
            raise SystemExit(f"end: {a.end} has another architecture than {a.start}, nor a widening of it: {e}"
                             ) from None
    task = get_task(meta["task"])
    if task.custom:
        raise SystemExit(f"{a.start}: task {task.name!r} has its own evaluation; blend_checkpoints.py takes "
                         "position tasks only")
    model = copy.deepcopy(start)
    try:
        model.load_state_dict(blend_state(start, end, a.alpha))
    except ValueError as e:
        raise SystemExit(f"end: {e}") from None
    model.eval()
    data = cached_dataset(task, a.variants or meta["n_variants"], meta["data_seed"] if a.seed is None else a.seed,
                          a.data_dir, a.duration or None)
    metrics = evaluate_scenes(model, task, data, a.duration or None, a.data_dir)
    fresh = None
    if a.val_seed is not None:
        val = cached_dataset(task, a.val_variants + 1, a.val_seed, a.data_dir, a.duration or None)
        fresh = {"seed": a.val_seed, "variants": a.val_variants,
                 **{f"score_{k}_mm": fresh_score(fresh_errors(m.eval(), task, val))
                    for k, m in (("start", start), ("end", end), ("blend", model))}}
    cmd = "python scripts/blend_checkpoints.py " + " ".join(
        shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    out = dict(meta)
    out.update(architecture=end_meta["architecture"], n_parameters=end_meta["n_parameters"], metrics=metrics,
               command=cmd, data_hash=data["meta"]["data_hash"], init_from=provenance(a.start, meta),
               blend={"alpha": a.alpha, "start": provenance(a.start, meta), "end": provenance(a.end, end_meta),
                      "fresh": fresh})
    out["check"] = recorded_check(model, out, a.duration, a.data_dir)
    save_checkpoint(a.out, model, out)
    print(f"wrote {a.out}: alpha {a.alpha} between {a.start} and {a.end}"
          + (f"; fresh seed {a.val_seed}: {fresh['score_start_mm']:.2f} | {fresh['score_end_mm']:.2f} | blend "
             f"{fresh['score_blend_mm']:.2f} mm" if fresh else ""))
    print("\n".join(metric_lines(metrics, ("free_running",))))
    res = {"checkpoint": a.out, "alpha": a.alpha, "fresh": fresh, "metrics": metrics}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
