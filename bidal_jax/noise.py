"""Observation noise of the robustness experiment (paper Sec. IV-B, Eq. 9, Table II).

`s_noisy = s + κ·n`, `n ~ N(0, σ)` per feature, where σ is the interquartile range (75th
minus 25th percentile) of that feature over the clean observations collected so far. The
noise is drawn for the proprio features of the named segments (the measured ones: the paper's
`ee_pos`, `ee_rot` and `obj_pos`) of what the agent observes: the policy's input in training and
evaluation rollouts, and the transitions stored for learning. Features the env derives from
measured ones (`ObservationSpec.derived`, e.g. nicol's `obj_rel_pos = obj_pos - ee_pos`) carry
their noise, as they would when computed from estimated poses. Rewards and success come from
the true state. Two labelled variants (`config.NOISE_VARIANTS`): `literal`, the paper's three segments alone
(a derived feature stays clean), and `noisy_goal`, where the achieved goal the agent stores and
relabels with is the noisy estimate too (`ObservationSpec.goal_segment`).

κ is data (`NoiseState.kappa`, one per seed), not a compile-time constant, so one compiled
epoch serves every κ and κ × seeds are vmapped together. σ is refreshed from the replay
window's clean copies of the noised features before every cycle's rollout.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from bidal_jax.config import NOISE_VARIANTS


class NoiseMap(NamedTuple):
    """Where the noise of the measured features goes (static, built once per env and config).

    indices: [F] the measured (noised) features in the flat proprio vector, in segment order.
    spread: [F, P] noise of feature f added to proprio feature p (identity on `indices`, the sources'
      coefficients on derived features).
    goal_spread: [F, G] noise added to the achieved goal, or None (it stays true).
    """

    indices: np.ndarray
    spread: np.ndarray
    goal_spread: np.ndarray | None


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


def _spread_rows(spread: np.ndarray, segments, indices: np.ndarray, source: str, target: slice, coef: float) -> None:
    """Add `coef` × the noise of measured segment `source` into columns `target` of `spread` [F, ·]."""
    source_cols = np.arange(*segments.segment_slice(source).indices(segments.proprio_size))
    for row, feature in enumerate(indices):
        hit = np.nonzero(source_cols == feature)[0]
        if len(hit):
            spread[row, target.start + hit[0]] += coef


def noise_map(spec, names: tuple[str, ...], variant: str = "derived") -> NoiseMap:
    """The `NoiseMap` of noise on the measured segments `names` of observation spec `spec` (an
    `envs_mjx.ObservationSpec`) under `variant` (`NOISE_VARIANTS`). Raises ValueError naming an unknown
    segment or variant."""
    if variant not in NOISE_VARIANTS:
        raise ValueError(f"unknown noise variant {variant!r}; valid: {', '.join(NOISE_VARIANTS)}")
    indices = feature_indices(spec.proprio_segments, names)
    spread = np.zeros((len(indices), spec.proprio_size), np.float32)
    spread[np.arange(len(indices)), indices] = 1.0
    if variant != "literal":
        for target, sources in spec.derived:
            for source, coef in sources:
                if source in names:
                    _spread_rows(spread, spec, indices, source, spec.segment_slice(target), coef)
    goal_spread = None
    if variant == "noisy_goal":
        if spec.goal_segment not in names:
            raise ValueError(f"noise variant noisy_goal: the achieved goal is segment {spec.goal_segment!r}, "
                             f"which gets no noise (noised: {', '.join(names) or 'none'})")
        goal_spread = np.zeros((len(indices), spec.goal_size), np.float32)
        _spread_rows(goal_spread, spec, indices, spec.goal_segment, slice(0, spec.goal_size), 1.0)
    return NoiseMap(indices, spread, goal_spread)


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


def observe(state: NoiseState, nmap: NoiseMap, obs: dict, key: jax.Array) -> dict:
    """What the agent sees of batched `obs`: the measured features `nmap.indices` plus κ·N(0, σ) noise
    (Eq. 9), spread onto the features derived from them (and the achieved goal) by `nmap`."""
    return noised(nmap, obs, draw(state, nmap, key, obs["proprio"].shape[:-1]))


def draw(state: NoiseState, nmap: NoiseMap, key: jax.Array, batch: tuple[int, ...]) -> jax.Array:
    """κ·N(0, σ) noise [*batch, F] on the `nmap.indices` features of `batch` observations (Eq. 9)."""
    return state.kappa * state.sigma * jax.random.normal(key, (*batch, len(nmap.indices)))


def noised(nmap: NoiseMap, obs: dict, noise: jax.Array) -> dict:
    """Batched `obs` with `noise` [..., F] (`draw`) on the measured features, spread onto the features
    derived from them (and the achieved goal) by `nmap`."""
    proprio = obs["proprio"]
    seen = {**obs, "proprio": proprio + noise @ jnp.asarray(nmap.spread)}
    if nmap.goal_spread is not None:
        seen["achieved_goal"] = obs["achieved_goal"] + noise @ jnp.asarray(nmap.goal_spread)
    return seen
