"""Smoke runs of the Cosserat benchmark and the Figure II.13 report with tiny budgets (eager path):
they run, agree with the scipy peer, and end with one JSON line."""
from test_scripts import ROOT, run_script


def test_bench_cosserat_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/bench/cosserat.py"), "--quick", "--no-compile", "--batch", "8",
                      "--window", "0.05"], tmp_path)
    for key in ("single_warm_hz", "single_cold_hz", "batched_solves_per_s", "scipy_warm_hz", "speedup_vs_scipy_warm",
                "max_tip_diff_vs_scipy_m", "n_nodes", "dtype", "threads", "batch", "device"):
        assert key in res
    assert res["n_nodes"] == 13 and res["batch"] == 8 and res["compiled"] is False
    assert res["max_tip_diff_vs_scipy_m"] < 1e-6 and res["single_warm_hz"] > 0


def test_report_cosserat_timing_quick(tmp_path):
    res = run_script([str(ROOT / "scripts/report_cosserat_timing.py"), "--quick", "--no-compile", "--reps", "1",
                      "--threads", "2", "--out", "timing.md"], tmp_path)
    # the command that made it, whole (it left out --reps and --threads), and the threads it ran on
    assert "`scripts/report_cosserat_timing.py --quick --no-compile --reps 1 --threads 2`" in \
        (tmp_path / "timing.md").read_text() and "2 thread(s)" in (tmp_path / "timing.md").read_text()
    assert (tmp_path / "timing.md").exists() and (tmp_path / "timing.png").stat().st_size > 10_000
    assert not list(tmp_path.glob("*.tmp*"))  # atomic writes leave no temporaries
    assert "8.33-50 Hz" in (tmp_path / "timing.md").read_text()
    assert res["tip_error_pct_L"]["13"] < res["tip_error_pct_L"]["7"] and len(res["hz_13_nodes"]) == 3
