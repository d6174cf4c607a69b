"""Acting: a trained policy loads without its replay buffer, evaluation reproduces the run's
logged eval success, the best checkpoint is kept and selected, and a video renders on CPU."""

import csv
import os
import shutil

import imageio.v2 as imageio
import jax
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting
from bidal_jax.run import checkpoint
from experiments import evaluate, run

SEEDS, EPOCHS = 2, 4
TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "4", "--batch-size", "16", "--buffer-episodes", "8", "--eval-envs", "16", "--quiet",
    "--seeds", str(SEEDS), "--epochs", str(EPOCHS), "--checkpoint-every", "1",
]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished tiny run with a checkpoint saved after every epoch, and its metrics rows."""
    run_dir = str(tmp_path_factory.mktemp("acting") / "run")
    assert run.main([*TINY, "--run-dir", run_dir]) == 0
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return run_dir, list(csv.DictReader(f))


@pytest.fixture(scope="module")
def env():
    return envs_mjx.make("planar_reach", render=False)


def test_evaluate_with_the_runs_key_reproduces_its_last_eval_success(finished, env):
    run_dir, rows = finished
    trained = acting.load_policy(run_dir)
    assert trained.step == EPOCHS and trained.seeds == SEEDS
    success = evaluate.evaluate_seeds(env, trained, trained.eval_key, trained.train.eval_envs)
    logged = [float(rows[-1][f"eval_success_seed{i}"]) for i in range(SEEDS)]
    assert success.mean(axis=1).tolist() == logged
    # one seed on its own, through the public policy
    one = acting.evaluate(env, trained.policy(1), trained.eval_key[1], trained.train.eval_envs)
    assert float(np.asarray(one).mean()) == logged[1]


def test_load_policy_never_reads_the_buffer(finished, tmp_path, env):
    run_dir, _ = finished
    copy = str(tmp_path / "no_buffer")
    shutil.copytree(run_dir, copy)
    for step in checkpoint.steps(os.path.join(copy, "checkpoints")):
        shutil.rmtree(os.path.join(copy, "checkpoints", str(step), "buffer"))
    trained, original = acting.load_policy(copy), acting.load_policy(run_dir)
    for a, b in zip(jax.tree.leaves(trained.params), jax.tree.leaves(original.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert set(trained.params.params) == {"actor"}  # the proprio baseline has no encoder; no critic is read
    # the whole training state (for resuming) does need the buffer
    with pytest.raises(checkpoint.CheckpointError, match="damaged"):
        checkpoint.read_metadata(os.path.join(copy, "checkpoints"))


def test_the_best_checkpoint_is_kept_beside_the_latest_two_and_selected_by_best(finished):
    run_dir, rows = finished
    success = {int(r["epoch"]): float(r["eval_success"]) for r in rows}
    best = max(success, key=lambda e: (success[e], e))
    ckpt_dir = os.path.join(run_dir, "checkpoints")
    assert set(checkpoint.steps(ckpt_dir)) == {EPOCHS - 1, EPOCHS, best}
    assert checkpoint.resolve_step(ckpt_dir, "best") == best
    assert acting.load_policy(run_dir, "best").step == best
    with pytest.raises(checkpoint.CheckpointError, match="'last': must be a step number or 'best'"):
        checkpoint.resolve_step(ckpt_dir, "last")


def test_evaluate_command_prints_per_seed_success_and_an_interval(finished, capsys):
    run_dir, rows = finished
    assert evaluate.main(["--run-dir", run_dir, "--episodes", "16"]) == 0
    out = capsys.readouterr().out
    for i in range(SEEDS):
        assert f"seed {i}: success {float(rows[-1][f'eval_success_seed{i}']):.3f}" in out
    assert "mean success" in out and "95 % interval" in out
    assert evaluate.main(["--run-dir", run_dir, "--checkpoint", "7"]) == 2
    assert "no checkpoint 7" in capsys.readouterr().err


def test_video_renders_mujoco_beside_the_agents_view(finished, tmp_path):
    run_dir, _ = finished
    path = str(tmp_path / "episode.mp4")
    assert evaluate.main(["--run-dir", run_dir, "--episodes", "2", "--video", path, "--video-episodes", "1", "--quiet"]) == 0
    frames = imageio.mimread(path, memtest=False)
    assert len(frames) == 51  # the start and 50 steps
    height, width, channels = frames[0].shape
    assert (height, channels) == (240, 3) and width == 320 + 5 * 42
    assert np.asarray(frames[0])[:, :320].std() > 1.0  # MuJoCo drew a scene
