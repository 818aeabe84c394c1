"""Smoke runs of the scripts with tiny budgets: they run and end with one JSON line."""
import csv
import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from forked_scripts import run_python

ROOT = Path(__file__).resolve().parents[1]


def run(args, tmp_path) -> subprocess.CompletedProcess:
    """``python ARGS`` in ``tmp_path`` with the repository importable (forked from a process that has imported
    the libraries: tests/forked_scripts.py)."""
    return run_python(args, tmp_path, {**os.environ, "PYTHONPATH": str(ROOT)})


def run_script(args, tmp_path):
    out = run(args, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def script_fails(args, tmp_path, msg: str) -> None:
    """The script exits with an error whose message contains ``msg``."""
    bad = run(args, tmp_path)
    assert bad.returncode != 0 and msg in bad.stderr, bad.stderr[-500:]


def load_script(name):
    import importlib.util
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / f"scripts/{name}.py")
    mod = sys.modules[f"script_{name}"] = importlib.util.module_from_spec(spec)  # dataclasses look it up
    spec.loader.exec_module(mod)
    return mod


def parse_fails(script: str, argv: list[str], msg: str, capsys) -> None:
    """The script's argument parser (``parse(argv)``, run in this process: no interpreter start per case)
    exits with a usage error whose message contains ``msg``."""
    with pytest.raises(SystemExit) as e:
        load_script(script).parse(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and msg in err, err[-500:]


def test_a_forked_script_runs_as_a_fresh_interpreter_would(tmp_path):
    """tests/forked_scripts.py, which runs the scripts of these tests: arguments, working directory, environment,
    ``sys.path[0]``, the two streams, exit statuses (normal, ``sys.exit``, an exception), atexit handlers, a timeout
    that kills the script, and a module run with ``-m``."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "helper.py").write_text("VALUE = 41\n")
    script = tmp_path / "sub" / "s.py"
    script.write_text(
        "import atexit, json, os, sys, time\n"
        "import helper\n"  # the script's own folder is importable, as sys.path[0]
        "atexit.register(lambda: print('atexit ran'))\n"
        "if sys.argv[1] == 'sleep':\n    time.sleep(60)\n"
        "if sys.argv[1] == 'raise':\n    print('before'); raise ValueError('boom')\n"
        "if sys.argv[1] == 'exit':\n    sys.exit('usage: bad')\n"
        "print('to stderr', file=sys.stderr)\n"
        "print(json.dumps({'argv': sys.argv, 'cwd': os.getcwd(), 'env': os.environ.get('FORK_T'), 'helper': "
        "helper.VALUE + 1, 'path0': sys.path[0], 'name': __name__}))\n")
    env = {**os.environ, "FORK_T": "yes"}
    out = run_python([str(script), "ok", "a b"], tmp_path, env)
    assert out.returncode == 0 and out.stderr == "to stderr\n" and out.stdout.endswith("atexit ran\n")
    assert json.loads(out.stdout.splitlines()[0]) == {"argv": [str(script), "ok", "a b"], "cwd": str(tmp_path),
                                                      "env": "yes", "helper": 42, "path0": str(tmp_path / "sub"),
                                                      "name": "__main__"}
    unset = run_python([str(script), "ok"], tmp_path, {k: v for k, v in env.items() if k != "FORK_T"})
    assert json.loads(unset.stdout.splitlines()[0])["env"] is None  # the request's environment, not the last one's
    bad = run_python([str(script), "raise"], tmp_path, env)
    assert bad.returncode == 1 and "ValueError: boom" in bad.stderr and bad.stdout == "before\natexit ran\n"
    ex = run_python([str(script), "exit"], tmp_path, env)
    assert ex.returncode == 1 and ex.stderr == "usage: bad\n"
    with pytest.raises(subprocess.TimeoutExpired):
        run_python([str(script), "sleep"], tmp_path, env, timeout=2)
    assert run_python([str(script), "ok"], tmp_path, env).returncode == 0  # the server goes on after a timeout
    mod = run_python(["-m", "cmlearn", "--version"], ROOT, env)
    assert mod.returncode == 0 and mod.stdout.strip(), mod.stderr


SCRIPTS = sorted(str(p.relative_to(ROOT / "scripts").with_suffix("")) for p in (ROOT / "scripts").rglob("*.py"))


#: the options through which a script writes its results (files or folders)
OUTPUTS = ("out", "data_dir", "log_dir", "ship", "report")
#: the options naming a file a run starts from or measures
INPUTS = ("resume", "init_from", "init", "checkpoint", "checkpoints", "agent", "run", "start", "end")
#: the options naming weights written with their metadata beside them as <name>.json
CHECKPOINT_OUTPUTS = {("train_surrogate", "out"), ("train_quasistatic", "out"), ("refine_surrogate", "out"),
                      ("blend_checkpoints", "out"), ("train_agent", "ship")}


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_numeric_option_of_every_script_is_checked_as_it_is_parsed(name, monkeypatch, capsys, tmp_path):
    """Each script's parser (caught as ``main([])`` parses, before any work): no option is a plain int or float, and
    each number option refuses 'nan' with argparse's usage error naming the flag; each output path (``--out``,
    ``--data-dir``, ``--log-dir``, ``--ship``, ``--report``) is refused there when it lies under a file, and each file
    a run starts from or measures (``--resume``, ``--init-from``, ``--init``, ``--checkpoint``, ``--agent``) when it
    does not exist."""
    import argparse

    class Parsed(Exception):
        pass

    parsers = []

    def catch(self, *a, **k):
        parsers.append(self)
        raise Parsed

    monkeypatch.syspath_prepend(str(ROOT / "scripts" / "bench"))  # work_precision_magnetic imports its sibling
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", catch)
    with pytest.raises(Parsed):
        load_script(name).main([])
    monkeypatch.undo()
    ap, checked = parsers[0], 0
    for act in ap._actions:
        flag = (act.option_strings or [act.dest])[0]
        assert act.type not in (int, float), f"{name} {flag}: a plain {act.type.__name__}, unchecked"
        if getattr(act.type, "__qualname__", "").startswith("bounded."):
            with pytest.raises(SystemExit) as e:
                ap.parse_args([flag, "nan"])
            err = capsys.readouterr().err
            assert e.value.code == 2 and f"argument {flag}: must be" in err, err[-300:]
            checked += 1
        if act.dest in OUTPUTS:
            assert getattr(act.type, "__qualname__", "").startswith("writable."), f"{name} {flag}: unchecked path"
            (tmp_path / "a_file").write_text("")
            with pytest.raises(SystemExit) as e:
                ap.parse_args([flag, str(tmp_path / "a_file" / "x")])
            err = capsys.readouterr().err
            assert e.value.code == 2 and f"argument {flag}: cannot write" in err and "is a file" in err, err[-300:]
            assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]
        if (name, act.dest) in CHECKPOINT_OUTPUTS:  # the metadata overwrote the weights at the end of the run
            with pytest.raises(SystemExit) as e:
                ap.parse_args([flag, str(tmp_path / "model.json")])
            err = capsys.readouterr().err
            assert e.value.code == 2 and f"argument {flag}: must not end in .json" in err, err[-300:]
        # train_agent's --resume is a switch (its run folder's state); eval_controllers loads --agent as it parses
        # when an iqn controller is asked for (test_rl_scripts), and runs the others without one; report_surrogates'
        # --checkpoints is the folder it lists; the reports whose --checkpoints option also finds a path under the
        # repository (its defaults) check them as they load (naming the flag)
        if act.dest in INPUTS and act.nargs != 0 and (name, act.dest) not in (
                ("eval_controllers", "agent"), ("report_surrogates", "checkpoints"),
                ("report_one_step_bias", "checkpoints"), ("report_free_running_spread", "checkpoints"),
                ("report_load_amplitude", "checkpoints"), ("report_step_baselines", "checkpoints")):
            assert getattr(act.type, "__qualname__", "").startswith("readable."), f"{name} {flag}: unchecked file"
            missing = str(tmp_path / "missing.ckpt")
            argv = [flag, missing] if act.option_strings else \
                [missing if p is act else str(tmp_path / "a_file") for p in ap._actions if not p.option_strings]
            (tmp_path / "a_file").write_text("")
            with pytest.raises(SystemExit) as e:
                ap.parse_args(argv)
            err = capsys.readouterr().err
            assert e.value.code == 2 and f"argument {flag}: no such file" in err, err[-300:]
    assert checked or name in ("report_agent", "report_lgvi_convergence", "report_rollout_sensitivity",
                               "report_surrogates"), f"{name}: no number option found"


def test_the_benches_last_line_is_strict_json_rounded_to_the_digits_asked():
    from cmlearn.eval.timing import json_line
    line = json_line({"hz": 1234.56789, "rows": [{"ratio": 2 / 3, "bad": math.nan}], "n": 7, "inf": -math.inf},
                     digits=4)
    res = json.loads(line, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert res == {"hz": 1235.0, "rows": [{"ratio": 0.6667, "bad": "nan"}], "n": 7, "inf": "-inf"}


def test_bench_lgvi_quick(tmp_path):
    pytest.importorskip("elastica")
    res = run_script([str(ROOT / "scripts/bench/lgvi.py"), "--quick", "--no-compile", "--window", "0.05",
                      "--batch", "8"], tmp_path)
    for key in ("single_rod_us_per_step", "pyelastica_us_per_step", "single_time_ratio_vs_pyelastica",
                "batched_node_steps_per_s", "pyelastica_node_steps_per_s", "batched_speedup_vs_pyelastica",
                "rtf_pdms_tip_magnet", "dtype", "threads", "device", "n_nodes", "batch"):
        assert key in res
    assert res["single_rod_us_per_step"] > 0 and res["tip_diff_vs_pyelastica_at_0.1s_pct_L"] < 10
    assert res["pyelastica_batch_rods"] == res["batch"] == 8  # the same rods on both sides
    assert res["rounds"] == 1 and len(res["pyelastica_node_steps_per_s_runs"]) == 1  # --quick: one round


def test_bench_dataset_quick(tmp_path):
    """The dataset-generation bench times the eager and the compiled LGVI on the same batch of Simulation III's pulses
    (traced as one batched force) and finds their data equal to round-off (the compiled rollout's fixed Newton count);
    the magnetic rod, whose data stay eager, is refused, and so is compiling its data."""
    res = run_script([str(ROOT / "scripts/bench/dataset.py"), "--quick"], tmp_path)
    assert res["task"] == "semicircle" and res["variants"] == 3 and res["duration_s"] == pytest.approx(0.02)
    assert res["eager_s"] > 0 and res["compiled_s"] > 0 and res["compile_s"] > 0 and res["threads"] == 1
    assert res["speedup_compiled"] == pytest.approx(res["eager_s"] / res["compiled_s"])
    assert res["max_diff_m"] < 1e-12 and isinstance(res["float32_identical"], bool)
    script_fails([str(ROOT / "scripts/bench/dataset.py"), "--task", "magnetic_rod"], tmp_path, "invalid choice")
    from cmlearn.data import simulate_task
    with pytest.raises(ValueError, match="compile"):
        simulate_task("magnetic_rod", 2, 0, 0.1, compile=True)


def test_convergence_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_lgvi_convergence.py"), "--quick", "--out", "report.md"], tmp_path)
    assert (tmp_path / "report.md").exists()
    assert all(abs(v) < 2.0 for k, v in res["freq_err_pct"].items() if "N=20" in k)
    assert all(1.8 < o < 2.3 for o in res["time_orders"])


def test_bench_magnetics_quick(tmp_path):
    pytest.importorskip("magpylib")
    res = run_script([str(ROOT / "scripts/bench/magnetics.py"), "--quick", "--points", "300"], tmp_path)
    for key in ("field_points_per_s", "magpylib_cuboid_points_per_s", "magpylib_dipoles_points_per_s",
                "speedup_vs_magpylib_dipoles", "force_points_per_s", "cube_dipole_rel_err_75mm", "n_dipoles",
                "n_points", "dtype", "threads"):
        assert key in res
    assert res["cube_dipole_rel_err_75mm"] < 1e-4 and res["max_rel_diff_vs_magpylib_dipoles"] < 1e-9


def test_field_table_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_field_table.py"), "--quick", "--out", "ft.md"], tmp_path)
    assert (tmp_path / "ft.md").exists()
    coarse, fine = res["rows"]  # order 4 and 6 on a 2 mm grid: order 6 gains two orders at 30 mm
    assert fine["field_err"]["0.03"] < 1e-7 < coarse["field_err"]["0.03"] < 1e-4


def test_magnet_convergence_report_quick(tmp_path):
    pytest.importorskip("magpylib")
    res = run_script([str(ROOT / "scripts/report_magnet_convergence.py"), "--quick", "--out", "conv.md"], tmp_path)
    assert (tmp_path / "conv.md").exists()
    errs = res["field_err_75mm"]
    assert errs["1728"] < 1e-4 < errs["8"]


@pytest.mark.parametrize("task", ["square_tracking", "magnetic_rod", "semicircle"])  # plain, own module, mirrored
def test_bench_surrogate_quick(tmp_path, task):
    res = run_script([str(ROOT / "scripts/bench/surrogate.py"), "--quick", "--task", task,
                      "--checkpoint", str(ROOT / f"checkpoints/{task}.pt")], tmp_path)
    for key in ("surrogate_step_hz", "lgvi_step_hz", "speedup_per_simulated_second", "quick_rollout_max_err_mm"):
        assert key in res
    assert res["surrogate_step_hz"] > 0 and res["speedup_per_simulated_second"] > 1
    lo, mid, hi = res["speedup_per_simulated_second_rounds"]  # interleaved rounds: the ratio is their mean
    assert lo <= mid == res["speedup_per_simulated_second"] <= hi and res["rounds"] == 3
    if task != "magnetic_rod":  # the rollout step on the scene, the LSTM states carried (the rod: its closed loop)
        assert res["surrogate_step_hz_rollout"] > 0 and res["speedup_per_simulated_second_rollout"] > 1
    if task == "semicircle":  # the printed push keeps one of the four mirror images
        assert res["scene_symmetry_axes"] == [0, 2]
    else:
        assert "scene_symmetry_axes" not in res
    if task == "magnetic_rod":  # its closed loop, in the tabulated field and in the exact one
        assert min(res["surrogate_closed_loop_step_hz"], res["surrogate_closed_loop_latency_us"],
                   res["surrogate_closed_loop_exact_field_step_hz"]) > 0


def test_bench_gpu_runs_both_sides_and_compares_them(tmp_path):
    """On the CPU twice (no GPU here): the script's timings and comparisons run; both sides agree exactly."""
    res = run_script([str(ROOT / "scripts/bench/gpu.py"), "--quick", "--device", "cpu", "--threads", "1",
                      "--window", "0.05", "--batches", "1", "4"], tmp_path)
    assert res["device"] == "cpu" and res["threads"] == 1
    assert [(r["dtype"], r["batch"]) for r in res["lgvi"]] == [("float64", 1), ("float64", 4), ("float32", 1),
                                                                ("float32", 4)]
    assert len(res["cosserat"]) == 1 and [r["batch"] for r in res["surrogate"]] == [1, 4]
    assert [r["batch"] for r in res["lgvi_compiled"]] == [1] and res["lgvi_compiled"][0]["cpu_compile_s"] > 0
    for rows in (res["lgvi"], res["lgvi_compiled"], res["cosserat"], res["surrogate"]):
        for r in rows:
            assert r["ratio_dev_over_cpu"] > 0 and max(v for k, v in r.items() if k.startswith("max_abs_diff")) == 0
    # the rollout step: the CPU's compiled step for the first batch only, the device's eager step for the graph's
    step = res["surrogate_step"]
    assert [r["batch"] for r in step] == [1, 4] and step[0]["cpu_compile_s"] > 0 and "cpu_compiled_error" in step[1]
    assert set(step[0]["s_per_step"]) == {"cpu_eager", "cpu_compiled", "dev_eager", "dev_graph",
                                          "dev_graph_host_round_trip"}
    for r in step:
        assert min(r["s_per_step"].values()) > 0 and r["swing_m"] > 0.01
        ratio = r["s_per_step"]["cpu_eager"] / r["s_per_step"]["dev_graph"]
        assert r["graph_speedup_over"]["cpu_eager"] == pytest.approx(ratio, rel=1e-3)
        assert r["max_abs_diff_m_graph_vs_cpu"] == r["max_abs_diff_m_graph_vs_dev_eager"] == 0


def test_train_surrogate_quick_closed_loop(tmp_path):
    res = run_script([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "magnetic_rod", "--closed-loop",
                      "--threads", "1", "--out", "ck.pt", "--max-time", "1e-6", "--val-fresh", "1"], tmp_path)
    meta = json.loads((tmp_path / "ck.json").read_text())
    assert res["checkpoint"].endswith("ck.pt") and meta["args"]["closed_loop"] and "--closed-loop" in meta["command"]
    assert meta["val_data_hash"] and meta["val_data_hash"] != meta["data_hash"]  # closed-loop inputs of fresh variants
    # the time budget ends the run after its first epoch of the two --quick allows, then it evaluates as usual
    assert meta["epochs_run"] == 1 and "orientation_deg" in meta["metrics"]["seen_last40"]
    assert all(len(m["free_running_nudged"]["sum_mean_deg"]) == 16 for m in meta["metrics"].values())
    script_fails([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--closed-loop"], tmp_path,
                 "--closed-loop: task 'semicircle'")
    assert not list((tmp_path / "data").glob("semicircle*"))  # refused before generating any data


def test_train_quasistatic_quick_writes_a_loadable_hybrid(tmp_path, capsys):
    """The hybrid's training script end to end on its smoke budget (LGVI and static tracks of 1 s), and its
    argument checks."""
    from cmlearn.surrogate.quasistatic import QuasiStaticSurrogate
    res = run_script([str(ROOT / "scripts/train_quasistatic.py"), "--quick", "--out", "q.pt", "--log-dir", "logs"],
                     tmp_path)
    meta = json.loads((tmp_path / "q.json").read_text())
    assert res["checkpoint"].endswith("q.pt") and meta["format"] == "cmlearn-quasistatic/1"
    assert meta["command"].startswith("python scripts/train_quasistatic.py --quick") and meta["data_hash"]
    assert meta["epochs_run"] == 2 and math.isfinite(meta["linear_fit_residual"])
    engine = QuasiStaticSurrogate.load(tmp_path / "q.pt", task="magnetic_rod")
    assert engine.model.config.eta == 2 and list((tmp_path / "logs").rglob("metrics.csv"))
    # started from those weights, a run validates first at the score they were selected by
    run_script([str(ROOT / "scripts/train_quasistatic.py"), "--quick", "--init-from", "q.pt", "--out", "q2.pt",
                "--log-dir", "logs"], tmp_path)
    again = json.loads((tmp_path / "q2.json").read_text())
    assert again["val_loss_start"] == pytest.approx(meta["val_loss_best"], rel=1e-6)
    assert again["val_loss_start"] != pytest.approx(meta["val_loss_start"], rel=1e-5)  # not the untrained network's
    script_fails([str(ROOT / "scripts/train_quasistatic.py"), "--quick", "--init-from", "q.pt", "--hidden", "16",
                  "--out", "q3.pt"], tmp_path, "--init-from q.pt: its hidden differ")
    # with the fold clock: the checkpoint records it and its network reads it (a 14th static column)
    # (and without --out: a smoke test writes under runs/quick/, not over the shipped checkpoints/ file it did)
    res = run_script([str(ROOT / "scripts/train_quasistatic.py"), "--quick", "--margin", "--fold-clock", "20",
                      "--log-dir", "logs"], tmp_path)
    assert res["checkpoint"] == "runs/quick/magnetic_rod_quasistatic.pt" and not (tmp_path / "checkpoints").exists()
    clocked = QuasiStaticSurrogate.load(tmp_path / res["checkpoint"], task="magnetic_rod").model
    assert clocked.config.fold_clock == 20.0 and clocked.dense[0].in_features == 12 * 3 + 12 + 4 + 1
    for extra, msg in ((["--eta", "1"], "argument --eta: must be >= 2, got '1'"),
                       (["--fresh", "2", "--fresh-seed", "0"], "--fresh-seed must differ from --seed 0"),
                       (["--variants", "2"], "--variants must be >= 3"), (["--horizon", "0"], "--horizon: must be >= 1"),
                       (["--lr", "-0.1"], "argument --lr: must be >= 0, got '-0.1'"),
                       (["--threads", "0"], "argument --threads: must be >= 1, got '0'"),
                       (["--fold-clock", "20"], "--fold-clock needs --margin"),
                       (["--margin", "--fold-clock", "-1"], "argument --fold-clock: must be >= 0, got '-1'")):
        parse_fails("train_quasistatic", extra, msg, capsys)


def test_bench_quasistatic_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/bench/quasistatic.py"), "--quick"], tmp_path)
    for key in ("hybrid_step_hz", "lgvi_step_hz", "lstm_closed_loop_step_hz", "speedup_per_simulated_second"):
        assert res[key] > 0, key
    # over the printed profile's first second, whose currents start at 0.6 s: the hybrid errs less than its static rod
    assert res["batch"] == 1 and 0 < res["check"]["sum_mean_deg"] < 0.5 * res["check"]["static_sum_mean_deg"]


def test_bench_work_precision_quick(tmp_path):
    """The physics on half the mesh at ten times the step, and each shipped Simulation III surrogate, beside the
    printed LGVI: the reference row errs nothing, the coarse physics a little in y (the push's plane), the mirrored
    model nothing out of the plane."""
    res = run_script([str(ROOT / "scripts/bench/work_precision.py"), "--quick", "--out", "wp"], tmp_path)
    (s,) = res["scenes"]
    rows = {(r["model"], r["n_elements"], r["dt_s"]): r for r in s["rows"]}
    assert set(rows) == {("LGVI, printed", 100, 1e-4), ("LGVI", 50, 1e-3), ("semicircle", None, 0.01),
                         ("semicircle_fast", None, 0.01)}
    assert rows[("LGVI, printed", 100, 1e-4)]["max_mm"] == [0.0, 0.0, 0.0]
    assert rows[("LGVI, printed", 100, 1e-4)]["speedup"] == 1.0
    coarse = rows[("LGVI", 50, 1e-3)]
    assert 0.05 < coarse["max_mm"][1] < 1.0 and coarse["max_mm"][2] == 0.0 and coarse["speedup"] > 2
    mirrored = rows[("semicircle", None, 0.01)]
    assert mirrored["max_mm"][0] < 1e-3 and mirrored["max_mm"][2] == 0.0 and 0 < mirrored["max_mm"][1] < 3
    assert mirrored["speedup"] > coarse["speedup"]
    assert (tmp_path / "wp/work_precision_semicircle.md").read_text().count("| LGVI") == 2
    assert (tmp_path / "wp/work_precision_semicircle.png").stat().st_size > 10_000


def test_bench_work_precision_magnetic_quick(tmp_path):
    """The magnetic rod's work precision, eager over the held-out profile's first 0.3 s from rest: the reference errs
    nothing, the coarser mesh a little, the hybrid less than its static rod alone, every row timed."""
    res = run_script([str(ROOT / "scripts/bench/work_precision_magnetic.py"), "--quick", "--eager", "--out", "wp"],
                     tmp_path)
    (s,) = res["scenes"]
    rows = {(r["model"], r["per_part"], r["dt_s"]): r for r in s["rows"]}
    assert set(rows) == {("LGVI", 4, 8e-5), ("LGVI", 2, 8e-5), ("static Cosserat, 13 nodes", None, None),
                         ("quasi-static hybrid", None, None), ("LSTM, closed loop", None, None)}
    ref, coarse = rows[("LGVI", 4, 8e-5)], rows[("LGVI", 2, 8e-5)]
    assert ref["sum_of_means_deg"] == 0.0 and ref["speedup"] == 1.0 and coarse["n_elements"] == 6
    assert 0 < coarse["sum_of_means_deg"] < 0.5 and 0 < max(coarse["distal"]["max_deg"]) < 1.0
    static, hybrid = rows[("static Cosserat, 13 nodes", None, None)], rows[("quasi-static hybrid", None, None)]
    assert hybrid["sum_of_means_deg"] < static["sum_of_means_deg"]
    assert all(r["wall_per_sim_s"] > 0 for r in s["rows"])
    assert (tmp_path / "wp/work_precision_magnetic_rod.md").read_text().count("| LGVI") == 2


def test_the_magnetic_rod_on_a_coarser_mesh_keeps_its_magnets_and_headline_nodes():
    from physics.scenes_magnetic_rod import magnetic_rod, on_mesh, rod
    printed = magnetic_rod()
    coarse = on_mesh(printed, 2)
    assert coarse.rod.N == 6 and coarse.rod.rigid_elements == (2, 5) and coarse.nodes_of_interest == (6, 3)
    assert coarse.rod.length == pytest.approx(printed.rod.length)
    assert [m.s for m in coarse.rod.magnets] == [m.s for m in printed.rod.magnets]
    assert on_mesh(printed, 4).rod == printed.rod and on_mesh(printed, 4).nodes_of_interest == printed.nodes_of_interest
    assert printed.rod.stable_time_step().dt_max == pytest.approx(1.12e-4, rel=0.01)  # a coarser mesh's step grows
    assert coarse.rod.stable_time_step().dt_max == pytest.approx(1.63e-4, rel=0.01)
    with pytest.raises(ValueError, match="per_part"):
        rod(0)


def test_work_precision_sweep_skips_what_a_scene_cannot_run():
    """A scene without a mesh-study builder runs only on its printed mesh; a step above a mesh's stability limit
    is refused by the LGVI (the benchmark reports it)."""
    from cmlearn.data import get_task
    wp = load_script("bench/work_precision")
    task = get_task("square_tracking")
    assert wp.physics_scene(task.scene_by_name("square_tracking_circle"), 4, 1e-4) is None
    assert wp.physics_scene(task.scene_by_name("square_tracking_circle"), 8, 1.25e-4).dt == 1.25e-4
    semi = get_task("semicircle").scene_by_name("semicircle")
    assert wp.physics_scene(semi, 26, 1e-3).rod.N == 26
    with pytest.raises(ValueError, match="stability limit"):
        wp.physics_runner(wp.physics_scene(semi, 50, 5e-3), 0.01, compiled=False)


def test_train_surrogate_selects_by_the_validation_rollout_and_reports_every_epoch(tmp_path, capsys):
    run_script([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--select-by", "rollout",
                "--keep-top-k", "-1", "--threads", "1", "--out", "ck.pt", "--log-dir", "logs", "--rest-anchor",
                "--mirror", "zx", "--head-hidden", "24", "--time-reversal"], tmp_path)
    meta = json.loads((tmp_path / "ck.json").read_text())
    arch = meta["architecture"]
    assert meta["args"]["time_reversal"] and "--time-reversal" in meta["command"]
    assert arch["head_hidden"] == 24 and arch["rest_anchor"] and arch["reflections"] == [[2, None], [0, list(range(22, -1, -1))]]
    rep = run_script([str(ROOT / "scripts/report_epoch_selection.py"), "ck.pt", "--out", "sel.md"], tmp_path)
    assert [e["epoch"] for e in rep["epochs"]] == [0, 1] and rep["cases"] == ["seen_last40", "semicircle_heldout"]
    scores = {e["epoch"]: e["val_rollout_mm"] for e in rep["epochs"]}
    chosen = rep["selected"]["val_rollout_mm"]
    assert scores[chosen] == min(scores.values())
    # the shipped weights are the selected epoch's: its rollouts reproduce the metrics train_surrogate recorded
    row = next(e for e in rep["epochs"] if e["epoch"] == chosen)["free_running_max_mm"]
    for errs, case in zip(row, rep["cases"]):
        want = [meta["metrics"][case]["free_running"]["node"][ax]["max_mm"] for ax in "xyz"]
        assert errs == pytest.approx(want, rel=1e-4, abs=1e-6)
    assert "| epoch | val_loss | val_rollout_mm |" in (tmp_path / "sel.md").read_text()
    # --init-from starts from those weights, scales included: at lr 0 the run leaves them as they are
    run_script([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--threads", "1",
                "--rest-anchor", "--mirror", "zx", "--head-hidden", "24", "--init-from", "ck.pt", "--lr", "0",
                "--epochs", "1", "--val-fresh", "2", "--val-stride", "2", "--log-dir", "logs_ft"],
               tmp_path)  # no --out: a smoke test writes under runs/quick/, not over checkpoints/semicircle.pt
    assert not (tmp_path / "checkpoints").exists()
    src, ft = (torch.load(tmp_path / f, weights_only=True)["state_dict"] for f in ("ck.pt", "runs/quick/semicircle.pt"))
    assert src.keys() == ft.keys() and all(torch.equal(src[k], ft[k]) for k in src)
    ft_meta = json.loads((tmp_path / "runs/quick/semicircle.json").read_text())
    for case in rep["cases"]:  # the same errors
        assert {m: ft_meta["metrics"][case][m] for m in ("one_step", "free_running")} == \
            {m: meta["metrics"][case][m] for m in ("one_step", "free_running")}
    # the held-out scene's LGVI run was read from data/, made by the first run: its wall time too
    assert (tmp_path / "data" / "semicircle_semicircle_heldout_0.3s_ref.pt").exists()
    assert ft_meta["metrics"]["semicircle_heldout"]["lgvi_wall_s"] == meta["metrics"]["semicircle_heldout"]["lgvi_wall_s"]
    assert "--init-from ck.pt" in ft_meta["command"] and ft_meta["init_from"]["command"] == meta["command"]
    # the starting weights were validated first: at lr 0 the one epoch scores exactly as they do
    ep = [r for r in csv.DictReader(next((tmp_path / "logs_ft").rglob("metrics.csv")).open()) if r.get("val_loss")]
    assert len(ep) == 1 and ft_meta["init_from"]["val"] == pytest.approx(
        {k: float(ep[0][k]) for k in ("val_loss", "val_rollout_mm")}, rel=1e-5)
    assert ft_meta["init_from"]["selected_beats_start"] is False
    fresh = torch.load(tmp_path / "data" / "semicircle_v3_s1_d0.3.pt", weights_only=False)  # validated on
    assert ft_meta["val_data_hash"] == fresh["meta"]["data_hash"] and ft_meta["args"]["val_seed"] == 1
    assert ft_meta["init_from"]["sha256"] == hashlib.sha256((tmp_path / "ck.pt").read_bytes()).hexdigest()
    # the chord projection and the mirrors have no weights: a run may add the one and drop the other; on other data
    # (two variants, not three) only with --keep-scales, which keeps the checkpoint's scales and records the gap
    cp_run = [str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--threads", "1",
              "--variants", "2", "--rest-anchor", "--head-hidden", "24", "--init-from", "ck.pt", "--lr", "0",
              "--epochs", "1", "--chord-projection", "--printed-repeat", "2", "--out", "cp.pt", "--log-dir", "logs_cp"]
    script_fails(cp_run, tmp_path, "and its scales differ by up to")
    run_script([*cp_run, "--keep-scales"], tmp_path)
    cp = torch.load(tmp_path / "cp.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(src[k], cp[k]) for k in src)
    cp_meta = json.loads((tmp_path / "cp.json").read_text())
    assert cp_meta["architecture"]["chord_projection"] and cp_meta["architecture"]["reflections"] == []
    assert cp_meta["init_from"]["scales_off"] > 1e-5 and cp_meta["data_hash"] != meta["data_hash"]
    assert cp_meta["args"]["printed_repeat"] == 2
    # a wider head, stencil and mix (its neighbours' outputs projected) start from the same steps: at lr 0 the same
    # errors, the old weights inside the new, the second ring's offset scales from the data
    run_script([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--threads", "1",
                "--rest-anchor", "--mirror", "zx", "--head-hidden", "40", "--stencil", "2", "--mix", "1",
                "--mix-width", "4", "--init-from", "ck.pt",
                "--lr", "0", "--epochs", "1", "--out", "wide.pt", "--log-dir", "logs_wide"], tmp_path)
    wide, wide_meta = torch.load(tmp_path / "wide.pt", weights_only=True)["state_dict"], \
        json.loads((tmp_path / "wide.json").read_text())
    assert wide_meta["architecture"]["head_hidden"] == 40 and wide["head.2.weight"].shape == (40, 40)
    assert torch.equal(wide["head.2.weight"][:24, :24], src["head.2.weight"])
    n_in = src["head.0.weight"].shape[1]  # the neighbours' LSTM outputs come after the head's own inputs
    assert wide_meta["architecture"]["mix"] == 1 and wide["head.0.weight"].shape[1] == n_in + 2 * 4
    assert torch.allclose(wide["mix_proj.weight"] @ wide["mix_proj.weight"].t(), torch.eye(4), atol=1e-6)
    assert torch.equal(wide["head.0.weight"][:24, :n_in], src["head.0.weight"]) and \
        not wide["head.0.weight"][:, n_in:].any()
    assert wide_meta["architecture"]["right2"][0] == 3 and wide["lstm.weight_ih_l0"].shape[1] == 30
    assert torch.equal(wide["lstm.weight_ih_l0"][:, :18], src["lstm.weight_ih_l0"])
    assert not wide["lstm.weight_ih_l0"][:, 18:].any() and torch.equal(wide["rel_scale"][:, :6], src["rel_scale"])
    ratio = wide["rel_scale"][:, 6:] / wide["rel_scale"][:, :6]  # a second neighbour's offset moves more
    assert 1.2 < float(ratio.median()) < 4 and not (wide["rel_scale"][:, 6:] == 1).any()
    for case in rep["cases"]:
        got, want = (m["metrics"][case]["free_running"]["node"] for m in (wide_meta, meta))
        assert [got[ax]["max_mm"] for ax in "xyz"] == pytest.approx([want[ax]["max_mm"] for ax in "xyz"], rel=1e-4,
                                                                   abs=1e-6)
    script_fails([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--threads", "1", "--rest-anchor", "--mirror",
                  "zx", "--head-hidden", "16", "--init-from", "ck.pt"], tmp_path,
                 "a --head-hidden, --stencil and --mix at least its own")
    for extra, msg in ((["--init-from", "ck.pt", "--eta", "3"], "--init-from: ck.pt: architecture"),
                       (["--init-from", "nothing.pt"], "argument --init-from: no such file: 'nothing.pt'")):
        script_fails([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--threads", "1", *extra], tmp_path, msg)
    torch.save({"state_dict": {}}, tmp_path / "x.ckpt")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    for extra, msg in ((["--init-from", str(tmp_path / "ck.pt"), "--resume", str(tmp_path / "x.ckpt")],
                        "--init-from and --resume exclude"),
                       (["--resume", str(tmp_path / "empty.ckpt")], "empty.ckpt is not a readable Lightning checkpoint"),
                       (["--keep-scales"], "--keep-scales needs --init-from"),
                       (["--printed-repeat", "0"], "argument --printed-repeat: must be >= 1, got '0'"),
                       (["--select-by", "loss"], "argument --select-by: invalid choice: 'loss'"),
                       (["--task", "rod"], "argument --task: invalid choice: 'rod'"),
                       (["--max-time", "-1"], "argument --max-time: must be >= 0, got '-1'"),
                       (["--head-hidden", "0"], "argument --head-hidden: must be >= 1, got '0'"),
                       (["--epochs", "0"], "argument --epochs: must be >= 1, got '0'"),
                       (["--lr", "-1"], "argument --lr: must be >= 0, got '-1'"),
                       (["--noise", "nan"], "argument --noise: must be finite, got 'nan'"),
                       (["--horizon", "two"], "argument --horizon: must be an integer, got 'two'"),
                       (["--mix-width", "8"], "--mix-width must be 0, or in 1..--hidden (48) with --mix 1 or 2"),
                       (["--val-fresh", "2", "--val-seed", "0"], "--val-seed must differ from --seed 0"),
                       # options that did nothing without the one they belong to
                       (["--val-seed", "7"], "--val-seed 7 seeds the --val-fresh variants, and none are asked for"),
                       (["--val-fresh", "2", "--val-seed", "-5"], "argument --val-seed: must be >= -1, got '-5'"),
                       (["--motion-floor", "0.05"], "--motion-floor 0.05 is the floor of --window-weighting "
                                                    "inverse_motion, which is off"),
                       (["--noise-shape", "offset"], "--noise-shape offset shapes the training noise, and --noise is 0"),
                       (["--val-tail", "0.6"], "--val-tail must lie in [0, 0.6)"),
                       (["--val-tail", "0.1", "--val-fresh", "2"], "--val-tail and --val-fresh exclude"),
                       (["--variants", "1"], "--variants 1 leaves no variant to validate on"),
                       (["--devices", "2"], "--devices must be 1, or more with --ddp"),
                       (["--ddp", "--devices", "0"], "argument --devices: must be >= 1, got '0'"),
                       (["--task", "magnetic_rod", "--time-reversal"],
                        "--time-reversal: task 'magnetic_rod' is not time-reversible"),
                       (["--task", "magnetic_rod", "--chord-projection"],
                        "--chord-projection: task 'magnetic_rod' tracks points that are not a chain")):
        parse_fails("train_surrogate", ["--quick", *extra], msg, capsys)
    with pytest.raises(SystemExit):
        load_script("train_surrogate").parse(["--help"])
    usage = " ".join(capsys.readouterr().out.split())  # every option explained, whatever the terminal width
    assert "--rest-anchor subtract the model's output at rest" in usage and usage.count("(default:") >= 30
    for mirror in ("w", "zz"):
        parse_fails("train_surrogate", ["--quick", "--mirror", mirror], "--mirror must name task 'semicircle'", capsys)


def test_train_surrogate_ddp_trains_on_two_processes_and_its_run_resumes_in_one(tmp_path):
    """--ddp: two CPU processes train one model, select the same epoch from synchronised metrics, and the
    first alone evaluates and writes it; --resume continues that run's last Lightning checkpoint."""
    base = [str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--threads", "1"]
    res = run_script([*base, "--ddp", "--devices", "2", "--epochs", "1", "--out", "ddp.pt", "--log-dir", "logs"],
                     tmp_path)
    meta = json.loads((tmp_path / "ddp.json").read_text())
    assert res["checkpoint"].endswith("ddp.pt") and meta["args"]["ddp"]
    assert meta["world_size"] == 2 and meta["epochs_run"] == 1
    rows = [r for r in csv.DictReader(next((tmp_path / "logs").rglob("metrics.csv")).open()) if r.get("val_loss")]
    assert len(rows) == 1  # one validation record an epoch, not one per process
    best = list((tmp_path / "logs").rglob("epoch=0-*.ckpt"))
    assert len(best) == 1  # both processes named the selected checkpoint alike
    selected = torch.load(best[0], map_location="cpu", weights_only=False)["state_dict"]
    written = torch.load(tmp_path / "ddp.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(selected[f"model.{k}"], v) for k, v in written.items())
    last = next((tmp_path / "logs").rglob("last.ckpt"))
    run_script([*base, "--resume", str(last), "--out", "res.pt", "--log-dir", "logs_res"], tmp_path)
    resumed = json.loads((tmp_path / "res.json").read_text())
    assert resumed["world_size"] == 1 and resumed["epochs_run"] == 2
    epochs = {r["epoch"] for r in csv.DictReader(next((tmp_path / "logs_res").rglob("metrics.csv")).open())}
    assert epochs == {"1"}  # it went on from the second epoch instead of training the first again


def test_train_surrogate_resumed_from_an_epoch_trains_the_next_as_the_uninterrupted_run(tmp_path):
    """--resume restores the training shuffle and the noise generator (the data module's checkpointed state): the
    second epoch resumed from the first one's checkpoint ends with the uninterrupted run's weights."""
    base = [str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--threads", "1",
            "--epochs", "2", "--batch-size", "8", "--train-batches", "3", "--hidden", "8", "--head-hidden", "8",
            "--noise", "0.1", "--keep-top-k", "-1"]
    run_script([*base, "--out", "a.pt", "--log-dir", "logs_a"], tmp_path)
    first = next((tmp_path / "logs_a").rglob("epoch=0-*.ckpt"))
    run_script([*base, "--resume", str(first), "--out", "b.pt", "--log-dir", "logs_b"], tmp_path)
    a, b = (torch.load(next((tmp_path / d).rglob("epoch=1-*.ckpt")), map_location="cpu", weights_only=False)
            for d in ("logs_a", "logs_b"))
    assert a["global_step"] == b["global_step"] > 0
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])


def test_train_surrogate_validates_on_the_printed_tail(tmp_path):
    """--variants 1 --val-tail: the thesis's one-trajectory protocol; the logged val_rollout_mm is the
    free-running error over the printed scene's tail before the cut, not over the test range after it."""
    from cmlearn.data import load_dataset
    from cmlearn.surrogate.checkpoint import load_checkpoint
    from cmlearn.surrogate.training import RolloutSelection, SurrogateDataModule, SurrogateModule
    run_script([str(ROOT / "scripts/train_surrogate.py"), "--quick", "--task", "semicircle", "--variants", "1",
                "--val-tail", "0.2", "--threads", "1", "--max-time", "1e-6", "--out", "ck.pt", "--log-dir", "logs"],
               tmp_path)
    model, meta = load_checkpoint(tmp_path / "ck.pt", task="semicircle")
    ep = [r for r in csv.DictReader(next((tmp_path / "logs").rglob("metrics.csv")).open()) if r.get("val_rollout_mm")]
    assert meta["args"]["val_tail"] == 0.2 and len(ep) == 1  # one epoch, the one shipped
    data = load_dataset(tmp_path / "data" / "semicircle_v1_s0_d0.3.pt")
    score = RolloutSelection(SurrogateDataModule(data, eta=2, horizon=4, val_tail=0.2)).score(SurrogateModule(model))
    assert score == pytest.approx(float(ep[0]["val_rollout_mm"]), rel=1e-4)
    with pytest.raises(ValueError, match="nothing to validate on but the test range"):  # without the tail
        RolloutSelection(SurrogateDataModule(data, eta=2, horizon=4)).score(SurrogateModule(model))


def test_train_surrogate_ema_validates_and_ships_the_averaged_weights(tmp_path, capsys):
    """--ema: an exponential moving average of the weights, updated every optimiser step, is what each
    epoch validates and what the checkpoint ships; the optimisation itself is the run's without it."""
    from cmlearn.data import load_dataset
    from cmlearn.surrogate.checkpoint import load_checkpoint
    from cmlearn.surrogate.training import RolloutSelection, SurrogateDataModule, SurrogateModule
    common = ["--quick", "--task", "semicircle", "--threads", "1", "--keep-top-k", "-1", "--select-by", "rollout"]
    for name, extra in (("ema", ["--ema", "0.75"]), ("plain", [])):
        run_script([str(ROOT / "scripts/train_surrogate.py"), *common, *extra, "--out", f"{name}.pt",
                    "--log-dir", f"logs_{name}"], tmp_path)
    logs = {name: [r for r in csv.DictReader(next((tmp_path / f"logs_{name}").rglob("metrics.csv")).open())]
            for name in ("ema", "plain")}
    train = {name: [float(r["train_loss"]) for r in rows if r.get("train_loss")] for name, rows in logs.items()}
    assert len(train["ema"]) == 2 and train["ema"] == train["plain"]  # the same optimisation path
    ckpts = {int(f.name.split("-")[0].split("=")[1]): torch.load(f, weights_only=False)
             for f in (tmp_path / "logs_ema").rglob("epoch=*.ckpt")}
    assert sorted(ckpts) == [0, 1] and [c["global_step"] for c in (ckpts[0], ckpts[1])] == [1, 2]
    raw = [ckpts[e]["current_model_state"] for e in (0, 1)]
    avg = [ckpts[e]["state_dict"] for e in (0, 1)]
    weights = [k for k in avg[1] if k.endswith("weight") and "head" in k]
    assert weights and all(torch.equal(avg[0][k], raw[0][k]) for k in weights)  # the first update copies
    for k in weights:  # then ema <- 0.75 ema + 0.25 w
        assert torch.allclose(avg[1][k], 0.75 * raw[0][k] + 0.25 * raw[1][k], atol=1e-7)
    assert any(not torch.equal(avg[1][k], raw[1][k]) for k in weights)
    model, _ = load_checkpoint(tmp_path / "ema.pt", task="semicircle")
    val = [r for r in logs["ema"] if r.get("val_rollout_mm")]
    best = min(range(len(val)), key=lambda e: float(val[e]["val_rollout_mm"]))
    shipped = torch.load(tmp_path / "ema.pt", weights_only=True)["state_dict"]
    assert weights[0].removeprefix("model.") in shipped  # the selected epoch's average is what ships
    assert all(torch.equal(shipped[k.removeprefix("model.")], avg[best][k]) for k in weights)
    data = load_dataset(tmp_path / "data" / "semicircle_v3_s0_d0.3.pt")
    selection = RolloutSelection(SurrogateDataModule(data, eta=2, horizon=4))
    module = SurrogateModule(model)
    module.load_state_dict(avg[1])  # epoch 1 validated its average, not its raw weights
    score = selection.score(module)
    assert score == pytest.approx(float(val[1]["val_rollout_mm"]), rel=1e-5)
    module.load_state_dict(raw[1])
    assert abs(selection.score(module) - score) > 1e-4 * score
    last = next((tmp_path / "logs_ema").rglob("last.ckpt"))
    for extra, msg in ((["--ema", "1"], "--ema must lie in [0, 1) (0: off), got 1.0"),
                       (["--resume", str(last)], f"--resume: {last} comes from a run with --ema")):
        parse_fails("train_surrogate", ["--quick", *extra], msg, capsys)


def test_init_from_accepts_regenerated_data_only_when_its_scales_fit(tmp_path):
    """Regenerated data that differs in its last bits (another hash) but gives the same scales is
    fine-tuned on; data whose scales differ is refused."""
    from types import SimpleNamespace
    from cmlearn.data import get_task
    ts = load_script("train_surrogate")
    task, a = get_task("semicircle"), ts.parse(["--quick"])
    gen = torch.Generator().manual_seed(0)
    n = len(task.tracked)
    trajs = [torch.randn(50, n, 3, generator=gen, dtype=torch.float64).cumsum(0) * 1e-3 for _ in range(3)]
    wrench = torch.randn(3, 49, 1, 3, generator=gen, dtype=torch.float64)
    init = ts.build_model(task, a)
    init.set_scales(trajs, wrench, 0.6)
    (tmp_path / "ck.pt").write_bytes(b"weights")
    meta, data = {"data_hash": "a" * 16, "command": "train"}, {"meta": {"data_hash": "b" * 16}}
    for factor, fits in ((1 + 1e-12, True), (1.001, False)):
        dm = SimpleNamespace(train_positions=lambda fresh_validation, val_tail: [p * factor for p in trajs],
                             train_wrench=lambda fresh_validation, val_tail: wrench)
        model = ts.build_model(task, a)
        if fits:
            prov = ts.start_from(model, init, meta, data, dm, str(tmp_path / "ck.pt"))
            assert prov["data_hash"] == "a" * 16 and prov["command"] == "train"
            assert all(torch.equal(v, init.state_dict()[k]) for k, v in model.state_dict().items())
        else:
            with pytest.raises(SystemExit, match="its scales differ by up to 1.0e-03"):
                ts.start_from(model, init, meta, data, dm, str(tmp_path / "ck.pt"))
    # a run with fresh validation variants (its dataset's last variant trains) fine-tunes a checkpoint whose
    # run validated on that variant: the scales are compared over the variants that run trained on
    from cmlearn.surrogate.training import SurrogateDataModule
    pos = torch.stack([t[:40] for t in trajs]).float()
    pos[2] *= 3  # the last variant moves more: the scales with it differ
    dset = {"positions": pos, "wrench": wrench[:, :39].float(),
            "meta": {"n_variants": 3, "wrench_nodes": list(task.wrench_nodes), "modeled": list(task.modeled),
                     "data_hash": "b" * 16}}
    dm_fresh = SurrogateDataModule(dset, eta=2, horizon=4, val_dataset=dset)
    plain = SurrogateDataModule(dset, eta=2, horizon=4)
    init.set_scales(plain.train_positions(), plain.train_wrench(), 0.6)
    prov = ts.start_from(ts.build_model(task, a), init, meta, data, dm_fresh, str(tmp_path / "ck.pt"))
    assert prov["data_hash"] == "a" * 16
    with pytest.raises(SystemExit, match="its scales differ"):  # as if that run had trained on every variant
        ts.start_from(ts.build_model(task, a), init, {**meta, "args": {"val_fresh": 4}}, data, dm_fresh,
                      str(tmp_path / "ck.pt"))
    # a --val-tail run trained on less of the printed scene: its scales are compared over that part
    tail = SurrogateDataModule(dset, eta=2, horizon=4, val_tail=0.3)
    init.set_scales(tail.train_positions(), tail.train_wrench(), 0.6)
    ts.start_from(ts.build_model(task, a), init, {**meta, "args": {"val_tail": 0.3}}, data, dm_fresh,
                  str(tmp_path / "ck.pt"))
    with pytest.raises(SystemExit, match="its scales differ"):
        ts.start_from(ts.build_model(task, a), init, meta, data, dm_fresh, str(tmp_path / "ck.pt"))


def test_surrogate_report(tmp_path):
    res = run_script([str(ROOT / "scripts/report_surrogates.py"), "--out", "s.md"], tmp_path)
    assert (tmp_path / "s.md").exists() and len(res["rows"]) >= 3
    NOTES = load_script("report_surrogates").NOTES  # hand-written notes below the marker survive a regeneration
    text = (tmp_path / "s.md").read_text()
    assert NOTES not in text
    (tmp_path / "s.md").write_text(text.replace("| scene |", "| stale |") + NOTES + "\nA study.\n")
    run_script([str(ROOT / "scripts/report_surrogates.py"), "--out", "s.md"], tmp_path)
    again = (tmp_path / "s.md").read_text()
    assert again == text + "\n" + NOTES + "\nA study.\n"


def test_surrogate_report_shows_the_nudged_free_running_spread_where_recorded():
    rows = load_script("report_surrogates").orientation_rows
    meta = json.loads((ROOT / "checkpoints/magnetic_rod.json").read_text())
    for c in meta["metrics"].values():  # as a checkpoint trained before the spread was recorded
        c.pop("free_running_nudged", None)
    case = meta["metrics"]["magnetic_rod_heldout"]
    plain = rows(meta)
    assert not any("nudged" in r for r in plain)
    stats = {m: {ax: {"max_deg": 30.0 + i, "mean_deg": 1.0 + i / 10} for i, ax in enumerate("xyz")}
             for m in ("distal", "proximal")}
    case["free_running_nudged"] = {"n": 16, "sigma_m": 1e-8, "sum_mean_deg": [20.0] * 16, **stats}
    nudged = [r for r in rows(meta) if "nudged" in r]
    assert nudged == [f"| magnetic_rod_heldout | {m} | ours: LSTM, free-running, 16 starts nudged 1e-08 m (mean; largest "
                      "max) | 30.00, 1.00 | 31.00, 1.10 | 32.00, 1.20 |" for m in ("distal", "proximal")]
    assert len(rows(meta)) == len(plain) + 2


def test_rollout_sensitivity_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_rollout_sensitivity.py"), "--quick", "--tasks", "semicircle",
                      "--out", "sens.md"], tmp_path)
    assert (tmp_path / "sens.md").exists()
    cases = res["semicircle"]["cases"]
    # a 10 um nudge of node 51 along x shows up in x, ten times the 1 um one (linear over 0.08 s)
    x1, x10 = cases["nudge 1 um"]["x"]["max_mm"], cases["nudge 10 um"]["x"]["max_mm"]
    assert 0 < x1 and abs(x10 / x1 - 10) < 0.5
    assert cases["float32"]["x"]["max_mm"] < x1
    # the LGVI's own step error converges at second order: |p(dt) - p(dt/4)| / |p(dt/2) - p(dt/4)| = (1 - 1/16) /
    # (1/4 - 1/16) = 5 along the load (y)
    step = res["semicircle"]["step_error"]["cases"]
    assert step["dt"]["y"]["max_mm"] > 0 and 4.5 < step["dt"]["y"]["max_mm"] / step["dt/2"]["y"]["max_mm"] < 5.5
    # the motion above f Hz shrinks as f grows (the pushed node's y motion is slow: mostly below 2 Hz)
    above = [res["semicircle"]["step_error"]["above_hz"][f]["y"]["mean_mm"] for f in ("1", "2", "5", "10")]
    assert above == sorted(above, reverse=True) and above[-1] < 0.01 * above[0]
    # on half the elements the push stays in the plane, and the mesh changes the node far more than the step does
    mesh = res["semicircle"]["step_error"]["mesh"]
    assert (mesh["n_elements"], mesh["printed"]) == (50, 100) and mesh["errors"]["z"]["max_mm"] == 0
    assert mesh["errors"]["y"]["max_mm"] > 100 * step["dt"]["y"]["max_mm"]
    assert "| semicircle (51) | 0.12-0.2 s | 50 of 100 |" in (tmp_path / "sens.md").read_text()


def test_load_amplitude_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_load_amplitude.py"), "--checkpoints",
                      str(ROOT / "checkpoints/semicircle_fast.pt"),
                      "--scales", "0", "1", "--duration", "1.2", "--out", "amp.md"], tmp_path)
    assert (tmp_path / "amp.md").exists() and res["scene"] == "semicircle_heldout"
    rest, pushed = res["rows"]
    # unloaded, the semicircle is an exact equilibrium: the node stays put and the surrogate stays near it
    assert max(rest["range_mm"]) < 1e-6 and rest["errors"]["semicircle_fast.pt"]["pct_of_range"] == [None] * 3
    assert max(rest["errors"]["semicircle_fast.pt"]["max_mm"]) < 5.0
    # the held-out load (out of plane, from t = 1 s) swings the node along z tens of millimetres within 0.2 s
    assert pushed["range_mm"][2] > 20.0 and pushed["range_mm"][0] < 1e-6
    err = pushed["errors"]["semicircle_fast.pt"]
    assert err["pct_of_range"][2] == pytest.approx(100 * err["max_mm"][2] / pushed["range_mm"][2])
    script_fails([str(ROOT / "scripts/report_load_amplitude.py"), "--checkpoints", str(ROOT / "checkpoints/semicircle.pt"),
                  str(ROOT / "checkpoints/square_tracking.pt")], tmp_path, "--checkpoints")


def test_free_running_spread_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_free_running_spread.py"), "--checkpoints",
                      str(ROOT / "checkpoints/magnetic_rod.pt"), "--duration", "0.3", "--starts", "2",
                      "--lgvi-eps", "1e-6", "--data-dir", str(tmp_path), "--out", "spread.md"], tmp_path)
    text = (tmp_path / "spread.md").read_text()
    assert "| magnetic_rod_heldout | magnetic_rod.pt |" in text and "open loop (the LGVI's wrench)" in text
    assert [r["case"] for r in res["rows"]] == ["magnetic_rod (last 40 %)", "magnetic_rod_heldout"]
    for row in res["rows"]:
        m = row["models"]["magnetic_rod.pt"]
        assert m["single"] > 0 and len(m["nudged"]["1e-08"]["sum_mean_deg"]) == 2
        # no snap-through within 0.3 s: nudges of 1e-8 m and currents changed by 1e-6 change (almost) nothing,
        # and the LGVI's wrench (open loop) is nearly the model's own
        assert max(abs(s - m["single"]) for s in m["nudged"]["1e-08"]["sum_mean_deg"]) < 1e-3
        assert len(m["open_loop"]["sum_mean_deg"]) == 2 and m["open_loop"]["sigma_m"] == 1e-8
        assert max(abs(s - m["single"]) for s in m["open_loop"]["sum_mean_deg"]) < 0.1
        assert row["lgvi"]["runs"]["1e-06"]["max_deg"] < 1e-3
    script_fails([str(ROOT / "scripts/report_free_running_spread.py"), "--checkpoints",
                  str(ROOT / "checkpoints/semicircle.pt")], tmp_path, "--checkpoints")


