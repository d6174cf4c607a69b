"""A pure-JAX ray-cast camera shared by every environment (docs/tasks.md, "camera").

The paper's visual input s^v_t is a 42×42 grayscale frame of the scene (Table I), "rendered ...
converted to gray format and scaled down": the camera casts `supersample`² rays per output pixel
(a frame of `resolution · supersample` rays a side), each ray takes the gray level of the first geom
it hits (the luminance of the geom's colour) or the background, and each output pixel is the mean of
its rays (area averaging), so a body smaller than a pixel still shades it. The image is rendered
inside jit on CPU and GPU alike and is what `mujoco.mjx.ray` cast per pixel sees (the same
intersection functions and geoms; tests/envs_mjx/test_camera.py compares them), organised for speed
(the camera bounds the image agents: docs/results.md):

- rays are precomputed once at construction in the world frame, so the camera must be
  fixed: its body and every ancestor have no joints and are not mocap bodies;
- geoms fixed to the world (table, floor, static links) are cast once at construction into
  a static depth and gray image;
- each moving geom is then cast against all rays and merged into a running nearest hit,
  one geom after another, in element-wise arithmetic that XLA fuses (no per-geom matrix
  products, no [rays × geoms] arrays and arg-min as in `mjx.ray`).

Only geoms of groups 0–2 (MuJoCo's visible groups) with nonzero alpha are seen, as with
`mjx.ray(geomgroup=VISIBLE_GROUPS)`; put collision-only geoms in group 3+. Like `mjx.ray`,
it cannot draw cylinders, height fields or meshes; a visible one is refused.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import ray as mjx_ray  # mjx.ray's per-type intersection functions

VISIBLE_GROUPS = (1, 1, 1, 0, 0, 0)
LUMA = np.array([0.299, 0.587, 0.114])
# the geom types mjx.ray draws, in its order (its arg-min keeps the first of equal distances)
RAY_TYPES = tuple(int(t) for t in (mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_SPHERE,
                                   mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                                   mujoco.mjtGeom.mjGEOM_BOX))
_RAY_FN = {t: mjx_ray._RAY_FUNC[mjx.GeomType(t)] for t in RAY_TYPES}


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


def visible_geoms(mj_model: mujoco.MjModel) -> list[int]:
    """Ids of the geoms the camera sees, in `mjx.ray`'s order: by type, then by id."""
    group_ok = np.array(VISIBLE_GROUPS, bool)[np.clip(mj_model.geom_group, 0, len(VISIBLE_GROUPS) - 1)]
    mat = mj_model.geom_matid
    alpha = np.where(mat >= 0, mj_model.mat_rgba[np.maximum(mat, 0), 3], mj_model.geom_rgba[:, 3])
    seen = [int(g) for g in np.nonzero(group_ok & (alpha != 0))[0]]
    for g in seen:
        if int(mj_model.geom_type[g]) not in RAY_TYPES:
            kind = mujoco.mjtGeom(int(mj_model.geom_type[g])).name
            raise ValueError(f"geom {g} is a visible {kind}; the camera draws planes, spheres, capsules, "
                             "ellipsoids and boxes (put it in group 3 or higher to hide it)")
    return sorted(seen, key=lambda g: (RAY_TYPES.index(int(mj_model.geom_type[g])), g))


def cast(directions: jax.Array, origin: jax.Array, geom_type: int, size: jax.Array, xpos: jax.Array,
         xmat: jax.Array) -> jax.Array:
    """Distance along each unit ray (P, 3) from `origin` to one geom (inf where missed)."""
    pnt = jnp.sum(xmat * (origin - xpos)[:, None], axis=0)  # xmat.T @ (origin - xpos)
    # each ray in the geom frame, xmat.T @ direction, written element-wise so that it fuses
    vecs = directions[:, 0:1] * xmat[0] + directions[:, 1:2] * xmat[1] + directions[:, 2:3] * xmat[2]
    return jax.vmap(_RAY_FN[geom_type], in_axes=(None, None, 0))(size, pnt, vecs)


def nearest(dist: jax.Array, label: jax.Array, hit: jax.Array, value) -> tuple[jax.Array, jax.Array]:
    """Merge one geom's distances `hit` (labelled `value`) into the running nearest (dist, label)."""
    closer = hit < dist
    return jnp.where(closer, hit, dist), jnp.where(closer, jnp.asarray(value, label.dtype), label)


def area_average(gray: jax.Array, factor: int) -> jax.Array:
    """Scale a [H·f, W·f] gray frame down by `factor` f: each output pixel the rounded mean of its f×f block."""
    rows, cols = gray.shape[0] // factor, gray.shape[1] // factor
    blocks = gray.reshape(rows, factor, cols, factor).astype(jnp.float32)
    return jnp.round(blocks.mean(axis=(1, 3))).astype(jnp.uint8)


BACKGROUND = -1  # the geom id of a ray that hits nothing


