"""The noise experiment's command end to end on a tiny planar_reach config: one program of
3 κ × runs per agent, the table beside the paper's, resumable (a finished agent is skipped)."""

import os

import numpy as np

from bidal_jax.run.policy import load_policy
from experiments.paper import noise_robustness as noise

TINY = ["--env", "planar_reach", "--noise-segments", "q", "--agents", "proprio_baseline", "--runs", "2",
        "--epochs", "2", "--num-envs", "4", "--cycles-per-epoch", "1", "--updates-per-cycle", "2",
        "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--quiet"]


def test_noise_experiment_writes_the_table_and_skips_finished_agents(tmp_path, capsys):
    out = str(tmp_path / "noise")
    assert noise.main([*TINY, "--out", out]) == 0
    text = open(os.path.join(out, "table.md")).read()
    assert "proprio_baseline (ours)" in text and "0.882 ± 0.0191" in text  # the paper's 5 % figure beside ours
    assert text.count("(last 2 of 2 epochs)") == 3  # a window longer than the run uses what there is, and says so
    assert os.path.isfile(os.path.join(out, "curves.png")) and os.path.isfile(os.path.join(out, "curves.csv"))
    run_dir = os.path.join(out, "proprio_baseline")
    trained = load_policy(run_dir)
    assert trained.seeds == 6 and trained.config.run.seeds == 6
    assert trained.config.train.noise_segments == "q"
    np.testing.assert_array_equal(noise.run_kappas(2), np.float32([0.05, 0.05, 0.10, 0.10, 0.15, 0.15]))
    capsys.readouterr()
    assert noise.main([*TINY, "--out", out]) == 0
    assert "finished" in capsys.readouterr().out