def test_step_baselines_report_quick(tmp_path):
    from cmlearn.data import get_task, reference_rollout
    from cmlearn.data.magnetic import magnet_frames
    from cmlearn.data.windows import split_ranges
    from cmlearn.surrogate.magnetic import orientation_errors
    res = run_script([str(ROOT / "scripts/report_step_baselines.py"), "--checkpoints", str(ROOT / "checkpoints/magnetic_rod.pt"),
                      "--duration", "0.3", "--variants", "2", "--data-dir", str(tmp_path), "--out", "base.md"], tmp_path)
    assert "| magnetic_rod_heldout | linear, global |" in (tmp_path / "base.md").read_text()
    assert [r["case"] for r in res["rows"]] == ["magnetic_rod (last 40 %)", "magnetic_rod_heldout"]
    task = get_task("magnetic_rod")
    for row, name in zip(res["rows"], ("magnetic_rod", "magnetic_rod_heldout")):
        models = row["models"]
        assert list(models) == ["magnetic_rod.pt", "constant velocity", "linear, local", "linear, global"]
        assert "closed_loop" in models["magnetic_rod.pt"] and "closed_loop" not in models["linear, local"]
        # the constant-velocity step by hand, on the LGVI run the report cached: p(t+1) = 2 p(t) - p(t-1)
        p, _, _ = reference_rollout(task, name, 0.3, tmp_path)
        p = p.double()
        if name == "magnetic_rod":
            s = split_ranges(1, p.shape[0])["test"][0][1]
        else:  # from rest: the frame before t = 0 is the rest frame itself
            p, s = torch.cat([p[:1], p]), 1
        cv = p[s + 1:].clone()
        cv[:, 1:] = (2 * p[s:-1] - p[s - 1:-2])[:, 1:]
        rod = task.base_scene().rod
        err = orientation_errors(magnet_frames(task, rod, cv)[1], magnet_frames(task, rod, p[s + 1:])[1])
        assert models["constant velocity"]["one_step"] == pytest.approx(float(err.abs().mean(0).sum()), rel=1e-4)
    script_fails([str(ROOT / "scripts/report_step_baselines.py"), "--checkpoints", str(ROOT / "checkpoints/magnetic_rod.pt"),
                  str(ROOT / "checkpoints/semicircle.pt")], tmp_path, "--checkpoints")
    script_fails([str(ROOT / "scripts/report_step_baselines.py"), "--variants", "1"], tmp_path, "--variants")
    script_fails([str(ROOT / "scripts/report_step_baselines.py"), "--eta", "1"], tmp_path, "--eta")


