"""Smoke runs of the environment benchmark and the controller evaluation with tiny budgets."""
import json
import os
import sys
from pathlib import Path

import pytest

from forked_scripts import run_python

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("pybullet")
pytest.importorskip("gymnasium")


def run_script(args, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CMLEARN_CACHE": str(tmp_path / "cache")}
    out = run_python(args, tmp_path, env)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_bench_env_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/bench/env.py"), "--quick", "--seconds", "0.5"], tmp_path)
    for key in ("env_steps_per_s", "render_ms_per_image", "atlas_build_s", "device", "threads", "processes"):
        assert key in res
    assert res["env_steps_per_s"] > 0 and res["steps"] > 0 and res["processes"] == 1
    assert list((tmp_path / "cache" / "atlas").glob("atlas_*.npz"))  # the atlas was cached


def test_train_agent_then_eval_controllers_quick(tmp_path):
    net = '{"stem_channels": 4, "widths": [4], "feature_dim": 16, "hidden_dim": 16, "num_cosines": 8}'
    res = run_script([str(ROOT / "scripts/train_agent.py"), "--quick", "--out", "run", "--no-progress", "--network", net,
                      "--ship", "agent.pt", "--waypoint-lookahead", "8"], tmp_path)
    assert res["frames"] == 1024 and res["updates"] > 0 and res["final_eval"] is not None
    meta = json.loads((tmp_path / "agent.json").read_text())
    assert "--quick" in meta["command"] and meta["frames"] == 1024 and meta["wall_s"] > 0
    assert meta["train_config"]["waypoint_lookahead"] == 8  # the evaluation gives the agent the same observation
    assert (tmp_path / "run" / "train_state.pt").exists() and (tmp_path / "run" / "log").is_dir()
    rep = run_script([str(ROOT / "scripts/report_agent.py"), "--agent", "agent.json", "--out", "rep"], tmp_path)
    assert rep["points"] == 2 and (tmp_path / "rep.png").exists() and (tmp_path / "rep.md").exists()
    res = run_script([str(ROOT / "scripts/eval_controllers.py"), "--quick", "--episodes", "1", "--train-maps", "1",
                      "--unseen-maps", "1", "--out", "ev", "--report", "ev/report.md", "--agent", "agent.pt"], tmp_path)
    table = res["results"]
    assert set(table) == {"iqn", "attractor", "errt", "memory"}
    for rows in table.values():
        assert set(rows) == {"undisturbed/train", "undisturbed/unseen", "disturbed/train", "disturbed/unseen"}
        for s in rows.values():
            assert s["episodes"] == 1 and 0 <= s["ci95"][0] <= s["success_rate"] <= s["ci95"][1] <= 1
            assert len(s["tracking_error_mean_m"]) == 2 and s["decision_ms"] > 0
    assert (tmp_path / "ev" / "report.md").exists() and len(list((tmp_path / "ev").glob("*.png"))) == 16


def test_wilson_interval():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from eval_controllers import wilson
    finally:
        sys.path.pop(0)
    lo, hi = wilson(50, 100)
    assert abs(lo - 0.4038) < 1e-3 and abs(hi - 0.5962) < 1e-3
    assert abs(wilson(0, 10)[0]) < 1e-12 and abs(wilson(10, 10)[1] - 1.0) < 1e-12


def test_train_agent_bad_config_is_a_usage_error(tmp_path):
    """Values the flags' types accept but the training config refuses end in argparse's usage error, not a
    traceback."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CMLEARN_CACHE": str(tmp_path / "cache")}
    for args, name in ((["--gamma", "1.5"], "gamma"), (["--network", '{"bogus": 1}'], "bogus"),
                       (["--batch-size", "64", "--buffer-size", "32"], "batch_size"),
                       (["--quick", "--ship", "agent.json"], "--ship")):
        out = run_python([str(ROOT / "scripts/train_agent.py"), "--out", "run", *args], tmp_path, env, timeout=300)
        assert out.returncode == 2 and "usage:" in out.stderr and name in out.stderr, out.stderr[-2000:]
        assert "Traceback" not in out.stderr


def test_eval_controllers_checks_controllers_and_agent_before_running(tmp_path):
    """An unknown controller name or an unusable ``--agent`` after others in ``--controllers`` stopped the run only
    when its turn came, after every episode of the controllers before it; ``--plots -1`` plotted all episodes but
    one."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CMLEARN_CACHE": str(tmp_path / "cache")}
    for controllers, extra, message in (("attractor,bogus", [], "unknown controller 'bogus'"),
                                        ("attractor,iqn", [], "--agent: missing.pt: no such agent checkpoint"),
                                        ("attractor", ["--plots", "-1"], "argument --plots: must be >= 0, got '-1'")):
        out = run_python([str(ROOT / "scripts/eval_controllers.py"), "--quick", "--episodes", "1", "--train-maps", "1",
                          "--unseen-maps", "1", "--controllers", controllers, "--agent", "missing.pt", "--out", "ev",
                          *extra], tmp_path, env)
        assert out.returncode != 0 and message in out.stderr and "Traceback" not in out.stderr, out.stderr[-2000:]
        assert "attractor" not in out.stdout and not (tmp_path / "ev").exists()  # nothing ran
