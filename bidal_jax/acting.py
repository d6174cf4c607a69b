"""Acting: the policy as a function of (parameters, normalisers, observation), one rollout
for everything that steps environments, and evaluation.

- `make_policy(networks, config, params, explore=False)`: the agent's policy (its family's `act`;
  DDPG's actor μ(ψ(s), η(g)), paper Eq. 7) on normalised inputs; exploring adds Gaussian noise and ε-random actions
  (`exploring`, HER's exploration).
- `rollout(env, policy, key, n_envs)`: `n_envs` vmapped envs stepped by `policy` for one
  episode (or `steps`) inside one `lax.scan`. Training, evaluation, the benchmark, the
  scripted NICOL controller and the tests all step envs through it.
- `evaluate(env, policy, key, n_episodes)`: success at the last step of each episode.

Loading a trained policy from a checkpoint is the run machinery's (`bidal_jax.run.policy`).

A policy is any function `policy(obs, x) -> action` of a batched observation dict
(`proprio` [N, D], `image` [N, 42, 42, 1], `achieved_goal`, `desired_goal` [N, G]) and the
step's input `x` (a PRNG key by default) returning actions [N, A] in [-1, 1]. The learner
sees an env only through its functional API (`reset`, `step`, `episode_length`,
`action_size`, `observation_spec`), so this module imports no MuJoCo.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import chex
import jax
import jax.numpy as jnp
from flax import struct

from bidal_jax import normalizer
from bidal_jax.config import Config

Policy = Callable[[dict, Any], jax.Array]
# what the agent observes of a state: observe(obs, key) -> obs (e.g. with sensor noise)
Observer = Callable[[dict, jax.Array], dict]


class Step(NamedTuple):
    """One control period of a rollout, as `record` sees it."""

    state: Any  # the batched env state before the step
    obs: dict  # what the policy observed of it (state.obs, or `observe`'s noisy version)
    action: jax.Array
    next_state: Any


# what a rollout records per step: record(step) -> pytree
Recorder = Callable[[Step], Any]
ACTING_SCOPE = "acting"  # `jax.named_scope` of the policy's pass in a rollout (profiles attribute kernels by it)


@struct.dataclass
class ActingParams:
    """What a policy needs: the parameters of the networks it reads and the normalisers' statistics."""

    params: dict
    proprio_norm: normalizer.NormalizerState
    goal_norm: normalizer.NormalizerState


def acting_params(state: Any, networks: tuple[str, ...]) -> ActingParams:
    """The acting part of a `TrainState` (or of any object with the same fields): the parameters of
    `networks` (the family's `acting_networks`) and the normalisers."""
    return ActingParams(
        params={k: v for k, v in state.params.items() if k in networks},
        proprio_norm=state.proprio_norm,
        goal_norm=state.goal_norm,
    )


def make_policy(networks: Any, config: Config, params: ActingParams, explore: bool | jax.Array = False) -> Policy:
    """The policy of `params` (the family's `act`; DDPG's μ(ψ(s), η(g)), paper Eq. 7) with the agent's
    `networks`, on batched observations.

    Proprio and goals are normalised (clipped to ±`train.clip_obs`) as in training. With
    `explore`, actions get Gaussian noise of std `noise_eps` (then clipped to [-1, 1]) and
    are replaced by uniform random actions with probability `random_eps` (HER's exploration);
    the policy's input `x` must then be a PRNG key. `explore` may be a traced bool (one program
    that both explores and evaluates, as a training epoch's one rollout): where it is false the
    actions are the greedy ones exactly.
    """
    agent, train = config.agent, config.train

    def act(obs: dict, x: Any) -> jax.Array:
        image = obs["image"] if agent.uses_image else None
        proprio = normalizer.normalize(params.proprio_norm, obs["proprio"], train.clip_obs)
        goal = normalizer.normalize(params.goal_norm, obs["desired_goal"], train.clip_obs)
        action = agent.family.act(networks, params.params, image, proprio, goal)
        if explore is False:
            return action
        explored = exploring(action, x, train.noise_eps, train.random_eps)
        return explored if explore is True else jnp.where(explore, explored, action)

    return act


def exploring(action: jax.Array, key: jax.Array, noise_eps: float, random_eps: float) -> jax.Array:
    """HER's exploration around actions [N, A]: Gaussian noise of std `noise_eps` (then clipped to [-1, 1]),
    and each row replaced by a uniform random action with probability `random_eps`."""
    chex.assert_rank(action, 2)
    key_noise, key_random, key_pick = jax.random.split(key, 3)
    action = jnp.clip(action + noise_eps * jax.random.normal(key_noise, action.shape), -1.0, 1.0)
    random_action = jax.random.uniform(key_random, action.shape, minval=-1.0, maxval=1.0)
    pick = jax.random.uniform(key_pick, (action.shape[0], 1)) < random_eps
    return jnp.where(pick, random_action, action)


def random_policy(action_size: int, scale: float = 1.0) -> Policy:
    """Uniform random actions in [-scale, scale] (scale > 1 tests the env's clipping)."""

    def act(obs: dict, key: jax.Array) -> jax.Array:
        n = obs["proprio"].shape[0]
        return jax.random.uniform(key, (n, action_size), minval=-scale, maxval=scale)

    return act


