"""Preparing a run: every check before anything is compiled or written, and the run directory's lock.

    with prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make) as prepared:
        row = loop.train(prepared.env, prepared.config, prepared.programs)

`prepare` is one pass, in this order: the run directory not in use (`rundir.check_not_in_use`); the config, resolved
from the values given (`resolve`) or, resuming, the checkpoint's (`resumed_config`: refused where it differs from
config.json or from the options given; the run's files, `runfiles.check_run_files`, and the checkpoint's replay
buffer), checked once (`validate.check`); a new run's directory (never mixed into an existing one; `overwrite`
deletes only what a run writes, `rundir.check_run_dir`); the env, and what it must offer
(`validate.check_env_support`); the run's programs, built once (`loop.make_programs`: its devices and physics engine
too), from whose training state (`jax.eval_shape`) a transfer's source run is checked, and whether it fits in the
device's memory (`memory.check_state`), and so does the least working memory of its epoch beside it, from shapes
alone (`memory.check_floor`: before XLA compiles a program too large to compile; the compiled epoch is checked once
compiled, `memory.check_program`), and one checkpoint of it on the disk (`rundir.check_space`). Then it locks the
run directory (`rundir.lock`, process 0), empties it with `overwrite`, and holds the lock until the `with` block
ends: a second run, resumed run or experiment on it is refused. Errors are one line each: `ConfigError`
(`rundir.RunDirInUse` and `runfiles.RunFileError`, a resumed run's damaged file, among them), `CheckpointError`,
`rundir.DiskError` (no space for one checkpoint, or a resumed run's file that it cannot write), `memory.OutOfMemory`
(a GPU that another process holds has too little free for the run's floor).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
from typing import Any, Callable, Iterable, Iterator, NamedTuple

from bidal_jax.config import Config, ConfigError, ConfigFormatError, option, resolve
from bidal_jax.run import loop, memory, rundir, runfiles, transfer, validate
from bidal_jax.run.checkpoint import CheckpointError, latest_step, read_config, read_metadata

# fields whose value on resume may differ from the checkpoint's: the budget, the place, how the convs are
# computed (the same function and parameters, `NetworkConfig.conv_impl`) and the physics engine (one model)
RESUME_MAY_CHANGE = ("epochs", "run_dir", "conv_impl", "physics")


class Prepared(NamedTuple):
    """A run that passed every check: its config, its env and its programs, each built once."""

    config: Config
    env: Any
    programs: loop.Programs


def _check_config_json(run_dir: str, saved: dict, where: str) -> None:
    """Refuse a checkpoint whose config differs from the run's config.json (one from another run)."""
    try:
        recorded = runfiles.read_json(os.path.join(run_dir, "config.json"))
    except runfiles.RunFileError:
        return  # a missing or damaged copy is rewritten from the checkpoint's config
    # (group, field, saved value, recorded value) of each field that differs, but for those that may change
    differences = [
        (group, field, value, recorded.get(group, {}).get(field))
        for group, values in saved.items()
        for field, value in values.items()
        if field not in RESUME_MAY_CHANGE and recorded.get(group, {}).get(field) != value
    ]
    if differences:
        group, field = differences[0][:2]
        what = {"env": "another env", "agent": "another agent"}.get(field) or (
            "another network shape" if group == "network" else f"another {group} config"
        )
        listed = ", ".join(f"{f} {s!r}" for _, f, s, _ in differences)
        recorded_values = ", ".join(f"{o!r}" for *_, o in differences)
        raise CheckpointError(
            f"{where} was written for {what}: it has {listed} where the run's config.json has {recorded_values}"
        )


