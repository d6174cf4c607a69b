"""Physics check of the NICOL scene: how hard can the hand throw the cube, how deep do bodies sink.

Batched rollouts of three scenarios, stepped by the env itself (MJX, `Env.probed_step`) or by
plain MuJoCo (`mujoco.mj_step`, with the env's own hand commands and target path):

- `push`: the hand driven at full speed towards the cube with noise (0.5 per action entry),
  random roll and tilt, and fingers and thumb opening and closing at random;
- `random`: uniformly random actions;
- `drop`: the cube, turned at random, dropped from `DROP_HEIGHTS` above the table beside the
  resting hand.

Each physics substep records the cube's position, linear and angular velocity and the deepest
contact of each pair of bodies (hand–cube, hand–table, cube–table) from MuJoCo's contact
distances (plain MuJoCo also the Newton solver's iteration count, `data.solver_niter`: the cost proxy of
the `iterations` limit; MJX computes it but does not keep it); each control step records the proprio
the agent sees. `summarize` reduces them to
the cube's top speed and spin, its greatest height above the table, the restitution of the
drops (rebound speed over impact speed), the penetration depths, the share of episodes that
end with the cube more than `FAR` from its start, and what the observation normaliser would
see: the largest feature std of each proprio segment, the share of entries at the clip, and
the std of the cube's height (the goal normaliser's height feature).

`--option NAME=VALUE` overrides a scalar of the model's `<option>` (e.g. iterations=5, ls_iterations=6,
timestep=0.01, cone=elliptic) for exploring settings without editing assets/nicol.xml (`Env.set_options`).

    python -m experiments.probes.physics --env nicol_lift --envs 64 [--native 8] [--option iterations=5]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from typing import Callable, NamedTuple

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import envs_mjx
from bidal_jax import normalizer
from envs_mjx.base import State
from envs_mjx.nicol import CUBE_HALF, TABLE_HEIGHT, NicolEnv

SCENARIOS = ("push", "random", "drop")
STEPS = 50  # control steps per episode: the tasks' T
PUSH_NOISE = 0.5
DROP_HEIGHTS = (0.05, 0.1, 0.2, 0.3)  # m from the table top to the cube's lowest possible point
DROP_OFFSET = (0.15, -0.15)  # m from the cube's start centre, clear of the resting hand
FAR = 0.5  # m
CLIP = 5.0  # the trainer's default clip_obs
HAND_GEOMS = ("r_palm", "r_index", "r_middle", "r_ring", "r_little", "r_thumb")
PAIRS = {
    "hand_cube": (HAND_GEOMS, ("cube",)),
    "hand_table": (HAND_GEOMS, ("table",)),
    "cube_table": (("cube",), ("table",)),
}
MAX_CONTACTS = 64  # per substep, for plain MuJoCo's records


# ----- scenarios -------------------------------------------------------------------------
def scenario_action(scenario: jax.Array, hand: jax.Array, cube: jax.Array, key: jax.Array) -> jax.Array:
    """The action (7,) of scenario index `scenario` (into `SCENARIOS`) from the grasp point and the cube centre."""
    key_noise, key_hand, key_random = jax.random.split(key, 3)
    towards = (cube - hand) / jnp.maximum(jnp.linalg.norm(cube - hand), 1e-6)
    noise = PUSH_NOISE * jax.random.normal(key_noise, (5,))
    hand_closure = jax.random.uniform(key_hand, (2,), minval=-1.0, maxval=1.0)
    push = jnp.concatenate([towards + noise[:3], noise[3:], hand_closure])
    random = jax.random.uniform(key_random, (7,), minval=-1.0, maxval=1.0)
    rest = jnp.zeros(7).at[5:].set(-1.0)
    return jnp.clip(jnp.select([scenario == 0, scenario == 1], [push, random], rest), -1.0, 1.0)


def random_quat(key: jax.Array) -> jax.Array:
    """A uniformly random unit quaternion."""
    quat = jax.random.normal(key, (4,))
    return quat / jnp.linalg.norm(quat)


def start_state(env: NicolEnv, scenario: jax.Array, episode: jax.Array, key: jax.Array) -> State:
    """The env's reset; for `drop`, the cube lifted by DROP_HEIGHTS[episode % 4] and turned at random."""
    key_reset, key_turn = jax.random.split(key)
    state = env.reset(key_reset)
    height = jnp.asarray(DROP_HEIGHTS)[episode % len(DROP_HEIGHTS)]
    # the lowest point of a turned cube lies at most half its diagonal below the centre
    centre = env._cube_centre + jnp.array([*DROP_OFFSET, height + np.sqrt(3.0) * CUBE_HALF - CUBE_HALF])
    adr = env._cube_qpos
    dropped = state.data.qpos.at[adr : adr + 3].set(centre).at[adr + 3 : adr + 7].set(random_quat(key_turn))
    qpos = jnp.where(scenario == 2, dropped, state.data.qpos)
    return state.replace(data=state.data.replace(qpos=qpos))


