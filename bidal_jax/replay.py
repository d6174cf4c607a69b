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
import numpy as np
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


def episode_template(env, uses_image: bool, n_noisy: int) -> dict:
    """Zeros shaped like one replay episode of `env`: T+1 observations, T actions, its desired goal
    (and the image, and the clean copies of `n_noisy` noised features, where the run has them)."""
    spec, horizon = env.observation_spec, env.episode_length
    episode = {
        "proprio": jnp.zeros((horizon + 1, spec.proprio_size), jnp.float32),
        "achieved_goal": jnp.zeros((horizon + 1, spec.goal_size), jnp.float32),
        "desired_goal": jnp.zeros((spec.goal_size,), jnp.float32),
        "action": jnp.zeros((horizon, env.action_size), jnp.float32),
    }
    if uses_image:
        episode["image"] = jnp.zeros((horizon + 1, *spec.image_shape), jnp.uint8)
    if n_noisy:
        episode["clean"] = jnp.zeros((horizon + 1, n_noisy), jnp.float32)
    return episode


def _with_final(x: jax.Array, last: jax.Array) -> jax.Array:
    """[T, N, ...] steps and the final [N, ...] as episodes [N, T+1, ...]."""
    return jnp.swapaxes(jnp.concatenate([x, last[None]]), 0, 1)


def to_episodes(records: tuple, final_obs: dict, last_obs: dict, noisy: jax.Array, uses_image: bool) -> dict:
    """Replay episodes [N, ...] from a rollout's `records` (observations as the agent saw them, actions
    and the clean noised features, each [T, N, ...]), the final true observation `final_obs` and what
    the agent saw of it, `last_obs`."""
    obs, actions, clean = records
    episodes = {
        "proprio": _with_final(obs["proprio"], last_obs["proprio"]),
        "achieved_goal": _with_final(obs["achieved_goal"], last_obs["achieved_goal"]),
        "desired_goal": final_obs["desired_goal"],
        "action": jnp.swapaxes(actions, 0, 1),
    }
    if uses_image:
        episodes["image"] = _with_final(obs["image"], last_obs["image"])
    if len(noisy):
        episodes["clean"] = _with_final(clean, final_obs["proprio"][..., noisy])
    return episodes


def _draw(episodes: dict, key: jax.Array, n: int, n_episodes: jax.Array | int, future_p: float, run: int = 1):
    """n transitions (episode, step t) drawn as n / `run` runs of `run` consecutive steps of one episode, the
    episodes uniform over the first `n_episodes` and each run's first step uniform over [0, T - run] (with run 1:
    uniform transitions, HER's draw), and their goals, each its own: with probability `future_p` the achieved goal
    of a later step t' ∈ [t+1, T] (HER `future`), else the episode's desired goal. Returns (ep, t, t', relabelled,
    goal), the transitions run after run."""
    horizon = episodes["action"].shape[1]
    # one draw of 32 random bits per choice, reduced modulo its range (a bias below range / 2^32): far less code
    # than three `jax.random.randint`s of two draws each, in a draw made in every update
    bits = jax.random.bits(key, (4, n), jnp.uint32)
    ep = jnp.repeat((bits[0, ::run] % jnp.asarray(n_episodes, jnp.uint32)).astype(jnp.int32), run)
    start = (bits[1, ::run] % (horizon - run + 1)).astype(jnp.int32)
    t = (start[:, None] + jnp.arange(run, dtype=jnp.int32)).reshape(n)
    future_t = t + 1 + (bits[2] % (horizon - t).astype(jnp.uint32)).astype(jnp.int32)
    relabel = (bits[3] >> 8).astype(jnp.float32) * 2.0**-24 < future_p  # uniform in [0, 1) on a 2^-24 grid
    goal = jnp.where(relabel[:, None], episodes["achieved_goal"][ep, future_t], episodes["desired_goal"][ep])
    return ep, t, future_t, relabel, goal


def her_goals(episodes: dict[str, jax.Array], key: jax.Array, n: int, future_p: float) -> jax.Array:
    """The goals [n, G] of n transitions of `episodes` relabelled as `sample` relabels them: what
    the goal normaliser sees (HER's reference normalises the goals the critic is given)."""
    return _draw(episodes, key, n, jax.tree.leaves(episodes)[0].shape[0], future_p)[-1]


def sample(
    state: ReplayState,
    key: jax.Array,
    batch_size: int,
    future_p: float,
    compute_reward: Callable[[jax.Array, jax.Array], jax.Array],
    run: int = 1,
) -> dict[str, jax.Array]:
    """A batch of HER-relabelled transitions (s_t, a_t, s_{t+1}, g, r_e) and their indices, drawn as
    batch_size / `run` runs of `run` consecutive steps (`_draw`). Image agents' frames come once per run:
    "frames" [batch_size / run, run + 1, H, W, 1], the run's s_t ... s_{t+run}, which its transitions share
    (`TrainConfig.sample_run`; with run 1, each transition's s_t and s_{t+1})."""
    chex.assert_equal(batch_size % run, 0)
    eps = state.episodes
    ep, t, future_t, relabel, goal = _draw(eps, key, batch_size, jnp.maximum(state.size, 1), future_p, run)
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
        steps = t[::run, None] + jnp.arange(run + 1, dtype=jnp.int32)
        batch["frames"] = eps["image"][ep[::run, None], steps]
    return batch


def _slots(capacity: int, shards: int) -> np.ndarray:
    """For each slot c of the shard-independent order, its index in a buffer kept by `shards`
    shards, each holding a contiguous block of `capacity / shards` slots: slot c is slot c // k
    of shard c % k (each shard writes its envs' episodes at the same local position)."""
    c = np.arange(capacity)
    return (c % shards) * (capacity // shards) + c // shards


def relayout(state: ReplayState, shards_from: int, shards_to: int, axis: int = 0) -> ReplayState:
    """The buffer kept by `shards_from` env shards (`train.make_train`; one shard's `position`
    and `size` count its own slots) as `shards_to` shards keep it: the same episodes in the
    same order of insertion, so that a run resumes on another device count. Episodes lie on
    `axis` (1 after a seed axis); both shard counts divide the envs per cycle."""
    if shards_from == shards_to:
        return state
    cap = jax.tree.leaves(state.episodes)[0].shape[axis]
    order = _slots(cap, shards_from)[np.argsort(_slots(cap, shards_to))]
    return ReplayState(
        episodes=jax.tree.map(lambda x: jnp.take(x, order, axis=axis), state.episodes),
        position=state.position * shards_from // shards_to,
        size=state.size * shards_from // shards_to,
    )
