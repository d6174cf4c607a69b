"""Throughput benchmark: env steps per second of MJX physics, physics + camera, frames per
second of the camera alone, whole training epochs, and native MuJoCo (`mujoco.rollout`,
2 threads) as the yardstick.

    python -m experiments.bench.throughput                       # planar_reach, 64/256/1024 envs
    python -m experiments.bench.throughput --envs ur5_reach nicol_slide --num-envs 64 256
    python -m experiments.bench.throughput --skip-train --json out.json
    python -m experiments.bench.throughput --envs nicol_slide --agent multimodal_bidal --devices 1 2 --physics warp

One env step is one 0.04 s control period (several physics substeps). Each figure is the
median of `--repeats` timed runs after a warm-up (compilation excluded); it prints a
Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import numpy as np

import envs_mjx
from bidal_jax import acting
from bidal_jax.config import ConfigError, TrainConfig
from bidal_jax.run import validate
from bidal_jax.run.devices import make_seeded
from bidal_jax.train import make_train
from experiments import cli
from experiments.bench.programs import seeded_program, timed


def env_steps_per_second(name: str, num_envs: int, render: bool, steps: int, repeats: int) -> float:
    """Random-action rollout of `steps` control periods in `num_envs` vmapped envs, in one jit."""
    env = envs_mjx.make(name, render=render)

    @jax.jit
    def run(key):
        state, _ = acting.rollout(env, acting.random_policy(env.action_size), key, num_envs, steps=steps)
        return state.obs["proprio"].sum() + state.obs["image"].sum()

    key = jax.random.PRNGKey(0)
    seconds = timed(lambda: run(key).block_until_ready(), repeats)["warm_seconds"]
    return num_envs * steps / seconds


def camera_frames_per_second(name: str, num_envs: int, repeats: int) -> float:
    """The camera alone: frames per second rendering `num_envs` reset states in one jit."""
    env = envs_mjx.make(name, render=False)
    data = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), num_envs)).data
    render = jax.jit(jax.vmap(lambda d: env.camera.render(env.mjx_model, d)))
    seconds = timed(lambda: render(data).block_until_ready(), repeats)["warm_seconds"]
    return num_envs / seconds


def training_steps_per_second(name: str, agent: str, num_envs: int, repeats: int) -> float:
    """Env steps per second of whole training epochs (rollouts, updates, evaluation)."""
    preset = cli.resolve({"env": name, "agent": agent})
    config = dataclasses.replace(
        preset.train,
        num_envs=num_envs,
        buffer_episodes=max(num_envs * 4, TrainConfig().buffer_episodes // num_envs * num_envs),
        cycles_per_epoch=2,
    )
    env = envs_mjx.make(name, render=preset.agent.uses_image)
    init, epoch = make_seeded(*make_train(env, dataclasses.replace(preset, train=config)))
    holder = {"state": init(jax.random.split(jax.random.PRNGKey(0), 1))}

    def one_epoch():
        holder["state"], metrics = epoch(holder["state"])
        jax.block_until_ready(metrics)

    seconds = timed(one_epoch, repeats)["warm_seconds"]
    return config.cycles_per_epoch * num_envs * env.episode_length / seconds


def sharded_training(
    name: str, agent: str, seeds: int, n_devices: int, repeats: int, env_shards: int = 1, physics: str = "jax"
) -> dict[str, float]:
    """Training throughput of `seeds` vmapped seeds of the env's preset on the first `n_devices`
    devices, laid out as a run lays them out (`devices.device_layout`: seeds over devices, up to
    `env_shards` of the devices left over splitting each seed's envs): env steps per second with
    learning, and seconds per epoch. The physics engine is `physics` (jax or warp) on every device count, so that
    the counts compare one engine."""
    init, epoch, config, env, devices, shards = seeded_program(name, agent, seeds, n_devices, env_shards,
                                                               backend=physics)
    start = time.perf_counter()
    holder = {"state": init(jax.random.split(jax.random.PRNGKey(0), seeds))}

    def one_epoch():
        holder["state"], metrics = epoch(holder["state"])
        jax.block_until_ready(metrics)

    one_epoch()  # compiles
    compile_seconds = time.perf_counter() - start
    seconds = timed(one_epoch, repeats)["warm_seconds"]
    steps = seeds * config.cycles_per_epoch * config.num_envs * env.episode_length
    return {
        "devices": len(devices),
        "engine": env.backend,
        "env_shards": shards,
        "seeds": seeds,
        "epoch_seconds": seconds,
        "env_steps_per_second": steps / seconds,
        "compile_and_first_epoch_seconds": compile_seconds,
    }


def native_steps_per_second(name: str, num_envs: int, steps: int, repeats: int, threads: int = 2) -> float:
    """Native MuJoCo through `mujoco.rollout` with `threads` threads, random controls."""
    import mujoco
    from mujoco import rollout

    env = envs_mjx.make(name, render=False)
    model = env.mj_model
    datas = [mujoco.MjData(model) for _ in range(threads)]
    state0 = np.zeros((mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS),))
    mujoco.mj_getState(model, datas[0], state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    nstep = steps * env.n_substeps
    rng = np.random.default_rng(0)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    control = rng.uniform(low, high, size=(num_envs, steps, 1, model.nu)).repeat(env.n_substeps, axis=2)
    control = control.reshape(num_envs, nstep, model.nu)
    initial = np.tile(state0, (num_envs, 1))

    def run():
        rollout.rollout(model, datas, initial, control, nstep=nstep, persistent_pool=True)

    seconds = timed(run, repeats)["warm_seconds"]
    return num_envs * steps / seconds


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench.throughput", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--envs", nargs="+", default=["planar_reach"], choices=envs_mjx.names())
    parser.add_argument("--num-envs", nargs="+", type=int, default=[64, 256, 1024])
    parser.add_argument("--steps", type=int, default=50, help="control periods per timed rollout")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per figure (median)")
    parser.add_argument("--agent", default="proprio_baseline", help="agent of the training-epoch figure")
    parser.add_argument("--skip-train", action="store_true", help="skip the training-epoch figures")
    parser.add_argument("--skip-native", action="store_true", help="skip native MuJoCo")
    parser.add_argument("--json", default="", help="also write the figures to this JSON file")
    parser.add_argument(
        "--devices",
        nargs="+",
        type=int,
        default=None,
        help="instead: training throughput of --seeds seeds of the first env's preset on each of "
        "these device counts (e.g. 1 2 4), with --agent: seeds over devices (and --env-shards), "
        "as a run lays them out",
    )
    parser.add_argument("--seeds", type=int, default=8, help="seeds of the --devices benchmark")
    parser.add_argument(
        "--env-shards",
        type=int,
        default=1,
        help="--devices benchmark: at most this many devices split each seed's envs (as a run's --env-shards)",
    )
    parser.add_argument(
        "--physics", choices=("jax", "warp"), default="jax",
        help="--devices benchmark: the physics engine on every device count (warp: MuJoCo Warp, NVIDIA GPUs)",
    )
    args = parser.parse_args(argv)

    device = jax.devices()[0]
    print(f"device: {device.platform} ({device.device_kind}), {jax.device_count()} device(s)")
    if args.devices:
        scaling(args)
        return
    rows = []
    for name in args.envs:
        for n in args.num_envs:
            row = {"env": name, "num_envs": n}
            row["physics"] = env_steps_per_second(name, n, False, args.steps, args.repeats)
            row["physics+camera"] = env_steps_per_second(name, n, True, args.steps, args.repeats)
            row["camera alone (frames/s)"] = camera_frames_per_second(name, n, args.repeats)
            if not args.skip_train:
                row[f"train epoch ({args.agent})"] = training_steps_per_second(name, args.agent, n, args.repeats)
            if not args.skip_native:
                row["native mujoco.rollout (2 threads)"] = native_steps_per_second(name, n, args.steps, args.repeats)
            rows.append(row)
            print(" ".join(f"{k}={v:.0f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
    columns = list(dict.fromkeys(k for row in rows for k in row))
    print("\n| " + " | ".join(columns) + " |\n|" + " --- |" * len(columns))
    for row in rows:
        print(
            "| "
            + " | ".join(f"{row[c]:,.0f}" if isinstance(row.get(c), float) else str(row.get(c, "")) for c in columns)
            + " |"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": str(device), "rows": rows}, f, indent=2)


def scaling(args: argparse.Namespace) -> None:
    """The --devices benchmark: one row per device count, with the speed-up over the first row."""
    bad = [n for n in args.devices if not 1 <= n <= jax.device_count()]
    if bad:
        raise SystemExit(f"error: --devices {bad[0]}: must be between 1 and the {jax.device_count()} visible device(s)")
    try:
        validate.check_field("env_shards", args.env_shards)
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from err
    rows = []
    for n in args.devices:
        try:
            rows.append(sharded_training(args.envs[0], args.agent, args.seeds, n, args.repeats, args.env_shards,
                                        args.physics))
        except ConfigError as err:  # e.g. --physics warp without NVIDIA GPUs: one line
            raise SystemExit(f"error: {err}") from err
        print(json.dumps(rows[-1]), flush=True)
    base = rows[0]
    print(f"\n{args.envs[0]} {args.agent}, {args.seeds} seeds: training throughput by device count\n")
    print(
        "| devices | env shards per seed | s / epoch | env steps / s (with learning) | speed-up | "
        "scaling efficiency |\n"
        "| --- | --- | --- | --- | --- | --- |"
    )
    for row in rows:
        speedup = row["env_steps_per_second"] / base["env_steps_per_second"]
        print(
            f"| {row['devices']} | {row['env_shards']} | {row['epoch_seconds']:.2f} | "
            f"{row['env_steps_per_second']:,.0f} | {speedup:.2f}× | "
            f"{speedup * base['devices'] / row['devices']:.0%} |"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": str(jax.devices()[0]), "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
