"""Cost of the Gymnasium adapter (envs_mjx.gym) per env step, against native MuJoCo.

    python -m experiments.bench.gym_adapter                            # planar_reach, 1/16/64/256 envs
    python -m experiments.bench.gym_adapter --num-envs 64 --repeats 9

One env step is one 0.04 s control period. The adapter figure is the wall time of
`VectorGoalEnv.step` (numpy actions in; numpy observations, rewards and infos out;
state-only observations; autoreset included) divided by the number of envs it steps. The
yardstick is native MuJoCo stepping one env: `mujoco.mj_step` for the env's `n_substeps`
substeps with random controls. Each figure is the median over `--repeats` rounds of
`--steps` steps after a warm-up (compilation excluded); every round times every
configuration once, so that all of them see the same load on a shared machine.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import mujoco
import numpy as np

import envs_mjx
from envs_mjx.gym import VectorGoalEnv


def adapter_steps(name: str, num_envs: int, steps: int) -> Callable[[], None]:
    """A function that runs `steps` steps of a reset `VectorGoalEnv` with random actions."""
    envs = VectorGoalEnv(name, num_envs)
    envs.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (steps, *envs.action_space.shape)).astype(np.float32)

    def run():
        for action in actions:
            envs.step(action)

    return run


def native_steps(name: str, steps: int) -> Callable[[], None]:
    """A function that runs `steps` control periods of native MuJoCo on one env, random controls."""
    env = envs_mjx.make(name, render=False)
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    controls = np.random.default_rng(0).uniform(low, high, (steps, model.nu))

    def run():
        mujoco.mj_resetData(model, data)
        for ctrl in controls:
            data.ctrl[:] = ctrl
            mujoco.mj_step(model, data, nstep=env.n_substeps)

    return run


def interleaved_medians(runs: dict[str, Callable[[], None]], repeats: int) -> dict[str, float]:
    """Median seconds of each run over `repeats` rounds, each round timing every run once,
    after one untimed warm-up round (which compiles)."""
    times: dict[str, list[float]] = {key: [] for key in runs}
    for round_ in range(repeats + 1):
        for key, run in runs.items():
            start = time.perf_counter()
            run()
            if round_:
                times[key].append(time.perf_counter() - start)
    return {key: statistics.median(values) for key, values in times.items()}


def main(argv: list[str] | None = None) -> None:
    """Print the adapter's and native MuJoCo's cost per env step as a Markdown table."""
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench.gym_adapter", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--env", default="planar_reach", choices=envs_mjx.names())
    parser.add_argument("--num-envs", nargs="+", type=int, default=[1, 16, 64, 256])
    parser.add_argument("--steps", type=int, default=100, help="env steps per timed run")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (median)")
    args = parser.parse_args(argv)
    for option, values in (("--num-envs", args.num_envs), ("--steps", [args.steps]), ("--repeats", [args.repeats])):
        if min(values) < 1:
            parser.error(f"{option} {min(values)}: must be >= 1")

    runs = {"native": native_steps(args.env, args.steps)}
    runs.update({n: adapter_steps(args.env, n, args.steps) for n in args.num_envs})
    seconds = interleaved_medians(runs, args.repeats)
    native = 1e3 * seconds.pop("native") / args.steps
    print(f"| {args.env} | envs | ms per env step | vs native MuJoCo |\n| --- | --- | --- | --- |")
    print(f"| native `mujoco.mj_step` | 1 | {native:.4f} | 1.00 |")
    for n, value in seconds.items():
        cost = 1e3 * value / (args.steps * n)
        print(f"| `envs_mjx.gym.VectorGoalEnv` | {n} | {cost:.4f} | {cost / native:.2f} |")


if __name__ == "__main__":
    main()
