"""Where a run's seeds and env shards live: devices, meshes and shardings (`jax.sharding`).

Seeds are a `vmap` of `train.make_train`'s `init` and `epoch`, their leading axis split over
devices (`SEED_AXIS`); devices the seeds leave over split each seed's envs (`ENV_AXIS`, a
`shard_map` whose collectives `train.Shards` traces). `device_layout` picks the devices and
the number of env shards, `make_seeded` compiles the seeds as one program over them, and
`seed_sharding` says where a training state lives for `jax.device_put` (a restored checkpoint,
a transferred state). With several processes the seeds span every process's devices.
`physics_engine` is the engine those devices step an env's physics on (MuJoCo Warp on NVIDIA GPUs,
else MJX-JAX) and `use_physics` sets it, sized for one device's worlds (`physics_worlds`).
"""

from __future__ import annotations

import functools
import importlib.util
import math
from typing import Any, Callable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from bidal_jax import replay
from bidal_jax.config import Config, ConfigError, TrainConfig
from bidal_jax.train import ENV_AXIS, SEED_AXIS, TrainState


def seed_devices(seeds: int, devices: Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The devices that `seeds` vmapped seeds are spread over: of each process's `devices` (default:
    all, of every process), as many as divide that process's share of the seeds evenly (one process
    with 4 GPUs: 8 seeds on 4, 6 on 2, 1 seed on 1; two with 2 devices each: 4 seeds on 2 + 2).
    Raises ConfigError when the processes cannot hold equal shares."""
    owned = _by_process(devices)
    if seeds % len(owned):
        raise ConfigError(
            f"--seeds {seeds}: must be a multiple of the {len(owned)} processes (each holds as many seeds)"
        )
    per_process = math.gcd(seeds // len(owned), min(len(own) for own in owned))
    return [d for own in owned for d in own[:per_process]]


def _by_process(devices: Sequence[jax.Device] | None) -> list[list[jax.Device]]:
    """`devices` (default: all, of every process) grouped by process, in process order."""
    devices = list(jax.devices() if devices is None else devices)
    return [[d for d in devices if d.process_index == p] for p in sorted({d.process_index for d in devices})]


def device_layout(
    seeds: int, config: TrainConfig, max_shards: int = 1, devices: Sequence[jax.Device] | None = None
) -> tuple[list, int]:
    """(the devices of a run, its env shards k): `seed_devices` hold the seeds, and each seed
    device's process lends it, of the devices left over, the most (k - 1, k ≤ `max_shards`)
    such that k divides the envs, evaluation envs and the batch's runs (k = 1 with observation noise, see
    `make_train`). The devices come seed device by seed device, each followed by its shards'
    others. One process with 4 devices, 16 envs, `max_shards` 4: 1 seed on 4 × 4 shards,
    2 seeds on 2 × 2, 4 on 4 × 1; with 6 envs, 1 seed on 2 × 2."""
    owned = _by_process(devices)
    per_process = len(seed_devices(seeds, devices)) // len(owned)
    spare = min(min(len(own) for own in owned) // per_process, max_shards)
    divisor = 1 if config.noise_segments else math.gcd(config.num_envs, config.eval_envs,
                                                             config.batch_size // config.sample_run)
    shards = max(k for k in range(1, spare + 1) if divisor % k == 0)
    return [d for own in owned for d in own[: per_process * shards]], shards


def _mesh(devices: Sequence[jax.Device], shards: int) -> Mesh:
    return Mesh(np.array(devices).reshape(-1, shards), (SEED_AXIS, ENV_AXIS))


def _state_specs() -> TrainState:
    """The mesh axes of a TrainState[S]'s leaves (a pytree prefix): the seed axis everywhere, and
    the replay buffer's episodes also split over the env shards (each shard keeps its own)."""
    seed = P(SEED_AXIS)
    return TrainState(
        params=seed,
        target_params=seed,
        opt_state=seed,
        proprio_norm=seed,
        goal_norm=seed,
        buffer=replay.ReplayState(episodes=P(SEED_AXIS, ENV_AXIS), position=seed, size=seed),
        key=seed,
        eval_key=seed,
        noise=seed,
        env_steps=seed,
        updates=seed,
        epoch=seed,
    )


def seed_sharding(devices: Sequence[jax.Device], shards: int = 1) -> Any:
    """Where a TrainState[S] (or any seed-leading pytree, on one device) lives on `devices`, for
    `jax.device_put`: on one device, every leaf's leading (seed) axis on a 1-D mesh named "seeds";
    on several, the state's leaves on the [seeds, envs] mesh (`_state_specs`, envs of size `shards`)."""
    if len(devices) == 1:
        return NamedSharding(Mesh(np.array(devices), (SEED_AXIS,)), P(SEED_AXIS))
    mesh = _mesh(devices, shards)
    return jax.tree.map(lambda spec: NamedSharding(mesh, spec), _state_specs(), is_leaf=lambda x: isinstance(x, P))


