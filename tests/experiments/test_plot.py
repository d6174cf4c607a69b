"""Learning-curve plots and their summaries (experiments/plot.py) on hand-written run directories."""

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from experiments import plot, report

# per epoch: per-seed eval success, env_steps_total (summed over seeds), wall_time
RUN_A = [((0.2, 0.4), 16000, 10.0), ((0.4, 0.6), 32000, 20.0), ((0.8, 1.0), 48000, 30.0)]  # 2 seeds
RUN_B = [((0.0, 0.5, 1.0), 24000, 5.0), ((1.0, 1.0, 0.7), 48000, 9.0)]  # 3 seeds


def _fake_run(path, agent, rows, env="ur5_reach", lam=0.1):
    """A run directory as experiments/run.py writes it (the columns plot.py reads, and one more)."""
    seeds = len(rows[0][0])
    path.mkdir()
    config = {"run": {"env": env, "agent": agent, "seeds": seeds}, "train": {"intrinsic_lambda": lam}, "network": {}}
    (path / "config.json").write_text(json.dumps(config))
    with open(path / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch", "critic_loss", "eval_success", *[f"eval_success_seed{i}" for i in range(seeds)],
                         "env_steps_total", "wall_time"])
        for epoch, (success, steps, wall) in enumerate(rows, start=1):
            writer.writerow([epoch, 0.1, np.mean(success), *success, steps, wall])
    return str(path)


@pytest.fixture
def two_runs(tmp_path):
    return _fake_run(tmp_path / "a", "multimodal_bidal", RUN_A), _fake_run(tmp_path / "b", "proprio_baseline", RUN_B)


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_load_run_gives_env_steps_per_seed(two_runs):
    run = report.load_run(two_runs[0])
    assert (run["env"], run["agent"], run["seeds"], run["name"]) == ("ur5_reach", "multimodal_bidal", 2, "a")
    np.testing.assert_allclose(run["env_steps"], [8000, 16000, 24000])  # 16000 summed over 2 seeds, ...
    np.testing.assert_allclose(run["success"], [[0.2, 0.4], [0.4, 0.6], [0.8, 1.0]])


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


def test_x_axis_epoch(two_runs, tmp_path):
    prefix = str(tmp_path / "by_epoch")
    assert plot.main([two_runs[1], "--out", prefix, "--x", "epoch"]) == 0
    assert [float(r["x"]) for r in _read_csv(prefix + ".csv")] == [1.0, 2.0]


def test_labels_by_basename_on_a_shared_agent_and_by_override(tmp_path):
    runs = [report.load_run(_fake_run(tmp_path / name, "multimodal_bidal", RUN_A)) for name in ("s1", "s2")]
    other = report.load_run(_fake_run(tmp_path / "slide", "multimodal_bidal", RUN_B, env="nicol_slide"))
    assert [(c.panel, c.label) for c in report.curves([*runs, other])] == [
        ("ur5_reach", "s1"), ("ur5_reach", "s2"), ("nicol_slide", "multimodal_bidal")]
    labels = {str(tmp_path / "s1") + "/": "scratch", str(tmp_path / "s2"): "transfer"}
    assert [c.label for c in report.curves(runs, labels=labels)] == ["scratch", "transfer"]
    assert [c.label for c in report.curves(runs, label_by=lambda r: r["name"].upper())] == ["S1", "S2"]
    with pytest.raises(ValueError, match="labelled 'same'"):
        report.curves(runs, labels={str(tmp_path / "s1"): "same", str(tmp_path / "s2"): "same"})


def test_label_by_a_config_value(tmp_path):
    runs = [report.load_run(_fake_run(tmp_path / f"k{i}", "multimodal_bidal", RUN_A, lam=lam))
            for i, lam in enumerate((0.05, 0.15))]
    assert [c.label for c in report.curves(runs, "train.intrinsic_lambda")] == [
        "intrinsic_lambda=0.05",
        "intrinsic_lambda=0.15",
    ]
    with pytest.raises(ValueError, match="train.kappa"):
        report.curves(runs, "train.kappa")


def test_panels_by_a_config_value(tmp_path, capsys):
    """The noise experiment's layout: one panel per level, one line per agent."""
    dirs = [
        _fake_run(tmp_path / f"{agent}{lam}", agent, RUN_A, lam=lam)
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


def test_threshold_and_auc_by_hand(two_runs):
    a, b = report.curves([report.load_run(d) for d in two_runs])
    # run a's seed means: 0.3, 0.5, 0.9
    assert report.time_to_threshold(a, 0.5) == report.Reached(epoch=2, env_steps=16000.0, wall_time=20.0)
    assert report.time_to_threshold(a, 0.95) is None
    assert report.time_to_threshold(b, 0.5) == report.Reached(epoch=1, env_steps=8000.0, wall_time=5.0)
    assert report.normalized_auc(a) == pytest.approx(1.7 / 3)
    assert report.normalized_auc(b) == pytest.approx(0.7)


def test_final_success_and_summary_table(two_runs):
    runs = [report.load_run(d) for d in two_runs]
    a, b = report.curves(runs)
    # last 2 epochs per seed, then across seeds: a (0.6, 0.8); b (0.5, 0.75, 0.85)
    np.testing.assert_allclose(report.final_success(a, 2), (0.7, 0.1, 2))
    np.testing.assert_allclose(report.final_success(b, 2), (0.7, np.sqrt(0.065 / 3), 2))
    # more epochs asked than run: all 3, a's seeds (1.4/3, 2/3)
    np.testing.assert_allclose(report.final_success(a, 5), (1.7 / 3, 0.1, 3))
    table = report.summary_table(runs, 5, threshold=0.8).splitlines()
    assert table[2] == "| ur5_reach | multimodal_bidal | 2 | 3 | 0.567 ± 0.100 (last 3) | 0.567 | 3, 24,000, 30 s |"
    assert table[3] == "| ur5_reach | proprio_baseline | 3 | 2 | 0.700 ± 0.147 (last 2) | 0.700 | 2, 16,000, 9 s |"


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
