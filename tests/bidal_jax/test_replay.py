"""Replay buffer and HER `future` relabelling (bidal_jax/replay.py)."""

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import replay

T, G = 5, 2


def _episodes(n, offset):
    """Episodes whose achieved goal at step t of episode i is (offset + i, t): traceable."""
    i = jnp.arange(n, dtype=jnp.float32)[:, None] + offset
    t = jnp.arange(T + 1, dtype=jnp.float32)[None, :]
    ag = jnp.stack(jnp.broadcast_arrays(i, t), axis=-1)
    return {
        "proprio": ag,
        "achieved_goal": ag,
        "desired_goal": jnp.full((n, G), -7.0),
        "action": jnp.zeros((n, T, 1)),
    }


def _reward(ag, g):
    return -(jnp.linalg.norm(ag - g, axis=-1) > 0.5).astype(jnp.float32)


def test_insert_wraps_around_and_counts():
    state = replay.init(4, jax.tree.map(lambda x: x[0], _episodes(1, 0)))
    state = replay.insert(state, _episodes(2, 0))
    assert int(state.size) == 2 and int(state.position) == 2
    state = replay.insert(state, _episodes(2, 10))
    state = replay.insert(state, _episodes(2, 20))
    assert int(state.size) == 4 and int(state.position) == 2
    np.testing.assert_array_equal(np.asarray(state.episodes["achieved_goal"][:, 0, 0]), [20, 21, 10, 11])


def test_her_goals_are_later_achieved_goals_of_the_same_episode_with_recomputed_rewards():
    state = replay.init(8, jax.tree.map(lambda x: x[0], _episodes(1, 0)))
    state = replay.insert(state, _episodes(8, 100))
    batch = jax.jit(replay.sample, static_argnums=(2, 3, 4))(state, jax.random.PRNGKey(0), 4096, 0.8, _reward)
    goal, ep, t = np.asarray(batch["goal"]), np.asarray(batch["episode"]), np.asarray(batch["t"])
    future_t = np.asarray(batch["future_t"])
    relabelled = future_t >= 0
    assert 0.75 < relabelled.mean() < 0.85
    # a relabelled goal is the achieved goal (episode id, step) of the same episode, later
    np.testing.assert_array_equal(goal[relabelled, 0], 100 + ep[relabelled])
    np.testing.assert_array_equal(goal[relabelled, 1], future_t[relabelled])
    assert (future_t[relabelled] > t[relabelled]).all() and (future_t[relabelled] <= T).all()
    # the others keep the episode's desired goal
    np.testing.assert_array_equal(goal[~relabelled], -7.0)
    # rewards are recomputed against the (relabelled) goal at s_{t+1}
    next_ag = np.stack([100 + ep, t + 1], axis=-1).astype(np.float32)
    expected = -(np.linalg.norm(next_ag - goal, axis=-1) > 0.5).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(batch["reward"]), expected)
    assert (np.asarray(batch["reward"])[future_t == t + 1] == 0).all()
    # transitions pair s_t with s_{t+1}
    np.testing.assert_array_equal(np.asarray(batch["next_proprio"])[:, 1], t + 1)


def test_her_goals_are_the_desired_and_future_achieved_goals_the_critic_sees():
    episodes = _episodes(3, 10)
    key = jax.random.PRNGKey(3)
    desired = np.asarray(replay.her_goals(episodes, key, 64, future_p=0.0))
    np.testing.assert_array_equal(desired, np.full((64, G), -7.0))
    future = np.asarray(replay.her_goals(episodes, key, 256, future_p=1.0))
    assert set(future[:, 0]) <= {10.0, 11.0, 12.0}  # achieved goals of the three episodes
    assert future[:, 1].min() >= 1 and future[:, 1].max() == T  # of a later step t' in [t+1, T]
    mixed = np.asarray(replay.her_goals(episodes, key, 1000, future_p=0.8))
    share = (mixed[:, 0] != -7.0).mean()
    assert 0.75 < share < 0.85


