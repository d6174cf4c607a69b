"""How often the trainer's exploration lifts the NICOL cube, or keeps it in the hand, before any learning: the
raw material HER has for learning to lift (docs/deviations.md, "Lift goals, held starts").

The mean action is `zero` (an untrained policy), `hover` (the hand driven to `GRASP_HEIGHT` above the
cube, as a policy that has learned to slide keeps it near the cube; fingers and thumb at 0) or `hold` (the hand
still, fingers and thumb at the closure of the held start); the trainer's exploration
(`bidal_jax.acting.exploring`, HER's: Gaussian noise of std `--noise-eps`, a uniform random action with
probability `--random-eps`) is added to it. Episodes begin from reset, or with `--start held` from the env's
exploration start (the cube held in the closed hand, HER's pick-and-place protocol). Printed: the share of
episodes in which the cube's centre rose at least 1, 2.5, 5 and 10 cm above its resting height, the mean number of
steps it spent 5 cm up, the share that ended 5 cm up, and the share that ended with the cube still in the hand
(within `HELD` of the grasp point).

    python -m experiments.probes.exploration --mean hover --episodes 256
    python -m experiments.probes.exploration --start held --mean hold --episodes 40 [--random-eps 0]
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp

from bidal_jax.acting import Policy, draw_starts, exploring, rollout, states_at
from bidal_jax.config import TrainConfig
from envs_mjx.base import ObservationSpec
from envs_mjx.nicol import CUBE_HALF, TABLE_HEIGHT, NicolLift
from experiments.probes.grasping import GRASP_HEIGHT, HELD, _move, _segment

RISES = (0.01, 0.025, 0.05, 0.10)  # m above the cube's resting centre
HELD_UP = 0.05  # m: "5 cm up"
MEANS = ("zero", "hover", "hold")
STARTS = ("reset", "held")


def mean_policy(kind: str, spec: ObservationSpec, action_size: int, grip: jax.Array) -> Policy:
    """The mean action of the exploration: zeros, the grasp point driven to `GRASP_HEIGHT` above the cube, or the
    hand still with fingers and thumb at `grip` (their two actions)."""
    if kind == "zero":
        return lambda obs, key: jnp.zeros((obs["proprio"].shape[0], action_size))
    if kind == "hold":
        still = jnp.concatenate([jnp.zeros(action_size - 2), grip])
        return lambda obs, key: jnp.broadcast_to(still, (obs["proprio"].shape[0], action_size))

    def hover(obs: dict) -> jax.Array:
        ee, obj = _segment(obs, spec, "ee_pos"), _segment(obs, spec, "obj_pos")
        move = _move(ee, obj + jnp.array([0.0, 0.0, GRASP_HEIGHT]))
        return jnp.concatenate([move, jnp.zeros(action_size - 3)])

    return lambda obs, key: jax.vmap(hover)(obs)


def held_grip(env: NicolLift) -> jax.Array:
    """The fingers' and thumb's actions that command the held start's closure (`NicolEnv.commands` inverted)."""
    return 2.0 * (env._held_ctrl - env._ctrl_low) / (env._ctrl_high - env._ctrl_low) - 1.0


@functools.partial(jax.jit, static_argnums=(0, 1, 3, 4, 5, 6))
def cube_rises(env: NicolLift, kind: str, key: jax.Array, episodes: int, noise_eps: float, random_eps: float,
               start: str = "reset") -> tuple[jax.Array, jax.Array]:
    """The cube centre's height above its resting height, and its distance from the grasp point, after each step,
    each [steps, episodes] (m), of `episodes` episodes from `start` of the `kind` mean action with the trainer's
    exploration."""
    spec = env.observation_spec
    mean = mean_policy(kind, spec, env.action_size, held_grip(env))

    def policy(obs: dict, key: jax.Array) -> jax.Array:
        key_mean, key_explore = jax.random.split(key)
        return exploring(mean(obs, key_mean), key_explore, noise_eps, random_eps)

    def record(step):
        proprio = step.next_state.obs["proprio"]
        obj, ee = proprio[:, spec.segment_slice("obj_pos")], proprio[:, spec.segment_slice("ee_pos")]
        return obj[:, 2], jnp.linalg.norm(obj - ee, axis=-1)

    key_start, key_run = jax.random.split(key)
    states = states_at(env, draw_starts(key_start, episodes, 1.0 if start == "held" else 0.0))
    _, (heights, grip) = rollout(env, policy, key_run, states=states, record=record)
    return heights - (TABLE_HEIGHT + CUBE_HALF), grip


def summarize(rise: jax.Array, grip: jax.Array) -> dict[str, float]:
    """Shares of episodes (columns of `rise` and `grip` [steps, episodes]) whose cube rose at least each of
    `RISES`, the mean number of steps spent `HELD_UP` up, the share that ended that high, and the share that ended
    with the cube within `HELD` of the grasp point."""
    top = rise.max(axis=0)
    shares = {f"rose >= {100 * r:g} cm": float((top >= r).mean()) for r in RISES}
    up = f"{100 * HELD_UP:g} cm"
    return {**shares, f"steps >= {up} (mean)": float((rise >= HELD_UP).sum(axis=0).mean()),
            f"ended >= {up}": float((rise[-1] >= HELD_UP).mean()),
            "ended in the hand": float((grip[-1] <= HELD).mean())}


def main(argv: list[str] | None = None) -> None:
    defaults = TrainConfig()
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mean", choices=MEANS, default="hover", help="the exploration's mean action")
    parser.add_argument("--start", choices=STARTS, default="reset", help="episodes begin from reset or held")
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise-eps", type=float, default=defaults.noise_eps)
    parser.add_argument("--random-eps", type=float, default=defaults.random_eps)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be a positive integer, got {args.episodes}")
    if args.noise_eps < 0 or not 0 <= args.random_eps <= 1:
        parser.error("--noise-eps must be >= 0 and --random-eps a probability in [0, 1]")
    rise, grip = cube_rises(NicolLift(render=False), args.mean, jax.random.PRNGKey(args.seed), args.episodes,
                            args.noise_eps, args.random_eps, args.start)
    figures = "; ".join(f"{name} {value:.3f}" for name, value in summarize(rise, grip).items())
    print(f"nicol_lift, start {args.start}, mean {args.mean}, noise_eps {args.noise_eps:g}, random_eps "
          f"{args.random_eps:g}, {args.episodes} episodes: {figures}")


if __name__ == "__main__":
    main()
