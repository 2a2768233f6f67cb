"""``aqfg bench --repeat 1`` runs end to end and prints every figure (no timing assertion)."""
import re

from aqfg import bench
from aqfg.cli import main


def test_bench_command_prints_the_figures(capsys, tmp_path):
    assert main(["bench", "--repeat", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for label in ("C++ dynamics factor", "fixed-lag update, 24 s window",
                  "update-error optimisation of the same 24 s window",
                  "ratio update-error / fixed-lag", "batch, 15-min mission",
                  "evaluations per optimisation", "gnss8:", "usbl:"):
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
