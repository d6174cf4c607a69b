"""The training program of an env's preset, laid out as a run lays it out: the benchmarks' shared start.

`seeded_program(env, agent, seeds, ...)` builds the env (`make_env`: on MJX's JAX or MuJoCo Warp
physics, by default the preset's choice), the preset config (`experiments.cli.resolve`, with any `TrainConfig`
overrides), the device layout (`bidal_jax.run.devices.device_layout`) and the seeds' one compiled program
(`make_seeded`), as `python -m experiments.run` would. `parse_variant` reads the overrides of a benchmark's
`--variant` (`a=1,net.hidden_size=256,opt.iterations=5`); `timed` times a blocking call cold and warm.
"""

from __future__ import annotations

import dataclasses
import re
import statistics
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

import envs_mjx
from bidal_jax import replay
from bidal_jax.config import Config, NetworkConfig, TrainConfig
from bidal_jax.run import validate
from bidal_jax.run.devices import device_layout, make_seeded, physics_engine, physics_worlds
from bidal_jax.train import make_train
from experiments import cli


class SeededProgram(NamedTuple):
    """`make_seeded`'s init and epoch, with what they were built from and laid out on."""
    init: Callable
    epoch: Callable
    config: TrainConfig
    env: Any
    devices: list
    shards: int


def make_env(name: str, backend: str, worlds: int, render: bool, options: dict | None = None):
    """The env `name` stepping its physics with `backend` ("jax" or "warp"), sized for `worlds` envs at once,
    with the physics `options` (`Env.set_options`) overriding its model's."""
    env = envs_mjx.make(name, render=render)
    if options:
        env.set_options(**options)
    if backend != "jax":
        env.use_backend(backend, worlds=worlds)
    return env


def program_config(name: str, agent: str, train: dict | None = None, network: dict | None = None) -> Config:
    """The preset config of `agent` on the env `name` with the `TrainConfig` overrides `train` and `NetworkConfig`
    overrides `network`, checked as a run checks its config (`validate.check`: ConfigError, one line)."""
    preset = cli.resolve({"env": name, "agent": agent})
    config = dataclasses.replace(preset, train=dataclasses.replace(preset.train, **(train or {})),
                                 network=dataclasses.replace(preset.network, **(network or {})))
    validate.check(config, env_names=envs_mjx.names())
    return config


def parse_variant(text: str) -> tuple[dict, dict, dict]:
    """(TrainConfig overrides, NetworkConfig overrides, physics options) of a variant: `preset` -> ({}, {}, {});
    `a=1,b=2.5,net.hidden_size=256,opt.iterations=5` -> ({"a": 1, "b": 2.5}, {"hidden_size": 256},
    {"iterations": "5"}), the overrides typed as the fields are; `opt.NAME` entries override the model's physics
    options (`envs_mjx.base.Env.set_options`)."""
    train, network, options = {}, {}, {}
    if text == "preset":
        return train, network, options
    groups = {"": (TrainConfig, train), "net.": (NetworkConfig, network)}
    for item in re.split(r",(?=[A-Za-z_.]+=)", text):  # a comma starts an item only before NAME=, so values
        # may hold commas (net.conv_strides=2,2,1,1)
        name, _, value = item.partition("=")
        if name.startswith("opt."):
            options[name[4:]] = value  # converted and checked by Env.set_options
            continue
        prefix = "net." if name.startswith("net.") else ""
        group, into = groups[prefix]
        fields = {f.name: f.type for f in dataclasses.fields(group)}
        field = name[len(prefix):]
        if field not in fields:
            raise SystemExit(f"error: --variant {text}: {name!r} is not a TrainConfig field, net.NAME of a "
                             "NetworkConfig field nor opt.NAME")
        kind = {"int": int, "float": float, "str": str}.get(str(fields[field]), float)
        into[field] = kind(value)
    return train, network, options


def seeded_program(
    name: str, agent: str, seeds: int, n_devices: int = 1, env_shards: int = 1, backend: str = "preset",
    train: dict | None = None, options: dict | None = None, network: dict | None = None,
) -> SeededProgram:
    """The training program of `seeds` vmapped seeds of the env's preset for `agent` (with the
    `TrainConfig` overrides `train` and `NetworkConfig` overrides `network`) on the first `n_devices` devices,
    laid out as a run lays them out (`devices.device_layout`), its env's physics on `backend` (jax, warp, auto,
    or the preset's `RunConfig.physics`; `devices.physics_engine`) with the physics `options`."""
    config = program_config(name, agent, train, network)
    devices, shards = device_layout(seeds, config.train, env_shards, jax.devices()[:n_devices])
    engine = physics_engine(config.run.physics if backend == "preset" else backend, devices)
    env = make_env(name, engine, physics_worlds(seeds, config.train, len(devices), shards),
                   render=config.agent.uses_image, options=options)
    init, epoch = make_seeded(*make_train(env, config, shards), devices, shards)
    return SeededProgram(init, epoch, config.train, env, devices, shards)


def full_buffer(ts):
    """`ts` with its replay buffer counted as full: batches are drawn from every slot (the update benches')."""
    return ts.replace(buffer=ts.buffer.replace(size=jnp.asarray(replay.capacity(ts.buffer), jnp.int32)))


def timed(fn, repeats: int) -> dict[str, float]:
    """`fn()` (blocking) once cold, then the median of `repeats` runs."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return {"first_call_seconds": first, "warm_seconds": statistics.median(times)}
