"""The noise experiment's command end to end on a tiny planar_reach config: one program of
3 κ × runs per agent, the table beside the paper's with short runs marked and the steadiness of each
cell, resumable (a finished agent is skipped), `--report` from the run folders alone."""

import json
import os

import numpy as np
import pytest

from bidal_jax.run.policy import load_noise, load_policy
from experiments import report
from experiments.paper import noise_robustness as noise
from experiments.paper import protocol
from tests.conftest import write_fake_run

TINY = ["--env", "planar_reach", "--noise-segments", "q", "--agents", "proprio_baseline", "--runs", "2",
        "--epochs", "2", "--num-envs", "4", "--cycles-per-epoch", "1", "--updates-per-cycle", "2",
        "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--checkpoint-every", "1", "--quiet"]


def test_noise_experiment_writes_the_table_and_skips_finished_agents(tmp_path, capsys):
    out = str(tmp_path / "noise")
    assert noise.main([*TINY, "--out", out]) == 0
    text = open(os.path.join(out, "table.md")).read()
    assert "proprio_baseline (ours)" in text and "0.882 ± 0.0191" in text  # the paper's 5 % figure beside ours
    # a window longer than the run uses what there is, and says so; 2 epochs of the noise budget 45: short
    assert text.count("(last 2 of 2 epochs; short run: 2 of 45 epochs)") == 3
    assert "Steadiness: each run's residual std" in text and "(slope " in text
    regenerate = f"Regenerate from the run folders: `python -m experiments.paper.noise_robustness --report --out {out}`"
    assert regenerate in text
    assert os.path.isfile(os.path.join(out, "curves.png")) and os.path.isfile(os.path.join(out, "curves.csv"))
    run_dir = os.path.join(out, "proprio_baseline")
    trained = load_policy(run_dir)
    assert trained.seeds == 6 and trained.config.run.seeds == 6
    assert trained.config.train.noise_segments == "q" and trained.config.run.checkpoint_every == 1
    np.testing.assert_array_equal(noise.run_kappas(2), np.float32([0.05, 0.05, 0.10, 0.10, 0.15, 0.15]))
    capsys.readouterr()
    assert noise.main([*TINY, "--out", out, "--dry-run"]) == 0
    assert f"in {run_dir} [done]" in capsys.readouterr().out
    assert noise.main([*TINY, "--out", out]) == 0
    assert "finished" in capsys.readouterr().out
    os.remove(os.path.join(out, "table.md"))
    assert noise.main(["--report", "--out", out]) == 0  # trains nothing: the table again, from the run folders
    assert open(os.path.join(out, "table.md")).read() == text


