"""Training: the epoch compiles once, exploration starts, and a short proprio run learns planar_reach."""

import dataclasses

import chex
import jax
import numpy as np
import pytest

import envs_mjx
from bidal_jax.agents import ddpg
from bidal_jax.config import Config, NetworkConfig, RunConfig, TrainConfig
from bidal_jax.run.devices import make_seeded
from bidal_jax.train import make_train
from envs_mjx.planar_reach import PlanarReach

TINY = TrainConfig(num_envs=4, cycles_per_epoch=2, updates_per_cycle=2, batch_size=8, buffer_episodes=8, eval_envs=4)


class FoldedPlanarReach(PlanarReach):
    """planar_reach whose exploration start is the folded arm q = (0, 2): easy to recognise."""

    has_exploration_start = True

    def _exploration_reset_data(self, key):
        data, goal = self._reset_data(key)
        q0 = np.array([0.0, 2.0], np.float32)
        return data.replace(qpos=q0, ctrl=q0), goal


@pytest.mark.parametrize("agent", ["proprio_baseline", "multimodal_bidal"])
def test_epoch_compiles_once_runs_several_seeds_and_mixes_exploration_starts(agent):
    """One compile serves every epoch and seed; with exploration_starts 0.5, some training
    episodes (picked at random) begin from the env's exploration start and some do not."""
    config = Config(
        RunConfig(agent=agent), dataclasses.replace(TINY, exploration_starts=0.5), NetworkConfig(conv_channels=4)
    )
    env = FoldedPlanarReach(render=config.agent.uses_image)
    chex.clear_trace_counter()
    init, epoch = make_train(env, config)
    init, epoch = make_seeded(init, chex.assert_max_traces(epoch, n=1))
    state = init(jax.random.split(jax.random.PRNGKey(0), 2))
    for _ in range(3):
        state, metrics = epoch(state)
    assert epoch._cache_size() == 1
    assert metrics["eval_success"].shape == (2,)
    assert np.asarray(state.env_steps).tolist() == [3 * 2 * 4 * 50] * 2
    assert np.asarray(state.buffer.size).tolist() == [8, 8]
    # both normalisers saw every transition of every rollout (goals: desired and HER-relabelled)
    assert np.asarray(state.goal_norm.count).tolist() == [3 * 2 * 4 * 50] * 2
    assert np.asarray(state.proprio_norm.count).tolist() == [3 * 2 * 4 * 51] * 2
    for key in ("critic_loss", "actor_loss", "q", "train_success"):
        assert np.isfinite(np.asarray(metrics[key])).all(), key
    if config.agent.family is ddpg.BIDAL:
        assert (np.asarray(metrics["intrinsic_reward"]) <= 0).all()
        assert np.isfinite(np.asarray(metrics["inverse_loss"])).all()
    folded = np.asarray(jax.jit(env.exploration_reset)(jax.random.PRNGKey(1)).obs["proprio"])
    first = np.asarray(state.buffer.episodes["proprio"][:, :, 0])  # step 0 of every stored episode
    eased = np.all(np.abs(first - folded) < 1e-6, axis=-1)
    assert eased.any() and not eased.all(), eased
    # seeds differ
    leaves = jax.tree.leaves(state.params["actor"])
    assert not np.array_equal(np.asarray(leaves[0][0]), np.asarray(leaves[0][1]))


@pytest.mark.slow
def test_proprio_baseline_learns_planar_reach():
    env = envs_mjx.make("planar_reach", render=False)
    config = dataclasses.replace(TrainConfig(), eval_envs=64)
    init, epoch = make_seeded(*make_train(env, Config(RunConfig(agent="proprio_baseline"), config)))
    state = init(jax.random.split(jax.random.PRNGKey(0), 1))
    best = 0.0
    for _ in range(40):
        state, metrics = epoch(state)
        best = max(best, float(metrics["eval_success"][0]))
        if best >= 0.8:
            break
    assert best >= 0.8
