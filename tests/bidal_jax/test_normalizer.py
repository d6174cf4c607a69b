"""The running normaliser (bidal_jax/normalizer.py) against hand-computed statistics."""

import jax.numpy as jnp
import numpy as np

from bidal_jax import normalizer


def test_normalizer_by_hand():
    state = normalizer.update(normalizer.init(2), jnp.array([[1.0, 10.0], [3.0, 10.0]]))
    np.testing.assert_allclose(state.mean, [2.0, 10.0])
    np.testing.assert_allclose(state.std, [1.0, normalizer.MIN_STD])
    np.testing.assert_allclose(normalizer.normalize(state, jnp.array([4.0, 10.0]), 5.0), [2.0, 0.0])
