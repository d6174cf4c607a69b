"""nicol_slide and nicol_lift: NICOL's right arm and hand move a cube (paper Sec. III-D.3, docs/tasks.md).

The scene (`assets/nicol.xml`, documented in `assets/README.md`) is NICOL's right
OpenManipulator-P arm with a simplified RH8D hand at a table, a 0.05 m cube and a dark
red ellipsoid goal marker, seen by a fixed camera on the robot's right, high above the table and
looking down 38° with a narrow field of view: steep enough that moving the cube by ε along either
table axis moves its image by ≥ 1.5 px (`python -m experiments.probes.resolvability`), and low
enough that the hand, which holds the cube from above, does not hide it
(`python -m experiments.probes.visibility`). The agents' frames do not draw the goal marker (its
geom is in `MARKER_GROUP`, which videos draw): the goal reaches the agents as a vector that HER
relabels, and a marker at the episode's goal would contradict the relabelled one.

Action (A = 7, paper Table I), each entry in [-1, 1]:
  0-2  hand position increment in Cartesian space, at most `MAX_MOVE` = 0.05 m per axis;
  3-4  hand roll and tilt increments, at most `MAX_TURN` = 0.1 rad per step;
  5    finger closure, absolute: -1 open, +1 closed (one coupled flexion of all fingers);
  6    thumb abduction, absolute: -1 along the palm, +1 opposing the fingers.

The arm follows the Cartesian command as in the Fetch tasks: a mocap body, welded to the
hand's grasp point, is moved to `clip(hand + increment)` inside the workspace box, and the
arm joints follow passively under the weld. The target moves there in even steps over the
physics substeps of the control period (`NicolEnv.target_path`), so the hand is led at
most 0.05 m per 0.04 s (1.25 m/s) instead of being pulled by a jump (tracking error after
one control period under 1 cm; see tests/envs_mjx/test_nicol.py). Roll and tilt are angles about the
hand's own x (along the fingers) and y (across the palm) axes relative to the rest
orientation, kept within `ROLL_RANGE` and `TILT_RANGE`. The contacts and solver settings
that keep the cube from being thrown are in `assets/nicol.xml`, with the measurements behind
them in `assets/README.md` (`python -m experiments.probes.physics` repeats them).

Proprio (D = 40, paper Table I), in this order: `ee_pos` 3 (the hand's grasp point),
`ee_rot` 3, `obj_pos` 3, `obj_rot` 3, `obj_rel_pos` 3 (cube minus hand), `obj_velp` 3,
`obj_velr` 3, `ee_velp` 3, `q` 8 (the six arm joints, finger closure, thumb abduction),
`qdot` 8. Rotations are continuous (a small physical rotation is a small change of input):
- `obj_rot` (`cube_rotation`) is the rotation vector from the cube's rest pose to the nearest
  of the 24 poses that look alike (the cube's rotation group): zero at rest, the same for
  alike poses, at most `MAX_CUBE_ANGLE` (62.8°) long. It jumps only where two alike poses are
  equally near, as any 3 numbers that respect the symmetry must; Euler angles of a tumbling
  cube wrap at ±π and flip near pitch ±π/2.
- `ee_rot` stays extrinsic x-y-z Euler angles (roll, pitch, yaw) of the hand's world
  rotation, as in Gymnasium-Robotics' Fetch observations: within `ROLL_RANGE` and
  `TILT_RANGE` of the rest pose (20° about z) they stay within |roll| ≤ 0.90, |pitch| ≤ 0.60,
  |yaw| ≤ 0.81 rad, far from the wrap at ±π and the flip at pitch ±π/2, so they are
  continuous over the hand's whole range.
Velocities are world-frame m/s and rad/s. The RH8D wrist flexion joint that helps the arm
reach is not part of `q` (docs/tasks.md fixes q to eight entries); its effect is seen through
`ee_rot`.

Goal (G = 3): the cube centre; ε = 0.05 m, T = 50 steps. The cube starts upright,
aligned with the resting hand, uniformly within ±`CUBE_START_RANGE` (xy) of a point in
front of the hand's rest position.
- nicol_slide: goal on the table within ±`SLIDE_GOAL_RANGE` of the cube's start region.
- nicol_lift: goal within ±`LIFT_GOAL_RANGE` (xy) of the cube's start; as in HER's pick-and-place
  (Gymnasium-Robotics Fetch, whose paper reports that pick-and-place trains without grasped starts
  only when goals are sometimes on the table), on the table with probability
  1 - `air_goal_probability` (0.5) and otherwise `LIFT_HEIGHT` above the table top. `goal_subsets`
  names the air goals, so that evaluation reports the lifting skill on its own (`eval_success_air`),
  and `never_lift_success` is what a policy that slides but never lifts scores.
  Its `exploration_reset` starts with the cube already held in the resting hand (the
  HER paper's pick-and-place aid, a labelled variant: the trainer's `exploration_starts`).
- nicol_lift_reduced (`NicolLiftReduced`): lift without obj_rot, obj_velp, obj_velr and
  obj_rel_pos (D = 28), for the transfer experiment (paper Sec. IV-C).
- nicol_slide_ee (`NicolSlideEE`, D = 3: `ee_pos`) and nicol_slide_ee_obj (`NicolSlideEEObj`, D = 6: `ee_pos`,
  `obj_pos`): slide whose proprio keeps only those segments (`NicolSlideKept`), the rungs of the pixel agents'
  ladder (`experiments.paper.ladder`): the image plus the hand's position, then plus the cube's. Labelled
  variants, no paper tasks.
"""

