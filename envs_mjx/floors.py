"""A task's floor: the success of a policy that does nothing, from the task's own start and goal distributions.

A score means little without it: on nicol_slide a policy that never moves succeeds whenever the goal happens to
lie within ε of the resting cube. `floor(env, key, rollouts, resets)` estimates it over all goals and over each
goal subset of the task (`Env.goal_subsets`, e.g. nicol_lift's air and table goals), with its Monte Carlo
interval, through the Env API alone (`reset`, `step`, `goal_subsets`), without rendering.

"Does nothing" (`idle_action`): every action entry that is an increment (hand or joint motion, hand roll and
tilt) is 0, so that the targets stay where the start left them; NICOL's finger closure and thumb abduction are
absolute commands (docs/tasks.md: -1 open, +1 closed), and 0 would half close the hand, so they hold the
command `reset` sets (open, -1). The arm still settles under its controllers (a droop that moves the achieved
goal counts: that is what doing nothing does).

The estimator. Success at the episode's last step, s_T, is estimated as

    floor = mean over N resets of s_0 + mean over M rollouts of (s_T − s_0),

s_0 the success of the start itself (the goal within ε of where the task's object starts): a control variate.
Resets cost a forward pass; rollouts cost T steps of physics (NICOL's about 0.1 s each on a CPU). Where doing
nothing leaves the object where it started, s_T − s_0 is almost always 0 and M rollouts pin down what a few
hundred thousand resets cannot afford to simulate. Both terms are unbiased and independent, so the estimate is,
and its variance is p₀(1 − p₀)/N + Var(s_T − s_0)/M (95 % half-width: 1.96 standard errors; Var(s_T − s_0) taken
at least 1/M, as if one of the M episodes had changed, so that M episodes without a change bound it rather than
call it exact). Per goal subset the
same, over the resets and rollouts whose goal lies in it.

The analytic values, where the distributions give one (the object at rest at its start): nicol_slide's goal is
drawn independently of the cube, uniformly over a 0.5 m square that holds every disk of radius ε around a
start, so its floor is πε²/0.5² = 0.0314; nicol_lift's table goals lie within ±0.1 m (xy) of the cube's start at
its resting height, πε²/0.2² = 0.196, its air goals 0.05-0.25 m above the table (the cube centre 0.025-0.225 m
above its resting centre): ∫ π(ε² − z²)/0.2² dz/0.2 over z in [0.025, ε] = 0.0102, and over all goals their
mean, 0.103. tests/envs_mjx/test_floors.py holds the estimates to them.
"""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np

from envs_mjx.base import Env
from envs_mjx.nicol import NicolEnv

ALL = "all"  # the subset of every goal
Z95 = 1.959963984540054
NICOL_ABSOLUTE = slice(5, 7)  # NICOL's finger closure and thumb abduction: absolute commands (envs_mjx/nicol.py)


@dataclasses.dataclass(frozen=True)
class Floor:
    """One subset's floor: the estimate, its 95 % Monte Carlo half-width, and the resets and rollouts behind it."""

    value: float
    half_width: float
    resets: int
    rollouts: int

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def idle_action(env: Env) -> jax.Array:
    """The action [A] of a policy that does nothing (see the module docstring): 0 for increments, and NICOL's
    absolute finger and thumb commands at reset's (-1, open)."""
    action = jnp.zeros(env.action_size, jnp.float32)
    return action.at[NICOL_ABSOLUTE].set(-1.0) if isinstance(env, NicolEnv) else action


def subsets(env: Env, goal: jax.Array) -> dict[str, jax.Array]:
    """{"all": every goal, **`env.goal_subsets`}: boolean masks [...] over goals [..., G]."""
    return {ALL: jnp.ones(goal.shape[:-1], bool), **env.goal_subsets(goal)}


def start_success(env: Env, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
    """(s_0, subsets) of one reset: whether its start already meets its goal, and the goal's subsets."""
    state = env.reset(key)
    success = env.compute_reward(state.obs["achieved_goal"], state.obs["desired_goal"]) == 0.0
    return success, subsets(env, state.obs["desired_goal"])


def idle_rollout(env: Env, key: jax.Array) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
    """(s_0, s_T, subsets) of one episode of `idle_action` from a reset."""
    action = idle_action(env)
    state = env.reset(key)
    first = env.compute_reward(state.obs["achieved_goal"], state.obs["desired_goal"]) == 0.0
    state = jax.lax.fori_loop(0, env.episode_length, lambda _, s: env.step(s, action), state)
    last = env.compute_reward(state.obs["achieved_goal"], state.obs["desired_goal"]) == 0.0
    return first, last, subsets(env, state.obs["desired_goal"])


def batched(fn, env: Env, key: jax.Array, n: int, batch: int):
    """`fn(env, key)` over `n` keys split from `key`, vmapped `batch` at a time (one compiled program), as numpy
    arrays concatenated over the batches."""
    run = jax.jit(jax.vmap(lambda k: fn(env, k)))
    keys = jax.random.split(key, -(-n // batch) * batch).reshape(-1, batch)
    parts = [jax.tree.map(np.asarray, run(k)) for k in keys]
    return jax.tree.map(lambda *xs: np.concatenate(xs)[:n], *parts)


def combine(start: np.ndarray, start_in: np.ndarray, first: np.ndarray, last: np.ndarray,
            rollout_in: np.ndarray) -> tuple[float, float]:
    """(estimate, 95 % half-width) of the module's estimator over one subset: `start` s_0 of the resets [N] and
    `start_in` whether each is in the subset; `first`, `last` s_0 and s_T of the rollouts [M], `rollout_in` theirs."""
    chex.assert_equal_shape([start, start_in])
    chex.assert_equal_shape([first, last, rollout_in])
    s0 = start[start_in].astype(np.float64)
    change = last[rollout_in].astype(np.float64) - first[rollout_in].astype(np.float64)
    if s0.size < 2 or change.size < 2:
        raise ValueError(f"floor: a subset needs at least 2 resets and 2 rollouts, got {s0.size} and {change.size}")
    # the change's variance at least that of one change in M: M idle episodes without one bound its rate, not zero it
    variance = s0.var(ddof=1) / s0.size + max(change.var(ddof=1), 1.0 / change.size) / change.size
    return float(s0.mean() + change.mean()), float(Z95 * np.sqrt(variance))


def floor(env: Env, key: jax.Array, rollouts: int, resets: int, batch: int = 1024) -> dict[str, Floor]:
    """Subset name ("all", then `env.goal_subsets`'s) -> its `Floor`: `resets` resets and `rollouts` episodes of
    `idle_action` (the module docstring's estimator), in vmapped batches of at most `batch`."""
    if env.render:
        raise ValueError(f"floor: build {env.name} with render=False (the floor needs no frames)")
    key_resets, key_rollouts = jax.random.split(key)
    start, start_in = batched(start_success, env, key_resets, resets, min(batch * 8, resets))
    first, last, rollout_in = batched(idle_rollout, env, key_rollouts, rollouts, min(batch, rollouts))
    found = {}
    for name in start_in:
        value, half = combine(start, start_in[name], first, last, rollout_in[name])
        found[name] = Floor(value, half, int(start_in[name].sum()), int(rollout_in[name].sum()))
    return found
