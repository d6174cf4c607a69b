"""A pure-JAX ray-cast camera shared by every environment (docs/tasks.md, "camera").

The paper's visual input s^v_t is a 42×42 grayscale frame of the scene (Table I), "rendered ...
converted to gray format and scaled down": the camera casts `supersample`² rays per output pixel
(a frame of `resolution · supersample` rays a side), each ray takes the gray level of the first geom
it hits (the luminance of the geom's colour) or the background, and each output pixel is the mean of
its rays (area averaging), so a body smaller than a pixel still shades it. The image is rendered
inside jit on CPU and GPU alike and is what `mujoco.mjx.ray` cast per pixel sees (the same
intersection functions and geoms; tests/envs_mjx/test_camera.py compares them), organised for speed
(the camera bounds the image agents: docs/performance.md):

- rays are precomputed once at construction in the world frame, so the camera must be
  fixed: its body and every ancestor have no joints and are not mocap bodies;
- geoms fixed to the world (table, floor, static links) are cast once at construction into
  a static depth and gray image;
- each moving geom is then cast and merged into a running nearest hit, one geom after another,
  in element-wise arithmetic that XLA fuses (no per-geom matrix products, no [rays × geoms]
  arrays and arg-min as in `mjx.ray`);
- culling: a moving geom is cast only against a square window of rays (`Camera.windows`, a
  static size per geom, placed where the screen-space bounding box of its bounding sphere
  falls), as no ray outside that box can hit it. Window sizes are static (jit) and chosen at
  construction from sampled poses; a geom whose box does not fit its window (too close to the
  camera) is detected exactly, and a batch of envs in which any does is cast in full instead
  (`jax.custom_batching.custom_vmap` decides once per batch, so vmapped envs do not pay for
  both). The frame is the same, bit for bit, as casting every ray (tests/envs_mjx/test_env_contract.py);
- ties: XLA contracts a multiply and an add into one fused multiply-add (one rounding) wherever both land
  in one fused kernel, and which pairs do depends on the program (window or frame, one scene or a batch),
  so one ray's distance to a geom may differ by a few 1e-6 between programs. Two geoms hit at the same
  distance (overlapping capsule caps at a joint) would then keep one geom in one program and the other in
  another; so a geom takes a ray from the running nearest only if nearer by more than the relative `TIE`
  (1e-4, 0.1 mm at 1 m), and of two tied geoms the one merged first keeps the ray in every program. Only
  a gap within rounding of `TIE` itself, or a ray grazing two coincident geoms, could still round apart
  (none over the tests' scenes). Where `mjx.ray` keeps the strictly nearer, the camera keeps the first of
  geoms within `TIE`.

Only geoms of groups 0–2 (MuJoCo's visible groups) with nonzero alpha are seen, as with
`mjx.ray(geomgroup=VISIBLE_GROUPS)`; put collision-only geoms in group 3+. Like `mjx.ray`,
it cannot draw cylinders, height fields or meshes; a visible one is refused.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.custom_batching import custom_vmap
from mujoco import mjx
from mujoco.mjx._src import ray as mjx_ray  # mjx.ray's per-type intersection functions

VISIBLE_GROUPS = (1, 1, 1, 0, 0, 0)
LUMA = np.array([0.299, 0.587, 0.114])
# relative difference of distance below which two geoms tie on a ray (`nearest`): far above the rounding that
# differently compiled programs give the same hit (a few 1e-6), far below a ray's spacing
TIE = 1e-4
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


def subtree_geoms(mj_model: mujoco.MjModel, body: str) -> tuple[int, ...]:
    """Ids of the geoms of body `body` and of every body below it."""
    root = mj_model.body(body).id
    inside = np.zeros(mj_model.nbody, bool)
    for b in range(mj_model.nbody):  # parents precede children in MuJoCo's body order
        inside[b] = b == root or (b > 0 and inside[mj_model.body_parentid[b]])
    return tuple(int(g) for g in np.nonzero(inside[mj_model.geom_bodyid])[0])


def cast(directions: jax.Array, origin: jax.Array, geom_type: int, size: jax.Array, xpos: jax.Array,
         xmat: jax.Array) -> jax.Array:
    """Distance along each unit ray (P, 3) from `origin` to one geom (inf where missed)."""
    pnt = jnp.sum(xmat * (origin - xpos)[:, None], axis=0)  # xmat.T @ (origin - xpos)
    # each ray in the geom frame, xmat.T @ direction, written element-wise so that it fuses
    vecs = directions[:, 0:1] * xmat[0] + directions[:, 1:2] * xmat[1] + directions[:, 2:3] * xmat[2]
    return jax.vmap(_RAY_FN[geom_type], in_axes=(None, None, 0))(size, pnt, vecs)


def nearest(dist: jax.Array, label: jax.Array, hit: jax.Array, value) -> tuple[jax.Array, jax.Array]:
    """Merge one geom's distances `hit` (labelled `value`) into the running nearest (dist, label): the geom takes
    a ray only where it is nearer by more than the relative `TIE`, so of two geoms hit at the same distance up to
    rounding the one merged first keeps the ray, however the compiled program rounds (module docstring, "ties")."""
    closer = hit * (1.0 + TIE) < dist
    return jnp.where(closer, hit, dist), jnp.where(closer, jnp.asarray(value, label.dtype), label)


def area_average(gray: jax.Array, factor: int) -> jax.Array:
    """Scale a [H·f, W·f] gray frame down by `factor` f: each output pixel the rounded mean of its f×f block."""
    rows, cols = gray.shape[0] // factor, gray.shape[1] // factor
    blocks = gray.reshape(rows, factor, cols, factor).astype(jnp.float32)
    return jnp.round(blocks.mean(axis=(1, 3))).astype(jnp.uint8)


BACKGROUND = -1  # the geom id of a ray that hits nothing
WINDOW_MARGIN = 1  # rays added on each side of a bounding box, against rounding at a geom's silhouette
POSE_SAMPLES = 256  # random joint poses that size the windows at construction
WINDOW_SLACK = 1.25  # window side over the largest box seen in those poses


def sphere_ray_box(centre: jax.Array, radius: float, tan_half_fovy: float, rays_per_side: int
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The rays that can hit a sphere of `radius` at `centre` (camera frame: x right, y up, looking along -z).

    Returns (lo, hi, seen): int32 [2] first and last (row, col) ray index of the sphere's screen-space bounding box
    (unclipped; `WINDOW_MARGIN` wider on each side) and whether that box is exact, i.e. the sphere lies wholly
    in front of the camera; a sphere wholly behind it is hit by no ray (lo > hi), one that straddles the camera's
    plane has no finite box (seen False). The box's edges are the planes through the camera and a frame axis that
    touch the sphere: angles φ ± asin(r/ρ) in each of the xz and yz planes."""
    x, y, depth = centre[0], centre[1], -centre[2]
    guard = radius * (1.0 + 1e-4) + 1e-6
    scale = rays_per_side / 2.0

    def tangents(a):  # tangents a/depth of the two planes through the camera that touch the sphere
        phi = jnp.arctan2(a, depth)
        beta = jnp.arcsin(jnp.minimum(radius / jnp.maximum(jnp.hypot(a, depth), guard), 1.0))
        return jnp.tan(jnp.clip(phi - beta, -1.5, 1.5)), jnp.tan(jnp.clip(phi + beta, -1.5, 1.5))

    def index(c):  # ray index of a coordinate c in [-1, 1] across the frame, clipped to just outside it
        return jnp.clip((c + 1.0) * scale - 0.5, -1.0 - WINDOW_MARGIN, rays_per_side + WINDOW_MARGIN)

    (u_lo, u_hi), (v_lo, v_hi) = tangents(x), tangents(y)
    t = tan_half_fovy
    lo = jnp.ceil(jnp.stack([index(-v_hi / t), index(u_lo / t)])).astype(jnp.int32) - WINDOW_MARGIN
    hi = jnp.floor(jnp.stack([index(-v_lo / t), index(u_hi / t)])).astype(jnp.int32) + WINDOW_MARGIN
    behind = depth < -guard
    return jnp.where(behind, rays_per_side, lo), jnp.where(behind, -1, hi), (depth > guard) | behind


