"""Training: the epoch compiles once, exploration starts, one traced env step serves the cycles and the
evaluation (which `acting.evaluate` reproduces), and a short proprio run learns planar_reach."""

import dataclasses
import functools

import chex
import jax
import jax.extend.core
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting, noise
from bidal_jax.agents import ddpg
from bidal_jax.config import Config, NetworkConfig, RunConfig, TrainConfig
from bidal_jax.run.devices import make_seeded
from bidal_jax.train import Shards, make_learner, make_train
from envs_mjx.planar_reach import PlanarReach
from experiments.bench.programs import full_buffer

TINY = TrainConfig(num_envs=4, cycles_per_epoch=2, updates_per_cycle=2, batch_size=8, buffer_episodes=8, eval_envs=4)


class FoldedPlanarReach(PlanarReach):
    """planar_reach whose exploration start is the folded arm q = (0, 2): easy to recognise."""

    has_exploration_start = True

    def _exploration_reset_data(self, key):
        data, goal = self._reset_data(key)
        q0 = np.array([0.0, 2.0], np.float32)
        return data.replace(qpos=q0, ctrl=q0), goal


@pytest.mark.parametrize("agent", ["proprio_baseline", "multimodal_bidal", "multimodal_bidal_no_ri"])
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
        assert (np.asarray(metrics["intrinsic_reward"]) < 0).all()
    if config.agent.family is ddpg.BIDAL_NO_REWARD:  # the models train, their reward is off (λ = 0)
        assert (np.asarray(metrics["intrinsic_reward"]) == 0).all() and config.train.intrinsic_lambda > 0
    if config.agent.family in (ddpg.BIDAL, ddpg.BIDAL_NO_REWARD):
        assert np.isfinite(np.asarray(metrics["inverse_loss"])).all()
        assert np.isfinite(np.asarray(metrics["forward_loss"])).all()
    folded = np.asarray(jax.jit(env.exploration_reset)(jax.random.PRNGKey(1)).obs["proprio"])
    first = np.asarray(state.buffer.episodes["proprio"][:, :, 0])  # step 0 of every stored episode
    eased = np.all(np.abs(first - folded) < 1e-6, axis=-1)
    assert eased.any() and not eased.all(), eased
    # seeds differ
    leaves = jax.tree.leaves(state.params["actor"])
    assert not np.array_equal(np.asarray(leaves[0][0]), np.asarray(leaves[0][1]))


class MarkedStartPlanarReach(PlanarReach):
    """planar_reach whose exploration start marks its goal (x = 9, out of reach) and whose success metric is that
    mark: an episode succeeds exactly when it began from `exploration_reset`."""

    has_exploration_start = True
    MARK = 9.0

    def _exploration_reset_data(self, key):
        data, goal = self._reset_data(key)
        return data, goal.at[0].set(self.MARK)

    def step(self, state, action):
        state = super().step(state, action)
        marked = (state.info["goal"][0] == self.MARK).astype(state.metrics["success"].dtype)
        return state.replace(metrics={**state.metrics, "success": marked})


def test_training_starts_held_in_about_half_of_the_episodes_and_evaluation_never():
    """With exploration_starts 0.5 (the lifting preset's), about half of the training episodes begin from the
    exploration start, each counted under its start kind, and no evaluation episode does."""
    train = dataclasses.replace(TINY, num_envs=64, buffer_episodes=128, eval_envs=64, exploration_starts=0.5)
    init, epoch = make_seeded(*make_train(MarkedStartPlanarReach(render=False),
                                          Config(RunConfig(agent="proprio_baseline"), train, NetworkConfig())))
    state, metrics = epoch(init(jax.random.split(jax.random.PRNGKey(3), 2)))
    held = np.asarray(metrics["train_success"])  # the share of the 128 training episodes of each seed begun held
    assert ((held > 0.35) & (held < 0.65)).all(), held
    assert np.asarray(metrics["train_success_held"]).tolist() == [1.0, 1.0]
    assert np.asarray(metrics["train_success_table"]).tolist() == [0.0, 0.0]
    assert np.asarray(metrics["eval_success"]).tolist() == [0.0, 0.0]


class GradedPlanarReach(PlanarReach):
    """planar_reach whose success metric is the final distance to the goal: an evaluation result that
    differs wherever one step of one episode does."""

    def step(self, state, action):
        state = super().step(state, action)
        return state.replace(metrics={**state.metrics, "success": state.metrics["distance"]})


