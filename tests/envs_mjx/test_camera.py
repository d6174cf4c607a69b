"""The shared ray-cast camera (envs_mjx/camera.py): planar_reach poses, and equality with mjx.ray."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import envs_mjx
from envs_mjx.camera import VISIBLE_GROUPS, Camera, geom_gray_levels
from envs_mjx.planar_reach import TARGET_HEIGHT, forward_kinematics


@pytest.fixture(scope="module")
def scene():
    env = envs_mjx.make("planar_reach")

    @jax.jit
    def render_at(q, goal_xy):
        data = mjx.make_data(env.mjx_model)
        data = data.replace(qpos=q, mocap_pos=data.mocap_pos.at[0].set(jnp.append(goal_xy, TARGET_HEIGHT)))
        data = mjx.kinematics(env.mjx_model, data)
        return env.camera.render(env.mjx_model, data)[..., 0]

    return env, render_at


def _geom_level(env, name):
    return geom_gray_levels(env.mj_model)[mujoco.mj_name2id(env.mj_model, mujoco.mjtObj.mjOBJ_GEOM, name)]


@pytest.mark.parametrize(
    "q, goal_q", [((0.3, 0.8), (-2.0, 1.0)), ((-1.2, -1.5), (2.5, -0.4)), ((2.9, 0.2), (0.0, 2.0))]
)
def test_end_effector_and_target_appear_where_forward_kinematics_puts_them(scene, q, goal_q):
    env, render_at = scene
    q, goal = jnp.array(q), forward_kinematics(jnp.array(goal_q))
    image = np.asarray(render_at(q, goal))
    ee = np.append(np.asarray(forward_kinematics(q)), 0.0)
    row, col = (int(v) for v in env.camera.project(ee))
    assert image[row, col] == _geom_level(env, "ee")
    row, col = (int(v) for v in env.camera.project(np.append(np.asarray(goal), TARGET_HEIGHT)))
    assert image[row, col] == _geom_level(env, "target")


def test_image_changes_when_the_arm_moves_and_levels_are_distinct(scene):
    env, render_at = scene
    goal = jnp.array([0.0, -0.2])
    a, b = (
        np.asarray(
            render_at(
                jnp.array(
                    [0.0, 0.5],
                ),
                goal,
            )
        ),
        np.asarray(render_at(jnp.array([1.5, 0.5]), goal)),
    )
    assert (a != b).sum() > 10
    levels = {_geom_level(env, n) for n in ("floor", "link1", "ee", "target")}
    assert len(levels) == 4


def test_only_fixed_cameras_are_accepted():
    model = mujoco.MjModel.from_xml_string(
        """<mujoco><asset><material name="m"/></asset><worldbody><body><joint type="hinge"/>
        <geom size="0.1" material="m"/><camera name="c"/></body></worldbody></mujoco>"""
    )
    with pytest.raises(ValueError, match="only fixed cameras"):
        Camera(model, "c", 8)
    with pytest.raises(ValueError, match="no camera named"):
        Camera(model, "nope", 8)


@pytest.mark.parametrize("name", ["planar_reach", "nicol_lift"])
def test_render_equals_mjx_ray_cast_per_pixel(name):
    """The fused renderer sees what `mjx.ray` sees, pixel by pixel, over random poses (on the
    CPU exactly; a GPU rounds some ray-grazing silhouette pixels differently, docs/results.md)."""
    env = envs_mjx.make(name)
    cam, model = env.camera, env.mjx_model
    hinges = env.mj_model.jnt_qposadr[env.mj_model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE]
    home = env.mj_model.key("home").qpos if env.mj_model.nkey else env.mj_model.qpos0

    @jax.jit
    @jax.vmap
    def both(key):
        offset = jax.random.uniform(key, (len(hinges),), minval=-0.5, maxval=0.5)
        data = mjx.make_data(model).replace(qpos=jnp.asarray(home, jnp.float32).at[hinges].add(offset))
        data = mjx.kinematics(model, data)
        ids = jax.vmap(lambda v: mjx.ray(model, data, jnp.asarray(cam.position), v, geomgroup=VISIBLE_GROUPS)[1])(
            jnp.asarray(cam.directions)
        )
        return cam.render(model, data)[..., 0], jnp.asarray(cam.gray_levels)[ids].reshape(cam.resolution, -1)

    image, reference = (np.asarray(x) for x in both(jax.random.split(jax.random.PRNGKey(0), 8)))
    assert len(np.unique(image)) >= 4  # several geoms in view, not a blank frame
    np.testing.assert_array_equal(image, reference)


def test_a_visible_cylinder_is_refused_with_a_clear_error():
    model = mujoco.MjModel.from_xml_string(
        """<mujoco><asset><material name="m"/></asset><worldbody><camera name="c"/>
        <geom type="cylinder" size="0.1 0.1" material="m"/></worldbody></mujoco>"""
    )
    with pytest.raises(ValueError, match="geom 0 is a visible mjGEOM_CYLINDER"):
        Camera(model, "c", 8)
