"""How far the task's object's image moves per ε of goal: the measure of the resolvability contract.

A goal the agent must reach within ε is only visible to the image branch if moving the task's object by ε moves
its image by a pixel or more (docs/tasks.md, "camera"). `shifts` measures that shift, per goal axis, over states
drawn from the goal region (`sample`): the object's image centroid, from the camera's per-ray geom ids
(`Camera.geom_map`, cast `supersample`² rays a pixel so that the centroid is finer than a pixel; in output pixels of
the 42×42 frame), before and after the object moves by ε along the axis (hidden behind another body: a shift of 0).

- nicol_slide, nicol_lift: the cube, at goals drawn from the task's goal distribution (the arm at rest), moved by
  ε = 0.05 m along x and y (slide) or x, y and z (lift, whose goals lie on the table and up to 0.25 m above it).
- planar_reach: the end-effector dot, at end-effector positions of the goal distribution, moved by ε = 0.02 m
  along x and y by the arm (the configuration that puts it there, elbow on the same side; where that lies out of
  reach, by -ε).
- ur5_reach: the goal is a joint configuration, so each axis is a joint: the wrist stub (the last link, ending at
  the tool point, the part of the arm that every joint moves furthest) at configurations of the goal
  distribution, turned by ε = 0.1 rad about one joint.

Only the object of the moving bodies is drawn (`object_camera`; `others` draws them all, the goal markers moved out
of view): where the arm and the markers stand is no part of the goal.

The command: `python -m experiments.probes.resolvability`; a camera pose search for ur5_reach:
`python -m experiments.probes.camera_search`.
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from envs_mjx.base import IMAGE_SHAPE, Env
from envs_mjx.camera import VISIBLE_GROUPS, Camera, subtree_geoms
from envs_mjx.nicol import NicolEnv, NicolLift
from envs_mjx.planar_reach import LINK_LENGTH, PlanarReach
from envs_mjx.planar_reach import forward_kinematics as planar_fk

CONTRACT_PX = 1.5  # px per ε in the lowest decile over the goal region (planar_reach's level)
SUPERSAMPLE = 4  # rays per pixel side the centroid is measured with
OUT_OF_VIEW = (0.0, 0.0, 100.0)  # where the goal markers go: above every camera, outside its frame
AXES_XYZ = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class Target:
    """What the probe moves: the object's geoms and the goal axes it moves along, by ε (in `unit`)."""

    name: str
    geoms: tuple[int, ...]
    axes: tuple[str, ...]
    epsilon: float
    unit: str


def target(env: Env) -> Target:
    """The object and goal axes of `env`'s task."""
    m = env.mj_model
    if isinstance(env, NicolEnv):
        axes = AXES_XYZ if isinstance(env, NicolLift) else AXES_XYZ[:2]
        return Target("cube", subtree_geoms(m, "cube"), axes, env.epsilon, "m")
    if isinstance(env, PlanarReach):
        return Target("end-effector dot", (m.geom("ee").id,), AXES_XYZ[:2], env.epsilon, "m")
    joints = tuple(m.joint(j).name for j in range(m.njnt))
    return Target("wrist stub", (m.geom("wrist_stub").id,), joints, env.epsilon, "rad")


def goal_qpos(env: Env, key: jax.Array) -> jax.Array:
    """A configuration (qpos) whose object stands where the goal distribution puts it: NICOL's cube at a drawn goal
    (the arm at rest), a reaching arm in a configuration drawn as the task draws its goals."""
    if isinstance(env, NicolEnv):
        data, goal = env._reset_data(key)
        return data.qpos.at[env._cube_qpos:env._cube_qpos + 3].set(goal)
    if isinstance(env, PlanarReach):
        return env._sample_q(key)
    return env.sample_configuration(key)


def planar_ik(ee: jax.Array, elbow: jax.Array) -> jax.Array:
    """planar_reach's joint angles (2,) that put the end effector at `ee` (2,), within reach, the elbow bent to the
    side of `elbow`'s sign."""
    reach2, link2 = jnp.sum(ee**2), LINK_LENGTH**2
    q2 = jnp.where(elbow < 0, -1.0, 1.0) * jnp.arccos(jnp.clip((reach2 - 2 * link2) / (2 * link2), -1.0, 1.0))
    q1 = jnp.arctan2(ee[1], ee[0]) - jnp.arctan2(LINK_LENGTH * jnp.sin(q2), LINK_LENGTH * (1 + jnp.cos(q2)))
    return jnp.stack([q1, q2])