def window_start(lo: jax.Array, hi: jax.Array, size: int, rays_per_side: int) -> tuple[jax.Array, jax.Array]:
    """Where a `size`² window of the ray grid covering the box [lo, hi] (`sphere_ray_box`) starts, and whether it
    covers the box's part inside the frame."""
    first, last = jnp.clip(lo, 0, rays_per_side - 1), jnp.clip(hi, 0, rays_per_side - 1)
    start = jnp.clip(first, 0, rays_per_side - size)
    return start, jnp.all((last - start < size) | (hi < lo))


def _sampled_poses(mj_model: mujoco.MjModel, samples: int, seed: int = 0) -> list[np.ndarray]:
    """qpos0, the keyframes and `samples` random poses: each hinge and slide joint uniform over its range (hinges
    without one over a turn), ball and free joints as in qpos0."""
    rng = np.random.default_rng(seed)
    poses = [mj_model.qpos0.copy(), *(mj_model.key_qpos[k].copy() for k in range(mj_model.nkey))]
    movable = [j for j in range(mj_model.njnt) if mj_model.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE,
                                                                           mujoco.mjtJoint.mjJNT_SLIDE)]
    for _ in range(samples):
        qpos = mj_model.qpos0.copy()
        for j in movable:
            lo, hi = mj_model.jnt_range[j] if mj_model.jnt_limited[j] else (-np.pi, np.pi)
            if mj_model.jnt_limited[j] or mj_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                qpos[mj_model.jnt_qposadr[j]] = rng.uniform(lo, hi)
        poses.append(qpos)
    return poses


