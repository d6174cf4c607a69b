"""Env wrappers that are Envs too (DESIGN.md, "The environment API").

`ReducedProprio` removes named proprio segments, e.g. the transfer experiment's reduced
lift task drops obj_rot, obj_velp, obj_velr and obj_rel_pos (paper Sec. IV-C, D = 28).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs_mjx.base import Env, State


class ReducedProprio:
    """`env` with the proprio segments named in `drop` removed; the rest of the API delegates.

    Args:
      env: the wrapped environment.
      drop: names of proprio segments to remove; each must exist in `env`.
    """

    def __init__(self, env: Env, drop: tuple[str, ...]):
        spec = env.observation_spec
        unknown = set(drop) - set(spec.segment_names)
        if unknown:
            raise ValueError(f"cannot drop unknown segments {sorted(unknown)}; segments are {spec.segment_names}")
        kept = tuple((name, size) for name, size in spec.proprio_segments if name not in drop)
        self.env = env
        self.observation_spec = dataclasses.replace(spec, proprio_segments=kept)
        self._keep = jnp.asarray(
            np.concatenate([np.arange(spec.segment_slice(name).start, spec.segment_slice(name).stop) for name, _ in kept])
        )

    def __getattr__(self, name: str) -> Any:
        # only called for attributes this wrapper lacks: action_size, episode_length, ...
        return getattr(self.env, name)

    def _reduce(self, state: State) -> State:
        return state.replace(obs={**state.obs, "proprio": state.obs["proprio"][self._keep]})

    def reset(self, key: jax.Array) -> State:
        return self._reduce(self.env.reset(key))

    def exploration_reset(self, key: jax.Array) -> State:
        return self._reduce(self.env.exploration_reset(key))

    def step(self, state: State, action: jax.Array) -> State:
        # the wrapped step recomputes the full observation from state.data
        return self._reduce(self.env.step(state, action))

    def compute_reward(self, achieved_goal: jax.Array, desired_goal: jax.Array) -> jax.Array:
        return self.env.compute_reward(achieved_goal, desired_goal)
