"""Observation noise of the robustness experiment (paper Sec. IV-B, Eq. 9, Table II).

`s_noisy = s + κ·n`, `n ~ N(0, σ)` per feature, where σ is the interquartile range (75th
minus 25th percentile) of that feature over the clean observations collected so far. The
noise touches only the proprio features of the named segments (the paper's `ee_pos`,
`ee_rot` and `obj_pos`) of what the agent observes: the policy's input in training and
evaluation rollouts, and the transitions stored for learning. Achieved goals, rewards and
success come from the true state.

κ is data (`NoiseState.kappa`, one per seed), not a compile-time constant, so one compiled
epoch serves every κ and κ × seeds are vmapped together. σ is refreshed from the replay
window's clean copies of the noised features before every cycle's rollout.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class NoiseState:
    """κ (a scalar) and the current σ of each noised feature [F]."""

    kappa: jax.Array
    sigma: jax.Array


def parse_segments(text: str) -> tuple[str, ...]:
    """"ee_pos,ee_rot" -> ("ee_pos", "ee_rot"); "" -> () (no noise)."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def feature_indices(proprio_segments: tuple[tuple[str, int], ...], names: tuple[str, ...]) -> np.ndarray:
    """Indices into the flat proprio vector of the features of the segments `names` (in that order).

    Raises ValueError naming a segment the observation does not have.
    """
    starts, start = {}, 0
    for name, size in proprio_segments:
        starts[name] = (start, size)
        start += size
    unknown = [n for n in names if n not in starts]
    if unknown:
        raise ValueError(f"unknown proprio segment {unknown[0]!r}; segments are {', '.join(starts)}")
    return np.concatenate([np.arange(starts[n][0], sum(starts[n])) for n in names] or [np.zeros(0, int)]).astype(int)


def init(kappa: float | jax.Array, n_features: int) -> NoiseState:
    return NoiseState(kappa=jnp.asarray(kappa, jnp.float32), sigma=jnp.zeros((n_features,), jnp.float32))


def interquartile_range(history: jax.Array, valid: jax.Array) -> jax.Array:
    """Per feature, the 75th minus the 25th percentile of the rows of `history` [M, F] where
    `valid` [M] is true (numpy's linear interpolation); 0 where no row is valid."""
    chex.assert_rank(history, 2)
    masked = jnp.where(valid[:, None], history, jnp.nan)
    q25, q75 = jnp.nanpercentile(masked, jnp.array([25.0, 75.0]), axis=0)
    return jnp.where(valid.any(), q75 - q25, 0.0).astype(jnp.float32)


def refresh(state: NoiseState, clean: jax.Array, n_episodes: jax.Array) -> NoiseState:
    """σ from the clean histories of the first `n_episodes` episodes of `clean` [E, T+1, F]."""
    valid = jnp.repeat(jnp.arange(clean.shape[0]) < n_episodes, clean.shape[1])
    return state.replace(sigma=interquartile_range(clean.reshape(-1, clean.shape[-1]), valid))


def observe(state: NoiseState, indices: np.ndarray, obs: dict, key: jax.Array) -> dict:
    """What the agent sees of batched `obs`: proprio features `indices` plus κ·N(0, σ) noise (Eq. 9)."""
    proprio = obs["proprio"]
    n = jax.random.normal(key, (*proprio.shape[:-1], len(indices)))
    return {**obs, "proprio": proprio.at[..., indices].add(state.kappa * state.sigma * n)}
