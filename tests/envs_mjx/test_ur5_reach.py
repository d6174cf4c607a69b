"""ur5_reach tests (docs/tasks.md ur5_reach): model, kinematics, sampling, control and camera.

The shared API tests (shapes, NaN, determinism, MJX vs mj_step) live in test_env_contract.py.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from bidal_jax import acting
from envs_mjx import ur5_reach
from envs_mjx.base import ASSETS_DIR, IMAGE_SHAPE
from envs_mjx.camera import Camera, visible_geoms
from envs_mjx.ur5_reach import UR5Reach, forward_kinematics

N_RESETS = 2000
N_ENVS = 16
N_STEPS = 50
ARM_GEOMS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_stub")


@pytest.fixture(scope="module")
def env():
    return UR5Reach(render=False)


@pytest.fixture(scope="module")
def resets(env):
    """N_RESETS initial states from one vmapped, jitted reset."""
    return jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), N_RESETS))


@pytest.fixture(scope="module")
def rollout(env):
    """Jitted (state batch, actions [N_STEPS, N_ENVS, 3]) -> qpos trajectory [N_STEPS, N_ENVS, 3]."""

    def run(states, actions):
        record = lambda step: step.next_state.data.qpos  # noqa: E731
        return acting.rollout(
            env, acting.open_loop, jax.random.PRNGKey(0), states=states, inputs=actions, record=record
        )[1]

    return jax.jit(run)


def first_envs(states, qpos=None):
    """The first N_ENVS states of a batch, optionally moved to joint angles `qpos` at rest."""
    states = jax.tree.map(lambda x: x[:N_ENVS], states)
    if qpos is None:
        return states
    qpos = jnp.asarray(qpos, jnp.float32)
    data = states.data.replace(qpos=qpos, qvel=jnp.zeros_like(qpos), ctrl=qpos)
    return states.replace(data=data)


def _id(m, obj, name):
    return mujoco.mj_name2id(m, obj, name)


def test_model_follows_the_contract(env):
    m = env.mj_model
    body = lambda name: _id(m, mujoco.mjtObj.mjOBJ_BODY, name)  # noqa: E731
    # UR5 DH parameters; link masses (the forearm body also carries the 2.6259 kg wrist stub)
    np.testing.assert_allclose(m.body_pos[body("shoulder_link")], [0, 0, 0.089159])
    np.testing.assert_allclose(m.body_pos[body("upper_arm_link")], [0, 0.13585, 0])
    np.testing.assert_allclose(m.body_pos[body("forearm_link")], [0.425, -0.1197, 0])
    links = [body(n) for n in ("shoulder_link", "upper_arm_link", "forearm_link")]
    np.testing.assert_allclose(m.body_mass[links], [3.7, 8.393, 2.275 + 2.6259])
    # joint ranges contain the sampling ranges
    sampling = np.array([[-np.pi / 2, np.pi / 2], [-np.pi + 0.3, -0.3], [-2.5, 2.5]])
    assert (m.jnt_range[:, 0] <= sampling[:, 0] + 1e-6).all() and (m.jnt_range[:, 1] >= sampling[:, 1] - 1e-6).all()
    np.testing.assert_allclose(m.actuator_ctrlrange, m.jnt_range)
    # primitive geoms the ray caster sees, each with a material; cube markers touch nothing
    allowed = {mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_BOX}
    assert set(m.geom_type) <= {int(t) for t in allowed}
    assert (m.geom_matid >= 0).all()
    assert (m.geom_contype == 0).all() and (m.geom_conaffinity == 0).all()
    cubes = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(m.nbody) if m.body_mocapid[b] >= 0]
    assert cubes == ["goal_elbow", "goal_wrist", "goal_tool"]
    assert np.linalg.norm(m.opt.gravity) > 9.0
    assert env.n_substeps == 4


def test_the_camera_draws_thick_massless_links_around_the_physical_ones(env):
    """Each link's drawn capsule is massless, thicker than its physical one and on the same axis; the physical
    one (the UR5's radius, mass and inertia) is in group 3, which the camera does not draw."""
    m = env.mj_model
    drawn = set(visible_geoms(m))
    for name in ARM_GEOMS:
        seen, physical = _id(m, mujoco.mjtObj.mjOBJ_GEOM, name), _id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{name}_mass")
        assert seen in drawn and physical not in drawn and m.geom_group[physical] == 3
        assert m.geom_bodyid[seen] == m.geom_bodyid[physical]
        np.testing.assert_array_equal(m.geom_pos[seen], m.geom_pos[physical])
        np.testing.assert_array_equal(m.geom_quat[seen], m.geom_quat[physical])
        assert m.geom_size[seen][1] == m.geom_size[physical][1]  # half-length
        assert m.geom_size[seen][0] >= m.geom_size[physical][0] + 0.02  # radius
    # the massless capsules add nothing: every link body's mass and inertia are its physical capsules'
    physical = mujoco.MjSpec.from_file(str(ASSETS_DIR / "ur5_reach.xml"))
    for name in ARM_GEOMS:
        physical.delete(physical.geom(name))
    bare = physical.compile()
    for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat"):
        np.testing.assert_array_equal(getattr(m, field), getattr(bare, field))


def test_forward_kinematics_matches_mujoco_sites(env):
    m = env.mj_model
    d = mujoco.MjData(m)
    sites = [_id(m, mujoco.mjtObj.mjOBJ_SITE, n) for n in ur5_reach.POINT_NAMES]
    qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (200, 3))
    points = np.asarray(forward_kinematics(jnp.asarray(qs, jnp.float32)))
    for q, p in zip(qs, points):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(p, d.site_xpos[sites], atol=1e-5)


