"""The running normaliser (bidal_jax/normalizer.py): hand-computed statistics, Chan et al.'s merge."""

import jax.numpy as jnp
import numpy as np

from bidal_jax import normalizer


def test_normalizer_by_hand():
    state = normalizer.update(normalizer.init(2), jnp.array([[1.0, 10.0], [3.0, 10.0]]))
    np.testing.assert_allclose(state.mean, [2.0, 10.0])
    np.testing.assert_allclose(state.std, [1.0, normalizer.MIN_STD])
    np.testing.assert_allclose(normalizer.normalize(state, jnp.array([4.0, 10.0]), 5.0), [2.0, 0.0])
def _batches(mean: float, std: float, n_batches: int, batch: int, size: int = 2) -> np.ndarray:
    return np.random.default_rng(0).normal(mean, std, size=(n_batches, batch, size)).astype(np.float32)


def test_a_large_mean_does_not_swamp_a_small_std_over_many_batches():
    """Mean 1e3, std 1e-2 over 200 batches: E[x²] - E[x]² in float32 (the former formula) loses every digit
    of the variance (1e6 leaves ~0.06 of resolution for 1e-4); the Chan merge keeps it within a few %."""
    batches = _batches(1e3, 1e-2, 200, 256)
    state = normalizer.init(2)
    for batch in batches:
        state = normalizer.update(state, jnp.asarray(batch))
    flat = batches.reshape(-1, 2).astype(np.float64)
    np.testing.assert_allclose(np.asarray(state.std), flat.std(0), rtol=0.03)
    np.testing.assert_allclose(np.asarray(state.mean), flat.mean(0), rtol=1e-6)
    # the former running sums, for the record: their variance is rounding noise
    total, total_sq = np.float32(0), np.float32(0)
    for batch in batches:
        total, total_sq = total + batch[:, 0].sum(), total_sq + np.square(batch[:, 0]).sum()
    count = np.float32(flat.shape[0])
    old_var = total_sq / count - np.square(total / count)
    assert abs(np.sqrt(max(old_var, 0.0)) - flat[:, 0].std()) > 0.5 * flat[:, 0].std()


def test_merging_batches_of_different_sizes_equals_the_whole():
    rng = np.random.default_rng(1)
    parts = [rng.normal(3.0, 2.0, size=(n, 3)).astype(np.float32) for n in (1, 7, 50, 3)]
    state = normalizer.init(3)
    for part in parts:
        state = normalizer.update(state, jnp.asarray(part))
    whole = np.concatenate(parts).astype(np.float64)
    assert float(state.count) == len(whole)
    np.testing.assert_allclose(np.asarray(state.mean), whole.mean(0), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(state.std), whole.std(0), rtol=1e-4)


def test_constant_features_get_the_std_floor_and_the_clip_applies_after_normalising():
    state = normalizer.update(normalizer.init(2), jnp.array([[1.0, 10.0], [3.0, 10.0]]))
    np.testing.assert_allclose(state.std, [1.0, normalizer.MIN_STD])
    np.testing.assert_allclose(normalizer.normalize(state, jnp.array([100.0, 10.0]), 5.0), [5.0, 0.0])


def test_checkpoints_of_the_former_layout_are_converted():
    """A state saved as (count, total, total_sq, mean, std), with a leading seed axis, restores to the same
    statistics, and further updates continue from them."""
    data = np.random.default_rng(2).normal(0.5, 0.3, size=(2, 100, 3)).astype(np.float64)
    legacy = {
        "count": np.full((2,), 100.0),
        "total": data.sum(1),
        "total_sq": np.square(data).sum(1),
        "mean": data.mean(1),
        "std": data.std(1),
    }
    state = normalizer.from_saved(legacy)
    np.testing.assert_allclose(np.asarray(state.m2), data.var(1) * 100, rtol=1e-4)
    fresh = normalizer.update(normalizer.init(3), jnp.asarray(data[0], jnp.float32))
    saved = {k: getattr(fresh, k) for k in ("count", "mean", "m2", "std")}
    np.testing.assert_allclose(np.asarray(normalizer.from_saved(saved).m2), np.asarray(fresh.m2))