def jit_calls(jaxpr: jax.extend.core.Jaxpr, name: str) -> int:
    """How many times `jaxpr` and the jaxprs inside it call a jitted function called `name`."""
    count = 0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("jit", "pjit") and eqn.params.get("name") == name:
            count += 1
            continue
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    count += jit_calls(sub.jaxpr, name)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    count += jit_calls(sub, name)
    return count


@pytest.mark.parametrize("eval_envs, places", [(8, 1), (6, 2)])
def test_the_epoch_steps_and_resets_the_env_in_one_place_when_eval_envs_is_a_multiple_of_num_envs(eval_envs, places):
    """With eval_envs a multiple of num_envs (4) the cycles' exploring rollouts and the evaluation chunks are
    one rollout in the program: one call of the env's (jitted, `acting.traced_once`) step and reset;
    otherwise the evaluation is a rollout of its own (a second call of each)."""
    config = Config(RunConfig(agent="proprio_baseline"), dataclasses.replace(TINY, eval_envs=eval_envs),
                    NetworkConfig())
    init, epoch = make_train(envs_mjx.make("planar_reach", render=False), config)
    jaxpr = jax.make_jaxpr(epoch)(jax.eval_shape(init, jax.random.PRNGKey(0))).jaxpr
    assert (jit_calls(jaxpr, "step"), jit_calls(jaxpr, "reset")) == (places, places)


def test_the_epochs_evaluation_is_acting_evaluate_with_its_eval_key():
    """The epoch evaluates in chunks of num_envs episodes inside its cycles' scan; its episodes, noise draws
    included, are those of one greedy rollout of eval_envs episodes with the state's `eval_key`, which is
    how `experiments.evaluate` reproduces a run's logged evaluation."""
    train = dataclasses.replace(TINY, num_envs=2, cycles_per_epoch=1, updates_per_cycle=1, buffer_episodes=4,
                                eval_envs=6, obs_noise=0.5, noise_segments="q")
    config = Config(RunConfig(agent="proprio_baseline"), train, NetworkConfig())
    env = GradedPlanarReach(render=False)
    init, epoch = make_train(env, config)
    state, metrics = jax.jit(epoch)(init(jax.random.PRNGKey(0)))
    networks = make_learner(env, config, Shards(1)).networks
    noise_map = noise.noise_map(env.observation_spec, ("q",), train.noise_variant)

    @jax.jit
    def mean_distance(state):
        params = acting.acting_params(state, config.agent.family.acting_networks)
        policy = acting.make_policy(networks, config, params)
        observe = functools.partial(noise.observe, state.noise, noise_map)
        return acting.evaluate(env, policy, state.eval_key, train.eval_envs, observe=observe).mean()

    # a 0/1 success's mean is exact in any order; these distances' float sums may differ in the last bit
    np.testing.assert_allclose(float(metrics["eval_success"]), float(mean_distance(state)), rtol=1e-6, atol=0)
    assert float(metrics["eval_success"]) > 0.0


def test_an_update_of_runs_encodes_each_runs_frames_once():
    """`sample_run` 4 with a batch of 8: the learner's update draws 2 runs of 4 transitions and its encoder reads
    their 2 × 5 frames once (10 frames in one pass, not 16); the update's losses are finite."""
    config = Config(RunConfig(agent="multimodal_bidal"), dataclasses.replace(TINY, sample_run=4),
                    NetworkConfig(conv_channels=4))
    env = PlanarReach(render=True)
    init, _ = make_train(env, config)
    state = full_buffer(init(jax.random.PRNGKey(0)))
    update = make_learner(env, config, Shards(1)).update
    frames = [eqn.invars[0].aval.shape[0] for eqn in jax.make_jaxpr(update)(state, jax.random.PRNGKey(1)).eqns
              if eqn.primitive.name == "convert_element_type" and eqn.invars[0].aval.shape[1:] == (42, 42, 1)]
    assert frames == [10]
    _, metrics = jax.jit(update)(state, jax.random.PRNGKey(1))
    for key in ("critic_loss", "forward_loss", "inverse_loss", "actor_loss"):
        assert np.isfinite(float(metrics[key])), key


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