from __future__ import annotations

import abc
import copy
import dataclasses
from typing import Any

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs_mjx.base import Env, ObservationSpec, load_model
from envs_mjx.task import Preset, Task

PROPRIO_SEGMENTS = (
    ("ee_pos", 3),
    ("ee_rot", 3),
    ("obj_pos", 3),
    ("obj_rot", 3),
    ("obj_rel_pos", 3),
    ("obj_velp", 3),
    ("obj_velr", 3),
    ("ee_velp", 3),
    ("q", 8),
    ("qdot", 8),
)
REDUCED_DROP = ("obj_rot", "obj_velp", "obj_velr", "obj_rel_pos")
# segments computed from measured ones: observation noise on the sources reaches them (bidal_jax/noise.py)
DERIVED = (("obj_rel_pos", (("obj_pos", 1.0), ("ee_pos", -1.0))),)

EPISODE_LENGTH = 50
EPSILON = 0.05  # m
MAX_MOVE = 0.05  # m per step and axis
MAX_TURN = 0.1  # rad per step
ROLL_RANGE = 0.8  # rad, either side of the rest orientation
TILT_RANGE = 0.6  # rad
# the hand's grasp point stays in this box above the table (world frame, m)
WORKSPACE_LOW = (0.2, -0.45, 0.825)
WORKSPACE_HIGH = (0.7, 0.1, 1.075)

TABLE_HEIGHT = 0.8
CUBE_HALF = 0.025
CUBE_START_RANGE = 0.1  # ± m around the keyframe's cube position
SLIDE_GOAL_RANGE = 0.15  # ± m beyond the start region
LIFT_GOAL_RANGE = 0.1  # ± m around the cube's start
LIFT_HEIGHT = (0.05, 0.25)  # m of an air goal above the table top
AIR_GOAL_PROBABILITY = 0.5  # HER's pick-and-place: half the goals in the air, half on the table
# HER's pick-and-place (arXiv 1707.01495, Sec. 4): half of the training episodes start with the cube held
# (`TrainConfig.exploration_starts` of nicol_lift's preset)
HELD_STARTS = 0.5
GRASP_CLOSE_TIME = 1.0  # s for fingers and thumb (at most 2 rad/s) to close on the cube, without gravity
GRASP_SETTLE_TIME = 0.4  # s for the held cube to settle under gravity