def test_step_baselines_report_on_positions_quick(tmp_path):
    from cmlearn.data import load_dataset
    from cmlearn.data.windows import split_ranges
    res = run_script([str(ROOT / "scripts/report_step_baselines.py"), "--checkpoints", str(ROOT / "checkpoints/semicircle.pt"),
                      "--duration", "0.3", "--variants", "2", "--eta", "3", "--data-dir", str(tmp_path),
                      "--out", "base.md"], tmp_path)
    text = (tmp_path / "base.md").read_text()
    assert "| semicircle_heldout | thesis (Paper II) | 3.73, 1.25 / 2.0, 0.2 / 8.1, 1.2 |" in text
    assert res["eta"] == 3 and [r["case"] for r in res["rows"]] == ["semicircle (last 40 %)", "semicircle_heldout"]
    models = res["rows"][0]["models"]
    assert list(models) == ["semicircle.pt", "constant velocity", "linear, local", "linear, global"]
    # the constant-velocity step by hand on the printed scene's last 40 %, node 50: p(t+1) = 2 p(t) - p(t-1)
    data = load_dataset(next(tmp_path.glob("semicircle_v2_*.pt")))
    p = data["positions"][0].double()[:, data["meta"]["tracked"].index(50)]
    s = split_ranges(2, p.shape[0])["test"][0][1]
    err = (p[s + 1:] - (2 * p[s:-1] - p[s - 1:-2])).abs() * 1e3
    for i, ax in enumerate("xyz"):
        cv = models["constant velocity"]["one_step"][ax]
        assert cv["max_mm"] == pytest.approx(float(err[:, i].max()), rel=1e-3, abs=1e-6)
        assert cv["mean_mm"] == pytest.approx(float(err[:, i].mean()), rel=1e-3, abs=1e-6)
    assert err[:, 1].max() > 1e-3  # the node moves: the check above is not of zeros


