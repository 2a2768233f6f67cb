"""``aqfg bench --repeat 1`` runs end to end and prints every figure (no timing assertion)."""
import re

import pytest

from aqfg import bench
from aqfg.cli import main


@pytest.mark.slow          # 40 s: every figure of the benchmark, each command a process
def test_bench_command_prints_the_figures(capsys, tmp_path):
    assert main(["bench", "--repeat", "1", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for label in ("C++ dynamics factor", "fixed-lag update, 24 s window",
                  "update-error optimisation of the same 24 s window",
                  "ratio update-error / fixed-lag", "batch, 15-min mission",
                  "evaluations per optimisation", "gnss8:", "usbl:",
                  # the speed targets' figures, in the same run
                  "ALL updates", "p90 fixed-lag update", "batch of otter-", "theta_e error",
                  "per-update median, last 10 min", "RSS",
                  # aqfg live on the same stream
                  "aqfg live, 0.33-h stream", "per fix, to its report", "per fix, all of it",
                  "real-time pace", "window solve alone",
                  # the cost of a command, each run a process
                  "start-up, `aqfg --version` as a process", "`aqfg fit otter-",
                  "the same with --no-plots"):
        assert label in out, label
    # every headline value is a finite number with its unit
    for unit in ("us", "ms", "x", "s"):
        assert re.search(r"\| \d+\.\d+ ?" + unit + r" \|", out), unit
    assert "nan" not in out.lower()
    assert (tmp_path / "bench.md").read_text().startswith("# aqfg bench")


def test_bench_rejects_a_bad_repeat(capsys):
    assert main(["bench", "--repeat", "0"]) == 2
    assert "--repeat" in capsys.readouterr().err


def test_headline_reads_the_figures():
    figs = {"kernel": [4e-6, 5e-6, 6e-6],
            "gnss8": {"fl_update": [0.001, 0.002, 0.003], "ue_opt": [0.04]},
            "usbl": {"ue_eval": [1e-4], "ue_nevals": [40, 50]},
            "batch": {"fg_batch": [1.0, 2.0]}}
    h = bench.headline(figs)
    assert abs(h["kernel_us"] - 5.0) < 1e-9 and abs(h["fl_update_ms"] - 2.0) < 1e-9
    assert abs(h["ratio"] - 20.0) < 1e-9 and abs(h["batch_s"] - 1.5) < 1e-9
    assert abs(h["nevals15"] - 45.0) < 1e-9
    assert "ratio_all" not in h and "otter_s" not in h      # not measured: not reported


def test_headline_reads_the_done_when_figures():
    figs = {"kernel": [5e-6], "gnss8": {"fl_update": [0.001], "fl_update_all": [0.001, 0.002, 0.003],
                                        "ue_opt": [0.1]},
            "usbl": {"ue_eval": [1e-4], "ue_nevals": [40]}, "batch": {"fg_batch": [1.0]},
            "otter": {"name": "x", "duration": 840.0, "wall": [0.5, 0.7, 0.9], "cpu": [0.4],
                      "iterations": [20], "theta_err_deg": [0.5, 0.7]},
            "stream": {"first": [0.002], "last": [0.0022]}}
    h = bench.headline(figs)
    assert abs(h["ratio_all"] - 50.0) < 1e-9 and abs(h["otter_s"] - 0.7) < 1e-9
    assert abs(h["otter_theta_deg"] - 0.7) < 1e-9 and abs(h["stream_growth"] - 1.1) < 1e-9


def test_headline_reads_the_command_figures():
    figs = {"kernel": [5e-6], "gnss8": {"fl_update": [0.001], "ue_opt": [0.1]},
            "usbl": {"ue_eval": [1e-4], "ue_nevals": [40]}, "batch": {"fg_batch": [1.0]},
            "command": {"name": "x", "startup": [0.2, 0.3, 0.25], "startup_cpu": [0.2],
                        "fit": [1.0, 3.0, 2.0], "fit_cpu": [1.5], "fit_no_plots": [1.0],
                        "fit_no_plots_cpu": [0.9]}}
    h = bench.headline(figs)
    assert abs(h["startup_s"] - 0.25) < 1e-9 and abs(h["fit_command_s"] - 2.0) < 1e-9
    rows = bench.command_rows(figs, h, lambda v, key, above=False: key)
    assert [r[2] for r in rows] == ["startup_s", "fit_command_s", ""]
    assert "2.00 s (CPU 1.50 s)" in rows[1][1]
