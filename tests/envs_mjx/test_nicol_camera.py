"""NICOL's camera (docs/tasks.md, "camera"): the agents' frames never draw the goal marker, MuJoCo's own renderer
sees what the ray-cast camera sees from the same pose, and the camera is part of the task's fingerprint."""

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

import envs_mjx  # noqa: F401 - before the first renderer: on a headless machine it picks MuJoCo's EGL backend
from envs_mjx import nicol
from envs_mjx.base import IMAGE_SHAPE, MARKER_GROUP
from envs_mjx.camera import Camera

SUPERSAMPLE = 2  # the agents' rays: 84×84, MuJoCo's renderer is run at the same size
# cube offsets from the centre of its start region (m): the slide area's corners, the centre, and 0.2 m up
CUBE_OFFSETS = ((0.0, 0.0, 0.0), (0.2, 0.2, 0.0), (-0.2, -0.2, 0.0), (0.2, -0.2, 0.0), (-0.2, 0.2, 0.0),
                (0.0, 0.0, 0.2))


@pytest.fixture(scope="module")
def slide():
    return nicol.NicolSlide()


def test_the_policy_frames_are_the_same_whatever_the_goal(slide):
    """One state with two desired goals (the marker moved with the goal, as reset puts it): the observed goals
    differ, the frames do not; a camera that drew the marker's group would tell them apart."""
    data, goal = slide._reset_data(jax.random.PRNGKey(0))
    other = goal.at[:2].set(slide._cube_centre[:2] - jnp.sign(goal[:2] - slide._cube_centre[:2]) * 0.15)

    @jax.jit
    def observe(goal):  # the observation of the state, its goal marker at `goal` (as reset puts it)
        marked = mjx.kinematics(slide.mjx_model, data.replace(mocap_pos=data.mocap_pos.at[slide._goal_mocap].set(goal)))
        return slide._observe(marked, goal), marked

    (a, data_a), (b, data_b) = observe(goal), observe(other)
    assert np.abs(np.asarray(a["desired_goal"] - b["desired_goal"]))[:2].min() > 0.1
    np.testing.assert_array_equal(np.asarray(a["image"]), np.asarray(b["image"]))
    drawn = copy.copy(slide.mj_model)
    drawn.geom_group[drawn.geom("goal").id] = 0
    camera = Camera(drawn, slide.camera_name, IMAGE_SHAPE[0], supersample=SUPERSAMPLE)
    assert not np.array_equal(*(np.asarray(camera.render(slide.mjx_model, d)) for d in (data_a, data_b)))


def _mujoco_ids(renderer: mujoco.Renderer, data: mujoco.MjData, camera: str, option=None) -> np.ndarray:
    """The geom id MuJoCo's renderer draws at each pixel (-1: none), from its segmentation render."""
    renderer.update_scene(data, camera=camera, scene_option=option)
    seg = renderer.render()
    return np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)


def test_mujoco_renders_the_scene_where_the_ray_cast_camera_does(slide):
    """MuJoCo's OpenGL renderer at 84×84 from the `front` camera and the ray-cast camera's 84×84 rays find the same
    geom at ≥ 99.5 % of pixels, and the cube's centroid within 0.05 px of the 42×42 frame, at the slide area's
    corners, its centre and in the air; MuJoCo draws the goal marker (as videos do) only with its group on."""
    m = slide.mj_model
    data = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, data, m.key("home").id)
    camera = Camera(m, slide.camera_name, IMAGE_SHAPE[0], supersample=SUPERSAMPLE)
    cube, marker = m.geom("cube").id, m.geom("goal").id
    rays = camera.rays_per_side
    renderer = mujoco.Renderer(m, rays, rays)
    try:
        renderer.enable_segmentation_rendering()
        for offset in CUBE_OFFSETS:
            data.qpos[slide._cube_qpos:slide._cube_qpos + 3] = np.asarray(slide._cube_centre) + offset
            data.mocap_pos[slide._goal_mocap] = np.asarray(slide._cube_centre) + (0.0, 0.1, 0.0)
            mujoco.mj_forward(m, data)
            ours = np.asarray(camera.geom_map(slide.mjx_model, mjx.put_data(m, data)))
            theirs = _mujoco_ids(renderer, data, slide.camera_name)
            assert (ours == theirs).mean() >= 0.995, offset
            centroids = [np.argwhere(ids == cube).mean(axis=0) / SUPERSAMPLE for ids in (ours, theirs)]
            np.testing.assert_allclose(*centroids, atol=0.05, err_msg=str(offset))
            assert marker not in theirs
            shown = mujoco.MjvOption()
            shown.geomgroup[MARKER_GROUP] = 1
            assert marker in _mujoco_ids(renderer, data, slide.camera_name, shown)
    finally:
        renderer.close()


def test_the_camera_is_part_of_the_fingerprint(slide):
    """Another pose, field of view or marker group gives another `physics_id` (runs made with it are stale)."""
    today = slide.physics_id
    cam, marker = slide.mj_model.camera(slide.camera_name).id, slide.mj_model.geom("goal").id
    for field, index, value in (("cam_pos", (cam, 2), 0.01), ("cam_quat", (cam, 1), 0.01),
                                ("cam_fovy", cam, 1.0), ("geom_group", marker, -MARKER_GROUP)):
        array = getattr(slide.mj_model, field)
        array[index] += value
        try:
            assert slide.physics_id != today, field
        finally:
            array[index] -= value
    assert slide.physics_id == today