# ----- what one substep shows --------------------------------------------------------------
def pair_geoms(mj_model: mujoco.MjModel) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Geom ids of the two sides of each of `PAIRS`."""
    def ids(names):
        return np.array([mj_model.geom(n).id for n in names])
    return {name: (ids(a), ids(b)) for name, (a, b) in PAIRS.items()}


def contact_depths(geom: jax.Array, dist: jax.Array, pairs: dict[str, tuple[np.ndarray, np.ndarray]]) -> jax.Array:
    """Deepest penetration (m, ≥ 0) of each of `PAIRS` among contacts `geom` (n, 2) at distances `dist` (n,)."""
    chex.assert_equal_shape_prefix([geom, dist], 1)
    depths = []
    for a, b in pairs.values():
        in_a, in_b = jnp.isin(geom, a), jnp.isin(geom, b)
        match = (in_a[:, 0] & in_b[:, 1]) | (in_b[:, 0] & in_a[:, 1])
        depths.append(jnp.max(jnp.where(match, -dist, 0.0), initial=0.0))
    return jnp.stack(depths)


def cube_motion(env: NicolEnv, qpos, qvel, concatenate=jnp.concatenate):
    """(9,): the cube's centre, linear velocity (world) and angular velocity (body frame)."""
    return concatenate([qpos[env._cube_qpos : env._cube_qpos + 3], qvel[env._cube_dof : env._cube_dof + 6]])


# ----- rollouts ---------------------------------------------------------------------------
def mjx_rollout(env: NicolEnv, scenario: str, key: jax.Array, n_envs: int) -> dict[str, jax.Array]:
    """MJX rollouts of one scenario: `motion` (envs, steps, substeps, 9), `depth` (envs, steps, substeps,
    pairs), `proprio` (envs, steps, D)."""
    return _mjx_rollouts(env)(jnp.int32(SCENARIOS.index(scenario)), jax.random.split(key, n_envs))


def _mjx_rollouts(env: NicolEnv):
    """One compiled program for every scenario and batch (the scenario is an argument, not a constant)."""
    if not hasattr(env, "_physics_check_rollouts"):
        pairs = pair_geoms(env.mj_model)

        def probe(data):
            contact = data._impl.contact
            return cube_motion(env, data.qpos, data.qvel), contact_depths(contact.geom, contact.dist, pairs)

        def one(scenario, episode, key):
            key_start, key_steps = jax.random.split(key)

            def control_step(state, key):
                data = state.data
                action = scenario_action(scenario, data.xpos[env._hand], data.xpos[env._cube], key)
                state, (motion, depth) = env.probed_step(state, action, probe)
                return state, {"motion": motion, "depth": depth, "proprio": state.obs["proprio"]}

            state = start_state(env, scenario, episode, key_start)
            return jax.lax.scan(control_step, state, jax.random.split(key_steps, STEPS))[1]

        env._physics_check_rollouts = jax.jit(
            lambda scenario, keys: jax.vmap(one, (None, 0, 0))(scenario, jnp.arange(keys.shape[0]), keys)
        )
    return env._physics_check_rollouts


class NativeHelpers(NamedTuple):
    """The compiled pieces of `native_rollout`, shared by every scenario and batch (the scenario is an argument)."""

    starts: Callable    # (scenario, episodes [N], keys [N, 2]) -> the start States
    actions: Callable   # (scenario, hand [N, 3], cube [N, 3], keys [N, 2]) -> actions
    commands: Callable  # env.commands over N envs
    path: Callable      # env.target_path over N envs and the substeps
    depths: Callable    # (geom [M, C, 2], dist [M, C]) -> [M, pairs]: `contact_depths` of M substeps


