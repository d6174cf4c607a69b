"""Can a fixed camera resolve ur5_reach's goal? A search over camera poses, and the bound that caps it.

The resolvability contract (docs/tasks.md, "camera") asks that turning any joint by ε = 0.1 rad moves the wrist
stub's image centroid by ≥ 1.5 px of the 42×42 frame in the lowest decile over the goal region, while every
reachable elbow, wrist and tool point stays inside the frame (docs/tasks.md, ur5_reach). This search projects,
with a pinhole camera, the points of `--configs` configurations of the goal distribution (their positions from
`mujoco.mj_kinematics` on the CPU model):

- for every camera position of a grid around the robot (bearing from the side (-y, 0°) to the pan axis (+x, 90°),
  horizontal distance from the base axis, height) and roll of the frame about its axis (`ROLLS_DEG`), the optical
  axis is centred on the projected elbow, wrist and tool points (`centred_rotation`) and the field of view is the
  narrowest that holds them all with `MARGIN_PX` to spare (`fitted_focal`);
- score: the stub centre's projected shift per ε along each joint, its 10th percentile over the configurations
  (`pose`), and the minimum over the three joints (`search` ranks by it).

The bound (`bound`): the frame must hold the pan sweep of the full reach (a disk of 0.975 m radius, whose diameter
every view sees whole), so at the workspace's distance a metre spans at most 2 · (21 - `MARGIN_PX`) / 1.95 = 20.5 px
(29.0 along the frame's diagonal); the elbow turns the stub's centre by ε · (forearm + stub / 2) = 0.048 m whatever
the configuration, and the pan by ε times its distance from the pan axis, under 0.08 m in a tenth of the goal
region. So in the lowest decile the elbow's image moves at most 0.99 px per ε (1.39 on the diagonal) and the pan's
0.16 (0.23). Perspective helps the stub only where it is nearer the camera than the framed points that set the field
of view.

    python -m experiments.probes.camera_search [--configs 4096] [--seed 0] [--top 3] [--states 256] [--epsilon RAD]
        [--out FILE]

Prints the poses (today's camera, the `--top` best of the grid, the best for each joint) with their projected p10
and the ray-cast p10 at `--states` goal states (`image_shift.shifts`, the resolvability probe's measure, with the
camera put at the pose in the CPU model), and the bound; `--out` writes them with the command, date and commit to a
new JSON file (one that exists is refused, not overwritten). `--epsilon` turns each joint by another angle than the
task's ε: what a larger ε would show.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys

import jax
import mujoco
import numpy as np

import envs_mjx
from bidal_jax.config import ConfigError
from envs_mjx.base import IMAGE_SHAPE, Env
from envs_mjx.ur5_reach import POINT_NAMES
from experiments import cli, report
from experiments.probes import image_shift

PROG = "python -m experiments.probes.camera_search"
ENV = "ur5_reach"
MARGIN_PX = 1.0  # the frame holds every framed point this many pixels inside its edge
HALF = IMAGE_SHAPE[0] / 2  # 21 px: the frame's half width
BEARINGS_DEG = np.arange(0.0, 91.0, 15.0)  # from the side (-y) to the pan axis (+x)
DISTANCES = np.arange(0.0, 4.01, 0.25)  # m, horizontal, from the base axis
HEIGHTS = np.arange(0.5, 4.51, 0.25)  # m
ROLLS_DEG = (0.0, 22.5, 45.0)  # a square frame holds a wide view better turned about its axis
CENTRING_STEPS = 12
MAX_OFF_AXIS_DEG = 80.0  # a pose that needs a wider half field of view is left out


def configurations(env: Env, n: int, seed: int) -> np.ndarray:
    """`n` configurations [n, nq] of the goal distribution (`image_shift.sample`)."""
    return np.asarray(image_shift.sample(env, n, seed), np.float64)


def points(env: Env, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the framed points: elbow, wrist and tool sites [N, 3, 3]; the object's centre at `qpos` and turned by ε about
    each joint [N, 1 + joints, 3]), from `mujoco.mj_kinematics` on the CPU model."""
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    tgt = image_shift.target(env)
    sites = [model.site(name).id for name in POINT_NAMES]
    turned = jax.vmap(lambda q, i: image_shift.moved(env, q, i, tgt.epsilon), in_axes=(0, None))
    variants = [qpos] + [np.asarray(turned(qpos, i), np.float64) for i in range(len(tgt.axes))]
    framed = np.empty((len(qpos), len(sites), 3))
    centre = np.empty((len(qpos), len(variants), 3))
    for v, batch in enumerate(variants):
        for n, q in enumerate(batch):
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            centre[n, v] = data.geom_xpos[list(tgt.geoms)].mean(axis=0)
            if v == 0:
                framed[n] = data.site_xpos[sites]
    return framed, centre


