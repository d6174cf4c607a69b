"""Running mean and standard deviation of observations, as a pytree (HER's normaliser).

Proprio features and goals are normalised as clip((x - mean) / std, ±clip) before they
reach the networks; the statistics are updated from every rollout.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

MIN_STD = 1e-2


@struct.dataclass
class NormalizerState:
    count: jax.Array
    total: jax.Array
    total_sq: jax.Array
    mean: jax.Array
    std: jax.Array


def init(size: int) -> NormalizerState:
    zeros = jnp.zeros((size,), jnp.float32)
    return NormalizerState(
        count=jnp.zeros((), jnp.float32), total=zeros, total_sq=zeros, mean=zeros, std=jnp.ones((size,), jnp.float32)
    )


def update(state: NormalizerState, x: jax.Array) -> NormalizerState:
    """Add a batch x [..., size] to the statistics."""
    chex.assert_axis_dimension(x, -1, state.mean.shape[0])
    flat = x.reshape(-1, x.shape[-1]).astype(jnp.float32)
    count = state.count + flat.shape[0]
    total = state.total + flat.sum(0)
    total_sq = state.total_sq + jnp.square(flat).sum(0)
    mean = total / count
    var = jnp.maximum(total_sq / count - jnp.square(mean), 0.0)
    return NormalizerState(
        count=count, total=total, total_sq=total_sq, mean=mean, std=jnp.maximum(jnp.sqrt(var), MIN_STD)
    )


def normalize(state: NormalizerState, x: jax.Array, clip: float) -> jax.Array:
    return jnp.clip((x - state.mean) / state.std, -clip, clip)
