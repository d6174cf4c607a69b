"""A scripted (non-learning) grasp controller for nicol_slide and nicol_lift.

It shows that the NICOL model's physics allows grasping and moving the cube within the
50-step episode (docs/tasks.md). One controller serves both tasks: `grasp_policy` hovers
above the cube, descends, closes fingers and thumb on it and carries it to the goal; on
nicol_slide the goal lies on the table, so the held cube slides along the table top. It
is a pure, stateless JAX function of one observation (its named proprio segments and the
desired goal), so it vmaps over environments; the phase of the manoeuvre is read from
the observation itself.

Its command line is `python -m experiments.probes.scripted` (success rates over 100 random episodes each).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from bidal_jax.acting import Policy, evaluate
from envs_mjx.base import Env, ObservationSpec, State
from envs_mjx.nicol import MAX_MOVE

FINGERS_ENGAGED = 0.3  # rad of finger closure: a grasp is under way
FINGERS_CLOSED = 1.3  # rad of finger closure that means the cube is held (they meet its top edges at about 1.35)
HOVER = 0.06  # m above the cube before descending
# m of the grasp point above the cube's centre: the closed fingers' tips then clear the table top
GRASP_HEIGHT = 0.02
ALIGNED = 0.005  # m
HELD = 0.04  # m between grasp point and cube while the fingers hold it
# m per step while carrying the cube (0.375 m/s): the grip holds; 0.01 left the farthest slide goals
# (> 0.28 m) unreached once issue 24's slower fingers held the cube only from step ~16 (assets/README.md)
CARRY_STEP = 0.015


def _segment(obs: dict[str, jax.Array], spec: ObservationSpec, name: str) -> jax.Array:
    return obs["proprio"][spec.segment_slice(name)]


def _clip_norm(vec: jax.Array, max_norm: jax.Array | float) -> jax.Array:
    return vec * jnp.minimum(1.0, max_norm / jnp.maximum(jnp.linalg.norm(vec), 1e-9))


def _move(ee: jax.Array, target: jax.Array, max_step: jax.Array | float = MAX_MOVE) -> jax.Array:
    """Position part of the action that moves the grasp point toward `target` by at most
    `max_step` per axis and in norm (m)."""
    return jnp.clip(_clip_norm(target - ee, max_step) / MAX_MOVE, -1.0, 1.0)


def _action(move: jax.Array, fingers: jax.Array, thumb: jax.Array) -> jax.Array:
    """Full action: move (3,), no roll or tilt, finger closure and thumb abduction."""
    return jnp.concatenate([move, jnp.zeros(2), jnp.stack([fingers, thumb])])


def grasp_policy(obs: dict[str, jax.Array], spec: ObservationSpec) -> jax.Array:
    """Grasp the cube between fingers and thumb and carry it to the goal: on the table
    (nicol_slide: the held cube slides along the table top) or in the air (nicol_lift).

    Hover above the cube with the thumb along the palm, oppose the thumb once aligned,
    descend until the grasp point is `GRASP_HEIGHT` above the cube's centre, close the fingers and, once
    they hold the cube, move the hand so that the cube reaches the goal.
    """
    ee = _segment(obs, spec, "ee_pos")
    obj = _segment(obs, spec, "obj_pos")
    closure = _segment(obs, spec, "q")[6]
    rel = obj - ee
    near = jnp.linalg.norm(rel) < HELD
    aligned = jnp.linalg.norm(rel[:2]) < ALIGNED
    lowered = aligned & (jnp.abs(rel[2] + GRASP_HEIGHT) < ALIGNED)
    # once the fingers are closing on a nearby cube, keep closing without re-aligning
    grasping = lowered | (near & (closure > FINGERS_ENGAGED))
    held = near & (closure > FINGERS_CLOSED)
    hover = obj + jnp.array([0.0, 0.0, HOVER])
    target = jnp.where(aligned, obj + jnp.array([0.0, 0.0, GRASP_HEIGHT]), hover)
    target = jnp.where(grasping, ee, target)
    target = jnp.where(held, ee + obs["desired_goal"] - obj, target)
    move = _move(ee, target, jnp.where(held, CARRY_STEP, MAX_MOVE))
    fingers = jnp.where(grasping, 1.0, -1.0)
    thumb = jnp.where(aligned | grasping, 1.0, -1.0)
    return _action(move, fingers, thumb)


def scripted_policy(spec: ObservationSpec) -> Policy:
    """`grasp_policy` as a batched policy for `bidal_jax.acting.rollout`."""
    return lambda obs, key: jax.vmap(lambda o: grasp_policy(o, spec))(obs)


def run_episodes(env: Env, states: State) -> jax.Array:
    """Success (at the last step, as in the env) of the scripted controller from each of the
    batched initial `states`. Apart from the states it depends on the env's step only, so one
    compiled program serves every task that shares a step (nicol_slide and nicol_lift)."""
    return evaluate(env, scripted_policy(env.observation_spec), jax.random.PRNGKey(0), states=states)
