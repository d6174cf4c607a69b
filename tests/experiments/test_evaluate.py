"""The evaluate command (experiments/evaluate.py): with the run's evaluation key it reproduces the
run's logged eval success, it prints each seed's success with an interval, and a video renders on CPU."""

import imageio.v2 as imageio
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting
from bidal_jax.run.policy import evaluate_seeds, load_policy
from experiments import evaluate
from tests.helpers import FINISHED_EPOCHS as EPOCHS
from tests.helpers import FINISHED_SEEDS as SEEDS


@pytest.fixture(scope="module")
def env():
    return envs_mjx.make("planar_reach", render=False)


def test_evaluate_with_the_runs_key_reproduces_its_last_eval_success(finished, env):
    run_dir, rows = finished
    trained = load_policy(run_dir)
    assert trained.step == EPOCHS and trained.seeds == SEEDS
    success = evaluate_seeds(env, trained, trained.eval_key, trained.config.train.eval_envs)
    logged = [float(rows[-1][f"eval_success_seed{i}"]) for i in range(SEEDS)]
    assert success.mean(axis=1).tolist() == logged
    # one seed on its own, through the public policy
    one = acting.evaluate(env, trained.policy(1), trained.eval_key[1], trained.config.train.eval_envs)
    assert float(np.asarray(one).mean()) == logged[1]


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
    assert (
        evaluate.main(["--run-dir", run_dir, "--episodes", "2", "--video", path, "--video-episodes", "1", "--quiet"])
        == 0
    )
    frames = imageio.mimread(path, memtest=False)
    assert len(frames) == 51  # the start and 50 steps
    height, width, channels = frames[0].shape
    assert (height, channels) == (240, 3) and width == 320 + 5 * 42
    assert np.asarray(frames[0])[:, :320].std() > 1.0  # MuJoCo drew a scene
