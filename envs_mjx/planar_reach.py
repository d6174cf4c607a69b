"""planar_reach: a two-link planar arm reaches a target point (paper Sec. III-D.1, docs/tasks.md).

Proprio is (q, qdot), D = 4; the action (A = 2) moves each joint's position target by at
most 0.2 rad from the current joint angle; the goal (G = 2) is the end-effector's xy,
drawn as the forward kinematics of a uniformly drawn joint configuration, so it is always
reachable. Success: ‖ee_xy - goal‖ ≤ 0.02 m at the end of the 50-step episode.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco

from envs_mjx.base import JointReachEnv, load_model
from envs_mjx.task import Task

LINK_LENGTH = 0.12
MAX_DELTA = 0.2  # rad per step
TARGET_HEIGHT = 0.02  # the goal marker floats just above the arm so the camera sees it


def forward_kinematics(q: jax.Array) -> jax.Array:
    """End-effector xy of joint angles q (..., 2)."""
    a1, a12 = q[..., 0], q[..., 0] + q[..., 1]
    x = LINK_LENGTH * (jnp.cos(a1) + jnp.cos(a12))
    y = LINK_LENGTH * (jnp.sin(a1) + jnp.sin(a12))
    return jnp.stack([x, y], axis=-1)


class PlanarReach(JointReachEnv):
    """The planar reaching task; see the module docstring for the contract."""

    name = "planar_reach"
    # sized for a run on a CPU: 40 epochs of the default sizes, 20 for the agents that learn from images; the
    # learning curves' budget is where visual_bidal comes within 0.05 of its plateau (0.93) in pilot runs, epoch 75,
    # plus a margin (docs/deviations.md, "Learning-curve budgets"; results/pilots)
    task = Task(contract="docs/tasks.md#planar_reach", presets={"run": {"epochs": 40}},
                image_presets={"run": {"epochs": 20}}, paper_epochs=100)

    def __init__(self, render: bool = True):
        mj_model = load_model("planar_reach.xml")
        super().__init__(
            mj_model, max_delta=MAX_DELTA, goal_size=2, camera_name="top", episode_length=50, epsilon=0.02,
            render=render,
        )
        self._ee_site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, "ee")

    def _sample_q(self, key: jax.Array) -> jax.Array:
        return jax.random.uniform(key, (2,), minval=self._q_low, maxval=self._q_high)

    def _reset_data(self, key):
        key_start, key_goal = jax.random.split(key)
        q0 = self._sample_q(key_start)
        goal = forward_kinematics(self._sample_q(key_goal))
        data = self.blank_data()
        data = data.replace(
            qpos=q0,
            ctrl=q0,
            mocap_pos=data.mocap_pos.at[0].set(jnp.concatenate([goal, jnp.array([TARGET_HEIGHT])])),
        )
        return data, goal

    def _achieved_goal(self, data):
        return data.site_xpos[self._ee_site, :2]
