"""ur5_reach's camera search (experiments/probes/camera_search.py): its pinhole projection is the camera's, a pose
it finds frames every point, the elbow's bound is the geometry's, and it refuses bad input."""

import numpy as np
import pytest

import envs_mjx
from envs_mjx.ur5_reach import A3, WRIST_STUB
from experiments.probes import camera_search as cs

CONFIGS = 64


@pytest.fixture(scope="module")
def scene():
    env = envs_mjx.make("ur5_reach", render=False)
    framed, centre = cs.points(env, cs.configurations(env, CONFIGS, seed=0))
    return env, framed, centre


def test_the_projection_is_the_cameras(scene):
    env, framed, centre = scene
    row = cs.current_pose(env, centre)
    rotation = np.stack([row["xyaxes"][:3], row["xyaxes"][3:], np.cross(row["xyaxes"][:3], row["xyaxes"][3:])])
    focal = cs.HALF / np.tan(np.radians(row["fovy_deg"]) / 2)
    t = cs.tangents(rotation, np.asarray(row["pos"]), framed[:4].reshape(-1, 3)) * focal
    expected = [env.camera.project(p) for p in framed[:4].reshape(-1, 3)]  # (row, col)
    np.testing.assert_allclose(np.stack([cs.HALF + t[:, 0], cs.HALF - t[:, 1]], axis=1),
                               np.asarray(expected)[:, ::-1], atol=1e-3)


def test_a_centred_pose_frames_every_point_with_the_margin_to_spare(scene):
    _, framed, _ = scene
    flat = framed.reshape(-1, 3)
    position = cs.camera_position(30.0, 1.5, 2.0)
    for roll in cs.ROLLS_DEG:
        rotation = cs.centred_rotation(position, flat, roll)
        t = cs.tangents(rotation, position, flat) * cs.fitted_focal(rotation, position, flat)
        assert np.abs(t).max() == pytest.approx(cs.HALF - cs.MARGIN_PX)
        extent = np.abs(t.min(axis=0) + t.max(axis=0)) / 2  # the box's offset from the frame's centre
        assert extent.max() < 0.05
    assert cs.centred_rotation(np.array([0.0, 0.0, 0.5]), flat) is None  # inside the workspace


def test_the_elbow_turns_the_stub_centre_by_epsilon_times_its_distance(scene):
    env, framed, centre = scene
    b = cs.bound(framed, centre)
    chord = 2 * np.sin(env.epsilon / 2) * (A3 + WRIST_STUB / 2)
    assert b["moved_p10_m"][2] == pytest.approx(chord, abs=1e-4)
    assert b["px_p10"][2] == pytest.approx(b["px_per_m"] * chord, abs=1e-3)


def test_set_camera_puts_the_pose_in_the_model(scene):
    env, _, centre = scene
    row = cs.current_pose(env, centre)
    moved = {**row, "pos": [0.5, -2.0, 2.5], "fovy_deg": 40.0}
    try:
        cs.set_camera(env, moved)
        assert cs.current_pose(env, centre)["xyaxes"] == pytest.approx(row["xyaxes"], abs=1e-4)
        assert cs.current_pose(env, centre)["pos"] == pytest.approx(moved["pos"])
    finally:
        cs.set_camera(env, row)


def test_bad_counts_and_an_existing_out_are_refused(tmp_path, capsys):
    assert cs.main(["--configs", "3"]) == 2
    assert "error: --configs 3" in capsys.readouterr().err
    assert cs.main(["--epsilon", "0"]) == 2
    assert "error: --epsilon 0" in capsys.readouterr().err
    out = tmp_path / "search.json"
    out.write_text("{}")
    assert cs.main(["--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert out.read_text() == "{}"