ARM_JOINTS = ("r_joint1", "r_joint2", "r_joint3", "r_joint4", "r_joint5", "r_joint6")
CHAIN_JOINTS = ARM_JOINTS + ("r_wrist",)  # every joint that moves the hand frame
HAND_JOINTS = ("r_fingers", "r_thumb")


# ----- rotations (w, x, y, z quaternions as in MuJoCo) ---------------------------------
def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product a ⊗ b."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_conj(q: jax.Array) -> jax.Array:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0])


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix of a unit quaternion."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def axis_quat(axis: int, angle: jax.Array) -> jax.Array:
    """Quaternion of a rotation by `angle` about coordinate axis `axis` (0, 1 or 2)."""
    vec = jnp.zeros(3).at[axis].set(jnp.sin(angle / 2))
    return jnp.concatenate([jnp.cos(angle / 2)[None], vec])


def roll_tilt(rest_quat: jax.Array, quat: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(roll, tilt) with quat = rest ⊗ Rx(roll) ⊗ Ry(tilt): angles about the hand's own axes."""
    rel = quat_to_mat(quat_mul(quat_conj(rest_quat), quat))
    tilt = jnp.arcsin(jnp.clip(rel[0, 2], -1.0, 1.0))
    roll = jnp.arctan2(rel[2, 1], rel[1, 1])
    return roll, tilt


def hand_quat(rest_quat: jax.Array, roll: jax.Array, tilt: jax.Array) -> jax.Array:
    return quat_mul(quat_mul(rest_quat, axis_quat(0, roll)), axis_quat(1, tilt))


def interpolate_pose(pos: jax.Array, quat: jax.Array, new_pos: jax.Array, new_quat: jax.Array, fraction):
    """The pose `fraction` of the way from (pos, quat) to (new_pos, new_quat): linear in position,
    normalised linear (nlerp, along the shorter arc) in orientation."""
    new_quat = jnp.where(jnp.dot(quat, new_quat) < 0.0, -new_quat, new_quat)
    between = quat + fraction * (new_quat - quat)
    return pos + fraction * (new_pos - pos), between / jnp.linalg.norm(between)


def euler_xyz(mat: jax.Array) -> jax.Array:
    """Extrinsic x-y-z Euler angles (roll, pitch, yaw) of mat = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = jnp.arctan2(mat[2, 1], mat[2, 2])
    pitch = jnp.arcsin(jnp.clip(-mat[2, 0], -1.0, 1.0))
    yaw = jnp.arctan2(mat[1, 0], mat[0, 0])
    return jnp.stack([roll, pitch, yaw])


def _cube_symmetries() -> np.ndarray:
    """The 24 proper rotations that map a cube onto itself (its rotation group), as unit quaternions."""
    h, q = np.sqrt(0.5), 0.5
    quats = [(1.0, 0.0, 0.0, 0.0)]
    for axis in np.eye(3):
        quats += [(0.0, *axis), (h, *(h * axis)), (h, *(-h * axis))]  # 180° and ±90° about each face axis
    for i, j in ((0, 1), (0, 2), (1, 2)):  # 180° about the six edge diagonals
        for sign in (1.0, -1.0):
            axis = np.zeros(3)
            axis[i], axis[j] = h, sign * h
            quats.append((0.0, *axis))
    # ±120° about the 4 body diagonals
    for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
        quats.append((q, *(q * signs)))
    return np.array(quats, np.float32)


CUBE_SYMMETRIES = _cube_symmetries()
# the largest angle between a cube's orientation and the nearest of its 24 symmetric poses:
# 2 arctan of the Rodrigues vector to a vertex of the fundamental zone, (√2-1)(1, 1, √2-1); 62.8°
MAX_CUBE_ANGLE = float(2 * np.arctan(np.linalg.norm((np.sqrt(2) - 1) * np.array([1.0, 1.0, np.sqrt(2) - 1]))))


def rotation_vector(quat: jax.Array) -> jax.Array:
    """Axis × angle (rad, in [0, π]) of a unit quaternion's rotation."""
    quat = jnp.where(quat[0] < 0.0, -quat, quat)
    sin = jnp.linalg.norm(quat[1:])
    angle = 2.0 * jnp.arctan2(sin, quat[0])
    # angle / sin → 2 as the rotation vanishes; the guard keeps the gradient finite there
    return quat[1:] * jnp.where(sin > 1e-7, angle / jnp.maximum(sin, 1e-7), 2.0)


def cube_rotation(quat: jax.Array, rest_quat: jax.Array) -> jax.Array:
    """A cube's orientation as 3 continuous numbers that respect its symmetry: the rotation vector
    (world frame) that turns its rest pose `rest_quat` onto the nearest of the 24 poses `quat`
    looks alike in (`quat` ⊗ s for s in `CUBE_SYMMETRIES`). Zero at rest and at every pose that
    looks like it, at most `MAX_CUBE_ANGLE` long, and a small rotation of the cube changes it by
    as little (except where two symmetric poses are equally near, where any such map must jump)."""
    chex.assert_shape([quat, rest_quat], (4,))
    poses = jax.vmap(lambda s: quat_mul(quat, s))(jnp.asarray(CUBE_SYMMETRIES))
    nearest = poses[jnp.argmax(jnp.abs(poses @ rest_quat))]
    return rotation_vector(quat_mul(nearest, quat_conj(rest_quat)))


def point_velocity(point: jax.Array, qvel: jax.Array, axes: jax.Array, anchors: jax.Array) -> jax.Array:
    """Linear velocity of a point moved by a chain of hinges (axes, anchors: (n, 3); qvel: (n,))."""
    return jnp.sum(qvel[:, None] * jnp.cross(axes, point - anchors), axis=0)


# ----- the environments ----------------------------------------------------------------
def held_cube_start(mj_model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, ctrl) of the home pose with the cube held between fingers and thumb.

    Native MuJoCo, once at construction: the cube is put at the resting hand's grasp
    point, fingers and thumb close on it without gravity (`GRASP_CLOSE_TIME`), then it
    settles in the grip under gravity (`GRASP_SETTLE_TIME`).
    """
    model = copy.copy(mj_model)  # a deep copy: gravity is switched off below
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_kinematics(model, data)
    cube = model.body("cube")
    adr = int(model.jnt_qposadr[cube.jntadr[0]])
    data.qpos[adr : adr + 3] = data.xpos[model.body("r_hand").id]
    data.ctrl[:] = model.actuator_ctrlrange[:, 1]
    gravity = model.opt.gravity.copy()
    model.opt.gravity[:] = 0.0
    mujoco.mj_step(model, data, nstep=int(round(GRASP_CLOSE_TIME / model.opt.timestep)))
    model.opt.gravity[:] = gravity
    mujoco.mj_step(model, data, nstep=int(round(GRASP_SETTLE_TIME / model.opt.timestep)))
    return data.qpos.astype(np.float32), data.ctrl.astype(np.float32)


def _ids(mj_model: mujoco.MjModel, kind: mujoco.mjtObj, names: tuple[str, ...]) -> np.ndarray:
    ids = np.array([mujoco.mj_name2id(mj_model, kind, n) for n in names])
    if (ids < 0).any():
        raise ValueError(f"model lacks one of {names}")
    return ids


class NicolEnv(Env):
    """The shared NICOL scene, action and proprio; subclasses draw the goal."""

    def __init__(self, render: bool = True):
        mj_model = load_model("nicol.xml")
        super().__init__(
            mj_model,
            episode_length=EPISODE_LENGTH,
            epsilon=EPSILON,
            action_size=7,
            observation_spec=ObservationSpec(proprio_segments=PROPRIO_SEGMENTS, goal_size=3, derived=DERIVED,
                                             goal_segment="obj_pos"),
            camera_name="front",
            render=render,
        )
        body, joint = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT
        self._hand = int(_ids(mj_model, body, ("r_hand",))[0])
        self._cube = int(_ids(mj_model, body, ("cube",))[0])
        self._target_mocap = int(mj_model.body_mocapid[_ids(mj_model, body, ("hand_target",))[0]])
        self._goal_mocap = int(mj_model.body_mocapid[_ids(mj_model, body, ("goal",))[0]])
        cube_joint = int(mj_model.body_jntadr[self._cube])
        self._cube_qpos = int(mj_model.jnt_qposadr[cube_joint])
        self._cube_dof = int(mj_model.jnt_dofadr[cube_joint])
        self._chain_joints = _ids(mj_model, joint, CHAIN_JOINTS)
        self._chain_dofs = mj_model.jnt_dofadr[self._chain_joints]
        q_joints = _ids(mj_model, joint, ARM_JOINTS + HAND_JOINTS)
        self._q_adr = mj_model.jnt_qposadr[q_joints]
        self._qdot_adr = mj_model.jnt_dofadr[q_joints]
        self._ctrl_low = jnp.asarray(mj_model.actuator_ctrlrange[:, 0], jnp.float32)
        self._ctrl_high = jnp.asarray(mj_model.actuator_ctrlrange[:, 1], jnp.float32)
        key = mj_model.key("home")
        self._home_qpos = jnp.asarray(key.qpos, jnp.float32)
        self._home_mocap_pos = jnp.asarray(key.mpos.reshape(-1, 3), jnp.float32)
        self._home_mocap_quat = jnp.asarray(key.mquat.reshape(-1, 4), jnp.float32)
        self._rest_quat = self._home_mocap_quat[self._target_mocap]
        self._cube_centre = jnp.asarray(key.qpos[self._cube_qpos : self._cube_qpos + 3], jnp.float32)
        self._cube_rest_quat = jnp.asarray(key.qpos[self._cube_qpos + 3 : self._cube_qpos + 7], jnp.float32)
        self._workspace_low = jnp.asarray(WORKSPACE_LOW, jnp.float32)
        self._workspace_high = jnp.asarray(WORKSPACE_HIGH, jnp.float32)

    # ----- task hook -------------------------------------------------------------------
    @abc.abstractmethod
    def _sample_goal(self, key: jax.Array, cube_pos: jax.Array) -> jax.Array:
        """The desired cube position (3,) for a cube starting at `cube_pos`."""

    # ----- Env hooks -------------------------------------------------------------------
    def _reset_data(self, key):
        key_cube, key_goal = jax.random.split(key)
        offset = jax.random.uniform(key_cube, (2,), minval=-CUBE_START_RANGE, maxval=CUBE_START_RANGE)
        cube_pos = self._cube_centre.at[:2].add(offset)
        goal = self._sample_goal(key_goal, cube_pos)
        qpos = self._home_qpos.at[self._cube_qpos : self._cube_qpos + 3].set(cube_pos)
        mocap_pos = self._home_mocap_pos.at[self._goal_mocap].set(goal)
        data = self.blank_data().replace(
            qpos=qpos, mocap_pos=mocap_pos, mocap_quat=self._home_mocap_quat, ctrl=self._ctrl_low
        )
        return data, goal

    def commands(self, hand_pos: jax.Array, target_quat: jax.Array, action: jax.Array) -> tuple[jax.Array, ...]:
        """(hand target position, hand target quaternion, ctrl) at the end of a control period, from
        the grasp point `hand_pos`, the current target quaternion and a clipped action."""
        target = jnp.clip(hand_pos + MAX_MOVE * action[:3], self._workspace_low, self._workspace_high)
        roll, tilt = roll_tilt(self._rest_quat, target_quat)
        roll = jnp.clip(roll + MAX_TURN * action[3], -ROLL_RANGE, ROLL_RANGE)
        tilt = jnp.clip(tilt + MAX_TURN * action[4], -TILT_RANGE, TILT_RANGE)
        ctrl = self._ctrl_low + 0.5 * (action[5:7] + 1.0) * (self._ctrl_high - self._ctrl_low)
        return target, hand_quat(self._rest_quat, roll, tilt), ctrl

    def target_path(self, pos: jax.Array, quat: jax.Array, new_pos: jax.Array, new_quat: jax.Array, i: jax.Array):
        """The hand target (position, quaternion) at physics substep `i` of a control period that moves
        it from (pos, quat) to (new_pos, new_quat): evenly spaced, reaching the new target at the last
        substep, so that the hand is led along the way instead of pulled by a jump."""
        return interpolate_pose(pos, quat, new_pos, new_quat, (i + 1) / self.n_substeps)

    def _apply_action(self, data, action):
        target, quat, ctrl = self.commands(data.xpos[self._hand], data.mocap_quat[self._target_mocap], action)
        return data.replace(
            mocap_pos=data.mocap_pos.at[self._target_mocap].set(target),
            mocap_quat=data.mocap_quat.at[self._target_mocap].set(quat),
            ctrl=ctrl,
        )

    def _substep_controls(self, before, commanded, data, i):
        t = self._target_mocap
        pos, quat = self.target_path(
            before.mocap_pos[t], before.mocap_quat[t], commanded.mocap_pos[t], commanded.mocap_quat[t], i
        )
        return data.replace(mocap_pos=data.mocap_pos.at[t].set(pos), mocap_quat=data.mocap_quat.at[t].set(quat))

    def _proprio(self, data):
        ee_pos = data.xpos[self._hand]
        obj_pos = data.xpos[self._cube]
        cube_vel = data.qvel[self._cube_dof : self._cube_dof + 6]
        ee_velp = point_velocity(
            ee_pos,
            data.qvel[self._chain_dofs],
            data.xaxis[self._chain_joints],
            data.xanchor[self._chain_joints],
        )
        return {
            "ee_pos": ee_pos,
            "ee_rot": euler_xyz(data.xmat[self._hand]),
            "obj_pos": obj_pos,
            "obj_rot": cube_rotation(data.xquat[self._cube], self._cube_rest_quat),
            "obj_rel_pos": obj_pos - ee_pos,
            "obj_velp": cube_vel[:3],
            # a free joint's angular velocity is in the body frame; rotate it to the world
            "obj_velr": data.xmat[self._cube] @ cube_vel[3:],
            "ee_velp": ee_velp,
            "q": data.qpos[self._q_adr],
            "qdot": data.qvel[self._qdot_adr],
        }

    def _achieved_goal(self, data):
        return data.xpos[self._cube]


def gpu_preset(epochs: int, num_envs: int, cycles_per_epoch: int, updates_per_cycle: int, **train: Any) -> Preset:
    """A NICOL task's preset, sized for one GPU and the same for every agent of the task (equal budgets): `epochs`
    epochs (the task's learning-curve budget) of `cycles_per_epoch` cycles of `num_envs` envs and
    `updates_per_cycle` gradient updates of batch 2,048, a buffer of the most whole rollouts of `num_envs` episodes
    that fit in 16,384 episodes, 128 evaluation episodes, and the learner fields `train`; many parallel envs, big
    batches and many gradient updates cost little beside the physics there. The vision branch's convs as matmuls in
    bfloat16, banded with the last two layers as whole-frame Toeplitz matmuls (`NetworkConfig.conv_impl` toeplitz,
    `vision_dtype`), the fastest image update on a GPU, with which nicol_slide and planar_reach learn as in float32
    (docs/performance.md, "Image updates"); the physics on MuJoCo Warp where a run's devices are NVIDIA GPUs and
    warp-lang imports (`RunConfig.physics` auto), whose epochs are shorter than MJX-JAX's there (docs/performance.md,
    "MJX-JAX against MuJoCo Warp"); a checkpoint every 10 epochs instead of 5, since one holds the replay buffer
    (GBs of frames) and its save costs the time of epochs (docs/performance.md, "What a checkpoint costs")."""
    sizes = {"num_envs": num_envs, "cycles_per_epoch": cycles_per_epoch, "updates_per_cycle": updates_per_cycle,
             "batch_size": 2048, "buffer_episodes": 16384 // num_envs * num_envs, "eval_envs": 128}
    return {"run": {"epochs": epochs, "physics": "auto", "checkpoint_every": 10}, "train": {**sizes, **train},
            "network": {"conv_impl": "toeplitz", "vision_dtype": "bfloat16"}}


class NicolSlide(NicolEnv):
    """Slide the cube along the table to a goal on the table."""

    name = "nicol_slide"
    # one cycle of 2,560 envs and 1,600 updates per epoch (128,000 env steps, one update per 80), since one wide
    # cycle costs fewer sequential physics steps than 512 envs × 5 cycles (the same env steps and updates): 50 in a
    # row an epoch instead of 250; 5 seeds of multimodal_bidal reach 0.9 in 9 epochs (docs/performance.md, "Cold to 0.9
    # on nicol_slide"). The learning curves' budget: the multimodal agents at ≥ 0.9 from epoch 10-13 in pilot runs,
    # the visual agents at the do-nothing level through 25 epochs, plus about 15 (docs/deviations.md,
    # "Learning-curve budgets")
    task = Task(contract="docs/tasks.md#nicol_slide-and-nicol_lift", presets=gpu_preset(30, 2560, 1, 1600),
                paper_epochs=30)

    def _sample_goal(self, key, cube_pos):
        reach = CUBE_START_RANGE + SLIDE_GOAL_RANGE
        offset = jax.random.uniform(key, (2,), minval=-reach, maxval=reach)
        return self._cube_centre.at[:2].add(offset)


class NicolLift(NicolEnv):
    """Grasp the cube and lift it to a goal in the air (or move it to one on the table).

    Args:
      render: as for `Env`.
      air_goal_probability: share of goals `LIFT_HEIGHT` above the table; the rest lie on it
        (1.0: every goal in the air, a labelled variant).
    """

    name = "nicol_lift"
    has_exploration_start = True
    # 6,400 updates per epoch (one per 32 env steps), since with 1,600 proprio_baseline (5 seeds) reached what sliding
    # alone can score (0.125) only by epoch 53 instead of 21; twice as many again gain nothing and cost time
    # (docs/results.md, "Lifting"); nor do a quarter as many of batch 8,192, the same samples: their epochs are
    # shorter, but they learn less per epoch (docs/performance.md, "Learning parity of the speed levers"). Every agent
    # trains under HER's pick-and-place protocol: half of the training episodes start with the cube held
    # (`HELD_STARTS`). The learning curves' budget: multimodal_bidal (λ 0.1) at ≥ 0.9 air-goal success from epoch 11
    # in pilot runs, proprio_baseline from 6, plus about 15 (docs/deviations.md, "Learning-curve budgets")
    task = Task(contract="docs/tasks.md#nicol_slide-and-nicol_lift",
                presets=gpu_preset(25, 2048, 2, 3200, exploration_starts=HELD_STARTS), paper_epochs=25)

    def __init__(self, render: bool = True, air_goal_probability: float = AIR_GOAL_PROBABILITY):
        if not 0.0 <= air_goal_probability <= 1.0:
            raise ValueError(f"air_goal_probability={air_goal_probability}: must be in [0, 1]")
        super().__init__(render=render)
        self.air_goal_probability = air_goal_probability
        held_qpos, held_ctrl = held_cube_start(self.mj_model)
        self._held_qpos, self._held_ctrl = jnp.asarray(held_qpos), jnp.asarray(held_ctrl)

    def goal_subsets(self, goal: jax.Array) -> dict[str, jax.Array]:
        """{"air": whether each goal [..., 3] lies above the table (the lifting skill), "table": whether it lies on
        it (pushing, which sliding alone solves)}."""
        air = goal[..., 2] > TABLE_HEIGHT + CUBE_HALF + 1e-3
        return {"air": air, "table": jnp.logical_not(air)}

    def never_lift_success(self) -> dict[str, float]:
        """Success of a policy that slides the cube perfectly but never lifts it, over all goals, over air goals
        (one counts when its height above the resting cube is at most ε) and over table goals (every one)."""
        low, high = LIFT_HEIGHT[0] - CUBE_HALF, LIFT_HEIGHT[1] - CUBE_HALF
        air = float(np.clip((EPSILON - low) / (high - low), 0.0, 1.0))
        return {"all": 1.0 - self.air_goal_probability * (1.0 - air), "air": air, "table": 1.0}

    def _exploration_reset_data(self, key):
        # the goal as in `reset` (drawn for a cube on the table); the cube starts in the hand
        data, goal = self._reset_data(key)
        return data.replace(qpos=self._held_qpos, ctrl=self._held_ctrl), goal

    def _sample_goal(self, key, cube_pos):
        key_xy, key_z, key_air = jax.random.split(key, 3)
        xy = cube_pos[:2] + jax.random.uniform(key_xy, (2,), minval=-LIFT_GOAL_RANGE, maxval=LIFT_GOAL_RANGE)
        height = jax.random.uniform(key_z, (), minval=LIFT_HEIGHT[0], maxval=LIFT_HEIGHT[1])
        in_air = jax.random.uniform(key_air) < self.air_goal_probability
        z = TABLE_HEIGHT + jnp.where(in_air, height, CUBE_HALF)
        return jnp.concatenate([xy, z[None]])


class NicolLiftReduced(NicolLift):
    """nicol_lift without obj_rot, obj_velp, obj_velr and obj_rel_pos (D = 28), paper Sec. IV-C.

    The same task and step; only the observation spec differs, and observations are built
    from the spec's segment names, so the dropped segments are never observed."""

    name = "nicol_lift_reduced"
    # nicol_lift's presets; the transfer's target (experiments.paper.transfer_learning), not a learning-curve task
    task = dataclasses.replace(NicolLift.task, paper_epochs=None)

    def __init__(self, render: bool = True, air_goal_probability: float = AIR_GOAL_PROBABILITY):
        super().__init__(render=render, air_goal_probability=air_goal_probability)
        self.observation_spec = self.observation_spec.without(REDUCED_DROP)


class NicolSlideKept(NicolSlide):
    """nicol_slide whose proprio keeps only the segments named in `keep`, in `PROPRIO_SEGMENTS` order (a labelled
    variant: the rungs of `experiments.paper.ladder`). The same task, step and camera; observations are built from
    the spec's segment names, so the other segments are never observed."""

    keep: tuple[str, ...] = ()
    task = dataclasses.replace(NicolSlide.task, paper_epochs=None)  # a variant, not a task of the learning curves

    def __init__(self, render: bool = True):
        super().__init__(render=render)
        names = self.observation_spec.segment_names
        unknown = sorted(set(self.keep) - set(names))
        if unknown or not self.keep:
            raise ValueError(f"{self.name}: cannot keep {unknown or 'no segment'}; segments are {names}")
        self.observation_spec = self.observation_spec.without(tuple(n for n in names if n not in self.keep))


class NicolSlideEE(NicolSlideKept):
    """nicol_slide observing, beside the image, only the hand's grasp point `ee_pos` (D = 3)."""

    name = "nicol_slide_ee"
    keep = ("ee_pos",)


class NicolSlideEEObj(NicolSlideKept):
    """nicol_slide observing, beside the image, only the hand's grasp point and the cube's position (D = 6)."""

    name = "nicol_slide_ee_obj"
    keep = ("ee_pos", "obj_pos")
