"""The functional environment API shared by every task (docs/tasks.md, "Common to all five").

An `Env` is a set of pure functions over a `State` pytree: `reset(key) -> State` and
`step(state, action) -> State`, both jit- and vmap-able, plus static facts fixed at
construction (`action_size`, `observation_spec`, `episode_length`). The extrinsic reward
is the paper's sparse reward (Eq. 6): `r_e = -[‖achieved_goal - desired_goal‖ > ε]`.

Subclasses describe one task through a few hooks (`_reset_data`, `_apply_action`,
`_proprio`, `_achieved_goal`); the physics loop, the camera, rewards, step counting and
action checks live here once.
"""

from __future__ import annotations

import abc
import dataclasses
import hashlib
import importlib
import importlib.resources
from collections.abc import Callable
from typing import Any

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from envs_mjx.camera import Camera
from envs_mjx.task import Task

# the top-level assets/ folder, installed as the package `envs_mjx.assets` (pyproject.toml), so
# that editable installs, wheels and `pip install .` all find the models from any directory
ASSETS_DIR = importlib.resources.files("envs_mjx.assets")
CONTROL_PERIOD = 0.04  # seconds, 25 Hz (docs/tasks.md)
IMAGE_SHAPE = (42, 42, 1)  # grayscale, paper Table I
# the geom group of goal markers that videos draw but the agents' camera does not (it sees groups 0-2,
# `camera.VISIBLE_GROUPS`): NICOL's, whose goal reaches the agents as a vector that HER relabels (docs/tasks.md)
MARKER_GROUP = 5
# `jax.named_scope`s of a step's physics and camera: profiles attribute their kernels by them (experiments/bench)
PHYSICS_SCOPE, CAMERA_SCOPE = "physics", "camera"


@struct.dataclass
class State:
    """One environment's state: MJX data, the observation dict, reward and bookkeeping."""

    data: mjx.Data
    obs: dict[str, jax.Array]
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array]
    info: dict[str, Any]


@dataclasses.dataclass(frozen=True)
class ObservationSpec:
    """Static description of an observation: named proprio segments, goal and image shapes."""

    proprio_segments: tuple[tuple[str, int], ...]
    goal_size: int
    image_shape: tuple[int, int, int] = IMAGE_SHAPE
    # segments computed from others, as (segment, ((source, coefficient), ...)): a linear combination of
    # equally sized source segments, e.g. ("obj_rel_pos", (("obj_pos", 1.0), ("ee_pos", -1.0))); observation
    # noise on a source reaches the derived segment (bidal_jax/noise.py)
    derived: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = ()
    # the proprio segment the achieved goal equals, if any (the noisy-goal variant of the noise experiment)
    goal_segment: str | None = None

    @property
    def proprio_size(self) -> int:
        return sum(size for _, size in self.proprio_segments)

    @property
    def segment_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.proprio_segments)

    def segment_slice(self, name: str) -> slice:
        """The slice of the flat proprio vector that holds segment `name`."""
        start = 0
        for seg, size in self.proprio_segments:
            if seg == name:
                return slice(start, start + size)
            start += size
        raise KeyError(f"unknown proprio segment {name!r}; segments are {self.segment_names}")

    def without(self, drop: tuple[str, ...]) -> ObservationSpec:
        """This spec with the proprio segments named in `drop` removed (e.g. reduced lift)."""
        unknown = sorted(set(drop) - set(self.segment_names))
        if unknown:
            raise ValueError(f"cannot drop unknown segments {unknown}; segments are {self.segment_names}")
        return dataclasses.replace(
            self,
            proprio_segments=tuple(s for s in self.proprio_segments if s[0] not in drop),
            derived=tuple(d for d in self.derived if d[0] not in drop and not {n for n, _ in d[1]} & set(drop)),
            goal_segment=None if self.goal_segment in drop else self.goal_segment,
        )

    def shapes(self) -> dict[str, tuple[tuple[int, ...], Any]]:
        """Shape and dtype of every observation entry."""
        return {
            "proprio": ((self.proprio_size,), jnp.float32),
            "image": (self.image_shape, jnp.uint8),
            "achieved_goal": ((self.goal_size,), jnp.float32),
            "desired_goal": ((self.goal_size,), jnp.float32),
        }


def substeps(timestep: float) -> int:
    """Physics substeps per control period; ValueError unless `timestep` divides `CONTROL_PERIOD`."""
    n_substeps = CONTROL_PERIOD / timestep
    if abs(n_substeps - round(n_substeps)) > 1e-6:
        raise ValueError(f"timestep {timestep} does not divide the control period {CONTROL_PERIOD}")
    return int(round(n_substeps))