def _native_helpers(env: NicolEnv) -> NativeHelpers:
    """`env`'s NativeHelpers, made at the first call and kept on `env` (as `_mjx_rollouts` keeps its program): built
    per call, they were traced and compiled again for each scenario."""
    if not hasattr(env, "_physics_check_native"):
        pairs = pair_geoms(env.mj_model)
        env._physics_check_native = NativeHelpers(
            starts=jax.jit(jax.vmap(lambda s, e, k: start_state(env, s, e, k), (None, 0, 0))),
            actions=jax.jit(jax.vmap(scenario_action, (None, 0, 0, 0))),
            commands=jax.jit(jax.vmap(env.commands)),
            path=jax.jit(jax.vmap(jax.vmap(env.target_path, (0, 0, 0, 0, None)), (None, None, None, None, 0), 1)),
            depths=jax.jit(jax.vmap(lambda g, d: contact_depths(g, d, pairs))),
        )
    return env._physics_check_native


def native_rollout(env: NicolEnv, scenario: str, key: jax.Array, n_envs: int) -> dict[str, np.ndarray]:
    """`mjx_rollout` stepped by plain MuJoCo (float64, `mujoco.mj_step`): the same starts, scenario
    actions, hand commands and target path; `proprio` is left out (its code is MJX's), and
    `solver_iterations` (envs, steps, substeps) is added (the Newton solver's `data.solver_niter`)."""
    index = jnp.int32(SCENARIOS.index(scenario))
    key_start, key_steps = jax.random.split(key)
    helpers = _native_helpers(env)
    starts = helpers.starts(index, jnp.arange(n_envs), jax.random.split(key_start, n_envs))
    model, t = env.mj_model, env._target_mocap
    datas = [mujoco.MjData(model) for _ in range(n_envs)]
    for i, data in enumerate(datas):
        for field in ("qpos", "qvel", "ctrl", "mocap_pos", "mocap_quat"):
            getattr(data, field)[:] = np.asarray(getattr(starts.data, field)[i])
        mujoco.mj_forward(model, data)
    motion = np.zeros((n_envs, STEPS, env.n_substeps, 9))
    geom = np.zeros((n_envs, STEPS, env.n_substeps, MAX_CONTACTS, 2), np.int32)
    dist = np.full((n_envs, STEPS, env.n_substeps, MAX_CONTACTS), np.inf)
    iterations = np.zeros((n_envs, STEPS, env.n_substeps), np.int32)
    for step, key_step in enumerate(jax.random.split(key_steps, STEPS)):
        hand = np.stack([d.xpos[env._hand] for d in datas])
        cube = np.stack([d.xpos[env._cube] for d in datas])
        action = helpers.actions(index, hand, cube, jax.random.split(key_step, n_envs))
        pos, quat = np.stack([d.mocap_pos[t] for d in datas]), np.stack([d.mocap_quat[t] for d in datas])
        new_pos, new_quat, ctrl = helpers.commands(hand, quat, action)
        path_pos, path_quat = map(np.asarray, helpers.path(pos, quat, new_pos, new_quat, jnp.arange(env.n_substeps)))
        for i, data in enumerate(datas):
            data.ctrl[:] = np.asarray(ctrl[i])
            for sub in range(env.n_substeps):
                data.mocap_pos[t], data.mocap_quat[t] = path_pos[i, sub], path_quat[i, sub]
                mujoco.mj_step(model, data)
                n = min(data.ncon, MAX_CONTACTS)
                motion[i, step, sub] = cube_motion(env, data.qpos, data.qvel, np.concatenate)
                iterations[i, step, sub] = data.solver_niter[0]
                geom[i, step, sub, :n] = data.contact.geom[:n]
                dist[i, step, sub, :n] = data.contact.dist[:n]
    depth = helpers.depths(geom.reshape(-1, MAX_CONTACTS, 2), dist.reshape(-1, MAX_CONTACTS))
    depth = np.asarray(depth).reshape(*motion.shape[:3], -1)
    return {"motion": motion, "depth": depth, "solver_iterations": iterations}