def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "noise"
    assert noise.main([*TINY, "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert not out.exists()
    assert lines[1:] == [
        "plan:",
        "proprio_baseline: planar_reach proprio_baseline, 6 seed(s), exploration starts 0; 2 epochs × 200 = 400 env "
        f"steps per seed in {out}/proprio_baseline [new]; estimated 35 s",  # 33.8 s + 2 × 0.66 s × 6 / 5
        "estimated time: 35 s (0.6 min) on one GPU running the runs one after another (an estimate from measured "
        "5-seed programs of the default sizes, in proportion to the seeds, compilation included)",
        "dry run: nothing trained or written",
    ]


def test_steadiness_is_each_runs_spread_around_its_trend_and_short_runs_are_marked():
    # 4 epochs × 2 runs: run 0 climbs 0.2 an epoch without scatter, run 1 is flat ± 0.1
    success = np.array([[0.0, 0.4], [0.2, 0.6], [0.4, 0.4], [0.6, 0.6]])
    curve = report.Curve("κ", "agent", "dir", np.arange(1.0, 5), np.arange(1.0, 5), np.arange(1.0, 5), success)
    slope, residuals = protocol.window_fit(curve, 30)
    np.testing.assert_allclose(slope, [0.2, 0.04])
    # run 1's line 0.44 + 0.04·(x − 2.5) leaves residuals −0.1+0.06, ...: their std with N − 2 degrees of freedom
    np.testing.assert_allclose(protocol.residual_spread(curve, 30), [0.0, np.sqrt((residuals[:, 1] ** 2).sum() / 2)],
                               atol=1e-12)
    climbing = report.Curve("κ", "agent", "dir", np.arange(1.0, 5), np.arange(1.0, 5), np.arange(1.0, 5),
                            np.array([[0.0, 0.01], [0.2, 0.19], [0.4, 0.42], [0.6, 0.6]]))
    assert protocol.trending(climbing, 30) and not protocol.trending(curve, 30)
    assert noise.window_note(40, 40, 40, 30) == " (40 epochs)"
    assert noise.window_note(19, 19, 100, 30) == " (last 19 of 19 epochs; short run: 19 of 100 epochs)"
    # rows lost outside the run: short only by the epoch reached, and the lost rows counted
    assert noise.window_note(42, 100, 100, 30) == " (42 epochs; 58 epochs without a row)"
    assert noise.window_note(26, 84, 100, 30) == (
        " (last 26 of 26 epochs; 58 epochs without a row; short run: 84 of 100 epochs)")


def test_a_bad_checkpoint_cadence_is_refused_before_anything_trains(tmp_path, capsys):
    out = str(tmp_path / "noise")
    assert noise.main([*TINY, "--checkpoint-every", "0", "--out", out]) == 2
    assert capsys.readouterr().err == "error: --checkpoint-every 0: must be a positive integer\n"
    assert not os.path.exists(os.path.join(out, "proprio_baseline"))


def test_one_kappa_alone_is_its_own_program_and_folder_and_joins_the_table(tmp_path):
    out = str(tmp_path / "noise")
    assert noise.main([*TINY, "--kappas", "0.10", "--out", out]) == 0
    run_dir = os.path.join(out, "proprio_baseline-kappa10")
    trained = load_policy(run_dir)
    assert trained.seeds == 2
    np.testing.assert_allclose(np.asarray(load_noise(run_dir, trained).kappa), [0.10, 0.10])
    rows = {}  # the first table's rows (the steadiness table below repeats the κ column)
    for line in open(os.path.join(out, "table.md")):
        rows.setdefault(line.split(" | ")[0], line)
    assert rows["| 10%"].count("(last 2 of 2 epochs; short run: 2 of 45 epochs)") == 1
    assert rows["| 5%"].startswith("| 5% | 5 | — ")  # the other κ are not trained


def test_a_kappa_in_both_layouts_is_refused(tmp_path, capsys):
    out = str(tmp_path / "noise")
    write_fake_run(os.path.join(out, "proprio_baseline"), "planar_reach", [[0.5] * 6], None, agent="proprio_baseline")
    write_fake_run(os.path.join(out, "proprio_baseline-kappa15"), "planar_reach", [[0.5] * 2], None,
                   agent="proprio_baseline")
    with pytest.raises(report.RunError, match="proprio_baseline at κ 15% is also in"):
        protocol.load_noise_curves(out)
    assert noise.main(["--report", "--out", out]) == 2  # one line, no traceback
    assert capsys.readouterr().err.startswith(f"error: {os.path.join(out, 'proprio_baseline-kappa15')}: ")
    assert noise.main([*TINY, "--kappas", "0.05", "--out", out]) == 2  # refused before training a κ again
    assert capsys.readouterr().err == (f"error: --kappas 0.05: {os.path.join(out, 'proprio_baseline')} already "
                                       "holds every κ of proprio_baseline; train them in another --out\n")
    os.rename(os.path.join(out, "proprio_baseline"), os.path.join(out, "old"))
    found, budgets = protocol.load_noise_curves(out)
    assert list(found) == [(0.15, "proprio_baseline")] and found[0.15, "proprio_baseline"].success.shape == (1, 2)
    config_path = os.path.join(out, "proprio_baseline-kappa15", "config.json")  # resumed elsewhere after epoch 1
    config = json.load(open(config_path))
    json.dump({**config, "fresh_buffer_epochs": [1]}, open(config_path, "w"))
    assert "empty replay buffer" in noise.write_report(out) and "proprio_baseline-kappa15 after epoch 1." in \
        open(os.path.join(out, "table.md")).read()


def test_kappas_other_than_the_papers_are_refused(capsys):
    assert noise.main([*TINY, "--kappas", "0.10,0.2"]) == 2
    assert capsys.readouterr().err == "error: --kappas 0.10,0.2: must be a comma list of 0.05, 0.10, 0.15\n"


def test_a_run_whose_metrics_lost_rows_is_short_by_the_epoch_it_reached_and_named(tmp_path):
    out = str(tmp_path / "noise")
    run_dir = os.path.join(out, "proprio_baseline-kappa10")
    write_fake_run(run_dir, "planar_reach", [[0.5, 0.5]] * 4, None, agent="proprio_baseline")
    path = os.path.join(run_dir, "metrics.csv")
    lines = open(path).read().splitlines(keepends=True)
    open(path, "w").writelines([lines[0], *lines[3:]])  # the rows of epochs 1 and 2 lost, 3 and 4 kept
    text = noise.write_report(out)
    assert "(last 2 of 2 epochs; 2 epochs without a row; short run: 4 of 45 epochs)" in text
    assert "Epochs without a row in metrics.csv: proprio_baseline-kappa10 (1-2); the final success averages the " \
           "last rows there are.\n" in text


def test_a_run_folder_the_table_cannot_read_after_training_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    out = str(tmp_path / "noise")
    broken = os.path.join(out, "proprio_baseline-kappa15")  # another program's folder, its config.json gone
    write_fake_run(broken, "planar_reach", [[0.5] * 2], None, agent="proprio_baseline")
    os.remove(os.path.join(broken, "config.json"))
    monkeypatch.setattr(noise.grid, "train_arms", lambda arms, envs, args, out: 0)  # this program's training, done
    assert noise.main([*TINY, "--kappas", "0.05", "--out", out]) == 2
    assert capsys.readouterr().err == f"error: {broken}: not a run directory (no config.json)\n"
