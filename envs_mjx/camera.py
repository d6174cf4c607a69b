"""A pure-JAX ray-cast camera shared by every environment (TASKS.md, "camera").

The paper's visual input s^v_t is a 42×42 grayscale frame of the scene (Table I). Here
each pixel is one `mujoco.mjx.ray` from the camera centre, vmapped over pixels, so the
image is rendered inside jit on CPU and GPU alike. A pixel's value is the gray level of
the first geom its ray hits (the luminance of the geom's colour), or the background.

Rays are precomputed once at construction in the world frame, so the camera must be
fixed: its body and every ancestor have no joints and are not mocap bodies. Only geoms
of groups 0–2 (MuJoCo's visible groups) are seen; put collision-only geoms in group 3+.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

VISIBLE_GROUPS = (1, 1, 1, 0, 0, 0)
LUMA = np.array([0.299, 0.587, 0.114])


def _assert_static(mj_model: mujoco.MjModel, cam_id: int, name: str) -> None:
    body = int(mj_model.cam_bodyid[cam_id])
    while body != 0:
        if mj_model.body_jntnum[body] > 0 or mj_model.body_mocapid[body] >= 0:
            raise ValueError(f"camera {name!r} moves with body {body}; only fixed cameras are supported")
        body = int(mj_model.body_parentid[body])


def geom_gray_levels(mj_model: mujoco.MjModel) -> np.ndarray:
    """uint8 gray level of every geom: luminance of its material's or its own rgba."""
    rgba = np.array(mj_model.geom_rgba)
    has_mat = mj_model.geom_matid >= 0
    rgba[has_mat] = mj_model.mat_rgba[mj_model.geom_matid[has_mat]]
    return np.clip(np.round(255.0 * rgba[:, :3] @ LUMA), 0, 255).astype(np.uint8)


class Camera:
    """A fixed pinhole camera of the model, rendering `resolution`² gray pixels.

    Args:
      mj_model: the model that holds the camera.
      camera_name: name of the `<camera>` element.
      resolution: image height and width in pixels.
      background: gray level of pixels whose ray hits nothing.
    """

    def __init__(self, mj_model: mujoco.MjModel, camera_name: str, resolution: int, background: int = 0):
        cam_id = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if cam_id < 0:
            raise ValueError(f"model has no camera named {camera_name!r}")
        _assert_static(mj_model, cam_id, camera_name)
        data = mujoco.MjData(mj_model)
        mujoco.mj_forward(mj_model, data)
        self.resolution = resolution
        self.position = np.array(data.cam_xpos[cam_id], np.float32)
        self.rotation = np.array(data.cam_xmat[cam_id], np.float64).reshape(3, 3)
        self.tan_half_fovy = float(np.tan(np.deg2rad(mj_model.cam_fovy[cam_id]) / 2.0))
        # pixel centres in the camera frame (x right, y up, looking along -z)
        centres = (np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0
        x = centres[None, :] * self.tan_half_fovy
        y = -centres[:, None] * self.tan_half_fovy
        local = np.stack(np.broadcast_arrays(x, y, -np.ones_like(x + y)), axis=-1).reshape(-1, 3)
        local /= np.linalg.norm(local, axis=-1, keepdims=True)
        self.directions = (local @ self.rotation.T).astype(np.float32)
        self.gray_levels = np.append(geom_gray_levels(mj_model), np.uint8(background))

    def render(self, mjx_model: mjx.Model, data: mjx.Data) -> jax.Array:
        """Render the scene of `data` (positions must be current) as uint8 [H, W, 1]."""
        pnt = jnp.asarray(self.position)

        def cast(vec):
            return mjx.ray(mjx_model, data, pnt, vec, geomgroup=VISIBLE_GROUPS)[1]

        geom_ids = jax.vmap(cast)(jnp.asarray(self.directions))
        # id -1 (no hit) indexes the appended background level
        gray = jnp.asarray(self.gray_levels)[geom_ids]
        return gray.reshape(self.resolution, self.resolution, 1)

    def project(self, point: np.ndarray) -> tuple[float, float]:
        """(row, col) pixel coordinates of a world point, continuous, for tests and tools."""
        local = self.rotation.T @ (np.asarray(point, np.float64) - self.position)
        if local[2] >= 0:
            raise ValueError(f"point {point} is behind the camera")
        u = local[0] / (-local[2]) / self.tan_half_fovy
        v = -local[1] / (-local[2]) / self.tan_half_fovy
        half = self.resolution / 2.0
        return (v + 1.0) * half, (u + 1.0) * half