class Camera:
    """A fixed pinhole camera of the model, rendering `resolution`² gray pixels.

    Args:
      mj_model: the model that holds the camera.
      camera_name: name of the `<camera>` element.
      resolution: image height and width in pixels.
      background: gray level of pixels whose ray hits nothing.
      supersample: rays per pixel along each axis; the frame is cast at `resolution · supersample`
        rays a side and area-averaged down (1: one ray per pixel, the frame `mjx.ray` sees).

    `windows` holds, per moving geom, the side of the square window of rays it is cast against (None: all rays;
    planes, and geoms whose sampled boxes nearly fill the frame). Any size gives the same frame: a smaller one
    only makes the all-rays fallback more frequent.
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
        self.rbound = np.array([mj_model.geom_rbound[g] for g, _ in self.moving_geoms], np.float32)
        self.windows = self._window_sizes(mj_model)
        self._culled_map = _per_batch(self._windowed_map, self._full_map)

    def _camera_frame(self, xpos: jax.Array) -> jax.Array:
        """World points [..., 3] in the camera frame."""
        return (xpos - self.position) @ jnp.asarray(self.rotation, jnp.float32)

    def _window_sizes(self, mj_model: mujoco.MjModel) -> tuple[int | None, ...]:
        """Each moving geom's window side: `WINDOW_SLACK` times the largest in-frame box of its bounding sphere over
        `_sampled_poses`, or None where that nears the frame (or the geom is a plane, whose rbound is 0)."""
        data, centres = mujoco.MjData(mj_model), []
        ids = [g for g, _ in self.moving_geoms]
        for qpos in _sampled_poses(mj_model, POSE_SAMPLES):
            data.qpos[:] = qpos
            mujoco.mj_kinematics(mj_model, data)
            centres.append(np.asarray(self._camera_frame(data.geom_xpos[ids].astype(np.float32))))
        n = self.rays_per_side
        lo, hi, seen = (np.asarray(a) for a in sphere_ray_box(np.moveaxis(np.array(centres), -1, 0), self.rbound,
                                                               self.tan_half_fovy, n))
        extent = np.clip(hi, 0, n - 1) - np.clip(lo, 0, n - 1) + 1  # [2, poses, geoms]
        need = np.where(seen & (hi >= lo), extent, 0).max(axis=(0, 1))
        sides = np.ceil(WINDOW_SLACK * need).astype(int) + 2
        planes = np.array([t == mujoco.mjtGeom.mjGEOM_PLANE for _, t in self.moving_geoms], bool)
        return tuple(None if plane or side >= n else int(side) for side, plane in zip(sides, planes))

    def _full_map(self, size: jax.Array, xpos: jax.Array, xmat: jax.Array) -> jax.Array:
        """The moving geoms (size, xpos, xmat stacked in `moving_geoms` order) cast against every ray and merged
        into the static image: int32 [rays_per_side²] of first-hit geom ids."""
        dirs, origin = jnp.asarray(self.directions), jnp.asarray(self.position)
        dist, ids = jnp.asarray(self.static_dist), jnp.asarray(self.static_ids)
        for k, (g, geom_type) in enumerate(self.moving_geoms):
            dist, ids = nearest(dist, ids, cast(dirs, origin, geom_type, size[k], xpos[k], xmat[k]), g)
        return ids

    def _windowed_map(self, size: jax.Array, xpos: jax.Array, xmat: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`_full_map` with each geom cast against its window of rays only; also whether every geom's bounding box
        fitted its window (else the map may miss part of a geom)."""
        n, origin = self.rays_per_side, jnp.asarray(self.position)
        dirs = jnp.asarray(self.directions).reshape(n, n, 3)
        dist, ids = jnp.asarray(self.static_dist).reshape(n, n), jnp.asarray(self.static_ids).reshape(n, n)
        centres, fits = self._camera_frame(xpos), []
        for k, ((g, geom_type), side) in enumerate(zip(self.moving_geoms, self.windows)):
            if side is None:
                hit = cast(dirs.reshape(-1, 3), origin, geom_type, size[k], xpos[k], xmat[k]).reshape(n, n)
                dist, ids = nearest(dist, ids, hit, g)
                continue
            lo, hi, seen = sphere_ray_box(centres[k], self.rbound[k], self.tan_half_fovy, n)
            start, covered = window_start(lo, hi, side, n)
            fits.append(seen & covered)
            rays = jax.lax.dynamic_slice(dirs, (start[0], start[1], 0), (side, side, 3)).reshape(-1, 3)
            hit = cast(rays, origin, geom_type, size[k], xpos[k], xmat[k]).reshape(side, side)
            near = nearest(jax.lax.dynamic_slice(dist, start, (side, side)),
                           jax.lax.dynamic_slice(ids, start, (side, side)), hit, g)
            dist, ids = (jax.lax.dynamic_update_slice(a, b, start) for a, b in zip((dist, ids), near))
        return ids.reshape(-1), jnp.all(jnp.array(fits, bool))

    def geom_map(self, mjx_model: mjx.Model, data: mjx.Data, cull: bool = True) -> jax.Array:
        """The id of the first geom each ray hits (`BACKGROUND` where none), int32 [rays_per_side, rays_per_side],
        for the scene of `data` (positions must be current): what `mjx.ray` returns per ray. `cull` False casts
        every geom against every ray (the same map, slower: the reference the culling is tested against)."""
        args = self._moving(mjx_model, data)
        flat = self._culled_map(*args) if cull else self._full_map(*args)
        return flat.reshape(self.rays_per_side, self.rays_per_side)

    def fits_windows(self, mjx_model: mjx.Model, data: mjx.Data) -> jax.Array:
        """Whether every moving geom's bounding box fits its window in the scene of `data` (if not, a batch holding
        this scene is cast against every ray)."""
        return self._windowed_map(*self._moving(mjx_model, data))[1]

    def _moving(self, mjx_model: mjx.Model, data: mjx.Data) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Size, position and orientation of the moving geoms, in `moving_geoms` order."""
        ids = np.array([g for g, _ in self.moving_geoms], np.int32)
        return mjx_model.geom_size[ids], data.geom_xpos[ids], data.geom_xmat[ids]

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


def _per_batch(windowed: Callable, full: Callable) -> Callable:
    """A geom map of one scene from `windowed` (→ map, fits) that falls back to `full` (→ map) where a geom did not
    fit its window, decided once per batch under vmap: `lax.cond` on a vmapped predicate would run both branches
    for every scene, so the vmap rule maps `windowed` over the whole batch (nested vmaps flattened into one axis)
    and casts the batch in full only if any scene of it needs that. Both are jitted per scene, so that the batches of
    every width (a run's training envs and its evaluation envs) batch one trace of each instead of tracing the
    camera's Python again at each width."""
    windowed, full = jax.jit(windowed), jax.jit(full)

    def batched(axis_size, in_batched, args):  # every argument with the vmapped axis leading
        return [a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for a, b in zip(args, in_batched)]

    @custom_vmap
    def batch_map(*args):  # each argument with a leading axis of scenes
        maps, fits = jax.vmap(windowed)(*args)
        return jax.lax.cond(jnp.all(fits), lambda: maps, lambda: jax.vmap(full)(*args))

    @batch_map.def_vmap
    def _(axis_size, in_batched, *args):
        maps = batch_map(*(a.reshape(-1, *a.shape[2:]) for a in batched(axis_size, in_batched, args)))
        return maps.reshape(axis_size, -1, *maps.shape[1:]), True

    @custom_vmap
    def one_map(*args):
        return batch_map(*(a[None] for a in args))[0]

    @one_map.def_vmap
    def _(axis_size, in_batched, *args):
        return batch_map(*batched(axis_size, in_batched, args)), True

    return one_map
