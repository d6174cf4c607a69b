"""The plot command (experiments/plot.py) on hand-written run directories: it writes the PNG and the
plotted numbers, and refuses a run directory it cannot read with one line and exit code 2."""

import csv
import subprocess
import sys

import numpy as np

from experiments import plot, report
from tests.experiments.runs import RUN_A, write_run


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_cli_writes_the_png_and_the_plotted_numbers(two_runs, tmp_path, capsys):
    prefix = str(tmp_path / "curves")
    assert plot.main([*two_runs, "--out", prefix, "--last-n", "2"]) == 0
    with open(prefix + ".png", "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    rows = _read_csv(prefix + ".csv")
    got = [(r["panel"], r["label"], float(r["x"]), float(r["mean"]), float(r["std"]), int(r["n_seeds"])) for r in rows]
    expected = [
        # run a: seeds (0.2, 0.4) → 0.3 ± 0.1 (population std), ...
        ("ur5_reach", "multimodal_bidal", 8000, 0.3, 0.1, 2),
        ("ur5_reach", "multimodal_bidal", 16000, 0.5, 0.1, 2),
        ("ur5_reach", "multimodal_bidal", 24000, 0.9, 0.1, 2),
        # run b: (0, 0.5, 1) → 0.5 ± √(0.5/3); (1, 1, 0.7) → 0.9 ± √(0.06/3)
        ("ur5_reach", "proprio_baseline", 8000, 0.5, np.sqrt(0.5 / 3), 3),
        ("ur5_reach", "proprio_baseline", 16000, 0.9, np.sqrt(0.02), 3),
    ]
    assert [g[:2] for g in got] == [e[:2] for e in expected]
    np.testing.assert_allclose([g[2:] for g in got], [e[2:] for e in expected], rtol=1e-9)
    out = capsys.readouterr().out
    assert "| ur5_reach | multimodal_bidal | 2 | 3 | 0.700 ± 0.100 | 0.567 |" in out  # seeds: 0.6, 0.8


def test_out_names_the_figure_and_its_numbers_go_beside_it(two_runs, tmp_path):
    (tmp_path / "figures").mkdir()
    assert plot.main([two_runs[1], "--out", str(tmp_path / "figures" / "fig.png")]) == 0
    assert sorted(p.name for p in (tmp_path / "figures").iterdir()) == ["fig.csv", "fig.png"]


def test_x_axis_epoch(two_runs, tmp_path):
    prefix = str(tmp_path / "by_epoch")
    assert plot.main([two_runs[1], "--out", prefix, "--x", "epoch"]) == 0
    assert [float(r["x"]) for r in _read_csv(prefix + ".csv")] == [1.0, 2.0]


def test_panels_by_a_config_value(tmp_path, capsys):
    """The noise experiment's layout: one panel per level, one line per agent."""
    dirs = [
        write_run(tmp_path / f"{agent}{lam}", agent, RUN_A, lam=lam)
        for lam in (0.05, 0.15)
        for agent in ("multimodal_bidal", "proprio_baseline")
    ]
    cs = report.curves([report.load_run(d) for d in dirs], panel_by="train.intrinsic_lambda")
    assert [(c.panel, c.label) for c in cs] == [
        ("intrinsic_lambda=0.05", "multimodal_bidal"),
        ("intrinsic_lambda=0.05", "proprio_baseline"),
        ("intrinsic_lambda=0.15", "multimodal_bidal"),
        ("intrinsic_lambda=0.15", "proprio_baseline"),
    ]
    assert plot.main([*dirs, "--panel-by", "train.intrinsic_lambda", "--out", str(tmp_path / "noise")]) == 0
    assert {r["panel"] for r in _read_csv(tmp_path / "noise.csv")} == {"intrinsic_lambda=0.05", "intrinsic_lambda=0.15"}
    assert "| train.intrinsic_lambda | label |" in capsys.readouterr().out


def test_a_missing_run_directory_is_one_line_and_exit_2(tmp_path):
    missing = str(tmp_path / "nope")
    proc = subprocess.run([sys.executable, "-m", "experiments.plot", missing], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [f"error: {missing}: no such run directory"]


def test_a_directory_without_metrics_is_one_line_and_exit_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "config.json").write_text("{}")
    assert plot.main([str(tmp_path / "empty"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"error: {tmp_path / 'empty'}: not a run directory (no metrics.csv)"]
    assert not (tmp_path / "x.png").exists()