# ----- figures ----------------------------------------------------------------------------
def summarize(env: NicolEnv, scenario: str, rollout: dict) -> dict:
    """The figures of one scenario's rollouts (see the module docstring); lengths in m, speeds in m/s."""
    motion = np.asarray(rollout["motion"], np.float64)
    episodes = motion.reshape(motion.shape[0], -1, 9)  # every substep of an episode in order
    pos, vel, spin = episodes[..., :3], episodes[..., 3:6], episodes[..., 6:9]
    height = pos[..., 2] - TABLE_HEIGHT - CUBE_HALF
    depth = np.asarray(rollout["depth"]).reshape(-1, len(PAIRS)).max(0)
    figures = {
        "max_speed": float(np.linalg.norm(vel, axis=-1).max()),
        "max_spin": float(np.linalg.norm(spin, axis=-1).max()),
        **{f"depth_{name}": float(d) for name, d in zip(PAIRS, depth)},
    }
    if scenario == "drop":
        impact = np.argmin(vel[..., 2], axis=1)  # the fastest fall comes just before the first impact
        after = np.arange(vel.shape[1])[None] > impact[:, None]
        impact_speed = -vel[np.arange(len(impact)), impact, 2]
        rebound = np.where(after, vel[..., 2], 0.0).max(1)
        restitution = rebound / np.maximum(impact_speed, 1e-6)
        figures |= {
            "max_restitution": float(restitution.max()),
            "mean_restitution": float(restitution.mean()),
            "max_rebound_height": float(np.where(after, height, -np.inf).max()),
        }
    else:
        figures |= {
            "max_height": float(height.max()),
            "far_share": float((np.linalg.norm(pos[:, -1] - pos[:, 0], axis=-1) > FAR).mean()),
        }
    if "solver_iterations" in rollout:
        iterations = np.asarray(rollout["solver_iterations"])
        figures |= {"solver_iterations_mean": float(iterations.mean()), "solver_iterations_max": int(iterations.max())}
    if "proprio" in rollout:
        figures |= normalizer_figures(env, np.asarray(rollout["proprio"]))
    return figures


def normalizer_figures(env: NicolEnv, proprio: np.ndarray) -> dict:
    """What the observation normaliser makes of `proprio` (..., D): per segment the largest feature
    std and the share of entries at ±CLIP after normalising; the std of the cube's height."""
    spec = env.observation_spec
    flat = proprio.reshape(-1, proprio.shape[-1])
    state = normalizer.update(normalizer.init(flat.shape[-1]), jnp.asarray(flat))
    at_clip = np.abs(np.asarray(normalizer.normalize(state, jnp.asarray(flat), CLIP))) >= CLIP * (1 - 1e-6)
    std = np.asarray(state.std)
    figures = {"cube_height_std": float(flat[:, spec.segment_slice("obj_pos")][:, 2].std())}
    for name in spec.segment_names:
        figures[f"std_{name}"] = float(std[spec.segment_slice(name)].max())
        figures[f"clip_{name}"] = float(at_clip[:, spec.segment_slice(name)].mean())
    return figures


def check(env: NicolEnv, key: jax.Array, n_envs: int, native_envs: int = 0) -> dict:
    """Figures of every scenario: {"mjx": {scenario: figures}, "native": … (when native_envs > 0)}."""
    keys = dict(zip(SCENARIOS, jax.random.split(key, len(SCENARIOS))))
    report = {"mjx": {s: summarize(env, s, mjx_rollout(env, s, keys[s], n_envs)) for s in SCENARIOS}}
    if native_envs:
        report["native"] = {s: summarize(env, s, native_rollout(env, s, keys[s], native_envs)) for s in SCENARIOS}
    return report


def format_table(report: dict) -> str:
    """One row per figure, one column per (stepper, scenario)."""
    columns = [(stepper, s) for stepper in report for s in report[stepper]]
    names = list(dict.fromkeys(k for stepper, s in columns for k in report[stepper][s]))
    lines = ["figure".ljust(24) + "".join(f"{stepper}/{s}".rjust(15) for stepper, s in columns)]
    for name in names:
        cells = (report[stepper][s].get(name) for stepper, s in columns)
        lines.append(name.ljust(24) + "".join(("-" if c is None else f"{c:.4g}").rjust(15) for c in cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env", default="nicol_lift", choices=("nicol_slide", "nicol_lift"))
    parser.add_argument("--envs", type=int, default=64, help="MJX episodes per scenario")
    parser.add_argument("--native", type=int, default=0, help="plain-MuJoCo episodes per scenario (0: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="override a scalar of the model's <option> (repeatable), e.g. iterations=5")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.envs < 1 or args.native < 0:
        parser.error("--envs must be positive and --native not negative")
    options = dict(option.split("=", 1) for option in args.option if "=" in option)
    if len(options) != len(args.option):
        parser.error("--option takes NAME=VALUE")
    env = envs_mjx.make(args.env, render=False)
    try:
        env.set_options(**options)
    except ValueError as err:
        parser.error(f"--option: {err}")
    report = check(env, jax.random.PRNGKey(args.seed), args.envs, args.native)
    print(format_table(report))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