class Camera:
    """A fixed pinhole camera of the model, rendering `resolution`² gray pixels.

    Args:
      mj_model: the model that holds the camera.
      camera_name: name of the `<camera>` element.
      resolution: image height and width in pixels.
      background: gray level of pixels whose ray hits nothing.
      supersample: rays per pixel along each axis; the frame is cast at `resolution · supersample`
        rays a side and area-averaged down (1: one ray per pixel, the frame `mjx.ray` sees).
    """

    def __init__(self, mj_model: mujoco.MjModel, camera_name: str, resolution: int, background: int = 0,
                 supersample: int = 1):
        cam_id = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if cam_id < 0:
            raise ValueError(f"model has no camera named {camera_name!r}")
        _assert_static(mj_model, cam_id, camera_name)
        data = mujoco.MjData(mj_model)
        mujoco.mj_forward(mj_model, data)
        if supersample < 1:
            raise ValueError(f"supersample={supersample}: rays per pixel side must be 1 or more")
        self.resolution, self.supersample = resolution, supersample
        self.rays_per_side = resolution * supersample
        self.position = np.array(data.cam_xpos[cam_id], np.float32)
        self.rotation = np.array(data.cam_xmat[cam_id], np.float64).reshape(3, 3)
        self.tan_half_fovy = float(np.tan(np.deg2rad(mj_model.cam_fovy[cam_id]) / 2.0))
        # pixel centres in the camera frame (x right, y up, looking along -z)
        centres = (np.arange(self.rays_per_side) + 0.5) / self.rays_per_side * 2.0 - 1.0
        x = centres[None, :] * self.tan_half_fovy
        y = -centres[:, None] * self.tan_half_fovy
        local = np.stack(np.broadcast_arrays(x, y, -np.ones_like(x + y)), axis=-1).reshape(-1, 3)
        local /= np.linalg.norm(local, axis=-1, keepdims=True)
        self.directions = (local @ self.rotation.T).astype(np.float32)
        # indexed by geom id; the last entry, index BACKGROUND, is the background's
        self.gray_levels = np.append(geom_gray_levels(mj_model), np.uint8(background))
        geoms = visible_geoms(mj_model)
        fixed = [g for g in geoms if mj_model.body_weldid[mj_model.geom_bodyid[g]] == 0]
        self.moving_geoms = tuple((g, int(mj_model.geom_type[g])) for g in geoms if g not in fixed)
        # the geoms fixed to the world, cast once: the background the moving geoms cover
        dist = jnp.full(len(local), jnp.inf, jnp.float32)
        ids = jnp.full(len(local), BACKGROUND, jnp.int32)
        for g in fixed:
            hit = cast(jnp.asarray(self.directions), jnp.asarray(self.position), int(mj_model.geom_type[g]),
                       jnp.asarray(mj_model.geom_size[g], jnp.float32), jnp.asarray(data.geom_xpos[g], jnp.float32),
                       jnp.asarray(data.geom_xmat[g].reshape(3, 3), jnp.float32))
            dist, ids = nearest(dist, ids, hit, g)
        self.static_dist, self.static_ids = np.asarray(dist), np.asarray(ids)

    def geom_map(self, mjx_model: mjx.Model, data: mjx.Data) -> jax.Array:
        """The id of the first geom each ray hits (`BACKGROUND` where none), int32 [rays_per_side, rays_per_side],
        for the scene of `data` (positions must be current): what `mjx.ray` returns per ray."""
        dirs, origin = jnp.asarray(self.directions), jnp.asarray(self.position)
        dist, ids = jnp.asarray(self.static_dist), jnp.asarray(self.static_ids)
        for g, geom_type in self.moving_geoms:
            hit = cast(dirs, origin, geom_type, mjx_model.geom_size[g], data.geom_xpos[g], data.geom_xmat[g])
            dist, ids = nearest(dist, ids, hit, g)
        return ids.reshape(self.rays_per_side, self.rays_per_side)

    def render(self, mjx_model: mjx.Model, data: mjx.Data) -> jax.Array:
        """Render the scene of `data` (positions must be current) as uint8 [H, W, 1]: each ray's gray level,
        area-averaged over the `supersample`² rays of a pixel."""
        gray = jnp.asarray(self.gray_levels)[self.geom_map(mjx_model, data)]
        return area_average(gray, self.supersample)[..., None]

    def project(self, point: np.ndarray) -> tuple[float, float]:
        """(row, col) pixel coordinates of a world point, continuous, for tests and tools."""
        local = self.rotation.T @ (np.asarray(point, np.float64) - self.position)
        if local[2] >= 0:
            raise ValueError(f"point {point} is behind the camera")
        u = local[0] / (-local[2]) / self.tan_half_fovy
        v = -local[1] / (-local[2]) / self.tan_half_fovy
        half = self.resolution / 2.0  # in output pixels
        return (v + 1.0) * half, (u + 1.0) * half