def test_one_step_bias_report_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_one_step_bias.py"), "--checkpoints", "checkpoints/semicircle.pt",
                      "--duration", "0.3", "--window", "10", "--out", "bias.md"], tmp_path)
    assert (tmp_path / "bias.md").exists()
    rows = res["results"][0]["rows"]
    assert [r["frames"] for r in rows] == [[3, 12], [13, 22], [23, 30]]
    # the printed pulse pushes node 51 along -y in the rod's plane: the true second difference is there
    # and negative while the pulse is on, zero out of the plane
    assert rows[0]["y"]["d2_mean_mm"] < -0.01 and abs(rows[0]["z"]["d2_mean_abs_mm"]) < 1e-9
    assert all(abs(r[ax]["bias_mm"]) <= r[ax]["mean_abs_err_mm"] + 1e-12 for r in rows for ax in "xyz")
    # after the cut (frame 18 of 30) the pulse still pushes in the rod's plane; out of it nothing moves
    after = res["results"][0]["after_cut"]
    assert res["results"][0]["cut_frame"] == 18
    assert 0 < after["y"]["d2_rms_mm"] <= after["y"]["d2_max_mm"] and after["z"]["d2_max_mm"] < 1e-9
    assert after["y"]["err_rms_mm"] <= after["y"]["err_max_mm"]
    assert after["y"]["d2_max_mm"] >= max(r["y"]["d2_mean_abs_mm"] for r in rows[2:])
    assert "against a zero second difference" in (tmp_path / "bias.md").read_text()


