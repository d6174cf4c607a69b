"""The evaluate command (experiments/evaluate.py): with the run's evaluation key it reproduces the
run's logged eval success, it prints each seed's success with an interval, and a video renders on CPU."""

import warnings

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
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = evaluate.main(["--run-dir", run_dir, "--episodes", "2", "--video", path, "--video-episodes", "1",
                              "--quiet"])
    assert code == 0
    frames = imageio.mimread(path, memtest=False)
    assert len(frames) == 51  # the start and 50 steps
    height, width, channels = frames[0].shape
    assert (height, channels) == (240, 3) and width == 320 + 5 * 42
    mujoco_half = np.asarray(frames[0])[:, :320]
    assert mujoco_half.std() > 1.0  # MuJoCo drew a scene
    assert mujoco_half.mean() > 50  # lit for people (`evaluate.lit`): the arm on a light floor, not on black
    assert not [w for w in caught if "fork" in str(w.message)]  # ffmpeg started without forking JAX's process


def test_the_videos_lighting_draws_a_copy_and_leaves_the_envs_model_alone(env):
    headlight, rgba = env.mj_model.vis.headlight.diffuse.copy(), env.mj_model.geom_rgba.copy()
    model = evaluate.lit(env.mj_model)
    np.testing.assert_allclose(model.vis.headlight.diffuse, evaluate.HEADLIGHT[1])
    np.testing.assert_array_equal(env.mj_model.vis.headlight.diffuse, headlight)  # what the physics' fingerprint
    np.testing.assert_array_equal(env.mj_model.geom_rgba, rgba)  # hashes, and what the agent's camera reads