def resumed_config(run_dir: str, given: dict[str, Any]) -> Config:
    """The config of the run in `run_dir`: its latest checkpoint's, with `given["epochs"]` if
    given; any other given field that differs from the checkpoint's is refused. Reads only."""
    ckpt_dir = os.path.join(run_dir, "checkpoints")
    if not os.path.isdir(run_dir):
        raise CheckpointError(f"--resume: run directory {run_dir} does not exist")
    step = latest_step(ckpt_dir)
    if step is None:
        raise CheckpointError(f"--resume: no checkpoint in {ckpt_dir} (to start the run again, use --overwrite)")
    where = f"checkpoint {step} in {ckpt_dir}"
    try:
        config = Config.from_dict(read_config(ckpt_dir, step), where)
    except ConfigFormatError as err:
        raise CheckpointError(str(err)) from err
    saved = config.to_dict()  # with the defaults of fields newer than the checkpoint
    _check_config_json(run_dir, saved, where)
    for values in saved.values():
        for field, value in values.items():
            if field in given and field not in RESUME_MAY_CHANGE and given[field] != value:
                raise ConfigError(
                    f"{option(field)} {given[field]} differs from the checkpoint's {value}; "
                    "a resumed run keeps its config (only --epochs, --conv-impl and --physics may change)"
                )
    run = dataclasses.replace(config.run, run_dir=run_dir, epochs=given.get("epochs", config.run.epochs),
                              physics=given.get("physics", config.run.physics))
    if run.epochs < step:
        raise ConfigError(f"--epochs {run.epochs}: must be at least the checkpoint's epoch {step}")
    network = dataclasses.replace(config.network, conv_impl=given.get("conv_impl", config.network.conv_impl))
    return dataclasses.replace(config, run=run, network=network)


def _resumed(given: dict[str, Any], fresh_buffer: bool) -> Config:
    """The config of the run that `given["run_dir"]` holds (`resumed_config`), once its files
    (`runfiles.check_run_files`) and, unless `fresh_buffer` starts an empty one, its checkpoint's replay
    buffer (a CheckpointError saying so when the item is missing) passed."""
    config = resumed_config(given["run_dir"], given)
    runfiles.check_run_files(config.run.run_dir)
    if not fresh_buffer:
        read_metadata(os.path.join(config.run.run_dir, "checkpoints"), names=("buffer",))
    return config


@contextlib.contextmanager
def prepare(
    given: dict[str, Any],
    *,
    env_names: Iterable[str],
    make_env: Callable[..., Any],
    resume: bool = False,
    overwrite: bool = False,
    fresh_buffer: bool = False,
    env: Any = None,
) -> Iterator[Prepared]:
    """The run that `given` (field -> value, e.g. a command line) asks for, after every check, with the
    run directory locked (and emptied with `overwrite`) until the block ends; compiles nothing. `env`:
    the run's env if built already, else `make_env(name, render=...)` builds it. Raises ConfigError or
    CheckpointError (a resumed run's checkpoint without its replay buffer, unless `fresh_buffer` starts
    an empty one).

    With several processes, each checks (the same files: the same outcome) and they wait for
    each other before the block, so that no process writes before every one has checked."""
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite exclude each other: continue the run or delete it")
    if resume and not given.get("run_dir"):
        raise ConfigError("--resume needs --run-dir, the directory of the run to continue")
    if fresh_buffer and not resume:
        raise ConfigError("--fresh-buffer needs --resume: it starts a resumed run's replay buffer empty")
    if given.get("run_dir"):  # a directory in use is refused before any other check names it
        rundir.main_decides(lambda: rundir.check_not_in_use(given["run_dir"]), f"run directory {given['run_dir']}")
    # the config: the values given, or the checkpoint's that a resumed run continues; checked once
    config = _resumed(given, fresh_buffer) if resume else resolve(given)
    validate.check(config, env_names=tuple(env_names))
    if not resume:  # a new run: into a directory of its own (by default one named after it and the time)
        if not config.run.run_dir:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            run_dir = os.path.join("runs", f"{config.run.env}-{config.run.agent}-{stamp}")
            config = dataclasses.replace(config, run=dataclasses.replace(config.run, run_dir=run_dir))
        rundir.check_run_dir(config.run.run_dir, overwrite)
    run = config.run
    # the env and the programs, built once: what the env must offer and whether the state fits (traces init,
    # compiles nothing)
    env = make_env(run.env, render=config.agent.uses_image) if env is None else env
    validate.check_env_support(config.train, env)
    programs = loop.make_programs(env, config)
    state = programs.abstract_state()
    if run.init_from and not resume:  # a resumed run continues its own checkpoint
        transfer.check(config, state, env.observation_spec.proprio_segments, make_env)
    whole = memory.tree_bytes(state)  # every seed's: what a checkpoint holds
    available, seed_devices = memory.device_memory(), len(programs.devices) // programs.shards
    memory.check_state(whole // len(programs.devices), available, run.seeds, resume)
    least = memory.floor(config, env, whole // len(programs.devices), run.seeds // seed_devices, programs.shards)
    memory.check_floor(least, available, config, resume)
    rundir.check_space(run.run_dir, whole)
    with rundir.lock(run.run_dir, resume, overwrite):
        yield Prepared(config, env, programs)