def test_rank_checkpoints_on_fresh_variants(tmp_path):
    """Checkpoints ranked on new variants of their scene; each error is the per-variant rollout's."""
    from cmlearn.data import get_task, load_dataset
    from cmlearn.data.windows import node_wrench
    from cmlearn.eval.metrics import axis_errors
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.evaluate import free_running, from_rest, interest_slots
    cks = [str(ROOT / "checkpoints" / f) for f in ("semicircle.pt", "semicircle_fast.pt")]
    res = run_script([str(ROOT / "scripts/rank_checkpoints.py"), *cks, "--duration", "0.3", "--variants", "2",
                      "--threads", "1", "--out", "rank.md"], tmp_path)
    rows = res["ranking"]
    assert sorted(r["checkpoint"] for r in rows) == sorted(cks) and len(res["variant_info"]) == 2
    assert [r["score_mm"] for r in rows] == sorted(r["score_mm"] for r in rows)
    for r in rows:
        assert r["score_mm"] == pytest.approx(sum(map(max, r["max_mm"])) / 2) and r["score_mm"] > 0.01
    task = get_task("semicircle")
    data = load_dataset(tmp_path / "data" / "semicircle_v3_s2_d0.3.pt", task="semicircle")
    model, _ = load_checkpoint(cks[1])
    wr = node_wrench(data["wrench"][2], task.wrench_nodes, task.modeled)
    pos, wk = from_rest(data["positions"][2], wr, model.config.eta)
    slot = interest_slots(task, task.base_scene())[0]
    pred = free_running(model, pos, wk, model.config.eta)[:, slot].double()
    want = axis_errors(pred, pos[model.config.eta + 1:, slot].double(), data["meta"]["rod_length"])
    got = next(r for r in rows if r["checkpoint"] == cks[1])["max_mm"][1]
    assert got == pytest.approx([want[ax]["max_mm"] for ax in "xyz"], rel=1e-4, abs=1e-6)
    assert "| 1 | " in (tmp_path / "rank.md").read_text()
    from cmlearn.surrogate import save_checkpoint
    _, meta = load_checkpoint(cks[1])  # semicircle_fast.pt, as if selected on seed-1 fresh variants
    save_checkpoint(tmp_path / "val1.pt", model, {**meta, "args": {**meta["args"], "val_fresh": 2, "val_seed": 1}})
    for args, msg in (([*cks, "--seed", "0"], "--seed 0 is no fresh seed for"),
                      ([*cks, str(ROOT / "checkpoints" / "ellipse.pt")], "all must be of one task"),
                      ([cks[1], "val1.pt", "--seed", "1"],
                       "--seed 1 is no fresh seed for val1.pt: it drew the validation variants that selected it"),
                      ([*cks, "--seed", "1"], "semicircle.pt: it drew the variants that selected its blend")):
        script_fails([str(ROOT / "scripts/rank_checkpoints.py"), *args], tmp_path, msg)