def moved(env: Env, qpos: jax.Array, axis: int, epsilon: float) -> jax.Array:
    """`qpos` with the task's object moved by `epsilon` along goal axis `axis` (`target`): NICOL's cube by its free
    joint, planar_reach's end effector by the arm (by -`epsilon` where +`epsilon` is out of reach), ur5_reach's
    joint `axis` turned."""
    if isinstance(env, NicolEnv):
        return qpos.at[env._cube_qpos + axis].add(epsilon)
    if isinstance(env, PlanarReach):
        ee, step = planar_fk(qpos), jnp.zeros(2).at[axis].set(epsilon)
        ahead = jnp.linalg.norm(ee + step) <= 2 * LINK_LENGTH
        return planar_ik(jnp.where(ahead, ee + step, ee - step), qpos[1])
    return qpos.at[axis].add(epsilon)


def centroid(ids: jax.Array, geoms: tuple[int, ...], supersample: int) -> tuple[jax.Array, jax.Array]:
    """(row, col) centroid in output pixels of the rays in `ids` [R, R] that hit `geoms`, and how many rays do."""
    hit = jnp.isin(ids, jnp.asarray(geoms))
    count = hit.sum()
    centres = (jnp.arange(ids.shape[0]) + 0.5) / supersample
    rows = (hit.sum(axis=1) * centres).sum() / jnp.maximum(count, 1)
    cols = (hit.sum(axis=0) * centres).sum() / jnp.maximum(count, 1)
    return jnp.stack([rows, cols]), count


def object_camera(env: Env, supersample: int, others: bool = False) -> Camera:
    """`env`'s camera, casting `supersample`² rays a pixel, that draws of the moving bodies only the task's object
    (`others`: all of them, as the env's camera does)."""
    model = copy.copy(env.mj_model)  # a deep copy: geom groups change below
    if not others:
        moving = model.body_weldid[model.geom_bodyid] != 0
        hidden = moving & ~np.isin(np.arange(model.ngeom), target(env).geoms)
        model.geom_group[hidden] = len(VISIBLE_GROUPS)  # past the groups the camera draws
    return Camera(model, env.camera_name, IMAGE_SHAPE[0], supersample=supersample)


def shifts(env: Env, qpos: jax.Array, supersample: int = SUPERSAMPLE,
           others: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(pixels the object's image centroid moves per ε [N, axes], whether it is hidden before or after [N, axes]),
    at the configurations `qpos` [N, nq], the other moving bodies drawn where `others`; a hidden object counts
    as a shift of 0."""
    tgt = target(env)
    camera = object_camera(env, supersample, others)

    def look(q):
        data = env.blank_data().replace(qpos=q)
        data = data.replace(mocap_pos=jnp.broadcast_to(jnp.asarray(OUT_OF_VIEW, jnp.float32), data.mocap_pos.shape))
        return mjx.kinematics(env.mjx_model, data)

    def one(q):
        data = look(q)
        before, seen = centroid(camera.geom_map(env.mjx_model, data), tgt.geoms, supersample)
        out = []
        for i in range(len(tgt.axes)):
            after, seen_after = centroid(camera.geom_map(env.mjx_model, look(moved(env, q, i, tgt.epsilon))),
                                         tgt.geoms, supersample)
            hidden = (seen == 0) | (seen_after == 0)
            out.append((jnp.where(hidden, 0.0, jnp.linalg.norm(after - before)), hidden))
        return jnp.stack([s for s, _ in out]), jnp.stack([h for _, h in out])

    px, hidden = jax.jit(jax.vmap(one))(qpos)
    return np.asarray(px), np.asarray(hidden)


def sample(env: Env, states: int, seed: int = 0) -> jax.Array:
    """`states` goal-region configurations [states, nq] of `env` (`goal_qpos`)."""
    return jax.jit(jax.vmap(lambda k: goal_qpos(env, k)))(jax.random.split(jax.random.PRNGKey(seed), states))


def summary(px: np.ndarray, hidden: np.ndarray) -> dict[str, np.ndarray]:
    """Per axis: mean px per ε, 10th percentile (the contract's lowest decile) and the share of hidden states."""
    return {"mean": px.mean(axis=0), "p10": np.percentile(px, 10, axis=0), "hidden": hidden.mean(axis=0)}


def meets_contract(px: np.ndarray) -> np.ndarray:
    """Whether each axis's lowest decile moves at least `CONTRACT_PX` pixels per ε [axes]."""
    return np.percentile(px, 10, axis=0) >= CONTRACT_PX
