"""The visibility probe (experiments/probes/visibility.py) and what the NICOL camera must show (docs/tasks.md,
"camera"): the cube stays in view where the hand is at it and where the hand holds it, and the frame holds
every place the task uses."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from envs_mjx import nicol, ur5_reach
from experiments.probes import visibility


@pytest.fixture(scope="module")
def lift():
    return nicol.NicolLift()


def _cube_pixels(env, qpos: np.ndarray) -> np.ndarray:
    """Pixels the cube covers [N] in the frames of the poses `qpos` [N, nq] (kinematics only, no stepping)."""
    groups = visibility.body_groups(env)

    @jax.jit
    @jax.vmap
    def pixels(q):
        data = mjx.kinematics(env.mjx_model, env.blank_data().replace(qpos=q))
        return visibility.coverage(env, groups, data)[0]

    assert next(iter(groups)) == "cube"
    return np.asarray(pixels(jnp.asarray(qpos)))


def test_the_cube_stays_in_view_under_and_in_the_hand(lift):
    """The cube covers at least 3 px when held in the closed hand and when it sits right under the resting hand
    (where a camera behind and above the hand sees only the hand), and at every start position."""
    adr = lift._cube_qpos
    home = np.asarray(lift._home_qpos)
    rest = mjx.kinematics(lift.mjx_model, lift.blank_data().replace(qpos=jnp.asarray(home)))
    hand = np.asarray(rest.xpos[lift._hand])
    offsets = np.stack(np.meshgrid(*[np.linspace(-nicol.CUBE_START_RANGE, nicol.CUBE_START_RANGE, 4)] * 2), -1)
    starts = np.repeat(home[None], 16, 0)
    starts[:, adr:adr + 2] += offsets.reshape(-1, 2)
    under_hand = home.copy()
    under_hand[adr:adr + 2] = hand[:2]
    poses = np.concatenate([np.asarray(lift._held_qpos)[None], under_hand[None], starts])
    pixels = _cube_pixels(lift, poses)
    assert pixels.min() >= visibility.VISIBLE_PX, pixels


def test_every_place_the_task_uses_projects_inside_the_frame(lift):
    """The corners of the slide area on the table, of the lift goals' box and of the hand's workspace box all
    project inside the 42×42 frame, so that cube, goal marker and hand stay in view wherever the task takes them."""
    centre = np.asarray(lift._cube_centre)
    slide = nicol.CUBE_START_RANGE + nicol.SLIDE_GOAL_RANGE
    lift_xy = nicol.CUBE_START_RANGE + nicol.LIFT_GOAL_RANGE
    boxes = {
        "slide area": ([centre[0] - slide, centre[0] + slide], [centre[1] - slide, centre[1] + slide],
                       [nicol.TABLE_HEIGHT]),
        "lift goals": ([centre[0] - lift_xy, centre[0] + lift_xy], [centre[1] - lift_xy, centre[1] + lift_xy],
                       [nicol.TABLE_HEIGHT + nicol.CUBE_HALF, nicol.TABLE_HEIGHT + nicol.LIFT_HEIGHT[1]]),
        "hand workspace": tuple(zip(nicol.WORKSPACE_LOW, nicol.WORKSPACE_HIGH)),
    }
    for name, box in boxes.items():
        pixels = np.array([lift.camera.project(np.array(corner)) for corner in itertools.product(*box)])
        assert (pixels >= 0).all() and (pixels < lift.camera.resolution).all(), (name, pixels)


def test_the_probe_prints_a_row_per_phase_and_appends_it_to_out(tmp_path, capsys):
    out = tmp_path / "visibility.md"
    assert visibility.main(["--env", "planar_reach", "--episodes", "4", "--out", str(out)]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| planar_reach")]
    assert [row.split("|")[2].strip() for row in rows] == ["start", "moving"]
    assert all(row.split("|")[3].strip() == "4" for row in rows)
    assert out.read_text().count("| planar_reach") == 2
    assert visibility.main(["--env", "planar_reach", "--episodes", "0"]) == 2


def test_a_reaching_arm_is_looked_for_in_the_geoms_the_camera_draws():
    """ur5_reach's links are drawn by thick massless capsules; their physical capsules (group 3) are not seen
    and are no rows of the probe."""
    groups = visibility.body_groups(ur5_reach.UR5Reach())
    assert list(groups) == ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_stub", "goal marker"]
    assert len(groups["goal marker"]) == 3