def over_seeds(fn: Callable) -> Callable:
    """`fn` mapped over the leading seed axis of its arguments and results: `jax.vmap(fn)`, except that an axis of
    one seed runs `fn` on its only row. Same maths and random draws, but XLA compiles a vmap's size-1 batch axis
    into slower code, which also takes longer to compile (docs/performance.md, "The main command"). Its floats round
    otherwise than in the vmapped program, so a one-seed run is not bitwise the one before."""
    vmapped = jax.vmap(fn)

    def mapped(*args):
        if jax.tree.leaves(args)[0].shape[0] != 1:
            return vmapped(*args)
        return jax.tree.map(lambda x: x[None], fn(*jax.tree.map(lambda x: x[0], args)))

    return mapped


def make_seeded(init: Callable, epoch: Callable, devices: Sequence[jax.Device] | None = None, shards: int = 1):
    """Seeds as one vmapped, jitted program: `init(keys[S]) -> TrainState[S]`, `epoch`.

    On one device (the default: the first) the program is the seeds' `over_seeds` map. On several,
    `devices` form a [seed devices, k] mesh (k = `shards`, with `init` and `epoch` from
    `make_train(..., env_shards=k)`) and the program is a `shard_map` over it: each device runs its
    S / (len(devices) / k) seeds' program on its 1 / k of their envs, with no communication between
    seeds. Each device's program is written out rather than left to JAX's SPMD partitioner, so that
    custom calls without a partitioning rule (MuJoCo Warp's physics) step each device's own envs.
    """
    devices = jax.devices()[:1] if devices is None else devices
    if len(devices) == 1:
        sharding = seed_sharding(devices)
        return (
            jax.jit(over_seeds(init), in_shardings=sharding, out_shardings=sharding),
            jax.jit(over_seeds(epoch), in_shardings=sharding, out_shardings=sharding, donate_argnums=0),
        )
    # no vma type check: MJX's loops carry env state that starts replicated (zeros) and becomes
    # shard-varying; what leaves the program replicated is averaged or gathered (`make_train`)
    mesh, specs, state = _mesh(devices, shards), _state_specs(), seed_sharding(devices, shards)
    sharded, seeds = functools.partial(jax.shard_map, mesh=mesh, check_vma=False), NamedSharding(mesh, P(SEED_AXIS))
    return (
        jax.jit(sharded(over_seeds(init), in_specs=P(SEED_AXIS), out_specs=specs), in_shardings=seeds,
                out_shardings=state),
        jax.jit(sharded(over_seeds(epoch), in_specs=(specs,), out_specs=(specs, P(SEED_AXIS))), in_shardings=(state,),
                out_shardings=(state, seeds), donate_argnums=0),
    )


# ----- the physics engine the devices step ----------------------------------------------------------


def physics_engine(choice: str, devices: list) -> str:
    """The engine of a run of `RunConfig.physics` `choice` laid out on `devices`: "warp" (MuJoCo Warp) needs NVIDIA
    GPUs and the warp-lang package, "auto" is warp where both hold and "jax" (MJX) elsewhere. On several devices each
    steps its own envs' Warp physics (`devices.make_seeded`). ConfigError for warp where it cannot run."""
    if choice == "jax":
        return "jax"
    problem = warp_problem(devices)
    if problem is None:
        return "warp"
    if choice == "auto":
        return "jax"
    raise ConfigError(f"--physics warp needs NVIDIA GPUs and warp-lang: {problem}; allowed here: jax, auto")


def warp_problem(devices: list) -> str | None:
    """Why MuJoCo Warp cannot step a run laid out on `devices`, or None where it can."""
    platforms = sorted({d.platform for d in devices})
    if platforms != ["gpu"]:
        return f"this run lays out {len(devices)} {'/'.join(platforms)} device(s)"
    if importlib.util.find_spec("warp") is None:
        return "the warp-lang package is not installed (pip install 'bidal-jax[warp]')"
    return None


def physics_worlds(seeds: int, train, devices: int = 1, shards: int = 1) -> int:
    """The most envs one device steps at once in a program of `seeds` seeds and the `TrainConfig` `train` laid out
    on `devices` devices with `shards` env shards (`devices.device_layout`), the worlds Warp's contact buffer is
    sized for: each seed device's seeds × the wider of its shard of the training and evaluation envs."""
    return seeds // (devices // shards) * (max(train.num_envs, train.eval_envs) // shards)


def use_physics(env, config: Config, devices: list, shards: int) -> None:
    """Step `env` on the engine of `config.run.physics` (`physics_engine`) for the worlds of one device of the run laid
    out on `devices` with `shards` env shards (`physics_worlds`)."""
    run = config.run
    env.use_backend(physics_engine(run.physics, devices),
                    worlds=physics_worlds(run.seeds, config.train, len(devices), shards))
