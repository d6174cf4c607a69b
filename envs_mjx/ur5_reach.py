"""ur5_reach: the first three joints of a UR5 reach goal joint angles (paper Sec. III-D.2, docs/tasks.md).

Proprio is (q, qdot), D = 6; the action (A = 3) moves each joint's position target by at
most 0.1 rad from the current joint angle; the goal (G = 3) is a configuration of shoulder
pan, shoulder lift and elbow, shown by three dark yellow cubes at the elbow, wrist and tool
points of that configuration. Start and goal are drawn from the same distribution:
uniform within the joint ranges (pan ±π/2, lift [-π + 0.3, -0.3], elbow ±2.5 rad),
rejecting configurations whose elbow, wrist or tool point is below 0.05 m. Success:
‖q - goal‖ ≤ 0.1 rad at the end of the 50-step episode. Gravity is on; stiff position
servos track a 0.1 rad step within one control period, and the actuators cancel the
gravity load, so a zero action holds the arm still (assets/README.md, ur5_reach).

The rejection runs inside jit: `N_CANDIDATES` configurations are drawn at once, their
points computed by the analytic `forward_kinematics`, and the first valid one is kept,
which is exactly a draw from the uniform distribution restricted to the valid set. About
83 % of the box is valid, so all candidates fail with probability about 0.17^32 ≈ 4e-25;
then the configuration falls back to `FALLBACK_Q` (upper arm up, forearm forward), which
is valid.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from envs_mjx.base import JointReachEnv, load_model
from envs_mjx.task import Task

# UR5 DH parameters (m), as in assets/ur5_reach.xml
D1 = 0.089159  # shoulder-lift axis height above the base
A2 = 0.425  # upper arm
A3 = 0.39225  # forearm
SHOULDER_OFFSET = 0.13585  # along the shoulder-lift axis, base axis to upper arm
ELBOW_OFFSET = -0.1197  # along the elbow axis, upper arm to forearm
WRIST_STUB = 0.09465 + 0.0823  # fixed wrist laid along the forearm: d5 + d6

MAX_DELTA = 0.1  # rad per step
MIN_HEIGHT = 0.05  # m, lowest allowed elbow, wrist and tool point of a start or goal
N_CANDIDATES = 32
FALLBACK_Q = (0.0, -np.pi / 2, np.pi / 2)
POINT_NAMES = ("elbow", "wrist", "tool")


def forward_kinematics(q: jax.Array) -> jax.Array:
    """World positions of the elbow, wrist and tool points, (..., 3, 3), of joint angles
    q = (pan, lift, elbow) (..., 3). At q = 0 the arm lies along +x; negative lift raises it."""
    pan, lift, elbow = q[..., 0], q[..., 1], q[..., 2]
    forearm = lift + elbow
    # radial distance and height in the arm's vertical plane, which pan turns about z
    radial_elbow = A2 * jnp.cos(lift)
    height_elbow = D1 - A2 * jnp.sin(lift)
    radial = jnp.stack(
        [radial_elbow, radial_elbow + A3 * jnp.cos(forearm), radial_elbow + (A3 + WRIST_STUB) * jnp.cos(forearm)],
        axis=-1,
    )
    height = jnp.stack(
        [height_elbow, height_elbow - A3 * jnp.sin(forearm), height_elbow - (A3 + WRIST_STUB) * jnp.sin(forearm)],
        axis=-1,
    )
    lateral = SHOULDER_OFFSET + ELBOW_OFFSET
    cos_pan, sin_pan = jnp.cos(pan)[..., None], jnp.sin(pan)[..., None]
    x = cos_pan * radial - sin_pan * lateral
    y = sin_pan * radial + cos_pan * lateral
    return jnp.stack([x, y, height], axis=-1)


def is_valid(q: jax.Array) -> jax.Array:
    """Whether the elbow, wrist and tool points of q (..., 3) are all at least MIN_HEIGHT up."""
    return jnp.all(forward_kinematics(q)[..., 2] >= MIN_HEIGHT, axis=-1)


class UR5Reach(JointReachEnv):
    """The UR5 joint-space reaching task; see the module docstring for the contract."""

    name = "ur5_reach"
    # the main command's task: one cycle of 160 envs per epoch (the default's 16 × 10 episodes and 400 updates), whose
    # epoch steps the physics 100 times in a row instead of 550 (evaluation: 160 episodes in the cycles' scan), and
    # learns as fast (docs/performance.md, "Learning parity of the speed levers"). The learning curves' budget: the
    # visual agents near their plateau by epoch 150 in pilot runs (docs/deviations.md, "Learning-curve budgets")
    task = Task(
        contract="docs/tasks.md#ur5_reach",
        presets={"run": {"epochs": 15}, "train": {"num_envs": 160, "cycles_per_epoch": 1, "updates_per_cycle": 400,
                                                  "buffer_episodes": 4000, "eval_envs": 160}},
        paper_epochs=150,
    )

    def __init__(self, render: bool = True):
        mj_model = load_model("ur5_reach.xml")
        super().__init__(
            mj_model, max_delta=MAX_DELTA, goal_size=3, camera_name="side", episode_length=50, epsilon=0.1,
            render=render,
        )
        body_ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, f"goal_{n}") for n in POINT_NAMES]
        self._cube_mocap_ids = jnp.asarray(mj_model.body_mocapid[body_ids])

    def sample_configuration(self, key: jax.Array) -> jax.Array:
        """A joint configuration (3,) uniform within the ranges and above MIN_HEIGHT."""
        candidates = jax.random.uniform(key, (N_CANDIDATES, 3), minval=self._q_low, maxval=self._q_high)
        valid = is_valid(candidates)
        first = candidates[jnp.argmax(valid)]
        return jnp.where(jnp.any(valid), first, jnp.asarray(FALLBACK_Q, jnp.float32))

    def _reset_data(self, key):
        key_start, key_goal = jax.random.split(key)
        q0 = self.sample_configuration(key_start)
        goal = self.sample_configuration(key_goal)
        data = self.blank_data()
        data = data.replace(
            qpos=q0,
            ctrl=q0,
            mocap_pos=data.mocap_pos.at[self._cube_mocap_ids].set(forward_kinematics(goal)),
        )
        return data, goal

    def _achieved_goal(self, data):
        return data.qpos