_OPTION_ENUMS = {"cone": (mujoco.mjtCone, "mjCONE_"), "solver": (mujoco.mjtSolver, "mjSOL_"),
                 "integrator": (mujoco.mjtIntegrator, "mjINT_")}


def _option_value(opt: mujoco.MjOption, name: str, value: float | str):
    """`value` as the type of `opt.NAME` (an enum from its name for cone, solver and integrator); ValueError
    naming what is allowed for anything else."""
    if name in _OPTION_ENUMS:
        enum, prefix = _OPTION_ENUMS[name]
        names = [m[len(prefix):].lower() for m in enum.__members__]
        if str(value).lower() not in names:
            raise ValueError(f"{name}={value!r}: valid {name}s are {', '.join(names)}")
        return enum.__members__[prefix + str(value).upper()]
    current = getattr(opt, name, None) if not name.startswith("_") else None
    if current is None or not np.isscalar(current):
        raise ValueError(f"{name!r} is not a scalar physics option; valid: fields of mujoco.MjOption such as "
                         "timestep, iterations, ls_iterations, tolerance, impratio, cone, solver, integrator")
    try:
        return type(current)(float(value))
    except ValueError as err:
        raise ValueError(f"{name}={value!r}: not a number") from err


def enable_warp() -> None:
    """Give mujoco.mjx its MuJoCo Warp backend where the process imported it without (the project's command lines
    do, `experiments.start_process`, since Warp's import costs seconds of CUDA start-up and most runs step MJX's JAX
    physics): import warp-lang, then run again the import-time code of the mujoco.mjx modules that bind Warp's names
    on import (its `warp` package, the types of its Warp data and its io module; reloaded in place, so that the
    functions mujoco.mjx exports see the new names). Called when an env first steps on Warp (`Env.use_backend`); a
    no-op where mujoco.mjx has Warp already. ImportError where warp-lang is not installed."""
    import mujoco.mjx.warp as mjx_warp

    if mjx_warp.WARP_INSTALLED:
        return
    import warp  # noqa: F401 - an ImportError here, not a message printed by mujoco.mjx
    from mujoco.mjx._src import io as mjx_io
    from mujoco.mjx.warp import types as mjx_warp_types

    for module in (mjx_warp_types, mjx_warp, mjx_io):
        importlib.reload(module)



def load_model(filename: str) -> mujoco.MjModel:
    """Load an MJCF model from `assets/` (the installed package `envs_mjx.assets`)."""
    with importlib.resources.as_file(ASSETS_DIR / filename) as path:
        return mujoco.MjModel.from_xml_path(str(path))


def sparse_reward(achieved_goal: jax.Array, desired_goal: jax.Array, epsilon: float) -> jax.Array:
    """Paper Eq. 6, batched over leading axes: 0 within `epsilon`, else -1; a non-finite goal (a NaN distance,
    which no comparison holds for) is -1, never a success."""
    dist = jnp.linalg.norm(achieved_goal - desired_goal, axis=-1)
    return jnp.where(dist <= epsilon, 0.0, -1.0).astype(jnp.float32)


def check_action(action: Any, action_size: int) -> None:
    """Reject NaN or wrongly shaped concrete actions with a clear error (outside jit)."""
    if isinstance(action, jax.core.Tracer):
        return
    arr = np.asarray(action)
    if arr.shape[-1:] != (action_size,):
        raise ValueError(f"action has shape {arr.shape}; expected trailing size {action_size}")
    if np.isnan(arr).any():
        raise ValueError(f"action contains NaN: {arr}; actions must be finite values in [-1, 1]")