def look_rotation(forward: np.ndarray, roll_deg: float = 0.0) -> np.ndarray:
    """Camera axes (rows: right, up, back; MuJoCo's camera looks along -z) looking along `forward`, the right axis
    horizontal turned by `roll_deg` about the optical axis."""
    back = -forward / np.linalg.norm(forward)
    right = np.cross(np.array([0.0, 0.0, 1.0]), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    return np.stack([c * right + s * up, c * up - s * right, back])


def tangents(rotation: np.ndarray, position: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Tangent-plane coordinates (x / depth, y / depth) [..., 2] of world points `pts` [..., 3]; inf behind the
    camera."""
    local = (pts - position) @ rotation.T
    depth = -local[..., 2:]
    return np.where(depth > 1e-6, local[..., :2] / np.maximum(depth, 1e-6), np.inf)


def centred_rotation(position: np.ndarray, framed: np.ndarray, roll_deg: float = 0.0) -> np.ndarray | None:
    """The camera axes at `position`, rolled by `roll_deg`, whose optical axis points at the centre of the framed
    points' tangent-plane bounding box (iterated, as turning the axis moves the box), or None where a point lies
    behind or beside the camera (more than `MAX_OFF_AXIS_DEG` off its axis)."""
    rotation = look_rotation(framed.mean(axis=0) - position, roll_deg)
    for step in range(CENTRING_STEPS + 1):
        t = tangents(rotation, position, framed)
        if not np.isfinite(t).all() or np.abs(t).max() > np.tan(np.radians(MAX_OFF_AXIS_DEG)):
            return None
        if step == CENTRING_STEPS:
            return rotation
        mid = (t.min(axis=0) + t.max(axis=0)) / 2
        rotation = look_rotation(mid[0] * rotation[0] + mid[1] * rotation[1] - rotation[2], roll_deg)


def fitted_focal(rotation: np.ndarray, position: np.ndarray, framed: np.ndarray) -> float:
    """The focal length (px) of the narrowest square frame that holds every framed point `MARGIN_PX` inside its
    edge."""
    return (HALF - MARGIN_PX) / np.abs(tangents(rotation, position, framed)).max()


def projected_shifts(rotation: np.ndarray, position: np.ndarray, focal: float, centre: np.ndarray) -> np.ndarray:
    """Pixels the object's projected centre moves per ε [N, joints] (`centre` [N, 1 + joints, 3] from `points`)."""
    t = tangents(rotation, position, centre) * focal
    return np.linalg.norm(t[:, 1:] - t[:, :1], axis=-1)


def camera_position(bearing_deg: float, distance: float, height: float) -> np.ndarray:
    """World position `distance` m from the base axis, `bearing_deg` from the -y side toward +x, `height` m up."""
    b = np.radians(bearing_deg)
    return np.array([distance * np.sin(b), -distance * np.cos(b), height])


def pose(position: np.ndarray, rotation: np.ndarray, focal: float, centre: np.ndarray) -> dict:
    """A candidate as data: position, MuJoCo `xyaxes`, angle below horizontal, fovy, projected p10 per joint."""
    p10 = np.percentile(projected_shifts(rotation, position, focal, centre), 10, axis=0)
    return {"pos": [round(float(v), 4) for v in position],
            "xyaxes": [round(float(v), 4) for v in rotation[:2].ravel()],
            "down_deg": round(float(np.degrees(np.arcsin(rotation[2, 2]))), 1),
            "fovy_deg": round(float(np.degrees(2 * np.arctan(HALF / focal))), 2),
            "projected_p10": [round(float(v), 3) for v in p10]}


def search(framed: np.ndarray, centre: np.ndarray) -> list[dict]:
    """Every grid pose (position × roll) that frames the points, best (largest minimum over the joints of the
    projected p10) first."""
    flat = framed.reshape(-1, 3)
    rows = []
    for bearing in BEARINGS_DEG:
        for distance in DISTANCES:
            if distance == 0 and bearing > 0:
                continue  # one column of poses above the base axis
            for height in HEIGHTS:
                position = camera_position(bearing, distance, height)
                for roll in ROLLS_DEG:
                    rotation = centred_rotation(position, flat, roll)
                    if rotation is not None:
                        row = pose(position, rotation, fitted_focal(rotation, position, flat), centre)
                        rows.append({"bearing_deg": float(bearing), "roll_deg": float(roll), **row})
    return sorted(rows, key=lambda r: -min(r["projected_p10"]))


def best_per_joint(rows: list[dict]) -> list[dict]:
    """The grid pose with the largest projected p10 of each joint."""
    return [max(rows, key=lambda r: r["projected_p10"][j]) for j in range(len(rows[0]["projected_p10"]))]


def bound(framed: np.ndarray, centre: np.ndarray) -> dict:
    """The orthographic bound: the frame holds the pan sweep of the full reach, a disk whose diameter every view
    sees whole, so a metre at the workspace's distance spans at most 2 · (21 - `MARGIN_PX`) px / (2 · reach), or √2
    times that with the diameter along the frame's diagonal (a roll of 45°); each joint's ε moves the object's
    centre the 10th percentile of its displacement in 3-D (pan: ε times the centre's distance from the pan axis;
    elbow: ε · 0.48 m always), which caps its image's shift there. Perspective beats it only for an object nearer
    the camera than the framed points that set the field of view."""
    reach = float(np.hypot(framed[..., 0], framed[..., 1]).max())
    px_per_m = 2 * (HALF - MARGIN_PX) / (2 * reach)
    moved_p10 = np.percentile(np.linalg.norm(centre[:, 1:] - centre[:, :1], axis=-1), 10, axis=0)
    radius = np.hypot(centre[:, 0, 0], centre[:, 0, 1])
    return {"reach_m": round(reach, 3), "px_per_m": round(px_per_m, 2),
            "object_axis_distance_p10_m": round(float(np.percentile(radius, 10)), 3),
            "moved_p10_m": [round(float(v), 4) for v in moved_p10],
            "px_p10": [round(float(v), 3) for v in px_per_m * moved_p10],
            "px_p10_diagonal": [round(float(v), 3) for v in np.sqrt(2) * px_per_m * moved_p10],
            "px_per_m_needed": [round(float(v), 1) for v in image_shift.CONTRACT_PX / moved_p10]}


def set_camera(env: Env, row: dict) -> None:
    """Put `env`'s camera at the pose `row` (`pose`), in its CPU model, which the probe's camera is built from."""
    m = env.mj_model
    cam = m.camera(env.camera_name).id
    x, y = np.asarray(row["xyaxes"][:3]), np.asarray(row["xyaxes"][3:])
    mat = np.stack([x, y, np.cross(x, y)], axis=1)  # columns: the camera's axes in the world
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, mat.ravel())
    m.cam_pos[cam], m.cam_quat[cam], m.cam_fovy[cam] = row["pos"], quat, row["fovy_deg"]


def ray_cast(env: Env, states: int, seed: int) -> dict[str, list[float]]:
    """The resolvability probe's p10 per joint (px per ε, ray cast) with `env`'s camera as it stands, and the share
    of states where the stub is hidden before or after the turn (a shift of 0: out of the frame, or under the floor
    where a large ε turns it there)."""
    stats = image_shift.summary(*image_shift.shifts(env, image_shift.sample(env, states, seed)))
    return {"ray_cast_p10": [round(float(v), 3) for v in stats["p10"]],
            "ray_cast_hidden": [round(float(v), 3) for v in stats["hidden"]]}


def current_pose(env: Env, centre: np.ndarray) -> dict:
    """`env`'s camera as it stands in the model file, as a `pose` row."""
    m, data = env.mj_model, mujoco.MjData(env.mj_model)
    mujoco.mj_kinematics(m, data)
    mujoco.mj_camlight(m, data)
    cam = m.camera(env.camera_name).id
    rotation = data.cam_xmat[cam].reshape(3, 3).T
    return pose(data.cam_xpos[cam].copy(), rotation, HALF / np.tan(np.radians(m.cam_fovy[cam]) / 2), centre)


def record(args: argparse.Namespace, command: str, found: dict) -> dict:
    """The search as a results record, in the figures.json style (not rendered in docs/results.md)."""
    head = ["pose", "position (m)", "view", "projected p10: pan / lift / elbow", "ray-cast p10: pan / lift / elbow",
            "hidden: pan / lift / elbow"]

    def line(label, row):
        view = f"{row['down_deg']:g}° down, fovy {row['fovy_deg']:g}°" + (
            f", roll {row['roll_deg']:g}°" if row.get("roll_deg") else "")
        return [label, "(" + ", ".join(f"{v:g}" for v in row["pos"]) + ")", view,
                " / ".join(f"{v:.2f}" for v in row["projected_p10"]),
                " / ".join(f"{v:.2f}" for v in row["ray_cast_p10"]),
                " / ".join(f"{v:.2f}" for v in row["ray_cast_hidden"])]

    rows = [line("today's `side`", found["current"])]
    rows += [line(f"best of the grid #{i + 1}", r) for i, r in enumerate(found["best"])]
    rows += [line(f"best for {axis}", r) for axis, r in zip(found["axes"], found["best_per_joint"])]
    return {
        "part": "Learning (paper Fig. 4)",
        "title": "ur5_reach's camera: can any fixed pose resolve the goal?",
        "about": f"Pinhole projection of {args.configs} configurations of ur5_reach's goal distribution (seed "
                 f"{args.seed}; points from mujoco.mj_kinematics): the wrist stub's centre turned by "
                 f"ε = {found['epsilon']:g} rad about each joint, and every elbow, wrist and tool point, which the "
                 "frame must hold 1 px inside its edge. "
                 f"{found['grid']} poses: bearing {BEARINGS_DEG[0]:g}–{BEARINGS_DEG[-1]:g}° from the side (-y) toward "
                 f"the pan axis (+x), {DISTANCES[0]:g}–{DISTANCES[-1]:g} m from the base axis, {HEIGHTS[0]:g}–"
                 f"{HEIGHTS[-1]:g} m up, roll {', '.join(f'{r:g}' for r in ROLLS_DEG)}°; each centred on the "
                 "framed points with the narrowest fovy that holds them. Score: the minimum over the joints of the "
                 "10th percentile of the projected shift per ε. The best poses were measured by the resolvability "
                 f"probe (ray cast, 4×4 rays a pixel, {args.states} goal states). Not rendered in docs/results.md.",
        "command": command,
        "machine": "a 2-core CPU",
        "date": datetime.date.today().isoformat(),
        "commit": report.checkout_commit(),
        "table": {"head": head, "rows": rows},
        "bound": found["bound"],
        "note": found["note"],
        "poses": found["best"] + found["best_per_joint"],
    }


def note(found: dict) -> str:
    """What the numbers say, in a few sentences."""
    b, axes = found["bound"], found["axes"]
    measured = [r["ray_cast_p10"] for r in found["best"]]
    best = max(measured, key=min)
    per_joint = ", ".join(f"{a} {r['ray_cast_p10'][j]:.2f}"
                          for j, (a, r) in enumerate(zip(axes, found["best_per_joint"])))
    meets = min(best) >= image_shift.CONTRACT_PX
    return (f"The frame must hold the pan sweep of the full reach ({b['reach_m']:g} m from the base axis), so at the "
            f"workspace's distance a metre spans at most {b['px_per_m']:g} px ({b['px_per_m'] * np.sqrt(2):.1f} along "
            "the frame's diagonal); in the lowest decile ε moves the stub's centre "
            + " / ".join(f"{v * 1000:.0f}" for v in b["moved_p10_m"]) + " mm (" + " / ".join(axes)
            + f"; the stub lies within {b['object_axis_distance_p10_m']:g} m of the pan axis in a tenth of the "
            "configurations), which caps its image at " + " / ".join(f"{v:.2f}" for v in b["px_p10"]) + " px ("
            + " / ".join(f"{v:.2f}" for v in b["px_p10_diagonal"]) + f" on the diagonal); "
            f"{image_shift.CONTRACT_PX:g} px would take " + " / ".join(f"{v:g}" for v in b["px_per_m_needed"])
            + " px per metre at the stub. Perspective adds what a nearer stub gains: the best pose of the grid reaches "
            + " / ".join(f"{v:.2f}" for v in best) + " px (ray cast), the best per joint " + per_joint
            + " px, each at its own pose (the grid includes poses level with the workspace, which the contract's "
            "camera above the robot excludes). "
            + ("A pose of the grid meets the contract." if meets else "No pose of the grid meets the contract.")
            + hidden_note(found))


def hidden_note(found: dict) -> str:
    """A sentence on the measured poses' hidden states, where there are any."""
    rows = [found["current"], *found["best"], *found["best_per_joint"]]
    worst = np.max([r["ray_cast_hidden"] for r in rows], axis=0)
    if not worst.any():
        return ""
    j = int(worst.argmax())
    return (f" The ray cast finds the stub hidden (a shift of 0) in up to {worst[j]:.2f} of the states on "
            f"{found['axes'][j]}: turned by ε = {found['epsilon']:g} rad it leaves the frame or goes under the floor.")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--configs", type=int, default=4096, help="goal-distribution configurations to project")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--top", type=int, default=3, help="best poses of the grid to keep and measure")
    parser.add_argument("--states", type=int, default=256, help="goal states of the ray-cast probe per pose")
    parser.add_argument("--epsilon", type=float, default=None,
                        help="rad each joint turns (default: the task's ε, 0.1), to ask what a larger ε would show")
    parser.add_argument("--out", default=None, help="a new JSON file for the record (default: none written)")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    for flag, value, least in (("--configs", args.configs, 10), ("--top", args.top, 1), ("--states", args.states, 1)):
        if value < least:
            return cli.exit_code(ConfigError(f"{flag} {value}: must be at least {least}"))
    if args.epsilon is not None and not 0 < args.epsilon <= np.pi:
        return cli.exit_code(ConfigError(f"--epsilon {args.epsilon}: must be in (0, π] rad"))
    if args.out is not None and pathlib.Path(args.out).exists():
        return cli.exit_code(ConfigError(f"--out {args.out}: exists; give a new file"))
    env = envs_mjx.make(ENV, render=False)
    if args.epsilon is not None:
        env.epsilon = args.epsilon  # what the probe's target turns each joint by
    framed, centre = points(env, configurations(env, args.configs, args.seed))
    rows = search(framed, centre)
    found = {"axes": list(image_shift.target(env).axes), "epsilon": env.epsilon, "grid": len(rows),
             "bound": bound(framed, centre), "current": current_pose(env, centre), "best": rows[:args.top],
             "best_per_joint": best_per_joint(rows)}
    found["current"].update(ray_cast(env, args.states, args.seed))
    for row in found["best"] + found["best_per_joint"]:
        if "ray_cast_p10" in row:
            continue  # the same pose, best in two ways
        set_camera(env, row)
        row.update(ray_cast(env, args.states, args.seed))
    found["note"] = note(found)
    result = record(args, " ".join([PROG, *argv]), found)
    print("| " + " | ".join(result["table"]["head"]) + " |\n|" + " --- |" * len(result["table"]["head"]))
    for row in result["table"]["rows"]:
        print("| " + " | ".join(row) + " |")
    print("\n" + found["note"])
    if args.out is not None:
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2, ensure_ascii=False) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
