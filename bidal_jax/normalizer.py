"""Running mean and standard deviation of observations, as a pytree (HER's normaliser).

Proprio features and goals are normalised as `clip((x - mean) / std, -clip, clip)` before
they reach the networks: the clip applies to the normalised value, not to the input, and
its value is the trainer's `clip_obs` (5 by default, `bidal_jax.config`). The statistics
are updated from every rollout.

The statistics are merged batch by batch with Chan et al.'s parallel algorithm (count,
mean and M2, the sum of squared deviations from the mean), which stays accurate in float32
where the textbook E[x²] - E[x]² cancels: a feature of mean 1e3 and std 1e-2 keeps its std,
where the running sums lose it entirely (its square, 1e6, leaves float32 no digits for a
variance of 1e-4).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

MIN_STD = 1e-2
# the fields with one entry per feature (the rest, `count`, is a scalar)
FEATURE_FIELDS = ("mean", "m2", "std")
# the per-feature fields of checkpoints written before the Chan merge: running sum and sum of squares
LEGACY_FEATURE_FIELDS = ("total", "total_sq")


@struct.dataclass
class NormalizerState:
    count: jax.Array  # () observations seen
    mean: jax.Array  # (size,)
    m2: jax.Array  # (size,) sum of squared deviations from `mean`
    std: jax.Array  # (size,) sqrt(m2 / count), at least MIN_STD


def init(size: int) -> NormalizerState:
    zeros = jnp.zeros((size,), jnp.float32)
    return NormalizerState(count=jnp.zeros((), jnp.float32), mean=zeros, m2=zeros, std=jnp.ones((size,), jnp.float32))


def update(state: NormalizerState, x: jax.Array) -> NormalizerState:
    """Add a batch x [..., size] to the statistics (Chan et al.'s merge of two partitions)."""
    chex.assert_axis_dimension(x, -1, state.mean.shape[0])
    flat = x.reshape(-1, x.shape[-1]).astype(jnp.float32)
    n = jnp.float32(flat.shape[0])
    batch_mean = flat.mean(0)
    batch_m2 = jnp.square(flat - batch_mean).sum(0)
    count = state.count + n
    delta = batch_mean - state.mean
    mean = state.mean + delta * (n / count)
    m2 = state.m2 + batch_m2 + jnp.square(delta) * (state.count * n / count)
    return NormalizerState(count=count, mean=mean, m2=m2, std=jnp.maximum(jnp.sqrt(m2 / count), MIN_STD))


def from_saved(fields: dict) -> NormalizerState:
    """The state from its restored fields; checkpoints of the older layout (count, total, total_sq,
    mean, std) are converted, their M2 recovered as total_sq - total² / count."""
    if "m2" in fields:
        return NormalizerState(**fields)
    count = jnp.asarray(fields["count"])
    per_feature = jnp.maximum(count, 1.0)[..., None]  # states may carry leading (seed) axes
    m2 = jnp.maximum(fields["total_sq"] - jnp.square(fields["total"]) / per_feature, 0.0)
    return NormalizerState(count=count, mean=jnp.asarray(fields["mean"]), m2=m2, std=jnp.asarray(fields["std"]))


def normalize(state: NormalizerState, x: jax.Array, clip: float) -> jax.Array:
    """(x - mean) / std, then clipped to ±clip."""
    return jnp.clip((x - state.mean) / state.std, -clip, clip)


def normalize_batch(batch: dict, proprio_norm: NormalizerState, goal_norm: NormalizerState, clip: float) -> dict:
    """A sampled replay batch with its proprio features (now and next) normalised by `proprio_norm` and its goals
    by `goal_norm`."""
    return {
        **batch,
        "proprio": normalize(proprio_norm, batch["proprio"], clip),
        "next_proprio": normalize(proprio_norm, batch["next_proprio"], clip),
        "goal": normalize(goal_norm, batch["goal"], clip),
    }