def model_digest(mj_model: mujoco.MjModel) -> str:
    """SHA-256 (hex) of a compiled model's numbers: each array of the `MjModel` (names included, as its `names`
    buffer) and each field of its `opt` (the physics options) and `stat` (the statistics the solver scales by), by
    name, but its `signature`. Not of MuJoCo's binary MJB, whose bytes change between releases (4.0.0 and 4.0.1) for
    one and the same model; a release that adds a model array changes the digest too."""
    digest = hashlib.sha256()
    parts = [(name, getattr(mj_model, name)) for name in dir(mj_model) if not name.startswith("_")
             and name != "signature"]  # the compiler's own hash of the model's structure, not kept in its binary
    parts += [(f"{struct}.{name}", getattr(getattr(mj_model, struct), name)) for struct in ("opt", "stat")
              for name in dir(getattr(mj_model, struct)) if not name.startswith("_")]
    for name, value in sorted(parts, key=lambda part: part[0]):
        if isinstance(value, (np.ndarray, int, float)):  # arrays and scalars; not methods or nested structs
            array = np.ascontiguousarray(value)
            digest.update(f"{name}:{array.dtype}:{array.shape}:".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


class Env(abc.ABC):
    """Base class of the MJX tasks. Subclasses set the static facts and implement the hooks.

    Args:
      mj_model: the compiled MuJoCo model.
      episode_length: T, steps per episode (no early termination).
      epsilon: success threshold ε of the sparse reward.
      action_size: A.
      observation_spec: the named proprio segments and goal size.
      camera_name: the model camera that renders the image observation.
      render: whether to render the image; when False the image is all zeros (proprio agents).
    """

    name: str = "env"
    # its presets, learning-curve budget and contract's section (envs_mjx/task.py): none by default
    task: Task = Task()
    # rays per image pixel along each axis: the frame is cast finer and area-averaged down to 42×42
    # (docs/tasks.md, "camera"); the cost of the camera grows with its square
    camera_supersample: int = 2
    # whether `exploration_reset` differs from `reset` (see there)
    has_exploration_start: bool = False

    def __init__(
        self,
        mj_model: mujoco.MjModel,
        *,
        episode_length: int,
        epsilon: float,
        action_size: int,
        observation_spec: ObservationSpec,
        camera_name: str,
        render: bool = True,
    ):
        self.n_substeps = substeps(mj_model.opt.timestep)
        self.mj_model = mj_model
        self.backend, self.worlds = "jax", 1
        self._put_jax()
        self.episode_length = episode_length
        self.epsilon = epsilon
        self.action_size = action_size
        self.observation_spec = observation_spec
        self.render = render
        self.camera_name = camera_name
        self.set_camera_supersample(self.camera_supersample)

    def set_camera_supersample(self, supersample: int) -> None:
        """Cast `supersample`² rays per pixel of the 42×42 frame (area-averaged down) and rebuild the camera,
        e.g. to measure what a finer frame would show (`experiments.probes.vision --supersample`)."""
        self.camera_supersample = supersample
        self.camera = Camera(self.mj_model, self.camera_name, IMAGE_SHAPE[0], supersample=supersample)

    def use_backend(
        self, backend: str, worlds: int = 1, contacts_per_world: int = 32, constraints_per_world: int = 128
    ):
        """Step this env's physics with MJX's `backend` ("jax" or "warp", MuJoCo Warp on an NVIDIA GPU).

        Warp keeps one contact buffer for all worlds: `worlds` is the most envs stepped at once (envs × seeds)
        and `contacts_per_world` sizes it (contacts beyond it are dropped); `constraints_per_world` is `njmax`.
        Nothing is rebuilt when the env already steps on `backend` (Warp: for `worlds`)."""
        if backend == self.backend and (backend == "jax" or worlds == self.worlds):
            return
        if backend == "jax":
            self._put_jax()
        elif backend == "warp":
            enable_warp()
            from mujoco.mjx.third_party.mujoco_warp import OverflowType

            model = mjx.put_model(self.mj_model, impl="warp")
            # the solver's iteration limit is the model's choice (assets/README.md), not an overflow to print
            opt = model.opt.replace(
                _impl=model.opt._impl.replace(
                    warn_overflow=model.opt._impl.warn_overflow
                    & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
                )
            )
            self.mjx_model = model.replace(opt=opt)
            self._blank = mjx.make_data(
                self.mj_model, impl="warp", naconmax=contacts_per_world * worlds, njmax=constraints_per_world
            )
        else:
            raise ValueError(f"unknown physics backend {backend!r}; valid: jax, warp")
        self.backend, self.worlds = backend, worlds

    def set_options(self, **options: float | str) -> None:
        """Override scalars of the model's physics options (`mujoco.MjOption`: timestep, iterations,
        ls_iterations, tolerance, impratio, ...; for `cone`, `solver` and `integrator` the name of MuJoCo's enum
        value, e.g. cone="elliptic") and rebuild the physics, e.g. `set_options(iterations=5)`. A new timestep
        changes the substeps per control period (nicol_lift's held start, built at construction, keeps the old).

        For measuring what a setting costs and does (`experiments.bench.engine --options`, `experiments.bench.sweep`
        variants `opt.NAME=VALUE`, `experiments.probes.physics --option`); a task's own settings are its model
        file's. Call it before `use_backend`; nothing is changed when a value is refused."""
        if self.backend != "jax":
            raise ValueError(f"set_options before use_backend: this env already steps on {self.backend!r}")
        values = {name: _option_value(self.mj_model.opt, name, value) for name, value in options.items()}
        n_substeps = substeps(values.get("timestep", self.mj_model.opt.timestep))
        for name, value in values.items():
            setattr(self.mj_model.opt, name, value)
        self.n_substeps = n_substeps
        self._put_jax()

    def _put_jax(self) -> None:
        """The model and a blank data of MJX's JAX implementation, from `mj_model`, on this process's first device
        (MJX's default, jax.devices()[0], is process 0's in a run over several)."""
        self.mjx_model = mjx.put_model(self.mj_model, device=jax.local_devices()[0])
        self._blank = mjx.make_data(self.mjx_model, device=jax.local_devices()[0])

    @property
    def physics_id(self) -> str:
        """A fingerprint of the physics this env steps and of the scene its camera sees: 16 hex digits of the
        SHA-256 of its compiled model's numbers (`model_digest`: every array of the `MjModel` and its `opt` and
        `stat` fields, so every number of the model file and of `set_options` counts, the camera's pose and field of
        view and each geom's group, which decides what the camera draws, among them). Runs record it in config.json
        (`bidal_jax.run.loop`), and the grid (`experiments.paper.grid.stale`) and `experiments.paper.claims` mark
        runs made on another model than today's, another camera included, as stale."""
        return model_digest(self.mj_model)[:16]

    def compile_physics(self) -> None:
        """Compile what the physics engine builds at its first launch rather than with the program around it: MuJoCo
        Warp builds its kernels' modules when a step first runs them (minutes for a NICOL model into an empty Warp
        kernel cache; docs/performance.md, "MJX-JAX against MuJoCo Warp"), so one world is forwarded and stepped here;
        MJX-JAX needs nothing, XLA compiles it with the epoch. `bidal_jax.run.loop` calls it beside the epoch's
        compile."""
        if self.backend == "warp":
            jax.block_until_ready(jax.jit(lambda d: mjx.step(self.mjx_model, mjx.forward(self.mjx_model, d)))(
                self._blank))

    def blank_data(self) -> mjx.Data:
        """A fresh `mjx.Data` of this env's backend, to be filled by `_reset_data`."""
        return self._blank

    # ----- hooks for subclasses -------------------------------------------------------
    @abc.abstractmethod
    def _reset_data(self, key: jax.Array) -> tuple[mjx.Data, jax.Array]:
        """Return the initial (data, desired_goal); data need not be forwarded."""

    def _exploration_reset_data(self, key: jax.Array) -> tuple[mjx.Data, jax.Array]:
        """Like `_reset_data`, for `exploration_reset`; envs that set `has_exploration_start` override it."""
        return self._reset_data(key)

    @abc.abstractmethod
    def _apply_action(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        """Write a clipped action in [-1, 1] into the controls (ctrl / mocap)."""

    def _substep_controls(self, before: mjx.Data, commanded: mjx.Data, data: mjx.Data, i: jax.Array) -> mjx.Data:
        """The controls of physics substep `i` (0 … n_substeps - 1): `data` with what changes within the
        control period written in. `before` is the data the step started from, `commanded` the data after
        `_apply_action`. By default the commanded controls hold over the whole period."""
        return data

    @abc.abstractmethod
    def _proprio(self, data: mjx.Data) -> dict[str, jax.Array]:
        """The proprio segments by name, in `observation_spec` order."""

    @abc.abstractmethod
    def _achieved_goal(self, data: mjx.Data) -> jax.Array:
        """The achieved goal (G,) of `data`."""

    # ----- the API ---------------------------------------------------------------------
    def goal_subsets(self, goal: jax.Array) -> dict[str, jax.Array]:
        """Named subsets of desired goals [..., G] that evaluation also reports success over (e.g. nicol_lift's
        air goals), as boolean masks [...]; none by default."""
        return {}

    def compute_reward(self, achieved_goal: jax.Array, desired_goal: jax.Array) -> jax.Array:
        """Sparse extrinsic reward (paper Eq. 6), batched, for HER relabelling."""
        return sparse_reward(achieved_goal, desired_goal, self.epsilon)

    def reset(self, key: jax.Array) -> State:
        """The task's initial state and goal (docs/tasks.md); evaluation always starts here."""
        return self._start(*self._reset_data(key))

    def exploration_reset(self, key: jax.Array) -> State:
        """An initial state that eases exploration, for some training episodes only.

        The goal is drawn as in `reset`; only the start differs, e.g. nicol_lift starts
        with the cube already held, as the HER paper (Andrychowicz et al. 2017) started
        half of its pick-and-place training episodes from a recorded grasp. Envs without
        such a start (`has_exploration_start` False) return a `reset` state.
        """
        return self._start(*self._exploration_reset_data(key))

    def _start(self, data: mjx.Data, goal: jax.Array) -> State:
        data = mjx.forward(self.mjx_model, data)
        obs = self._observe(data, goal)
        zero = jnp.zeros((), jnp.float32)
        return State(
            data=data,
            obs=obs,
            reward=self.compute_reward(obs["achieved_goal"], goal),
            done=jnp.zeros((), jnp.bool_),
            metrics={"success": zero, "distance": self._distance(obs)},
            info={"step": jnp.zeros((), jnp.int32), "goal": goal},
        )

    def step(self, state: State, action: jax.Array) -> State:
        """Advance one control period (0.04 s). Actions are clipped to [-1, 1]; NaN is
        rejected with an error when the action is concrete, and replaced by 0 under jit."""
        return self.probed_step(state, action, lambda data: ())[0]

    def probed_step(self, state: State, action: jax.Array, probe: Callable[[mjx.Data], Any]) -> tuple[State, Any]:
        """`step`, also returning `probe(data)` after each physics substep, stacked on a leading
        axis of `n_substeps` (diagnostics such as `experiments.probes.physics` see every substep)."""
        check_action(action, self.action_size)
        chex.assert_shape(action, (self.action_size,))
        action = jnp.clip(jnp.nan_to_num(action, nan=0.0), -1.0, 1.0)
        commanded = self._apply_action(state.data, action)

        def substep(data, i):
            data = mjx.step(self.mjx_model, self._substep_controls(state.data, commanded, data, i))
            return data, probe(data)

        with jax.named_scope(PHYSICS_SCOPE):
            data, trace = jax.lax.scan(substep, commanded, jnp.arange(self.n_substeps))
            # mjx.step leaves positions one substep behind qpos; refresh them for obs and camera
            data = mjx.kinematics(self.mjx_model, data)
        goal = state.info["goal"]
        obs = self._observe(data, goal)
        reward = self.compute_reward(obs["achieved_goal"], goal)
        step = state.info["step"] + 1
        return state.replace(
            data=data,
            obs=obs,
            reward=reward,
            done=step >= self.episode_length,
            metrics={"success": (reward == 0.0).astype(jnp.float32), "distance": self._distance(obs)},
            info={**state.info, "step": step},
        ), trace

    # ----- shared helpers -------------------------------------------------------------
    def _observe(self, data: mjx.Data, goal: jax.Array) -> dict[str, jax.Array]:
        segments = self._proprio(data)
        proprio = jnp.concatenate([segments[n] for n in self.observation_spec.segment_names]).astype(jnp.float32)
        if self.render:
            with jax.named_scope(CAMERA_SCOPE):
                image = self.camera.render(self.mjx_model, data)
        else:
            image = jnp.zeros(IMAGE_SHAPE, jnp.uint8)
        return {
            "proprio": proprio,
            "image": image,
            "achieved_goal": self._achieved_goal(data).astype(jnp.float32),
            "desired_goal": goal.astype(jnp.float32),
        }

    @staticmethod
    def _distance(obs: dict[str, jax.Array]) -> jax.Array:
        return jnp.linalg.norm(obs["achieved_goal"] - obs["desired_goal"])


class JointReachEnv(Env):
    """An arm whose action moves each joint's position target by at most `max_delta` rad from
    the current angle (clipped to the joint ranges), with proprio (q, qdot): the reaching tasks.

    Args:
      mj_model: the model; one position actuator per hinge joint, in joint order.
      max_delta: largest target increment per step (rad), reached at action ±1.
      camera_name, episode_length, epsilon, goal_size, render: as for `Env`.
    """

    def __init__(
        self,
        mj_model,
        *,
        max_delta: float,
        goal_size: int,
        camera_name: str,
        episode_length: int,
        epsilon: float,
        render: bool,
    ):
        n = mj_model.njnt
        super().__init__(
            mj_model,
            episode_length=episode_length,
            epsilon=epsilon,
            action_size=n,
            observation_spec=ObservationSpec(proprio_segments=(("q", n), ("qdot", n)), goal_size=goal_size),
            camera_name=camera_name,
            render=render,
        )
        self.max_delta = max_delta
        self._q_low = jnp.asarray(mj_model.jnt_range[:, 0], jnp.float32)
        self._q_high = jnp.asarray(mj_model.jnt_range[:, 1], jnp.float32)

    def _apply_action(self, data, action):
        target = jnp.clip(data.qpos + self.max_delta * action, self._q_low, self._q_high)
        return data.replace(ctrl=target)

    def _proprio(self, data):
        return {"q": data.qpos, "qdot": data.qvel}
