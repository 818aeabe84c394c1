"""Train the Rainbow-IQN-ResNet agent (Sub-controller 2) on the magnetic-particle environment.

Every field of :class:`cmlearn.rl.training.AgentTrainConfig` is a flag (``--total-frames``,
``--num-envs``, ``--workers`` for multi-process collection with ``MultiSyncCollector``, ``--lr``,
``--n-steps``, ...); ``--network '{"widths": [16, 32]}'`` changes the architecture. Writes to
``--out``: ``train_state.pt`` (everything needed to resume: weights, target network, optimiser,
counters, random state; the replay buffer too with ``--save-buffer``), ``agent.pt`` + ``agent.json``
(the network and metadata, the format shipped in ``checkpoints/``), CSV and TensorBoard logs and
``summary.json``. ``--resume`` continues from ``train_state.pt`` and says whether the replay buffer
was restored. ``--ship PATH`` copies the final agent to PATH (e.g. ``checkpoints/iqn_agent.pt``), or with
``--ship-best`` the one of the best periodic evaluation (``best_agent.pt``).
``--demo-episodes N`` adds demonstrations of the privileged teacher (DQfD: a large-margin loss on
them, ``--demo-batch`` of them in every update, ``--pretrain-updates`` on them alone before
collection starts). ``--quick`` is a smoke-test budget (a few thousand frames).

    python scripts/train_agent.py --total-frames 400000 --out runs/iqn --ship checkpoints/iqn_agent.pt
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import fields

from cmlearn.args import bounded, writable
from cmlearn.rl.agent import load_agent, save_agent
from cmlearn.rl.training import AgentTrainConfig, config_from_args, train_agent


#: --quick: the smoke-test budget (each at most the option's default)
QUICK = dict(total_frames=1_024, init_random_frames=512, eval_every=512, eval_episodes=2, checkpoint_every=512,
             buffer_size=4_096, train_maps=1, max_steps=30, demo_episodes=4, pretrain_updates=20)


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for f in fields(AgentTrainConfig):
        flag = "--" + f.name.replace("_", "-")
        if f.name == "network":
            ap.add_argument(flag, type=json.loads, default={}, help="IQNConfig fields as JSON")
        elif f.type in ("bool", bool):
            ap.add_argument(flag, action="store_true", default=f.default)
        else:
            kind = type(f.default)
            kind = bounded(kind) if kind in (int, float) else writable(folder=True) if f.name == "out" else kind
            ap.add_argument(flag, type=kind, default=f.default)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--quick", action="store_true", help="smoke-test budget")
    ap.add_argument("--ship", type=writable(checkpoint=True), default="", help="copy the final agent checkpoint here")
    ap.add_argument("--ship-best", action="store_true",
                    help="with --ship: copy the agent of the best periodic evaluation instead of the final one")
    ns = ap.parse_args(argv)
    if ns.quick:  # the smoke-test budget for each option not given on the command line (it overrode given ones)
        ap.set_defaults(**{k: min(v, ap.get_default(k)) for k, v in QUICK.items()})
        ns = ap.parse_args(argv)
    if ns.no_progress:
        ns.progress = False
    if ns.ship_best and not ns.ship:
        ap.error("--ship-best chooses the agent --ship copies, and no --ship is given")
    try:  # the config's checks (ranges, --network fields) as a usage error, not a traceback
        config_from_args(ns)
    except (TypeError, ValueError) as e:
        ap.error(str(e))
    return ns


def main(argv=None):
    ns = parse(argv)
    cfg = config_from_args(ns)
    command = "python scripts/train_agent.py " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None
                                                                                    else argv))
    res = train_agent(cfg, command=command)
    if ns.ship:
        best = ns.ship_best and res.best_agent_path
        net, meta = load_agent(res.best_agent_path if best else res.agent_path)
        if best:  # the shipped agent's own frames and wall time, and the whole run's
            meta["run"] = {"frames": res.frames, "updates": res.updates, "wall_s": round(res.wall_s, 1),
                           "evaluations": res.evaluations}
        save_agent(ns.ship, net, meta)
        print(f"shipped {ns.ship}")
    print(json.dumps({"frames": res.frames, "updates": res.updates, "wall_s": round(res.wall_s, 1),
                      "resumed_from": res.resumed_from, "buffer_restored": res.buffer_restored,
                      "final_eval": res.evaluations[-1] if res.evaluations else None, "agent": res.agent_path}))
    return res


if __name__ == "__main__":
    main()
