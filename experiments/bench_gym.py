"""Cost of the Gymnasium adapter (envs_mjx.gym) per env step, against native MuJoCo.

    python -m experiments.bench_gym                            # planar_reach, 1/16/64/256 envs
    python -m experiments.bench_gym --num-envs 64 --repeats 5

One env step is one 0.04 s control period. The adapter figure is the wall time of
`VectorGoalEnv.step` (numpy actions in, numpy observations, rewards and infos out,
state-only observations, autoreset included) divided by the number of envs it steps; the
yardstick is native MuJoCo stepping one env (`mujoco.mj_step`, the env's `n_substeps`
substeps with random controls). Each figure is the median of `--repeats` timed runs of
`--steps` steps after a warm-up (compilation excluded); it prints a Markdown table.
"""

from __future__ import annotations

import argparse

import mujoco
import numpy as np

import envs_mjx
from envs_mjx.gym import VectorGoalEnv
from experiments.bench import _timed


def adapter_ms_per_env_step(name: str, num_envs: int, steps: int, repeats: int) -> float:
    """Milliseconds per env step of `VectorGoalEnv.step` at `num_envs` envs, random actions."""
    envs = VectorGoalEnv(name, num_envs)
    envs.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (steps, num_envs, envs.env.action_size)).astype(np.float32)

    def run():
        for action in actions:
            envs.step(action)

    return 1e3 * _timed(run, repeats) / (steps * num_envs)


def native_ms_per_env_step(name: str, steps: int, repeats: int) -> float:
    """Milliseconds per env step of native MuJoCo on one env: `n_substeps` mj_steps per step."""
    env = envs_mjx.make(name, render=False)
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    controls = np.random.default_rng(0).uniform(low, high, (steps, model.nu))

    def run():
        mujoco.mj_resetData(model, data)
        for ctrl in controls:
            data.ctrl[:] = ctrl
            mujoco.mj_step(model, data, nstep=env.n_substeps)

    return 1e3 * _timed(run, repeats) / steps


def main(argv: list[str] | None = None) -> None:
    """Print the adapter's and native MuJoCo's cost per env step as a Markdown table."""
    parser = argparse.ArgumentParser(prog="python -m experiments.bench_gym", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="planar_reach", choices=envs_mjx.names())
    parser.add_argument("--num-envs", nargs="+", type=int, default=[1, 16, 64, 256])
    parser.add_argument("--steps", type=int, default=100, help="env steps per timed run")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per figure (median)")
    args = parser.parse_args(argv)
    if min(args.num_envs) < 1 or args.steps < 1 or args.repeats < 1:
        parser.error(f"--num-envs {args.num_envs}, --steps {args.steps}, --repeats {args.repeats}: must be >= 1")

    native = native_ms_per_env_step(args.env, args.steps, args.repeats)
    print(f"| {args.env} | envs | ms per env step | vs native MuJoCo |\n| --- | --- | --- | --- |")
    print(f"| native `mujoco.mj_step` | 1 | {native:.4f} | 1.00 |", flush=True)
    for n in args.num_envs:
        cost = adapter_ms_per_env_step(args.env, n, args.steps, args.repeats)
        print(f"| envs_mjx.gym.VectorGoalEnv | {n} | {cost:.4f} | {cost / native:.2f} |", flush=True)


if __name__ == "__main__":
    main()