def _sharded_buffer(shards, capacity, envs, cycles):
    """A buffer as `shards` env shards keep it (each its own contiguous block, `train.make_seeded`)
    after `cycles` inserts of `envs` episodes; episode (cycle c, shard d, env i) is labelled
    100c + 10d + i in its achieved goal."""
    blocks = []
    for d in range(shards):
        state = replay.init(capacity // shards, jax.tree.map(lambda x: x[0], _episodes(1, 0)))
        for c in range(cycles):
            state = replay.insert(state, _episodes(envs // shards, 100 * c + 10 * d))
        blocks.append(state)
    return replay.ReplayState(
        episodes=jax.tree.map(lambda *x: jnp.concatenate(x), *[b.episodes for b in blocks]),
        position=blocks[0].position, size=blocks[0].size,
    )


def test_relayout_keeps_the_episodes_in_insertion_order_for_any_shard_count():
    two = _sharded_buffer(shards=2, capacity=8, envs=4, cycles=3)  # cycle 2 overwrote cycle 0
    one = replay.relayout(two, 2, 1)
    assert int(one.position) == 4 and int(one.size) == 8
    cycle = np.asarray(one.episodes["achieved_goal"][:, 0, 0]) // 100
    np.testing.assert_array_equal(cycle, [2, 2, 2, 2, 1, 1, 1, 1])  # the next insert overwrites cycle 1
    back = replay.relayout(replay.relayout(one, 1, 4), 4, 2)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(two), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a buffer not yet full: its episodes are the first `size` slots in one shard's view
    partial = replay.relayout(_sharded_buffer(shards=4, capacity=16, envs=4, cycles=2), 4, 1)
    assert int(partial.size) == 8 and int(partial.position) == 8
    np.testing.assert_array_equal(np.asarray(partial.episodes["achieved_goal"][:8, 0, 0]) // 100, [0] * 4 + [1] * 4)


def test_draws_are_uniform_over_episodes_steps_and_later_steps():
    """Every episode of the first `n_episodes`, every step and every later step t' in [t+1, T] is drawn, as often
    as the others within sampling error."""
    n, episodes = 64_000, _episodes(8, 0)
    ep, t, future_t, relabel, _ = replay._draw(episodes, jax.random.PRNGKey(1), n, 5, 0.8)
    ep, t, future_t = np.asarray(ep), np.asarray(t), np.asarray(future_t)
    for values, size in ((ep, 5), (t, T)):
        counts = np.bincount(values, minlength=size)
        assert len(counts) == size and np.abs(counts / (n / size) - 1).max() < 0.1
    assert ((future_t > t) & (future_t <= T)).all()
    first = t == 0  # t' uniform over [1, T]
    counts = np.bincount(future_t[first], minlength=T + 1)[1:]
    assert np.abs(counts / (first.sum() / T) - 1).max() < 0.1
    assert 0.79 < np.asarray(relabel).mean() < 0.81


def test_runs_are_consecutive_steps_of_one_episode_and_share_their_frames():
    """`run` 3: each run's transitions are steps t0, t0+1, t0+2 of one episode, t0 uniform over [0, T - 3]; its
    frames are that episode's images at t0 ... t0+3; the goals are drawn per transition (some relabelled, some
    not, within a run)."""
    episodes = {**_episodes(8, 100), "image": (jnp.arange(8 * (T + 1), dtype=jnp.uint8).reshape(8, T + 1, 1, 1, 1))}
    state = replay.insert(replay.init(8, jax.tree.map(lambda x: x[0], episodes)), episodes)
    batch = jax.jit(replay.sample, static_argnums=(2, 3, 4, 5))(state, jax.random.PRNGKey(2), 3000, 0.8, _reward, 3)
    ep, t = np.asarray(batch["episode"]).reshape(1000, 3), np.asarray(batch["t"]).reshape(1000, 3)
    assert (ep == ep[:, :1]).all() and (t == t[:, :1] + np.arange(3)).all()
    counts = np.bincount(t[:, 0], minlength=T - 2)
    assert len(counts) == T - 2 and np.abs(counts / (1000 / (T - 2)) - 1).max() < 0.15
    frames = np.asarray(batch["frames"])
    assert frames.shape == (1000, 4, 1, 1, 1)
    np.testing.assert_array_equal(frames[:, :, 0, 0, 0], ep[:, :1] * (T + 1) + t[:, :1] + np.arange(4))
    relabelled = (np.asarray(batch["future_t"]) >= 0).reshape(1000, 3)
    assert 0 < relabelled.all(axis=1).mean() < relabelled.any(axis=1).mean() < 1