def test_report_node_recursion_splits_the_free_running_error(tmp_path):
    """One-step, the node of interest alone on its own predictions, free-running: each row the evaluation
    functions' errors; a task with its own evaluation is refused."""
    from dataclasses import replace

    from cmlearn.data import get_task, scene_rollout
    from cmlearn.data.windows import node_wrench
    from cmlearn.eval.metrics import axis_errors
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.evaluate import interest_slots, node_recursive
    ck = str(ROOT / "checkpoints" / "semicircle_fast.pt")
    res = run_script([str(ROOT / "scripts/report_node_recursion.py"), ck, "--duration", "0.3", "--out", "nr.md"],
                     tmp_path)
    seen, held = res[ck]
    assert seen["case"] == "semicircle (last 40 %)" and held["case"] == "semicircle_heldout" and seen["node"] == 50
    for row in (seen, held):
        assert set(row) >= {"one_step", "node_alone", "free_running", "chord_error_mm", "lgvi_chord_change_mm"}
    assert seen["node_alone"]["y"]["max_mm"] > seen["one_step"]["y"]["max_mm"] > 0.01
    task, (model, _) = get_task("semicircle"), load_checkpoint(ck)
    p, w, _ = scene_rollout(task, replace(task.base_scene(), duration=0.3))
    slot, start = interest_slots(task, task.base_scene())[0], int(round(0.6 * 30))
    pred = node_recursive(model, p, node_wrench(w.float(), task.wrench_nodes, task.modeled), start, slot)
    want = axis_errors(pred.double(), p[start + 1:, slot].double(), task.base_scene().rod.length)
    assert seen["node_alone"]["y"]["max_mm"] == pytest.approx(want["y"]["max_mm"], rel=1e-4)
    table = (tmp_path / "nr.md").read_text()
    assert "semicircle (last 40 %) (node 51) |" in table and "semicircle_heldout (node 51) |" in table
    script_fails([str(ROOT / "scripts/report_node_recursion.py"), str(ROOT / "checkpoints" / "magnetic_rod.pt")],
                 tmp_path, "has its own evaluation")


def test_report_loop_swing_against_the_lgvi(tmp_path):
    """Node 30's swing on the loops from rest: the LGVI's figures are the physics' own, the shipped (anchored)
    loop model holds the circle and the same weights without the anchor do not, a window past the run is
    refused."""
    from dataclasses import replace

    from cmlearn.data import get_task, scene_rollout
    from cmlearn.models import NodeLSTMSurrogate
    from cmlearn.surrogate import load_checkpoint, save_checkpoint
    shipped = ROOT / "checkpoints" / "ellipse.pt"
    model, meta = load_checkpoint(shipped)
    assert model.config.rest_anchor
    free = NodeLSTMSurrogate(replace(model.config, rest_anchor=False, rest_shape=None))
    free.load_state_dict(model.state_dict())
    save_checkpoint(tmp_path / "unanchored.pt", free, meta)
    res = run_script([str(ROOT / "scripts/report_loop_swing.py"), str(shipped), str(tmp_path / "unanchored.pt"),
                      "--variants", "2", "--duration", "2", "--after", "0.5", "--out", "ls.md"], tmp_path)
    drift = res["circle_drift_mm"]
    assert drift["ellipse.pt"] == 0.0 and drift["unanchored.pt"] > 1.0
    assert [r["loop"] for r in res["loops"]] == ["printed, h/w 3.00", "training, h/w 1.41",
                                                 "held out (ellipse_horizontal)"]
    task = get_task("ellipse")
    p, _, _ = scene_rollout(task, replace(task.base_scene(), duration=2.0))
    y = p[51:, list(task.tracked).index(29), 1].float().double() * 1e3  # after 0.5 s, from frame 1
    lgvi = res["loops"][0]["lgvi"]
    assert lgvi["min_mm"] == pytest.approx(float(y.min()), abs=1e-4)
    assert lgvi["mean_mm"] == pytest.approx(float(y.mean()), abs=1e-4) and lgvi["max_mm"] - lgvi["min_mm"] > 50
    for r in res["loops"]:
        for name in ("ellipse.pt", "unanchored.pt"):
            assert r[name]["err_max_mm"] >= abs(r[name]["mean_mm"] - r["lgvi"]["mean_mm"]) - 1e-6
    assert "| printed, h/w 3.00 |" in (tmp_path / "ls.md").read_text()
    script_fails([str(ROOT / "scripts/report_loop_swing.py"), "--variants", "2", "--duration", "2", "--after", "5"],
                 tmp_path, "leaves nothing")


def test_bench_surrogate_program_quick(tmp_path):
    """The current program form of the mirrored Simulation III step, the five it replaced and the rollout's carried
    step (ahead of time, through the JIT wrapper, with Sleef's exp) compile and equal the eager step to round-off; the
    timings are there (not compared: a shared CI machine)."""
    res = run_script([str(ROOT / "scripts/bench/surrogate_program.py"), "--quick",
                      "--checkpoint", str(ROOT / "checkpoints/semicircle.pt")], tmp_path)
    (images, fig), = res["images"].items()
    assert images == "1" and fig["axes"] == [2, 0] and res["gemm_templates"] is False
    assert min(fig["current_us"], fig["torch_us"], fig["current_wrapped_us"], fig["input_product_first_us"],
               fig["current_jit_us"], fig["carried_us"], fig["carried_jit_us"], fig["current_sleef_exp_us"],
               fig["carried_sleef_exp_us"]) > 0
    assert len(fig["max_abs_vs_eager_m"]) == 9 and max(fig["max_abs_vs_eager_m"].values()) < 1e-7


def test_training_fit_report_splits_windows_by_what_was_trained_on(tmp_path):
    """Each group's figures are those of the windows' free-running rollouts: the largest of the training group
    is the largest of the windows rolled out one by one; a task with its own evaluation is refused."""
    from cmlearn.data import get_task, load_dataset
    from cmlearn.data.windows import node_wrench
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.evaluate import free_running, interest_slots
    ck = str(ROOT / "checkpoints" / "semicircle_fast.pt")
    res = run_script([str(ROOT / "scripts/report_training_fit.py"), ck, "--variants", "3", "--duration", "0.3",
                      "--starts", "3", "10", "--steps", "6", "--data-dir", str(tmp_path), "--out", "fit.md"],
                     tmp_path)[ck]
    # 31 frames, the cut at 18: variants 0 (to the cut) and 1 train, variant 2 validates
    assert {k: v["windows"] for k, v in res.items()} == {"trained on": 4, "validation": 2, "printed, test part": 1}
    task, (model, _) = get_task("semicircle"), load_checkpoint(ck)
    data = load_dataset(next(tmp_path.glob("semicircle_v3_*.pt")))
    slot = interest_slots(task, task.base_scene())[0]

    def largest(v, s, steps):
        p = data["positions"][v]
        pred = free_running(model, p, node_wrench(data["wrench"][v], task.wrench_nodes, task.modeled), s)
        return float((pred[:steps, slot].double() - p[s + 1:s + 1 + steps, slot].double()).abs().max()) * 1e3

    train = [largest(v, s, 6) for v in (0, 1) for s in (3, 10)]
    assert res["trained on"]["max_mm"] == pytest.approx(max(train), rel=1e-4)
    assert res["trained on"]["mean_mm"] == pytest.approx(sum(train) / 4, rel=1e-4) and max(train) > 0.01
    assert res["printed, test part"]["max_mm"] == pytest.approx(largest(0, 18, 12), rel=1e-4)
    assert "| trained on | 4 |" in (tmp_path / "fit.md").read_text()
    script_fails([str(ROOT / "scripts/report_training_fit.py"), str(ROOT / "checkpoints" / "magnetic_rod.pt")],
                 tmp_path, "has its own evaluation")
    script_fails([str(ROOT / "scripts/report_training_fit.py"), ck, "--variants", "1"], tmp_path, "--variants")


def test_refine_surrogate_lowers_the_rollout_loss_on_its_fixed_windows(tmp_path):
    """Full-batch L-BFGS: the written model's rollout loss on the run's windows is the best one the run reports,
    below the starting model's; ``--printed-weight`` and ``--node-weight`` weigh the printed windows and the node of
    interest in that mean; the checkpoint records where it came from; other data, a task with its own evaluation and bad counts are refused."""
    from torch.utils.data import default_collate

    from cmlearn.data import load_dataset
    from cmlearn.data.windows import RolloutWindows
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.training import SurrogateDataModule, SurrogateModule
    ck = str(ROOT / "checkpoints" / "semicircle_fast.pt")
    args = [str(ROOT / "scripts/refine_surrogate.py"), ck, "--variants", "3", "--duration", "0.3", "--data-dir",
            str(tmp_path), "--windows", "30", "--horizon", "4", "--chunk", "8", "--max-evals", "4"]
    res = run_script(args + ["--keep-scales", "--out", "ref.pt"], tmp_path)
    assert res["loss_best"] < 0.9 * res["loss_start"]
    assert res["evaluations"] == 4 and res["stop"] == "--max-evals 4 reached"
    model, meta = load_checkpoint(tmp_path / "ref.pt")
    start, _ = load_checkpoint(ck)
    assert meta["init_from"]["sha256"] == hashlib.sha256(Path(ck).read_bytes()).hexdigest()
    assert meta["refine"]["windows"] == 30 and meta["command"].startswith("python scripts/refine_surrogate.py")
    assert meta["metrics"] == res["metrics"] and meta["check"]["max_err_mm"] > 0
    data = load_dataset(next(tmp_path.glob("semicircle_v3_*.pt")))
    dm = SurrogateDataModule(data, eta=2, horizon=4)
    train = dm.ranges["train"]
    ds = RolloutWindows(dm.positions, dm.wrench, train, 2, 4)
    printed = len(RolloutWindows(dm.positions, dm.wrench, train[:1], 2, 4))
    idx = load_script("refine_surrogate").fixed_windows(ds, printed, 30, 1)
    assert len(set(idx)) == 30 and idx[:printed] == list(range(printed)) and min(idx[printed:]) >= printed
    batch = default_collate([ds[i] for i in idx])

    def loss(m):
        with torch.no_grad():
            return float(SurrogateModule(m.train(), horizon=4).rollout_loss(batch, 4)[0])
    assert loss(model) == pytest.approx(res["loss_best"], rel=1e-4)
    assert loss(start) == pytest.approx(res["loss_start"], rel=1e-4)
    # --printed-weight 5: each printed window counts five times in the mean; --node-weight 3: node 51 (the
    # headline, index 50) three times among the modelled nodes
    weighted = run_script(args[:-1] + ["1", "--printed-weight", "5", "--node-weight", "3", "--keep-scales",
                                       "--out", "w.pt"], tmp_path)
    w = torch.ones(len(start.config.modeled))
    w[list(start.config.modeled).index(list(meta["tracked"]).index(50))] = 3.0

    def node_loss(part):
        b = [t[part] for t in batch]
        with torch.no_grad():
            pred = SurrogateModule(start.train(), horizon=4).rollout_loss(b, 4)[1]
        e2 = ((pred[:, :, start.idx_modeled] - b[1][:, :4, start.idx_modeled]) / start.a_scale.mean()).pow(2)
        return float((e2.mean((0, 1, 3)) * w).sum() / w.sum())
    n = 30 - printed
    expect = (5 * printed * node_loss(slice(None, printed)) + n * node_loss(slice(printed, None))) / (5 * printed + n)
    assert weighted["loss_start"] == pytest.approx(expect, rel=1e-4)
    assert abs(weighted["loss_start"] - res["loss_start"]) > 1e-3 * res["loss_start"]
    refine = load_checkpoint(tmp_path / "w.pt")[1]["refine"]
    assert refine["printed_weight"] == 5 and refine["node_weight"] == 3
    for flag in ("--printed-weight", "--node-weight"):
        script_fails(args + [flag, "0", "--out", "x.pt"], tmp_path, flag)
    script_fails(args + ["--out", "x.pt"], tmp_path, "--variants/--seed")
    script_fails([str(ROOT / "scripts/refine_surrogate.py"), str(ROOT / "checkpoints" / "magnetic_rod.pt"),
                  "--out", "x.pt"], tmp_path, "position tasks only")
    script_fails(args + ["--windows", "0", "--out", "x.pt"], tmp_path, "--windows")


