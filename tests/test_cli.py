"""The ``cmlearn`` command line (cmlearn.cli)."""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from cmlearn.cli import DEFAULT_SCENE, main
from forked_scripts import run_python

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


def _run(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return run_python(list(args), ROOT, env, timeout=120)


def test_help_and_light_import():
    r = _run("-m", "cmlearn", "--help")
    assert r.returncode == 0 and "simulate" in r.stdout and "scenes" in r.stdout
    r = _run("-c", "import sys, cmlearn; assert 'torch' not in sys.modules and 'matplotlib' not in sys.modules")
    assert r.returncode == 0, r.stderr


def test_scenes_lists_every_scene(capsys):
    from physics.scenes import SCENES

    assert main(["scenes"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == list(SCENES)
    assert all(len(line) < 140 for line in out)


def test_simulate_default_scene(tmp_path, capsys):
    import matplotlib
    out, backend = tmp_path / "sim", matplotlib.get_backend()
    matplotlib.use("svg")  # the caller's backend (a notebook's inline one), which the plots must leave alone
    try:
        assert main(["simulate", "--duration", "0.009", "--out", str(out)]) == 0
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(backend)
    text = capsys.readouterr().out
    for key in ("wall time", "real-time factor", "energy: relative drift", "Newton:", "position (mm)"):
        assert key in text
    assert sorted(p.name for p in out.iterdir()) == ["shapes.png", "summary.json", "tip_trajectory.png"]
    for name in ("shapes.png", "tip_trajectory.png"):
        assert (out / name).read_bytes()[:8] == PNG
    s = json.loads((out / "summary.json").read_text())
    assert s["scene"] == DEFAULT_SCENE and s["n_steps"] == 100 and s["dtype"] == "float64"
    assert s["energy"]["conserved"] is True and s["energy"]["relative_drift"] < 1e-3
    assert s["real_time_factor"] > 0 and s["newton"]["max_iterations"] >= 1
    assert s["frames"] == 101 and len(s["node"]["min_mm"]) == 3
    assert s["node"]["max_mm"][2] <= 60.55  # tip z in mm, never beyond the rod length


def test_simulate_driven_scene_float32(tmp_path, capsys):
    out = tmp_path / "circ"
    rc = main(["simulate", "--scene", "pdms_circular", "--duration", "0.0045", "--dtype", "float32",
               "--record-every", "10", "--out", str(out)])
    assert rc == 0
    assert "not conserved" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    assert s["dtype"] == "float32" and s["energy"]["conserved"] is False and s["frames"] == 6
    assert (out / "shapes.png").exists() and (out / "tip_trajectory.png").exists()


def test_unknown_scene_is_a_clear_error(tmp_path, capsys):
    rc = main(["simulate", "--scene", "nope", "--out", str(tmp_path / "x")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "unknown scene 'nope'" in err and DEFAULT_SCENE in err and "semicircle_heldout" in err
    assert not (tmp_path / "x").exists()
    r = _run("-m", "cmlearn", "simulate", "--scene", "nope")
    assert r.returncode != 0 and "valid scenes" in r.stderr


@pytest.mark.parametrize("args", [["simulate", "--duration", "-1"], ["simulate", "--record-every", "0"],
                                  ["simulate", "--dtype", "float16"], []])
def test_bad_arguments_exit_nonzero(args):
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2


@pytest.mark.parametrize("command", ["simulate", "compare"])
def test_an_unwritable_output_folder_is_refused_before_the_run(command, tmp_path, capsys):
    (tmp_path / "f").write_text("")
    with pytest.raises(SystemExit) as exc:
        main([command, "--out", str(tmp_path / "f" / "plots")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "argument --out: cannot write" in err and "is a file, not a folder" in err


def test_solver_failure_is_reported(tmp_path, capsys, monkeypatch):
    import cmlearn.cli as cli
    from physics.errors import SolverError

    def fail(*args, **kwargs):
        raise SolverError("non-finite state", step=3, time=3e-4, node=7)

    monkeypatch.setattr(cli, "run_scene", fail)
    assert main(["simulate", "--out", str(tmp_path / "f")]) == 1
    assert "solver failed: non-finite state (step=3" in capsys.readouterr().err
