"""Episode-shaped replay buffer in device memory with HER `future` relabelling.

The buffer is a pytree: arrays with a leading capacity axis of whole episodes plus its
own position counters, so `init / insert / sample` are pure and jit-able. Images are
kept as uint8. `sample` relabels goals with HER's `future` strategy (Andrychowicz et
al. 2017; paper Sec. III-C.3): with probability 1 - 1/(1+k) the goal of a transition
(t) becomes the achieved goal at a uniformly drawn later step t' ∈ [t+1, T] of the same
episode, and the sparse reward (paper Eq. 6) is recomputed for it.

Episode layout: `proprio` [T+1, D], `image` [T+1, H, W, 1] (image agents only),
`achieved_goal` [T+1, G], `desired_goal` [G], `action` [T, A].
"""

from __future__ import annotations

from typing import Callable

import chex
import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class ReplayState:
    episodes: dict[str, jax.Array]
    position: jax.Array  # next episode slot to write
    size: jax.Array  # number of stored episodes


def init(capacity: int, example_episode: dict[str, jax.Array]) -> ReplayState:
    """An empty buffer of `capacity` episodes shaped like `example_episode`."""
    episodes = jax.tree.map(lambda x: jnp.zeros((capacity, *x.shape), x.dtype), example_episode)
    return ReplayState(episodes=episodes, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def capacity(state: ReplayState) -> int:
    return jax.tree.leaves(state.episodes)[0].shape[0]


def insert(state: ReplayState, batch: dict[str, jax.Array]) -> ReplayState:
    """Write a batch of N whole episodes at the ring position (capacity % N == 0)."""
    cap = capacity(state)
    n = jax.tree.leaves(batch)[0].shape[0]
    chex.assert_equal(cap % n, 0)
    episodes = jax.tree.map(
        lambda buf, x: jax.lax.dynamic_update_slice_in_dim(buf, x.astype(buf.dtype), state.position, axis=0),
        state.episodes,
        batch,
    )
    return ReplayState(episodes=episodes, position=(state.position + n) % cap, size=jnp.minimum(state.size + n, cap))


def sample(
    state: ReplayState,
    key: jax.Array,
    batch_size: int,
    future_p: float,
    compute_reward: Callable[[jax.Array, jax.Array], jax.Array],
) -> dict[str, jax.Array]:
    """A batch of HER-relabelled transitions (s_t, a_t, s_{t+1}, g, r_e) and their indices."""
    eps = state.episodes
    horizon = eps["action"].shape[1]
    key_ep, key_t, key_her, key_future = jax.random.split(key, 4)
    ep = jax.random.randint(key_ep, (batch_size,), 0, jnp.maximum(state.size, 1))
    t = jax.random.randint(key_t, (batch_size,), 0, horizon)
    future_t = jax.random.randint(key_future, (batch_size,), t + 1, horizon + 1)
    relabel = jax.random.uniform(key_her, (batch_size,)) < future_p
    goal = jnp.where(relabel[:, None], eps["achieved_goal"][ep, future_t], eps["desired_goal"][ep])
    next_ag = eps["achieved_goal"][ep, t + 1]
    batch = {
        "proprio": eps["proprio"][ep, t],
        "next_proprio": eps["proprio"][ep, t + 1],
        "action": eps["action"][ep, t],
        "goal": goal,
        "reward": compute_reward(next_ag, goal),
        "episode": ep,
        "t": t,
        "future_t": jnp.where(relabel, future_t, -1),
    }
    if "image" in eps:
        batch["image"] = eps["image"][ep, t]
        batch["next_image"] = eps["image"][ep, t + 1]
    return batch
