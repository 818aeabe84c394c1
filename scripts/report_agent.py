"""Training curve of the shipped Rainbow-IQN agent, from the evaluations stored in its metadata.

Reads ``<agent>.json`` (written by ``scripts/train_agent.py``: periodic greedy evaluations with
frames, updates and wall time) and writes a PNG (success rate and return against frames and wall
time) and a markdown table.

    python scripts/report_agent.py [--agent checkpoints/iqn_agent.json] [--out docs/agent_training]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from cmlearn.args import readable, writable


def main(argv=None):
    root = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agent", type=readable(), default=str(root / "checkpoints" / "iqn_agent.json"),
                    help="the agent's metadata (<name>.json), or its checkpoint with the metadata beside it")
    ap.add_argument("--out", type=writable(), default=str(root / "docs" / "agent_training"),
                    help="prefix of the report: <out>.png and <out>.md")
    a = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cmlearn.io import atomic_write, write_text_atomic
    path = Path(a.agent) if a.agent.endswith(".json") else Path(a.agent).with_suffix(".json")
    try:  # the checkpoint itself gave a UnicodeDecodeError traceback
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SystemExit(f"--agent: cannot read the agent's metadata {str(path)!r} ({type(e).__name__}: {e})")
    run = meta.get("run") or {}  # shipped with --ship-best: the whole run's evaluations are under "run"
    ev = run.get("evaluations") or meta.get("evaluations") or []
    if not ev:
        raise SystemExit(f"{a.agent}: no evaluations recorded")
    cfg = meta.get("train_config", {})
    frames = [e["frames"] for e in ev]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.8))
    ax.plot(frames, [100 * e["success_rate"] for e in ev], "o-")
    ax.set(xlabel="environment frames", ylabel="greedy success (%)",
           title=f"{cfg.get('eval_episodes', '?')} episodes per point, training maps")
    bx.plot([e["wall_s"] / 60 for e in ev], [e["return"] for e in ev], "o-", color="tab:orange")
    bx.set(xlabel="wall time (min)", ylabel="mean return")
    fig.tight_layout()
    out = Path(a.out)
    out = out.with_suffix("") if out.suffix in (".png", ".md") else out  # a prefix: x.v2 wrote x.png and x.md
    png, md_path = out.with_name(out.name + ".png"), out.with_name(out.name + ".md")
    atomic_write(png, lambda f: fig.savefig(f, format="png", dpi=110))
    lines = [f"Training of `{path.with_suffix('.pt').name}`: `{meta.get('command', '')}`; "
             f"{meta.get('frames')} frames, {meta.get('updates')} updates, {meta.get('wall_s')} s wall "
             f"({meta.get('threads')} thread(s), {meta.get('workers')} collector process(es) x "
             f"{meta.get('num_envs')} envs)." + (
                 f" The whole run: {run.get('frames')} frames, {run.get('updates')} updates, {run.get('wall_s')} s; "
                 f"shipped: the network of its best evaluation (`--ship-best`), after {meta.get('frames')} frames "
                 f"and {meta.get('updates')} updates." if run else ""), "",
             "| frames | updates | wall (min) | success | mean decisions | mean return |", "|---|---|---|---|---|---|"]
    tag = {"pretrain": " (after pre-training)"}
    lines += [f"| {e['frames']}{tag.get(e.get('phase'), '')} | {e['updates']} | {e['wall_s'] / 60:.1f} | "
              f"{100 * e['success_rate']:.0f} % | {e['mean_steps']:.1f} | {e['return']:.3f} |" for e in ev]
    md = "\n".join(lines) + "\n"
    write_text_atomic(md_path, md)
    print(md)
    print(json.dumps({"points": len(ev), "final_success": ev[-1]["success_rate"], "png": str(png)}))


if __name__ == "__main__":
    main()
