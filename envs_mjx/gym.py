"""Gymnasium adapters of the envs_mjx tasks (needs the `gym` extra: gymnasium>=1.0).

`VectorGoalEnv` is a `gymnasium.vector.VectorEnv` over `num_envs` copies of a registered
task, stepped together by one jitted, vmapped function; `GoalEnv` is the single-env
`gymnasium.Env` (num_envs = 1) that `gymnasium.utils.env_checker.check_env` accepts.
Importing this module registers every task with Gymnasium:

    import gymnasium, envs_mjx.gym
    envs = gymnasium.make_vec("bidal/PlanarReach-v0", num_envs=64)  # VectorGoalEnv
    env = gymnasium.make("bidal/PlanarReach-v0", image=True)          # GoalEnv

Observations are goal-env dicts of numpy arrays: `observation` (the task's proprio vector,
float32 [D]), `achieved_goal` and `desired_goal` (float32 [G]), and `image` (uint8
[42, 42, 1], the agent's ray-cast camera) only when built with `image=True`; otherwise the
task is built with render=False and no ray is cast. Rewards are the task's sparse reward
(0 within ε of the goal, else -1), `info["is_success"]` says whether each env is within ε
now, and `compute_reward(achieved_goal, desired_goal, info)` recomputes rewards for any
batch of goals (HER relabelling). Episodes never terminate; they are truncated after the
task's T steps (`episode_length`).

Edges: an action whose shape is not the action space's ([A] for `GoalEnv`, [num_envs, A] for
`VectorGoalEnv`), or that holds NaN, is refused with a ValueError before anything is stepped (the
env's state is unchanged); finite actions outside [-1, 1] are clipped. `compute_reward` counts a
goal that is not finite (NaN, or inf against inf) as a failure: -1, never 0.

Autoreset: Gymnasium's same-step mode (`AutoresetMode.SAME_STEP`). On the step that
truncates an episode the env is reset within that step: the returned observation is the
first of the next episode, the last observation of the ended episode is in
`info["final_obs"]` (an object array of one observation dict per env, None where no episode
ended; mask `info["_final_obs"]`) and its success in `info["final_info"]["is_success"]`,
as Gymnasium's SyncVectorEnv returns them in this mode.

Seeding: `reset(seed=s)` seeds the env's numpy generator (`np_random`), from which the JAX
key of the batch is drawn; each env keeps a key split from it for its autoresets, so the
same seed gives the same episodes, autoresets included. `render()` draws the first
env with MuJoCo's own offscreen renderer (`mujoco.Renderer`) through the model's first
camera, which in every task is the agent's camera.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

import envs_mjx
from envs_mjx.base import State, check_action

NAMESPACE = "bidal"
RENDER_SIZE = (480, 640)  # (height, width) of render() frames: MuJoCo's default offscreen buffer
METADATA = {"render_modes": ["rgb_array"], "render_fps": 25, "autoreset_mode": AutoresetMode.SAME_STEP}


def gym_id(name: str) -> str:
    """The Gymnasium id of task `name`, e.g. planar_reach -> "bidal/PlanarReach-v0"."""
    return f"{NAMESPACE}/{''.join(part.capitalize() for part in name.split('_'))}-v0"


def observation_space(env: Any, image: bool) -> spaces.Dict:
    """The goal-env observation space of one env of the envs_mjx task `env`."""
    spec = env.observation_spec
    goal = spaces.Box(-np.inf, np.inf, (spec.goal_size,), np.float32)
    entries = {
        "observation": spaces.Box(-np.inf, np.inf, (spec.proprio_size,), np.float32),
        "achieved_goal": goal,
        "desired_goal": goal,
    }
    if image:
        entries["image"] = spaces.Box(0, 255, spec.image_shape, np.uint8)
    return spaces.Dict(entries)


def goal_obs(obs: dict[str, jax.Array], image: bool) -> dict[str, jax.Array]:
    """An envs_mjx observation dict as a goal-env observation (proprio -> observation)."""
    out = {"observation": obs["proprio"], "achieved_goal": obs["achieved_goal"], "desired_goal": obs["desired_goal"]}
    if image:
        out["image"] = obs["image"]
    return out


def host_view(state: State, reward: jax.Array, truncated: jax.Array, image: bool) -> dict[str, Any]:
    """What the numpy side reads of batched `state`: goal observation, reward, truncation, success."""
    return {"obs": goal_obs(state.obs, image), "reward": reward, "truncated": truncated,
            "is_success": state.metrics["success"] > 0}


def batched_reset(env: Any, keys: jax.Array) -> tuple[State, jax.Array]:
    """Initial states of `env`, one per key in `keys` [num_envs, 2], and the keys each env
    keeps for its later autoresets."""
    split = jax.vmap(jax.random.split)(keys)
    return jax.vmap(env.reset)(split[:, 0]), split[:, 1]


def reset_views(env: Any, num_envs: int, image: bool, key: jax.Array) -> tuple[tuple[State, jax.Array], dict]:
    """(initial states, per-env keys) to carry, and their host views ("now" and, alike, "final")."""
    state, keys = batched_reset(env, jax.random.split(key, num_envs))
    view = host_view(state, state.reward, state.done, image)
    return (state, keys), {"now": view, "final": view}


def autoreset(env: Any, done: jax.Array, carry: tuple[State, jax.Array]) -> tuple[State, jax.Array]:
    """`carry` (states, keys) with the envs flagged in `done` replaced by fresh initial states."""
    def pick(new: jax.Array, old: jax.Array) -> jax.Array:
        return jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old)

    return jax.tree.map(pick, batched_reset(env, carry[1]), carry)


# Pytrees cross the jit boundary packed. Every argument and result of a jitted call costs
# microseconds of dispatch and conversion on the CPU, and an MJX state has ~95 arrays, which
# cost more than the physics of a small batch; so the state, and what the host reads, travel
# as one [num_envs, k] buffer per dtype.
@dataclasses.dataclass(frozen=True)
class Packing:
    """Where each leaf of a batched pytree lives: (dtype, first column, end column, per-env shape)."""

    treedef: Any
    slots: tuple[tuple[str, int, int, tuple[int, ...]], ...]


def packing_of(tree: Any) -> Packing:
    """The packing of a batched pytree (arrays or shape structs with a leading env axis)."""
    leaves, treedef = jax.tree.flatten(tree)
    ends: dict[str, int] = {}
    slots = []
    for leaf in leaves:
        dtype = np.dtype(leaf.dtype).name
        start = ends.get(dtype, 0)
        ends[dtype] = start + math.prod(leaf.shape[1:])
        slots.append((dtype, start, ends[dtype], tuple(leaf.shape[1:])))
    return Packing(treedef, tuple(slots))


def pack(tree: Any, packing: Packing) -> dict[str, jax.Array]:
    """The leaves of batched `tree` as one [num_envs, k] buffer per dtype."""
    columns: dict[str, list[jax.Array]] = {}
    for leaf, (dtype, *_) in zip(jax.tree.leaves(tree), packing.slots):
        columns.setdefault(dtype, []).append(leaf.reshape(leaf.shape[0], -1))
    return {dtype: jnp.concatenate(parts, axis=1) for dtype, parts in columns.items()}


def unpack(buffers: dict[str, Any], packing: Packing) -> Any:
    """The pytree that `pack` packed into `buffers` (jax or numpy arrays; numpy gives views)."""
    n = next(iter(buffers.values())).shape[0]
    leaves = [buffers[dtype][:, start:end].reshape((n, *shape)) for dtype, start, end, shape in packing.slots]
    return jax.tree.unflatten(packing.treedef, leaves)


def packed_reset(env: Any, num_envs: int, image: bool, packings: tuple[Packing, Packing], key: jax.Array):
    """The jitted body of `VectorGoalEnv.reset`: the packed carry and packed host views."""
    carry, views = reset_views(env, num_envs, image, key)
    return pack(carry, packings[0]), pack(views, packings[1])


def packed_step(env: Any, image: bool, packings: tuple[Packing, Packing], buffers: dict[str, jax.Array],
                action: jax.Array):
    """The jitted body of `VectorGoalEnv.step`: every env steps, then same-step autoreset.

    Returns the packed carry (states, per-env keys) and the packed host views: "now", read
    every step (observation after any reset, reward, truncation, success), and "final", the
    stepped states before the reset, read on steps that truncate (the ended episodes' last step).
    """
    state, keys = unpack(buffers, packings[0])
    stepped = jax.vmap(env.step)(state, action)
    done = stepped.done
    # every env of a batch ends on the same step (same T, reset together): one branch per batch
    carry = jax.lax.cond(jnp.any(done), functools.partial(autoreset, env, done), lambda c: c, (stepped, keys))
    views = {"now": host_view(carry[0], stepped.reward, done, image),
             "final": host_view(stepped, stepped.reward, done, image)}
    return pack(carry, packings[0]), pack(views, packings[1])


@dataclasses.dataclass(frozen=True)
class Batched:
    """A task, its jitted batched functions and the packings (carry, host views) they use."""

    env: Any
    packings: tuple[Packing, Packing]
    reset: Callable
    step: Callable
    reward: Callable


@functools.cache
def batched(name: str, num_envs: int, image: bool) -> Batched:
    """The task `name` (render=image) and its jitted functions for `num_envs` envs, built once
    per process and shared by every adapter with the same arguments (one compilation)."""
    env = envs_mjx.make(name, render=image)
    carry, views = jax.eval_shape(functools.partial(reset_views, env, num_envs, image), jax.random.PRNGKey(0))
    packings = (packing_of(carry), packing_of(views))
    return Batched(
        env=env,
        packings=packings,
        reset=jax.jit(functools.partial(packed_reset, env, num_envs, image, packings)),
        step=jax.jit(functools.partial(packed_step, env, image, packings)),
        reward=jax.jit(env.compute_reward),
    )


def to_host(buffers: dict[str, jax.Array], packing: Packing) -> dict[str, Any]:
    """Packed device buffers as the numpy pytree they hold: one writable host copy per buffer
    (fresh on every call), its leaves views of those copies."""
    return unpack({k: np.array(v) for k, v in buffers.items()}, packing)


def vector_info(is_success: np.ndarray) -> dict[str, np.ndarray]:
    """A vector env's info dict: per-env success and its Gymnasium mask (every env has it)."""
    return {"is_success": is_success, "_is_success": np.ones_like(is_success)}


def unbatch(obs: dict[str, np.ndarray], index: int) -> dict[str, np.ndarray]:
    """The observation of env `index` of a batched observation dict."""
    return {k: v[index] for k, v in obs.items()}


def per_env_obs(obs: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray:
    """An object array holding env i's observation dict where `mask[i]`, else None."""
    out = np.full(mask.shape[0], None, dtype=object)
    for i in np.flatnonzero(mask):
        out[i] = unbatch(obs, i)
    return out


def mjx_to_mjdata(data: Any, mj_model: mujoco.MjModel, mj_data: mujoco.MjData) -> mujoco.MjData:
    """Copy env 0 of batched MJX data (host arrays: qpos, qvel, mocap) into `mj_data` and forward it."""
    mj_data.qpos[:], mj_data.qvel[:] = data.qpos[0], data.qvel[0]
    mj_data.mocap_pos[:], mj_data.mocap_quat[:] = data.mocap_pos[0], data.mocap_quat[0]
    mujoco.mj_forward(mj_model, mj_data)
    return mj_data


class VectorGoalEnv(VectorEnv):
    """`num_envs` copies of the envs_mjx task `name` as a Gymnasium vector env (module docstring).

    Args:
      name: a registered task, one of `envs_mjx.names()`.
      num_envs: number of parallel envs, at least 1.
      image: whether observations include the 42x42x1 camera image (ray-cast inside the step).
      render_mode: None or "rgb_array" (`render()` frames of the first env).
    """

    metadata = METADATA

    def __init__(self, name: str = "planar_reach", num_envs: int = 1, image: bool = False,
                 render_mode: str | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs {num_envs!r}: must be an integer >= 1")
        if render_mode not in (None, *METADATA["render_modes"]):
            raise ValueError(f"render_mode {render_mode!r}: must be None or one of {METADATA['render_modes']}")
        self.name, self.num_envs, self.image, self.render_mode = name, int(num_envs), bool(image), render_mode
        self._batched = batched(self.name, self.num_envs, self.image)
        self.env = self._batched.env
        self.single_observation_space = observation_space(self.env, image)
        self.single_action_space = spaces.Box(-1.0, 1.0, (self.env.action_size,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._carry: dict[str, jax.Array] | None = None  # packed (states, per-env keys)
        self._renderer: tuple[mujoco.Renderer, mujoco.MjData] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset every env; the JAX key is drawn from `np_random` (seeded by `seed`)."""
        if options:
            raise ValueError(f"reset options {sorted(options)}: this env takes no reset options")
        super().reset(seed=seed)
        self._carry, views = self._batched.reset(jax.random.PRNGKey(self.np_random.integers(2**32, dtype=np.uint32)))
        now = to_host(views, self._batched.packings[1])["now"]
        return now["obs"], vector_info(now["is_success"])

    def step(self, actions: Any):
        """Step every env by `actions` ([num_envs, A], clipped to [-1, 1]); same-step autoreset."""
        if self._carry is None:
            raise RuntimeError("step() called before reset(); call reset() first")
        actions = np.asarray(actions, np.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions have shape {actions.shape}; expected {self.action_space.shape}")
        check_action(actions, self.env.action_size)
        self._carry, views = self._batched.step(self._carry, actions)
        views = to_host(views, self._batched.packings[1])
        now, final, truncated = views["now"], views["final"], views["now"]["truncated"]
        info = vector_info(now["is_success"])
        if truncated.any():
            info["final_obs"] = per_env_obs(final["obs"], truncated)
            info["_final_obs"] = truncated.copy()
            info["final_info"] = {"is_success": final["is_success"], "_is_success": truncated.copy()}
            info["_final_info"] = truncated.copy()
        terminated = np.zeros(self.num_envs, bool)
        return now["obs"], now["reward"], terminated, truncated, info

    def compute_reward(self, achieved_goal: Any, desired_goal: Any, info: Any = None) -> np.ndarray:
        """The task's sparse reward for goals batched over leading axes (numpy in and out): 0 within ε, else -1;
        -1 for a goal that is not finite."""
        achieved_goal, desired_goal = np.asarray(achieved_goal, np.float32), np.asarray(desired_goal, np.float32)
        return np.asarray(self._batched.reward(achieved_goal, desired_goal))

    def render(self) -> tuple[np.ndarray, ...] | None:
        """(frame,): the first env drawn by `mujoco.Renderer`, uint8 [480, 640, 3]; None
        unless render_mode is "rgb_array"."""
        if self.render_mode is None:
            return None
        if self._carry is None:
            raise RuntimeError("render() called before reset(); call reset() first")
        if self._renderer is None:
            mj_model = self.env.mj_model
            self._renderer = (mujoco.Renderer(mj_model, *RENDER_SIZE), mujoco.MjData(mj_model))
        renderer, mj_data = self._renderer
        state, _ = unpack(jax.device_get(self._carry), self._batched.packings[0])
        renderer.update_scene(mjx_to_mjdata(state.data, self.env.mj_model, mj_data),
                              camera=0 if self.env.mj_model.ncam else -1)
        return (renderer.render(),)

    def close_extras(self, **kwargs: Any) -> None:
        """Free the renderer's GL context, if one was made."""
        if self._renderer is not None:
            self._renderer[0].close()
            self._renderer = None


class GoalEnv(gymnasium.Env):
    """One env of the envs_mjx task `name` as a `gymnasium.Env` (a VectorGoalEnv of one env).

    Unlike the vector env it returns the episode's last observation with truncated=True;
    call reset() to start the next episode.

    Args:
      name, image, render_mode: as for `VectorGoalEnv`.
    """

    metadata = METADATA

    def __init__(self, name: str = "planar_reach", image: bool = False, render_mode: str | None = None):
        self.vector = VectorGoalEnv(name, 1, image, render_mode)
        self.render_mode = render_mode
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode; the vector env is seeded from this env's `np_random`."""
        super().reset(seed=seed)
        obs, info = self.vector.reset(seed=int(self.np_random.integers(2**32)), options=options)
        return unbatch(obs, 0), {"is_success": bool(info["is_success"][0])}

    def step(self, action: Any):
        """One step; at truncation the returned observation is the episode's last one. ValueError (nothing
        stepped) for an action not of the action space's shape [A]."""
        action = np.asarray(action, np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action has shape {action.shape}; expected {self.action_space.shape}")
        obs, reward, terminated, truncated, info = self.vector.step(action[None])
        if truncated[0]:
            obs, success = info["final_obs"][0], info["final_info"]["is_success"][0]
        else:
            obs, success = unbatch(obs, 0), info["is_success"][0]
        return obs, float(reward[0]), bool(terminated[0]), bool(truncated[0]), {"is_success": bool(success)}

    def compute_reward(self, achieved_goal: Any, desired_goal: Any, info: Any = None) -> np.ndarray:
        """As `VectorGoalEnv.compute_reward`."""
        return self.vector.compute_reward(achieved_goal, desired_goal, info)

    def render(self) -> np.ndarray | None:
        """The env drawn by `mujoco.Renderer`, uint8 [480, 640, 3] (after a truncation: the next
        episode's start); None unless render_mode is "rgb_array"."""
        frames = self.vector.render()
        return None if frames is None else frames[0]

    def close(self) -> None:
        """Free the renderer's GL context, if one was made."""
        self.vector.close()


def register_all() -> None:
    """Register every envs_mjx task with Gymnasium under `gym_id(name)` (single and vector entry points)."""
    for name in envs_mjx.names():
        if gym_id(name) not in gymnasium.registry:
            gymnasium.register(
                id=gym_id(name),
                entry_point=f"{__name__}:GoalEnv",
                vector_entry_point=f"{__name__}:VectorGoalEnv",
                kwargs={"name": name},
            )


register_all()