def test_refine_surrogate_keeps_the_weights_the_fresh_variants_score_best(tmp_path):
    """``--val-seed``: the fresh variants are scored at the first evaluation, every ``--val-every``-th and the last;
    the written model is the scored one with the lowest score, which ``fresh_score`` reproduces on it (and the
    starting model the first score); the data's own seed and a device that does not exist are refused."""
    from cmlearn.data import cached_dataset, get_task
    from cmlearn.surrogate import load_checkpoint
    from cmlearn.surrogate.evaluate import fresh_errors, fresh_score
    ck = str(ROOT / "checkpoints" / "semicircle_fast.pt")
    args = [str(ROOT / "scripts/refine_surrogate.py"), ck, "--variants", "3", "--duration", "0.3", "--data-dir",
            str(tmp_path), "--windows", "24", "--horizon", "4", "--chunk", "12", "--keep-scales",
            "--val-variants", "2", "--val-every", "2"]
    res = run_script(args + ["--max-evals", "5", "--val-seed", "2", "--device", "cpu", "--out", "v.pt"], tmp_path)
    sel = res["select"]
    assert [s[0] for s in sel["scored"]] == [1, 2, 4, 5] and res["evaluations"] == 5
    n, loss, score = min(sel["scored"], key=lambda s: s[2])
    assert res["kept_evaluation"] == n and res["loss_best"] == loss and sel["score_best_mm"] == score
    model, meta = load_checkpoint(tmp_path / "v.pt")
    assert meta["refine"]["select"] == sel and meta["refine"]["device"] == "cpu"
    task = get_task(meta["task"])
    val = cached_dataset(task, 3, 2, tmp_path, 0.3)
    assert fresh_score(fresh_errors(model.eval(), task, val)) == pytest.approx(score, rel=1e-4)
    start = load_checkpoint(ck)[0].eval()
    assert fresh_score(fresh_errors(start, task, val)) == pytest.approx(sel["scored"][0][2], rel=1e-4)
    assert len({s[2] for s in sel["scored"]}) > 1  # the weights moved between the scorings
    script_fails(args + ["--val-seed", "0", "--out", "x.pt"], tmp_path, "--val-seed 0")
    script_fails(args + ["--device", "nonsense", "--out", "x.pt"], tmp_path, "--device")


def test_blend_checkpoints_lerps_the_weights_and_keeps_the_scales(tmp_path):
    """``--alpha 0.25``: each parameter is 0.75 A + 0.25 B, the scales A's; the fresh scores of A, B and the blend
    are those ``fresh_score`` gives them; the metadata names both parents; another task, other scales and an alpha
    outside [0, 1] are refused. A B with a mixing head and a ring A lacks blends with A widened to it; B narrower is
    refused."""
    import copy
    from dataclasses import replace

    from cmlearn.data import cached_dataset, get_task
    from cmlearn.surrogate import load_checkpoint, save_checkpoint
    from cmlearn.surrogate.evaluate import fresh_errors, fresh_score
    ck = ROOT / "checkpoints" / "semicircle_fast.pt"
    a_model, meta = load_checkpoint(ck)
    b_model = load_checkpoint(ck)[0]
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in b_model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g) * p.abs().mean())
    save_checkpoint(tmp_path / "b.pt", b_model, meta)
    args = [str(ROOT / "scripts/blend_checkpoints.py"), str(ck), "b.pt", "--variants", "3", "--duration", "0.3",
            "--data-dir", str(tmp_path)]
    res = run_script(args + ["--alpha", "0.25", "--val-seed", "2", "--val-variants", "2", "--out", "m.pt"], tmp_path)
    model, m_meta = load_checkpoint(tmp_path / "m.pt")
    params = dict(model.named_parameters())
    for (k, pa), pb in zip(a_model.named_parameters(), b_model.parameters()):
        assert torch.allclose(params[k], 0.75 * pa + 0.25 * pb, rtol=1e-6, atol=1e-7), k
        assert not torch.allclose(params[k], pa)
    for (k, ba), bm in zip(a_model.named_buffers(), model.buffers()):
        assert torch.equal(ba, bm), k
    blend = m_meta["blend"]
    assert blend["alpha"] == 0.25 and m_meta["metrics"] == res["metrics"]
    assert blend["start"]["sha256"] == hashlib.sha256(ck.read_bytes()).hexdigest() == m_meta["init_from"]["sha256"]
    assert blend["end"]["sha256"] == hashlib.sha256((tmp_path / "b.pt").read_bytes()).hexdigest()
    assert m_meta["command"].startswith("python scripts/blend_checkpoints.py") and m_meta["check"]["max_err_mm"] > 0
    task = get_task(meta["task"])
    val = cached_dataset(task, 3, 2, tmp_path, 0.3)
    for key, m in (("start", a_model), ("end", b_model), ("blend", model)):
        assert blend["fresh"][f"score_{key}_mm"] == pytest.approx(fresh_score(fresh_errors(m.eval(), task, val)),
                                                                  rel=1e-6)
    with torch.no_grad():
        b_model.a_scale.mul_(1.5)
    save_checkpoint(tmp_path / "c.pt", b_model, meta)
    script_fails(args[:2] + ["c.pt", "--alpha", "0.5", "--out", "x.pt"], tmp_path, "buffer 'a_scale'")
    script_fails(args[:2] + [str(ROOT / "checkpoints" / "magnetic_rod.pt"), "--alpha", "0.5", "--out", "x.pt"],
                 tmp_path, "task 'magnetic_rod'")
    script_fails(args + ["--alpha", "1.5", "--out", "x.pt"], tmp_path, "--alpha")
    # B fine-tuned with a mixing head and a ring A lacks: A is first widened as the fine-tuning started (the ring's
    # offset scales B's, from its data), the blend is B's kind
    wide = a_model.widened_to(replace(a_model.config, mix=1, mix_width=4).with_stencil(2))
    w_model = copy.deepcopy(wide)
    with torch.no_grad():
        w_model.rel_scale[:, 6:] = 1.7 * a_model.rel_scale
        for p in w_model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g) * p.abs().mean())
    w_meta = {**meta, "architecture": w_model.config.to_dict(),
              "n_parameters": sum(p.numel() for p in w_model.parameters())}
    save_checkpoint(tmp_path / "w.pt", w_model, w_meta)
    run_script(args[:2] + ["w.pt", *args[3:], "--alpha", "0.5", "--out", "mw.pt"], tmp_path)
    model, mw_meta = load_checkpoint(tmp_path / "mw.pt")
    assert (model.config.mix, model.config.mix_width, model.config.stencil) == (1, 4, 2)
    assert torch.equal(model.rel_scale, w_model.rel_scale)
    assert mw_meta["architecture"] == load_checkpoint(tmp_path / "w.pt")[1]["architecture"]
    params = dict(model.named_parameters())
    for (k, pa), pb in zip(wide.named_parameters(), w_model.parameters()):
        assert torch.allclose(params[k], 0.5 * pa + 0.5 * pb, rtol=1e-6, atol=1e-7), k
    script_fails(args[:1] + ["w.pt", str(ck), *args[3:], "--alpha", "0.5", "--out", "x.pt"], tmp_path,
                 "nor a widening of it")  # the other way round: B narrower than A


def _loop_rest(n: int) -> torch.Tensor:
    """A circle of ``n`` nodes whose ends meet at the origin, symmetric under x -> -x with the nodes reversed."""
    theta = torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)
    return torch.stack([0.2 * torch.sin(theta), -0.2 * (1 - torch.cos(theta)), torch.zeros(n, dtype=torch.float64)], -1)


def _arch_rest(n: int) -> torch.Tensor:
    """A semicircle of ``n`` nodes from (0, 0) to (0.2, 0) in the xy-plane, symmetric under x -> 0.2 - x with the
    nodes reversed and under z -> -z."""
    phi = torch.linspace(0, math.pi, n, dtype=torch.float64)
    return torch.stack([0.1 * (1 - torch.cos(phi)), 0.1 * torch.sin(phi), torch.zeros(n, dtype=torch.float64)], -1)


@pytest.mark.parametrize("conservative", [False, True])
@pytest.mark.parametrize("scene", ["loop", "arch"])
def test_position_only_step_is_reversible_volume_preserving_and_symmetric(conservative, scene):
    """The study's step (scripts/study_position_only_step.py) has what its docstring claims for any weights: run back
    from its last two frames (the external force played backwards) it retraces them, its map of (previous, current)
    frames has Jacobian determinant 1, it is zero at the rest shape and it commutes with every reflection of its
    group: the loop's x -> -x with the nodes reversed; the arch's x -> 0.2 - x with the nodes reversed, z -> -z and
    both at once, with a force on its middle node."""
    mod = load_script("study_position_only_step")
    torch.manual_seed(0)
    n = 9
    if scene == "loop":
        rest, kw = _loop_rest(n), {}
    else:
        rest, kw = _arch_rest(n), {"mirrors": {"x": "reversed", "z": "same"}, "force_slot": 4}
    model = mod.PositionOnlyStep(rest, r=2, hidden=16, a_scale=1e-2, conservative=conservative, **kw).double()
    assert len(model.signs) == (2 if scene == "loop" else 4)
    if scene == "arch":
        with torch.no_grad():
            model.G.normal_()
    inner = torch.zeros(1, n, 1, dtype=torch.float64)
    inner[:, 1:-1] = 1.0
    p0 = rest[None] + 0.02 * torch.randn(1, n, 3, dtype=torch.float64) * inner
    p1 = p0 + 0.002 * torch.randn(1, n, 3, dtype=torch.float64) * inner
    force = 0.05 * torch.randn(1, 60, 3, dtype=torch.float64) if scene == "arch" else None
    with torch.no_grad():
        fwd = model.rollout(p0, p1, 60, force)
        back = model.rollout(fwd[:, -1], fwd[:, -2], 60, None if force is None else force.flip(1))
        assert (fwd[:, -1] - p1).abs().max() > 1e-3  # it moved
        assert torch.allclose(back[:, -2], p1, atol=1e-11) and torch.allclose(back[:, -1], p0, atol=1e-11)
        assert model.accel(rest[None]).abs().max() < 1e-15
        a = model.accel(p1)
        assert a.abs().max() > 1e-6
        for g in range(1, len(model.signs)):
            assert torch.allclose(model.accel(model.reflect(p1, g)), model.reflect_accel(a, g), atol=1e-14)
            if force is not None:
                f = force[:, 0]
                assert torch.allclose(model.forcing(f * model.signs[g]), model.reflect_accel(model.forcing(f), g),
                                      atol=1e-14)
                assert model.forcing(f).abs().max() > 1e-4

    def step(x):  # (previous, current) modelled coordinates -> (current, next)
        prev, cur = rest[None].clone(), rest[None].clone()
        prev[:, 1:-1], cur[:, 1:-1] = x[:21].reshape(1, 7, 3), x[21:].reshape(1, 7, 3)
        nxt = model.rollout(prev, cur, 1, None if force is None else force[:, :1])[:, 0]
        return torch.cat([cur[:, 1:-1].reshape(-1), nxt[:, 1:-1].reshape(-1)])

    x = torch.cat([p0[0, 1:-1].reshape(-1), p1[0, 1:-1].reshape(-1)])
    assert abs(float(torch.linalg.det(torch.autograd.functional.jacobian(step, x))) - 1.0) < 1e-12