def open_loop(obs: dict, action: jax.Array) -> jax.Array:
    """A policy that plays the rollout's `inputs` (actions [steps, N, A]) one step at a time."""
    return action


@functools.lru_cache(maxsize=16)
def traced_once(env_fn: Callable) -> Callable:
    """`jax.jit(env_fn)`, the same object for each env function (a bound method: `env.step`, `env.reset`), so
    that every rollout of a program reuses its jaxpr from JAX's trace cache: a program that steps the env in
    several places traces the physics once. Inside a program the jit is inlined; the computation is the same."""
    return jax.jit(env_fn)


class Starts(NamedTuple):
    """How `n` episodes begin: the keys of `env.reset` [n], and with exploration starts the keys of
    `env.exploration_reset` [n] and which episodes begin from it (bool [n])."""

    reset: jax.Array
    eased: jax.Array | None = None
    pick: jax.Array | None = None


def draw_starts(key: jax.Array, n_envs: int, exploration_starts: float = 0.0) -> Starts:
    """The starts of `n_envs` episodes, a fraction `exploration_starts` of them (drawn at random) from
    `env.exploration_reset` (e.g. nicol_lift's cube already held); 0: every one from `env.reset`."""
    if exploration_starts <= 0:
        return Starts(jax.random.split(key, n_envs))
    key_reset, key_eased, key_pick = jax.random.split(key, 3)
    pick = jax.random.uniform(key_pick, (n_envs,)) < exploration_starts
    return Starts(jax.random.split(key_reset, n_envs), jax.random.split(key_eased, n_envs), pick)


def states_at(env, starts: Starts):
    """The batched initial states of `starts`."""
    state = jax.vmap(traced_once(env.reset))(starts.reset)
    if starts.eased is None:
        return state
    return picked(starts.pick, jax.vmap(traced_once(env.exploration_reset))(starts.eased), state)


def picked(pick: jax.Array, eased: Any, state: Any) -> Any:
    """The states [n] of `eased` where `pick` [n] holds, else of `state`. A leaf without the envs' axis (MuJoCo Warp's
    data holds empty arrays that all its worlds share) is the same in either and is kept."""

    def leaf(e: jax.Array, s: jax.Array) -> jax.Array:
        if s.shape[:1] != pick.shape:
            return s
        return jnp.where(pick.reshape((-1,) + (1,) * (s.ndim - 1)), e, s)

    return jax.tree.map(leaf, eased, state)


def _no_record(step: Step) -> None:
    return None


def rollout(
    env,
    policy: Policy,
    key: jax.Array,
    n_envs: int | None = None,
    *,
    states: Any = None,
    steps: int | None = None,
    inputs: Any = None,
    record: Recorder = _no_record,
    observe: Observer | None = None,
) -> tuple[Any, Any]:
    """Step `n_envs` vmapped envs with `policy` for `steps` control periods (default: one episode).

    Args:
      env: an environment with the functional API (`reset`, `step`, `episode_length`, ...).
      policy: `policy(obs, x) -> action` on batched observations (module docstring).
      key: PRNG key: the start states (unless `states` is given) and each step's key (the
        policy's input unless `inputs` is given).
      n_envs: how many envs start from `env.reset`; omit when `states` is given.
      states: batched start states (e.g. `states_at(env, draw_starts(...))` with exploration starts).
      steps: control periods to run (default `env.episode_length`).
      inputs: per-step policy inputs [steps, ...] used instead of keys (e.g. open-loop actions).
      record: `record(step)` of each `Step`, stacked over steps as the second output.
      observe: `observe(obs, key) -> obs`, what the policy sees of each state (e.g. noisy
        proprio); its key is `fold_in(step key, 1)`, so the policy's own keys are unchanged.

    Returns:
      (final batched state, the stacked records [steps, ...]).
    """
    key_reset, key_steps = jax.random.split(key)
    if states is None:
        states = states_at(env, draw_starts(key_reset, n_envs))
    n_steps = jax.tree.leaves(inputs)[0].shape[0] if inputs is not None else steps or env.episode_length
    keys = jax.random.split(key_steps, n_steps)

    def body(state, xs):
        key, x = xs
        with jax.named_scope(ACTING_SCOPE):
            obs = state.obs if observe is None else observe(state.obs, jax.random.fold_in(key, 1))
            action = policy(obs, x)
        next_state = jax.vmap(traced_once(env.step))(state, action)
        return next_state, record(Step(state, obs, action, next_state))

    return jax.lax.scan(body, states, (keys, keys if inputs is None else inputs))


def evaluate(
    env, policy: Policy, key: jax.Array, n_episodes: int | None = None, states: Any = None,
    observe: Observer | None = None,
) -> jax.Array:
    """Success (paper Eq. 6 at the episode's last step, on the true state) of `policy` in each of
    `n_episodes` episodes from `env.reset`, or from the given batched `states`; float32 [n_episodes]."""
    final, _ = rollout(env, policy, key, n_episodes, states=states, observe=observe)
    return final.metrics["success"]
