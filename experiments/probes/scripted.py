"""The scripted grasp controller on the NICOL tasks (`experiments/probes/grasping.py`): does the
model's physics allow grasping and moving the cube within the 50-step episode? No learning.

    python -m experiments.probes.scripted      # success rates over 100 random episodes each
"""

from __future__ import annotations

import argparse

import jax

from bidal_jax.acting import evaluate
from envs_mjx.nicol import NicolLift, NicolSlide
from experiments.probes.grasping import scripted_policy


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be a positive integer, got {args.episodes}")
    key_slide, key_lift = jax.random.split(jax.random.PRNGKey(args.seed))
    for name, env, key in (
        ("nicol_slide", NicolSlide(render=False), key_slide),
        ("nicol_lift", NicolLift(render=False), key_lift),
    ):
        success = jax.jit(evaluate, static_argnums=(0, 1, 3))(
            env, scripted_policy(env.observation_spec), key, args.episodes
        )
        print(f"{name}: scripted success {float(success.mean()):.2f} over {args.episodes} episodes")


if __name__ == "__main__":
    main()