def test_position_only_step_forces_at_frames():
    """The study's force at a frame is the mean of the interval forces either side (none before the first), so a
    force switched on at a frame of a body at rest moves it by half of it in the first step, as the exact motion
    under a constant force does."""
    mod = load_script("study_position_only_step")
    w = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    assert torch.equal(mod.centred(w), torch.tensor([[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
    rest = _arch_rest(9).float()
    model = mod.PositionOnlyStep(rest, r=2, hidden=16, mirrors={"x": "reversed"}, force_slot=4)
    with torch.no_grad():
        model.G.normal_()
        first = model.from_rest(rest[None], 1, mod.centred(w)[None])[0, 0]
        assert torch.allclose(first[1:-1] - rest[1:-1], 0.5 * model.forcing(w[None, 0])[0], atol=1e-6)
        assert (first - rest).abs().max() > 1e-4
    with pytest.raises(ValueError, match="force_slot 3 is moved"):
        mod.PositionOnlyStep(rest, mirrors={"x": "reversed"}, force_slot=3)


def test_position_only_latent_step_is_reversible_volume_preserving_and_observed():
    """The study's step with latent coordinates (``--latent``) keeps what the position-only step has for any weights
    (reversible with the force played backwards, Jacobian determinant 1 over positions and latent coordinates, zero
    second difference at rest), and :meth:`start` driven by the positions of the step's own run from rest recovers that run's
    latent state, so a rollout from it continues the run."""
    mod = load_script("study_position_only_step")
    torch.manual_seed(3)
    n, M = 9, 2
    rest = _arch_rest(n)
    model = mod.LatentStep(rest, M, r=2, hidden=16, a_scale=1e-2, force_slot=4).double()
    inner = torch.zeros(1, n, 1, dtype=torch.float64)
    inner[:, 1:-1] = 1.0
    x0 = model.state(rest[None]) + 0.02 * torch.randn(1, n, 3 + M, dtype=torch.float64) * inner
    x1 = x0 + 0.002 * torch.randn(1, n, 3 + M, dtype=torch.float64) * inner
    force = 0.05 * torch.randn(1, 40, 3, dtype=torch.float64)
    with torch.no_grad():
        fwd = model.rollout(x0, x1, 40, force)
        back = model.rollout(fwd[:, -1], fwd[:, -2], 40, force.flip(1))
        assert (fwd[:, -1, :, 3:] - x1[..., 3:]).abs().max() > 1e-3  # the latent coordinates moved
        assert torch.allclose(back[:, -2], x1, atol=1e-11) and torch.allclose(back[:, -1], x0, atol=1e-11)
        assert model.accel(model.state(rest[None])).abs().max() < 1e-15
        run = model.from_rest(rest[None], 30, force[:, :30])  # positions only
        full = model.rollout(*model.start(rest[None, None].repeat(1, 2, 1, 1)), 30, force[:, :30])
        assert torch.allclose(full[..., :3], run, atol=1e-12)
        frames = torch.cat([rest[None, None], run], 1)
        prev, cur = model.start(frames[:, :21], force[:, :20])
        assert torch.allclose(cur, full[:, 19], atol=1e-11) and torch.allclose(prev, full[:, 18], atol=1e-11)
        assert torch.allclose(model.rollout_frames(prev, cur, 10, force[:, 20:30]), run[:, 20:], atol=1e-11)
    d = 2 * 7 * (3 + M)

    def step(x):
        prev, cur = model.state(rest[None]), model.state(rest[None])
        prev[:, 1:-1], cur[:, 1:-1] = x[:d // 2].reshape(1, 7, -1), x[d // 2:].reshape(1, 7, -1)
        nxt = model.rollout(prev, cur, 1, force[:, :1])[:, 0]
        return torch.cat([cur[:, 1:-1].reshape(-1), nxt[:, 1:-1].reshape(-1)])

    x = torch.cat([x0[0, 1:-1].reshape(-1), x1[0, 1:-1].reshape(-1)])
    assert abs(float(torch.linalg.det(torch.autograd.functional.jacobian(step, x))) - 1.0) < 1e-12


def test_position_only_linear_step_recovers_a_linear_system():
    """The study's least-squares linear step (``--linear``) recovers the stiffness and force maps of trajectories made
    by a known linear step, and the study reports a rollout that leaves the finite numbers by its step."""
    mod = load_script("study_position_only_step")
    torch.manual_seed(2)
    n, K = 9, 7
    rest = _arch_rest(n).float()
    B = torch.randn(3 * K, 3 * K, dtype=torch.float64)
    stiff, G = -1e-3 * (B @ B.T / (3 * K) + torch.eye(3 * K, dtype=torch.float64)), 1e-3 * torch.randn(3, 3 * K)
    force = 0.1 * torch.randn(3, 80, 3, dtype=torch.float64)
    P = rest.double()[None, None].repeat(3, 81, 1, 1)
    P[:, 1, 1:-1] += 0.01 * torch.randn(3, K, 3, dtype=torch.float64)
    P[:, 0] = P[:, 1]
    for t in range(1, 80):
        u = (P[:, t] - rest.double())[:, 1:-1].flatten(1)
        P[:, t + 1, 1:-1] = 2 * P[:, t, 1:-1] - P[:, t - 1, 1:-1] + (u @ stiff + force[:, t] @ G.double()).view(3, K, 3)
    lin = mod.LinearStep(rest, P, force, [(v, 0, 80) for v in range(3)], force_slot=4)
    assert torch.allclose(lin.K.double(), stiff, atol=1e-6) and torch.allclose(lin.Gf.double(), G.double(), atol=1e-6)
    blown = torch.ones(2, 5, n, 3)
    blown[1, 3:] = float("inf")
    assert mod.node_errors(blown, blown, 4, "y") == {"diverged_at_step": 4}
    assert mod.fresh_errors(blown, blown, 4, "y") == {"diverged_at_step": 4}


@pytest.mark.parametrize("conservative", [False, True])
def test_position_only_step_force_is_a_gradient_only_when_conservative(conservative):
    """With ``conservative`` the study's second difference is minus a gradient: its Jacobian in the modelled
    positions is symmetric; without, it is not."""
    mod = load_script("study_position_only_step")
    torch.manual_seed(1)
    n = 9
    rest = _loop_rest(n)
    model = mod.PositionOnlyStep(rest, r=2, hidden=16, a_scale=1e-2, conservative=conservative).double().eval()
    p = rest[None].clone()
    p[:, 1:-1] += 0.02 * torch.randn(1, n - 2, 3, dtype=torch.float64)

    def accel(x):
        q = p.clone()
        q[:, 1:-1] = x.reshape(1, n - 2, 3)
        return model.accel(q).reshape(-1)

    J = torch.autograd.functional.jacobian(accel, p[0, 1:-1].reshape(-1))
    asym = float((J - J.t()).abs().max() / J.abs().max())
    assert asym < 1e-10 if conservative else asym > 1e-3
    other = mod.PositionOnlyStep(rest, r=2, hidden=16, a_scale=1e-2, conservative=conservative).double().eval()
    mean = mod.EnsembleStep([model, other])  # the mean step: conservative where its members are
    assert torch.allclose(mean.accel(p), 0.5 * (model.accel(p) + other.accel(p)), atol=1e-15)
    if conservative:
        Jm = torch.autograd.functional.jacobian(
            lambda x: mean.accel(torch.cat([p[:, :1], x.reshape(1, n - 2, 3), p[:, -1:]], 1)).reshape(-1),
            p[0, 1:-1].reshape(-1))
        assert float((Jm - Jm.t()).abs().max() / Jm.abs().max()) < 1e-10


def test_report_hybrid_tolerance_eager(tmp_path):
    """The hybrid's solve tolerance against its run time: the reference tolerance deviates by nothing from itself, a
    looser one needs fewer Levenberg-Marquardt iterations (1e-4 over the first 10 frames: 1.90 -> 0.90 a solve) and
    moves the magnets far less than the hybrid errs against the LGVI (3.4e-4 deg; 0.008 deg, the sum of the six
    means); the table is written."""
    out = tmp_path / "tol.md"
    res = run_script([str(ROOT / "scripts/report_hybrid_tolerance.py"), "--eager", "--duration", "0.2", "--tols",
                      "1e-10", "1e-4", "--data-dir", str(tmp_path), "--out", str(out)], tmp_path)
    ref, loose = res["rows"]
    assert res["frames"] == 10 and not res["compiled"] and ref["deviation_max_deg"] == 0.0
    assert loose["mean_iterations"] < ref["mean_iterations"]
    assert 0 < loose["deviation_max_deg"] < 0.05 and ref["lgvi_sum_mean_deg"] > 0
    assert loose["lgvi_sum_mean_deg"] == pytest.approx(ref["lgvi_sum_mean_deg"], abs=0.01)
    assert "| 0.0001 |" in out.read_text() and "--eager --duration 0.2" in out.read_text()
    script_fails([str(ROOT / "scripts/report_hybrid_tolerance.py"), "--tols", "0"], tmp_path,
                 "argument --tols: must be > 0, got '0'")


def test_every_bench_ends_with_the_shared_json_line():
    """The benches' last line goes through :func:`cmlearn.eval.timing.json_line` (non-finite floats as strings), not
    ``json.dumps``, which writes ``NaN`` / ``Infinity``: not JSON."""
    for path in sorted((ROOT / "scripts" / "bench").glob("*.py")):
        src = path.read_text()
        assert "json_line(" in src and "json.dumps(" not in src, path.name


def test_bench_dataset_last_line_is_strict_json_when_a_run_is_not_finite(monkeypatch, capsys):
    """A non-finite figure (here both runs' positions NaN, so their difference) is written as the string "nan"."""
    mod = load_script("bench/dataset")

    def frames(sim, state, n_frames, every, compiled):
        p = state.p
        return torch.full((*p.shape[:-2], n_frames, *p.shape[-2:]), math.nan, dtype=p.dtype), 0.5, 0.0
    monkeypatch.setattr(mod, "lgvi_frames", frames)
    mod.main(["--quick", "--task", "ellipse", "--variants", "2"])
    line = capsys.readouterr().out.strip().splitlines()[-1]
    res = json.loads(line, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert res["max_diff_m"] == "nan" and res["speedup_compiled"] == 1.0


@pytest.mark.parametrize("script, argv, msg", [
    ("bench/dataset", ["--quick", "--task", "ellipse", "--variants", "2", "--duration", "0.001"],
     "--duration: duration must be a time of at least one surrogate step"),
    ("bench/quasistatic", ["--quick", "--task", "magnetic_rod_planar"],
     "--hybrid: no checkpoints/magnetic_rod_planar_quasistatic.pt"),
    ("bench/quasistatic", ["--quick", "--hybrid", "missing.pt"], "argument --hybrid: no such file"),
    ("bench/surrogate", ["--quick", "--task", "rod"], "argument --task: invalid choice: 'rod'"),
    ("bench/surrogate", ["--quick", "--checkpoint", "missing.pt"], "argument --checkpoint: no such file"),
    ("bench/surrogate", ["--quick", "--scene", "bogus"],
     "--scene: 'bogus' is not a scene of task 'semicircle'; choose from semicircle, semicircle_heldout"),
    ("report_node_density", ["--variants", "1"], "argument --variants: must be >= 2, got '1'"),
])
def test_bench_and_report_arguments_that_cannot_run_are_usage_errors(script, argv, msg, monkeypatch, capsys, tmp_path):
    """Arguments a run cannot use stop it with argparse's usage error naming the flag, before any work (not a
    traceback from inside it: a division by a zero simulated time, a checkpoint looked up by a flag the script lacks,
    an unknown task's KeyError)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        load_script(script).main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and msg in err, err[-500:]


def test_agent_scripts_refuse_numbers_that_failed_late_and_options_given_for_nothing(capsys):
    """eval_controllers took --threads 0, --seed -1 and --unseen-maps 0 and failed once their turn came (a
    disturbance probability of 2 after both undisturbed settings' episodes), and --agent-waypoints -5 as -1;
    train_agent's --quick overrode the budget options given beside it, and --ship-best without --ship did nothing."""
    base = ["--controllers", "attractor"]
    for extra, msg in ((["--threads", "0"], "argument --threads: must be >= 1, got '0'"),
                       (["--seed", "-1"], "argument --seed: must be >= 0, got '-1'"),
                       (["--unseen-maps", "0"], "argument --unseen-maps: must be >= 1, got '0'"),
                       (["--agent-waypoints", "-5"], "argument --agent-waypoints: must be >= -1, got '-5'"),
                       (["--disturbance-min", "0"], "argument --disturbance-min: must be > 0, got '0'"),
                       (["--disturbance-probability", "2"], "probability must be in [0, 1], got 2.0"),
                       (["--switch-distance", "0.01"], "release_distance=0.02 must be <= switch_distance=0.01")):
        parse_fails("eval_controllers", base + extra, msg, capsys)
    parse_fails("train_agent", ["--ship-best"], "--ship-best chooses the agent --ship copies, and no --ship", capsys)
    quick = load_script("train_agent").parse(["--quick", "--total-frames", "2048", "--max-steps", "40"])
    assert (quick.total_frames, quick.max_steps, quick.eval_episodes, quick.buffer_size) == (2048, 40, 2, 4096)



def test_report_agent_reads_the_metadata_beside_a_checkpoint_and_names_a_bad_file(tmp_path, capsys):
    """``--agent checkpoints/iqn_agent.pt`` (the checkpoint, not its .json) ended in a UnicodeDecodeError traceback."""
    report = load_script("report_agent")
    report.main(["--agent", str(ROOT / "checkpoints" / "iqn_agent.pt"), "--out", str(tmp_path / "rep")])
    assert "Training of `iqn_agent.pt`" in (tmp_path / "rep.md").read_text()
    (tmp_path / "bad.json").write_text("{bad")
    with pytest.raises(SystemExit, match=r"--agent: cannot read the agent's metadata .*bad.json' \(JSONDecodeError"):
        report.main(["--agent", str(tmp_path / "bad.json"), "--out", str(tmp_path / "rep2")])
    # --out is a prefix: x.v2 wrote x.png and x.md (with_suffix), so x.v3 overwrote it
    report.main(["--agent", str(ROOT / "checkpoints" / "iqn_agent.json"), "--out", str(tmp_path / "run.v2")])
    report.main(["--agent", str(ROOT / "checkpoints" / "iqn_agent.json"), "--out", str(tmp_path / "run.v3.md")])
    assert sorted(p.name for p in tmp_path.glob("run.*")) == ["run.v2.md", "run.v2.png", "run.v3.md", "run.v3.png"]
