"""Observation noise (paper Eq. 9): σ is numpy's IQR of the clean history, only the named
segments and the features derived from them get noise (achieved goals only in the noisy-goal
variant, rewards never), κ = 0 equals a run without noise up to float rounding, and one traced epoch
serves every κ."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting, noise
from bidal_jax.config import Config, RunConfig, TrainConfig
from bidal_jax.run.devices import make_seeded, seed_sharding
from bidal_jax.train import make_train
from envs_mjx import nicol
from envs_mjx.base import ObservationSpec

TINY = TrainConfig(num_envs=4, cycles_per_epoch=2, updates_per_cycle=2, batch_size=8, buffer_episodes=8, eval_envs=4)
NOISY = dataclasses.replace(TINY, noise_segments="q")
KAPPAS = np.array([0.0, 0.05, 0.15], np.float32)


@pytest.fixture(scope="module")
def env():
    return envs_mjx.make("planar_reach", render=False)


def test_sigma_is_numpys_interquartile_range_of_the_valid_history():
    rng = np.random.default_rng(0)
    history = rng.normal(size=(7, 5, 3)).astype(np.float32)  # 7 episodes of 5 steps, 3 features
    valid = 4  # only the first 4 episodes are filled
    state = noise.refresh(noise.init(0.1, 3), jnp.asarray(history), jnp.asarray(valid))
    rows = history[:valid].reshape(-1, 3)
    expected = np.percentile(rows, 75, axis=0) - np.percentile(rows, 25, axis=0)
    np.testing.assert_allclose(np.asarray(state.sigma), expected, rtol=1e-6)
    empty = noise.refresh(noise.init(0.1, 3), jnp.asarray(history), jnp.asarray(0))
    np.testing.assert_array_equal(np.asarray(empty.sigma), np.zeros(3))


def test_unknown_segments_are_refused():
    with pytest.raises(ValueError, match="'obj_pos'"):
        noise.feature_indices((("q", 2), ("qdot", 2)), ("obj_pos",))


def test_only_the_named_segments_get_noise_never_achieved_goals_or_rewards(env):
    """The same open-loop actions with and without noise: identical env states, rewards and
    achieved goals; the agent's q differs by noise of std κσ, its qdot not at all."""
    kappa, sigma = 0.5, np.array([0.2, 0.4], np.float32)
    state = noise.NoiseState(kappa=jnp.float32(kappa), sigma=jnp.asarray(sigma))
    noise_map = noise.noise_map(env.observation_spec, ("q",))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (env.episode_length, 64, 2), minval=-1, maxval=1)

    def run(observe):
        return acting.rollout(
            env, acting.open_loop, jax.random.PRNGKey(0), 64, inputs=actions, observe=observe,
            record=lambda step: (step.obs, step.state.obs, step.next_state.reward),
        )[1]

    seen, true, reward = jax.jit(lambda: run(lambda obs, key: noise.observe(state, noise_map, obs, key)))()
    _, clean, clean_reward = jax.jit(lambda: run(None))()
    np.testing.assert_array_equal(np.asarray(true["proprio"]), np.asarray(clean["proprio"]))
    np.testing.assert_array_equal(np.asarray(reward), np.asarray(clean_reward))
    np.testing.assert_array_equal(np.asarray(seen["achieved_goal"]), np.asarray(clean["achieved_goal"]))
    np.testing.assert_array_equal(np.asarray(seen["proprio"][..., 2:]), np.asarray(clean["proprio"][..., 2:]))
    error = np.asarray(seen["proprio"][..., :2] - clean["proprio"][..., :2]).reshape(-1, 2)
    np.testing.assert_allclose(error.std(axis=0), kappa * sigma, rtol=0.05)
    assert abs(error.mean()) < 0.01


def _train(env, config, kappas=None, epochs=2, count_traces=False):
    init, epoch = make_train(env, Config(RunConfig(agent="proprio_baseline"), config))
    if count_traces:
        chex.clear_trace_counter()
        epoch = chex.assert_max_traces(epoch, n=1)
    init, epoch = make_seeded(init, epoch)
    n = 1 if kappas is None else len(kappas)
    state = init(jax.random.split(jax.random.PRNGKey(0), n))
    if kappas is not None:  # as loop.build places an initialized state: on the seed devices
        state = jax.device_put(state.replace(noise=state.noise.replace(kappa=jnp.asarray(kappas))),
                               seed_sharding(jax.devices()[:1]))
    history = []
    for _ in range(epochs):
        state, metrics = epoch(state)
        history.append(jax.device_get(metrics))
    return state, history, epoch


@pytest.fixture(scope="module")
def noisy_runs(env):
    """Three κ as three vmapped runs of one program (the same seed key for each, so only κ differs)."""
    return _train(env, NOISY, kappas=KAPPAS, count_traces=True)


