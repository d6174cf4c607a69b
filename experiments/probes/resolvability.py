"""Does the agents' camera resolve the goal? Pixels the task's object moves in the 42×42 frame per ε of goal.

For each goal axis of the task, the shift of the object's image centroid when the object moves by ε, over states
drawn from the goal region (the measure, the object of each task and the states: `experiments.probes.image_shift`).
The probe asks what the object's own motion shows: the other moving bodies (the arm, goal markers) are not
drawn, since where they stand is no part of the goal, and whether they hide the object in the states the task
passes through is the visibility probe's measure (`experiments.probes.visibility`). `--others` draws them too
(NICOL's arm at rest over the cube's start region; the markers moved out of view).

    python -m experiments.probes.resolvability --env nicol_slide [--states 256] [--supersample 4] [--seed 0] [--others]

Prints a markdown table: per goal axis the mean shift in pixels per ε, its 10th percentile (the contract,
`image_shift.CONTRACT_PX`, holds it there) and the share of states where the object is hidden.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

import envs_mjx
from bidal_jax.config import ConfigError
from envs_mjx.base import Env
from experiments import cli
from experiments.probes.image_shift import CONTRACT_PX, SUPERSAMPLE, sample, shifts, summary, target

PROG = "python -m experiments.probes.resolvability"


def table(env: Env, px: np.ndarray, hidden: np.ndarray) -> str:
    """Markdown: one row per goal axis of `env`."""
    tgt, stats = target(env), summary(px, hidden)
    lines = ["| env | object | axis | ε | states | mean px per ε | p10 px per ε | hidden | "
             f"≥ {CONTRACT_PX:g} px (p10) |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for i, axis in enumerate(tgt.axes):
        ok = "yes" if stats["p10"][i] >= CONTRACT_PX else "**no**"
        lines.append(f"| {env.name} | {tgt.name} | {axis} | {tgt.epsilon:g} {tgt.unit} | {len(px)} | "
                     f"{stats['mean'][i]:.2f} | {stats['p10'][i]:.2f} | {stats['hidden'][i]:.2f} | {ok} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--env", required=True, choices=envs_mjx.names())
    parser.add_argument("--states", type=int, default=256, help="goal-region states to measure over")
    parser.add_argument("--supersample", type=int, default=SUPERSAMPLE,
                        help="rays per pixel side the centroid is measured with")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--others", action="store_true",
                        help="draw the other moving bodies too (the arm, which may hide part of the object)")
    args = parser.parse_args(argv)
    for flag, value in (("--states", args.states), ("--supersample", args.supersample)):
        if value < 1:
            return cli.exit_code(ConfigError(f"{flag} {value}: must be at least 1"))
    env = envs_mjx.make(args.env, render=False)
    px, hidden = shifts(env, sample(env, args.states, args.seed), args.supersample, args.others)
    print(table(env, px, hidden))
    return 0


if __name__ == "__main__":
    sys.exit(main())