def test_cubes_sit_at_the_goal_configuration(env, resets):
    expected = np.asarray(forward_kinematics(resets.info["goal"]))
    np.testing.assert_allclose(np.asarray(resets.data.mocap_pos), expected, atol=1e-5)
    cube_geoms = [_id(env.mj_model, mujoco.mjtObj.mjOBJ_GEOM, f"goal_{n}") for n in ur5_reach.POINT_NAMES]
    np.testing.assert_allclose(np.asarray(resets.data.geom_xpos[:, cube_geoms]), expected, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(resets.obs["desired_goal"]), np.asarray(resets.info["goal"]))


@pytest.mark.parametrize("which", ["start", "goal"])
def test_starts_and_goals_obey_the_ranges_and_the_height_rule(resets, which):
    q = np.asarray(resets.data.qpos if which == "start" else resets.info["goal"])
    low = np.array([-np.pi / 2, -np.pi + 0.3, -2.5])
    high = np.array([np.pi / 2, -0.3, 2.5])
    assert ((q >= low - 1e-6) & (q <= high + 1e-6)).all()
    heights = np.asarray(forward_kinematics(jnp.asarray(q)))[..., 2]
    assert heights.min() >= ur5_reach.MIN_HEIGHT
    # uniform within the valid set: every joint spreads over most of its range
    assert (q.max(0) - q.min(0) > 0.9 * (high - low)).all()
    assert len(np.unique(q, axis=0)) == N_RESETS
    assert bool(ur5_reach.is_valid(jnp.asarray(ur5_reach.FALLBACK_Q)))


def test_action_moves_each_joint_by_a_tenth_of_a_radian(resets, rollout):
    q_mid = np.array([0.2, -1.4, 1.0], np.float32)
    actions = np.zeros((N_STEPS, N_ENVS, 3), np.float32)
    for j in range(3):
        actions[0, j, j] = 1.0
        actions[0, 3 + j, j] = -1.0
    qpos = np.asarray(rollout(first_envs(resets, np.tile(q_mid, (N_ENVS, 1))), jnp.asarray(actions)))
    delta = qpos[0] - q_mid
    for j in range(3):
        for row, sign in [(j, 1.0), (3 + j, -1.0)]:
            assert abs(delta[row, j] - sign * 0.1) < 0.005, (j, delta[row])
            assert np.abs(np.delete(delta[row], j)).max() < 0.02, (j, delta[row])
    # once the action stops the target follows the joint, which settles within 0.005 of the step
    np.testing.assert_allclose(qpos[-1, :6], q_mid + 0.1 * actions[0, :6], atol=0.005)
    np.testing.assert_allclose(qpos[:, 6:], np.broadcast_to(q_mid, qpos[:, 6:].shape), atol=1e-5)


def test_arm_holds_still_under_gravity_with_zero_action(resets, rollout):
    start = first_envs(resets)
    qpos = np.asarray(rollout(start, jnp.zeros((N_STEPS, N_ENVS, 3))))
    drift = np.abs(qpos - np.asarray(start.data.qpos)[None]).max()
    assert drift < 0.01, drift


def test_random_actions_keep_the_joints_in_range(env, resets, rollout):
    actions = jax.random.uniform(jax.random.PRNGKey(1), (N_STEPS, N_ENVS, 3), minval=-1.5, maxval=1.5)
    qpos = np.asarray(rollout(first_envs(resets), actions))
    low, high = env.mj_model.jnt_range[:, 0], env.mj_model.jnt_range[:, 1]
    assert ((qpos >= low - 1e-3) & (qpos <= high + 1e-3)).all()


def test_every_start_and_goal_point_is_inside_the_frame(env, resets):
    camera = Camera(env.mj_model, "side", IMAGE_SHAPE[0])
    q = np.concatenate([np.asarray(resets.data.qpos), np.asarray(resets.info["goal"])])
    points = np.asarray(forward_kinematics(jnp.asarray(q))).reshape(-1, 3)
    pixels = np.array([camera.project(p) for p in points])
    assert pixels.min() >= 0.5 and pixels.max() <= IMAGE_SHAPE[0] - 0.5, (pixels.min(), pixels.max())


def test_camera_sees_the_arm_move_and_the_cubes():
    env = UR5Reach(render=True)
    gray = env.camera.gray_levels
    geoms = [_id(env.mj_model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("floor", "upper_arm_link", "goal_tool")]
    floor, arm, cube = gray[geoms]
    # the cubes darker than every arm link: the goal configuration is not drawn as a second arm
    links = gray[[_id(env.mj_model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ARM_GEOMS]]
    assert floor < cube < links.min()
    state = jax.jit(env.reset)(jax.random.PRNGKey(4))
    before = np.asarray(state.obs["image"])
    assert (before == cube).sum() >= 3
    assert (before == arm).sum() >= 3
    step = jax.jit(env.step)
    for _ in range(3):
        state = step(state, jnp.array([1.0, 1.0, -1.0]))
    after = np.asarray(state.obs["image"])
    assert (before != after).sum() >= 5
    # the cubes do not move with the arm
    assert (after == cube).sum() >= 3