def test_one_traced_epoch_serves_every_kappa(noisy_runs):
    state, history, epoch = noisy_runs
    assert epoch._cache_size() == 1  # and chex.assert_max_traces(n=1) did not raise
    np.testing.assert_array_equal(np.asarray(state.noise.kappa), KAPPAS)
    # the stored transitions hold what the agent saw: clean q plus κ-scaled noise
    stored = np.asarray(state.buffer.episodes["proprio"][..., :2])
    clean = np.asarray(state.buffer.episodes["clean"])
    error = (stored - clean).reshape(len(KAPPAS), -1, 2)
    assert np.all(error[0] == 0) and error[1].std() > 0 and error[2].std() > 2 * error[1].std()
    # the last rollout's noise has std κσ with σ from its refresh (the σ still in the state)
    last = (np.asarray(state.buffer.position)[0] - TINY.num_envs) % TINY.buffer_episodes
    newest = error.reshape(len(KAPPAS), TINY.buffer_episodes, -1, 2)[:, last : last + TINY.num_envs].reshape(
        len(KAPPAS), -1, 2
    )
    sigma = np.asarray(state.noise.sigma)
    assert (sigma > 0).all()
    np.testing.assert_allclose(newest[2].std(axis=0), KAPPAS[2] * sigma[2], rtol=0.25)


def test_kappa_zero_equals_a_run_without_noise(env, noisy_runs):
    # two different XLA programs (with and without the noise code; one seed, three vmapped κ): equal up to
    # float rounding, not bit for bit (XLA:CPU orders some sums differently); any noise reaching the κ = 0 run
    # would move these by far more than the tolerance
    plain_state, plain, _ = _train(env, TINY)
    noisy_state, noisy, _ = noisy_runs
    for before, after in zip(plain, noisy):
        for key, value in before.items():
            np.testing.assert_allclose(
                np.asarray(value)[0], np.asarray(after[key])[0], rtol=1e-5, atol=1e-6, err_msg=key
            )
    for a, b in zip(jax.tree.leaves(plain_state.params), jax.tree.leaves(noisy_state.params)):
        np.testing.assert_allclose(np.asarray(a)[0], np.asarray(b)[0], rtol=1e-5, atol=1e-6)


NICOL_SPEC = ObservationSpec(proprio_segments=nicol.PROPRIO_SEGMENTS, goal_size=3, derived=nicol.DERIVED,
                             goal_segment="obj_pos")
MEASURED = ("ee_pos", "ee_rot", "obj_pos")


def _noisy_nicol_obs(variant: str, spec: ObservationSpec = NICOL_SPEC):
    """(true obs, what the agent sees) of 256 random NICOL observations under `variant`."""
    key_obs, key_goal, key_noise = jax.random.split(jax.random.PRNGKey(3), 3)
    obs = {"proprio": jax.random.normal(key_obs, (256, spec.proprio_size)),
           "achieved_goal": jax.random.normal(key_goal, (256, 3))}
    nmap = noise.noise_map(spec, MEASURED, variant)
    state = noise.NoiseState(kappa=jnp.float32(1.0), sigma=jnp.linspace(0.1, 0.9, len(nmap.indices)))
    return obs, noise.observe(state, nmap, obs, key_noise)


def _segment(obs, name, spec=NICOL_SPEC):
    return np.asarray(obs["proprio"][:, spec.segment_slice(name)])


def test_obj_rel_pos_carries_the_noise_of_obj_pos_and_ee_pos():
    """A feature derived from noisy measurements is noisy: obj_rel_pos = noisy obj_pos - noisy ee_pos."""
    true, seen = _noisy_nicol_obs("derived")
    delta = {n: _segment(seen, n) - _segment(true, n) for n in ("ee_pos", "obj_pos", "obj_rel_pos", "q")}
    assert np.abs(delta["obj_pos"]).min() > 0 and np.abs(delta["ee_pos"]).min() > 0
    np.testing.assert_allclose(delta["obj_rel_pos"], delta["obj_pos"] - delta["ee_pos"], atol=1e-5)
    np.testing.assert_array_equal(delta["q"], 0.0)
    np.testing.assert_array_equal(np.asarray(seen["achieved_goal"]), np.asarray(true["achieved_goal"]))


def test_the_literal_variant_leaves_derived_features_clean_and_noisy_goal_moves_the_achieved_goal():
    true, seen = _noisy_nicol_obs("literal")
    np.testing.assert_array_equal(_segment(seen, "obj_rel_pos"), _segment(true, "obj_rel_pos"))
    assert np.abs(_segment(seen, "obj_pos") - _segment(true, "obj_pos")).min() > 0
    true, seen = _noisy_nicol_obs("noisy_goal")
    np.testing.assert_allclose(np.asarray(seen["achieved_goal"] - true["achieved_goal"]),
                               _segment(seen, "obj_pos") - _segment(true, "obj_pos"), atol=1e-5)


def test_a_reduced_spec_drops_the_derived_segment_and_a_noisy_goal_needs_its_segment_noised():
    reduced = NICOL_SPEC.without(nicol.REDUCED_DROP)
    assert reduced.derived == () and reduced.goal_segment == "obj_pos"
    nmap = noise.noise_map(reduced, MEASURED)
    np.testing.assert_array_equal(nmap.spread[:, nmap.indices], np.eye(len(nmap.indices)))
    assert np.count_nonzero(nmap.spread) == len(nmap.indices)
    with pytest.raises(ValueError, match="noisy_goal: the achieved goal is segment 'obj_pos'"):
        noise.noise_map(NICOL_SPEC, ("ee_pos",), "noisy_goal")
    with pytest.raises(ValueError, match="unknown noise variant 'loud'"):
        noise.noise_map(NICOL_SPEC, MEASURED, "loud")
