"""The shared ray-cast camera (envs_mjx/camera.py): planar_reach poses, equality with mjx.ray ray by ray, and
the area averaging of its supersampled frame."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import envs_mjx
from envs_mjx.camera import TIE, VISIBLE_GROUPS, Camera, area_average, cast, geom_gray_levels
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
    """The fused renderer sees what `mjx.ray` sees, ray by ray, over random poses (on the CPU up to ties: two geoms
    hit within the relative `camera.TIE`, where the camera keeps the one it merges first and `mjx.ray` the nearer;
    a GPU rounds some ray-grazing silhouette rays differently, docs/results.md)."""
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
        dist, ids = jax.vmap(lambda v: mjx.ray(model, data, jnp.asarray(cam.position), v, geomgroup=VISIBLE_GROUPS))(
            jnp.asarray(cam.directions)
        )
        n = cam.rays_per_side
        return (cam.geom_map(model, data), ids.reshape(n, n), dist.reshape(n, n), cam.render(model, data)[..., 0],
                data.geom_xpos, data.geom_xmat)

    ids, reference, ref_dist, image, xpos, xmat = (
        np.asarray(x) for x in both(jax.random.split(jax.random.PRNGKey(0), 8))
    )
    assert len(np.unique(ids)) >= 4  # several geoms in view, not a blank frame
    # the same first hit ray by ray, except at ties (link capsules that overlap at a joint or cross): there the
    # camera's geom is hit within `TIE` of mjx.ray's nearer one (up to the rounding of a lone ray's cast)
    ties = np.argwhere(ids != reference)
    assert len(ties) <= 1e-3 * ids.size, len(ties)
    for pose, row, col in ties:
        g = ids[pose, row, col]
        assert g >= 0 and reference[pose, row, col] >= 0, (g, reference[pose, row, col])
        ray = cam.directions[row * cam.rays_per_side + col][None]
        d = float(cast(ray, cam.position, int(env.mj_model.geom_type[g]), env.mj_model.geom_size[g], xpos[pose, g],
                       xmat[pose, g])[0])
        assert d <= ref_dist[pose, row, col] * (1 + TIE + 1e-5), (g, d, ref_dist[pose, row, col])
    # each pixel is the rounded mean gray level of its supersample² rays
    k = cam.supersample
    rays = cam.gray_levels[ids].reshape(8, cam.resolution, k, cam.resolution, k).astype(float)
    np.testing.assert_array_equal(image, np.round(rays.mean(axis=(2, 4))).astype(np.uint8))


def test_area_averaging_shades_a_pixel_by_the_share_of_its_rays_on_a_body():
    gray = jnp.array([[0, 0, 255, 255], [0, 255, 255, 255], [10, 20, 0, 0], [30, 40, 0, 0]], jnp.uint8)
    np.testing.assert_array_equal(np.asarray(area_average(gray, 2)), [[64, 255], [25, 0]])


def test_a_visible_cylinder_is_refused_with_a_clear_error():
    model = mujoco.MjModel.from_xml_string(
        """<mujoco><asset><material name="m"/></asset><worldbody><camera name="c"/>
        <geom type="cylinder" size="0.1 0.1" material="m"/></worldbody></mujoco>"""
    )
    with pytest.raises(ValueError, match="geom 0 is a visible mjGEOM_CYLINDER"):
        Camera(model, "c", 8)


def test_a_geom_too_large_for_its_window_falls_back_to_every_ray():
    """Windows too small for the scene (one ray) are detected and the whole batch is cast in full: the same frames,
    vmapped and not."""
    env = envs_mjx.make("planar_reach")
    cam, model = env.camera, env.mjx_model
    small = Camera(env.mj_model, env.camera_name, cam.resolution, supersample=cam.supersample)
    small.windows = tuple(None if side is None else 1 for side in cam.windows)
    data = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 4)).data
    fits = jax.vmap(lambda d: small.fits_windows(model, d))(data)
    assert not np.asarray(fits).any()
    reference = jax.jit(jax.vmap(lambda d: cam.geom_map(model, d, cull=False)))(data)
    np.testing.assert_array_equal(jax.jit(jax.vmap(lambda d: small.geom_map(model, d)))(data), reference)
    one = jax.tree.map(lambda x: x[0], data)
    np.testing.assert_array_equal(jax.jit(lambda d: small.geom_map(model, d))(one), reference[0])
