"""The vision probe (experiments/probes/vision.py): its success test by hand, bad input, a tiny run."""

import numpy as np
import pytest

import envs_mjx
from experiments.probes import vision as vision_probe


def test_located_is_the_share_within_epsilon():
    goals = np.zeros((4, 2))
    pred = np.array([[0.01, 0.0], [0.0, 0.019], [0.02, 0.0], [0.3, 0.4]])
    assert vision_probe.located(pred, goals, 0.02) == 0.5  # strictly within ε, as the sparse reward


@pytest.mark.parametrize("argv, expected", [
    (["--envs", "nope"], "error: --envs nope: unknown env 'nope'; allowed: planar_reach"),
    (["--conv-strides", "2,2,1"], "error: --conv-strides 2,2,1: must be four comma-separated positive integers"),
    (["--frames", "4"], "error: --frames 4: must be an integer >= 5"),
    (["--steps", "0"], "error: --steps 0: must be an integer >= 1"),
    (["--random-steps", "-1"], "error: --random-steps -1: must be an integer >= 0"),
    (["--lr-final", "1.5"], "error: --lr-final 1.5: must be a share of --lr, between 0 and 1"),
    (["--supersample", "-1"], "error: --supersample -1: must be an integer >= 0"),
    (["--envs", "planar_reach", "--target", "ee_pos"],
     "error: --target ee_pos: not a proprio segment of planar_reach; allowed: achieved_goal, q, qdot"),
])
def test_bad_input_is_one_line_before_any_work(argv, expected, tmp_path, capsys):
    out = tmp_path / "table.md"
    assert vision_probe.main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(expected) and err.count("\n") == 1
    assert not out.exists()


def test_the_env_column_names_a_target_and_random_steps_only_where_not_the_default():
    assert vision_probe.label("nicol_slide", "achieved_goal", 0) == "nicol_slide"
    assert vision_probe.label("nicol_slide", "ee_pos", 0) == "nicol_slide: ee_pos"
    assert vision_probe.label("nicol_slide", "ee_pos", 10) == "nicol_slide: ee_pos after 10 random actions"


def test_supersample_recasts_the_camera_only_where_set():
    env = envs_mjx.make("planar_reach", render=True)
    assert vision_probe.with_supersample(env, 0).camera.supersample == env.camera_supersample
    assert vision_probe.with_supersample(env, 3).camera.supersample == 3


def test_the_learning_rate_falls_along_a_cosine_to_its_final_share():
    lrs = [float(vision_probe.schedule(1e-3, 100, 0.1)(t)) for t in (0, 50, 100)]
    np.testing.assert_allclose(lrs, [1e-3, 0.55e-3, 1e-4], rtol=1e-5)
    constant = vision_probe.schedule(1e-3, 100, 1.0)
    assert float(constant(0)) == float(constant(100)) == pytest.approx(1e-3)


@pytest.mark.parametrize("extra, env_column, located", [
    ([], "planar_reach", "goal"),  # the achieved goal (hand xy) of start states
    (["--target", "qdot", "--random-steps", "2"], "planar_reach: qdot after 2 random actions", "qdot"),
    (["--supersample", "1"], "planar_reach", "goal"),
])
def test_a_tiny_probe_writes_its_table(extra, env_column, located, tmp_path):
    out = tmp_path / "table.md"
    argv = ["--envs", "planar_reach", "--conv-strides", "3,2,2,2", "--frames", "20", "--steps", "3", "--batch", "4",
            "--lr-final", "0.1"]
    assert vision_probe.main([*argv, *extra, "--out", str(out)]) == 0
    header = out.read_text().splitlines()[0]
    assert f"| held-out RMSE per {located} dimension (constant prediction) |" in header
    row = out.read_text().splitlines()[-1]
    assert row.startswith(f"| {env_column} | 3,2,2,2 | 0.02 | ") and row.endswith("| 16 / 4 |")
    assert row.count("|") == header.count("|")
    # the located shares, held out and on training frames, are shares of 4 frames
    assert all(4 * float(row.split(" | ")[i]) in (0, 1, 2, 3, 4) for i in (4, 5))
    constant_rmse = [float(x.split("(")[1].rstrip(")")) for x in row.split(" | ")[3].split(", ")]
    assert len(constant_rmse) == 2  # one per target dimension
    # the start states vary in hand position; their joint velocities are all zero until random actions move the arm
    assert min(constant_rmse) > 0
