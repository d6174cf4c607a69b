"""Scripted NICOL episodes sorted into the phases of the task: what the camera probes look at.

The visibility probe (`experiments.probes.visibility`) counts the pixels the cube and
the hand cover, and the vision probe (`experiments.probes.vision --phase`) trains on the frames, of the
states a NICOL task passes through. They come from scripted episodes with Gaussian action noise, in
turn the grasp controller (`experiments.probes.grasping`), a push (`push_policy`) and the grasp
controller from the held start (where the env has one: nicol_lift), and each state is sorted by its
true proprio (`nicol_phase`) into

- `start`: the first frame;
- `approach`: hand 5-20 cm from the cube, the cube on the table;
- `contact`: hand within 5 cm of the cube, the cube on the table (a push or a grasp under way);
- `held`: the cube lifted off the table within 4 cm of the closed hand.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs_mjx.base import State
from envs_mjx.nicol import CUBE_HALF, MAX_MOVE, TABLE_HEIGHT, NicolEnv
from experiments.probes.grasping import HELD, grasp_policy

PHASES_NICOL = ("start", "approach", "contact", "held")
CONTACT = 0.05  # m, hand to cube
APPROACH = 0.20  # m
LIFTED = 0.01  # m above resting on the table
PUSH_BEHIND = 0.06  # m behind the cube (seen from the goal) where the push starts
SCRIPT_NOISE = 0.3  # std of the Gaussian noise on the scripted actions (spreads the states)
FRAME_CHUNK = 256  # episodes simulated at once (vmapped): 16,000 NICOL envs stepped at once need over 20 GB


def push_policy(obs: dict, spec) -> jax.Array:
    """A scripted push: go behind the cube (seen from the goal) at its height, then push it to the goal."""
    ee, obj = obs["proprio"][spec.segment_slice("ee_pos")], obs["proprio"][spec.segment_slice("obj_pos")]
    heading = obs["desired_goal"][:2] - obj[:2]
    heading = heading / jnp.maximum(jnp.linalg.norm(heading), 1e-6)
    behind = obj.at[:2].add(-PUSH_BEHIND * heading)
    ready = jnp.linalg.norm(ee[:2] - behind[:2]) < 0.02
    hover = behind.at[2].add(0.08)
    target = jnp.where(ready | (ee[2] < obj[2] + 0.03), behind, hover)
    target = jnp.where(ready, obs["desired_goal"].at[2].set(obj[2]), target)
    move = jnp.clip((target - ee) / MAX_MOVE, -1.0, 1.0)
    return jnp.concatenate([move, jnp.zeros(2), jnp.array([-1.0, -1.0])])


def nicol_rollouts(env: NicolEnv, episodes: int, noise: float, key: jax.Array,
                   record: Callable[[State], Any]) -> tuple[Any, np.ndarray]:
    """(`record(state)` of every state [N, ...], its phase [N]: an index into `PHASES_NICOL`, or -1) over
    `episodes` scripted episodes, in turn a grasp, a push and a carry from the held start (where the env has
    one, else a grasp), with Gaussian action noise of std `noise`."""
    spec = env.observation_spec
    policies = [lambda o: grasp_policy(o, spec), lambda o: push_policy(o, spec), lambda o: grasp_policy(o, spec)]

    def episode(key, scripted):
        key_reset, key_noise = jax.random.split(key)
        # every third episode starts with the cube held, where the env has such a start (nicol_lift), and carries it
        start = jax.lax.cond(scripted == 2, env.exploration_reset, env.reset, key_reset)

        def step(state, key):
            action = jax.lax.switch(scripted, policies, state.obs) + noise * jax.random.normal(key, (env.action_size,))
            out = (record(state), state.obs["proprio"], state.info["step"])
            return env.step(state, jnp.clip(action, -1.0, 1.0)), out

        return jax.lax.scan(step, start, jax.random.split(key_noise, env.episode_length))[1]

    records, proprio, step = jax.jit(jax.vmap(episode))(jax.random.split(key, episodes), jnp.arange(episodes) % 3)
    records, proprio, step = jax.tree.map(lambda x: np.asarray(x).reshape(-1, *x.shape[2:]), (records, proprio, step))
    return records, nicol_phase(spec, proprio, step)


def chunked_rollouts(env: NicolEnv, episodes: int, key: jax.Array, record: Callable[[State], Any]
                     ) -> tuple[Any, np.ndarray]:
    """`nicol_rollouts` of `episodes` episodes with noise `SCRIPT_NOISE`, simulated `FRAME_CHUNK` at a time (each
    chunk's key folded from `key`), concatenated: (records [N, ...], phases [N])."""
    chunks = [nicol_rollouts(env, min(FRAME_CHUNK, episodes - i), SCRIPT_NOISE, jax.random.fold_in(key, i), record)
              for i in range(0, episodes, FRAME_CHUNK)]
    return jax.tree.map(lambda *parts: np.concatenate(parts), *chunks)


def nicol_phase(spec, proprio: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The phase of each state (`PHASES_NICOL` index, -1 for none) from its true proprio [N, D] and step [N]."""
    ee, obj = proprio[:, spec.segment_slice("ee_pos")], proprio[:, spec.segment_slice("obj_pos")]
    closure = proprio[:, spec.segment_slice("q")][:, 6]
    dist = np.linalg.norm(obj - ee, axis=-1)
    lifted = obj[:, 2] > TABLE_HEIGHT + CUBE_HALF + LIFTED
    phase = np.full(len(step), -1)
    phase[(step > 0) & ~lifted & (dist >= CONTACT) & (dist < APPROACH)] = 1
    phase[(step > 0) & ~lifted & (dist < CONTACT)] = 2
    phase[lifted & (dist < HELD) & (closure > 1.0)] = 3
    phase[step == 0] = 0
    return phase
