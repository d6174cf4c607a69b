"""experiments.probes.exploration: the hover mean action and the summary of cube heights (pure parts; the
rollout is acting.rollout's)."""

import jax.numpy as jnp
import numpy as np
import pytest

from envs_mjx.base import ObservationSpec
from envs_mjx.nicol import PROPRIO_SEGMENTS
from experiments.probes import exploration

SPEC = ObservationSpec(proprio_segments=PROPRIO_SEGMENTS, goal_size=3)


def proprio(ee, obj):
    x = np.zeros(SPEC.proprio_size, np.float32)
    x[SPEC.segment_slice("ee_pos")], x[SPEC.segment_slice("obj_pos")] = ee, obj
    return x


def test_hover_drives_the_grasp_point_above_the_cube_and_leaves_the_hand_still():
    # the cube 3 cm ahead in x, 1 cm to the side in y, 10 cm below the grasp point; a second hand already there
    obs = {"proprio": jnp.stack([proprio((0.4, -0.1, 0.95), (0.43, -0.11, 0.85)),
                                 proprio((0.4, -0.1, 0.87), (0.4, -0.1, 0.85))])}
    grip = jnp.array([0.5, -0.2])
    action = np.asarray(exploration.mean_policy("hover", SPEC, 7, grip)(obs, None))
    assert action.shape == (2, 7) and np.all(action[:, 3:] == 0)
    assert action[0, 0] > 0 and action[0, 1] < 0 and action[0, 2] < 0  # towards 2 cm above the cube
    np.testing.assert_allclose(action[1, :3], 0.0, atol=1e-5)
    assert np.all(np.asarray(exploration.mean_policy("zero", SPEC, 7, grip)(obs, None)) == 0)
    held = np.asarray(exploration.mean_policy("hold", SPEC, 7, grip)(obs, None))  # the hand still, the grip kept
    np.testing.assert_allclose(held, [[0, 0, 0, 0, 0, 0.5, -0.2]] * 2)


def test_summary_counts_episodes_by_their_highest_rise():
    # 3 steps × 4 episodes: one never rises, one tips (1.5 cm), one lifts 6 cm and drops it, one ends 12 cm up
    rise = jnp.array([[0.0, 0.015, 0.06, 0.03],
                      [0.0, 0.0, 0.06, 0.08],
                      [0.0, 0.0, 0.0, 0.12]])
    grip = jnp.array([[0.01, 0.02, 0.03, 0.03], [0.01, 0.02, 0.03, 0.03], [0.01, 0.09, 0.20, 0.03]])
    figures = exploration.summarize(rise, grip)
    assert figures["rose >= 1 cm"] == 0.75 and figures["rose >= 2.5 cm"] == 0.5
    assert figures["rose >= 5 cm"] == 0.5 and figures["rose >= 10 cm"] == 0.25
    assert figures["steps >= 5 cm (mean)"] == pytest.approx(4 / 4) and figures["ended >= 5 cm"] == 0.25
    assert figures["ended in the hand"] == 0.5  # the grasp point 4 cm or nearer at the last step
