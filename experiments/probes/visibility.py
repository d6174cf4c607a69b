"""What does the agents' camera show? Pixels covered by each task-relevant body, by phase of the task.

The image agents can only learn what their 42×42 frame shows (docs/tasks.md, "camera"). This
probe counts, from the camera's per-ray geom ids (`Camera.geom_map`, the first geom each ray hits),
how many output pixels each task-relevant body covers (rays on the body over rays per pixel, so a
body seen by half the rays of 6 pixels covers 3) in the states a task passes through:

- NICOL (nicol_slide, nicol_lift): the cube and the hand (palm, fingers, thumb; the agents' frames do not
  draw the goal marker: docs/tasks.md, "camera"), in the scripted episodes of `experiments.probes.phases`
  (grasps, pushes and carries from the held start), sorted by the true state into `start`, `approach`,
  `contact` (the hand at the cube) and `held` (the cube lifted in the closed hand).
- reaching (planar_reach, ur5_reach): the arm's links and the goal marker(s), at start states and
  after random actions.

    python -m experiments.probes.visibility --env nicol_lift [--episodes 128] [--out docs/visibility.md]

Prints a markdown table (one row per phase: frames, and per body the mean pixels covered, the
10th percentile and the share of frames where it covers at least `VISIBLE_PX` pixels) and, with
`--out`, appends it to that file.
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np

import envs_mjx
from bidal_jax.config import ConfigError
from envs_mjx.base import Env
from envs_mjx.camera import subtree_geoms, visible_geoms
from envs_mjx.nicol import NicolEnv
from experiments import cli
from experiments.probes.phases import PHASES_NICOL, SCRIPT_NOISE, nicol_rollouts

PROG = "python -m experiments.probes.visibility"
VISIBLE_PX = 3.0  # pixels a body must cover to count as seen
RANDOM_STEPS = 10  # random actions before a reaching frame of the `moving` phase


def body_groups(env: Env) -> dict[str, tuple[int, ...]]:
    """The task-relevant bodies of `env` that its camera draws, as named groups of geom ids."""
    m = env.mj_model
    if isinstance(env, NicolEnv):
        return {"cube": subtree_geoms(m, "cube"), "hand": subtree_geoms(m, "r_hand")}
    names = [m.geom(g).name for g in range(m.ngeom)]
    goals = tuple(g for g, n in enumerate(names) if n.startswith("goal") or n == "target")
    # a link's geoms the camera does not draw (e.g. ur5_reach's physical capsules in group 3) are not looked for
    seen = set(visible_geoms(m))
    links = [(n, (g,)) for g, n in enumerate(names) if m.geom_bodyid[g] > 0 and g not in goals and g in seen]
    return dict(links) | {"goal marker": goals}


def coverage(env: Env, groups: dict[str, tuple[int, ...]], data) -> jax.Array:
    """Output pixels covered by each group [len(groups)] in the frame of `data`."""
    ids = env.camera.geom_map(env.mjx_model, data)
    rays = jnp.stack([jnp.isin(ids, jnp.asarray(g)).sum() for g in groups.values()])
    return rays / env.camera.supersample**2


def reach_frames(env: Env, groups, episodes: int, key: jax.Array) -> tuple[np.ndarray, np.ndarray]:
    """(coverage, phase) at start states (phase 0) and after `RANDOM_STEPS` random actions (phase 1)."""

    def frames(key):
        key_reset, key_act = jax.random.split(key)
        state = env.reset(key_reset)
        start = coverage(env, groups, state.data)
        actions = jax.random.uniform(key_act, (RANDOM_STEPS, env.action_size), minval=-1.0, maxval=1.0)
        state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), state, actions)
        return jnp.stack([start, coverage(env, groups, state.data)])

    cov = np.asarray(jax.jit(jax.vmap(frames))(jax.random.split(key, episodes)))
    return cov.reshape(-1, cov.shape[-1]), np.tile([0, 1], episodes)


PHASES_REACH = ("start", "moving")


def table(env_name: str, groups, cov: np.ndarray, phase: np.ndarray, phases: tuple[str, ...]) -> str:
    """Markdown: per phase, frames and per group mean pixels, 10th percentile and share ≥ `VISIBLE_PX`."""
    head = "| env | phase | frames | " + " | ".join(f"{g}: mean px, p10, ≥ {VISIBLE_PX:g} px" for g in groups) + " |"
    lines = [head, "|" + " --- |" * (3 + len(groups))]
    for i, name in enumerate(phases):
        rows = cov[phase == i]
        if not len(rows):
            lines.append(f"| {env_name} | {name} | 0 |" + " – |" * len(groups))
            continue
        cells = [f"{c.mean():.1f}, {np.percentile(c, 10):.1f}, {(c >= VISIBLE_PX).mean():.2f}" for c in rows.T]
        lines.append(f"| {env_name} | {name} | {len(rows)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def measure(env: Env, episodes: int, noise: float, seed: int = 0) -> str:
    """The probe's table for `env`."""
    groups = body_groups(env)
    key = jax.random.PRNGKey(seed)
    if isinstance(env, NicolEnv):
        cov, phase = nicol_rollouts(env, episodes, noise, key, lambda state: coverage(env, groups, state.data))
        return table(env.name, groups, cov, phase, PHASES_NICOL)
    cov, phase = reach_frames(env, groups, episodes, key)
    return table(env.name, groups, cov, phase, PHASES_REACH)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--env", required=True, choices=envs_mjx.names())
    parser.add_argument("--episodes", type=int, default=128, help="episodes (NICOL) or start states (reaching)")
    parser.add_argument("--noise", type=float, default=SCRIPT_NOISE,
                        help="std of the Gaussian noise on scripted actions")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="markdown file to append the table to")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        return cli.exit_code(ConfigError(f"--episodes {args.episodes}: must be at least 1"))
    # the probe casts its own rays (`coverage`); the env need not render its observations too
    text = measure(envs_mjx.make(args.env, render=False), args.episodes, args.noise, args.seed)
    print(text)
    if args.out:
        with open(args.out, "a") as f:
            f.write(text + "\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
