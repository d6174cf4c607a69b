"""bidal_jax.acting: HER's exploration (Gaussian noise, clipped, and ε-random actions) and the picked starts."""

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax.acting import exploring, picked


def test_without_noise_the_action_is_kept_and_with_random_eps_1_every_row_is_redrawn():
    action = jnp.full((512, 7), 0.5)
    key = jax.random.PRNGKey(0)
    assert np.array_equal(np.asarray(exploring(action, key, 0.0, 0.0)), np.asarray(action))
    redrawn = np.asarray(exploring(action, key, 0.0, 1.0))
    assert np.all(np.abs(redrawn) <= 1.0) and np.all(redrawn != 0.5)
    assert abs(redrawn.mean()) < 0.05 and abs(redrawn.std() - 1 / np.sqrt(3)) < 0.02  # uniform on [-1, 1]


def test_noise_is_clipped_and_random_rows_are_whole_rows():
    action = jnp.ones((4096, 7))
    noisy = np.asarray(exploring(action, jax.random.PRNGKey(1), 0.2, 0.3))
    assert np.all(noisy <= 1.0) and np.all(noisy >= -1.0)
    # a row is either the (clipped) noisy action, all entries within 1 ± 5σ, or a random action
    kept = np.all(noisy > 0.0, axis=1)
    assert 0.6 < kept.mean() < 0.8  # about 0.7 kept; a random row has all 7 entries > 0 with probability 2^-7


def test_picked_starts_take_the_eased_rows_and_keep_leaves_without_the_envs_axis():
    """`picked`: per env, the exploration start where `pick` holds, else the reset; a leaf without the envs'
    axis (MuJoCo Warp's data holds such empty arrays) is kept as it is, whose `jnp.where` would not broadcast."""
    pick = jnp.array([True, False, True])
    eased = {"qpos": jnp.ones((3, 2)), "done": jnp.ones(3), "shared": jnp.zeros((0,))}
    state = {"qpos": jnp.zeros((3, 2)), "done": jnp.zeros(3), "shared": jnp.zeros((0,))}
    out = picked(pick, eased, state)
    np.testing.assert_array_equal(out["qpos"], [[1, 1], [0, 0], [1, 1]])
    np.testing.assert_array_equal(out["done"], [1, 0, 1])
    assert out["shared"].shape == (0,)
