"""What the commands share: the config's options, starting a run, and the exit codes.

- `task_preset(env, agent)`: a task's preset for an agent, read from its env class's `task` (envs_mjx/task.py);
  `resolve(given)`: a new run's config, the defaults with that preset and `given` laid over them.
- `run_parser()`: `python -m experiments.run`'s options, one per config field (their help is
  the field's documentation), after what the command does, its agents and tasks with their presets
  (`run_description`); the paper experiments pass their extra options through it.
- `start_run(given, ...)`: the one sequence that starts a run: prepare (every check, the env
  and the programs built once, the run directory locked and, when asked, emptied), restore
  another run's parameters when `init_from` asks, train.
- `exit_code(err)`: the one mapping of an error that ends a command to its exit code, after
  its one line on stderr (`failure`: the two without printing, as a grid's cell reports them): 2 bad
  input (an option, config, checkpoint or file, a run file that is damaged, unreadable or of the
  wrong type, an output folder that is missing, a run directory in use, a state or epoch program
  larger than the device's memory); 3 diverged; 4 the disk (no room for a checkpoint, or a write
  failed: no space, quota, read-only file system, I/O error, permission denied); 6 the device ran out
  of memory all the same while the program compiled or trained, or XLA's GPU autotuner had no memory to try
  its kernels in (the last good checkpoint is kept), or a GPU that other processes hold has too little free for
  the run at its start (`memory.share_gpu`);
  130 and 143 stopped by SIGINT and SIGTERM (a checkpoint was saved). 5 is a grid's (a cell whose
  worker died more often than its retries allow: `experiments.cluster`).
- `command(main)`: how every command's `__main__` runs its `main`: Ctrl-C where no run's stop
  handler is installed (while the env is built, a program compiles, episodes are evaluated)
  ends it with one line and exit 130, without a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import os
import signal
import sys
import textwrap
from typing import Any, Callable, Sequence

import envs_mjx
from bidal_jax import config as config_lib
from bidal_jax.config import AGENTS, CONFIG_CLASSES, Config, ConfigError, RunConfig, fields_help, option
from bidal_jax.run import cachefolder, loop, memory, preflight, transfer
from bidal_jax.run.checkpoint import CheckpointError
from bidal_jax.run.guard import EXIT_ON_SIGNAL, Diverged, Interrupted
from bidal_jax.run.memory import OutOfMemory
from bidal_jax.run.rundir import DiskError

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_DISK = 4
EXIT_MEMORY = 6  # (5: a grid's cell lost, `experiments.cluster.EXIT_LOST`)
# what ends a command that trains: bad input, a diverged run, the disk, the device's memory, a stop signal
FAILURES = (ConfigError, CheckpointError, Diverged, DiskError, OutOfMemory, Interrupted)
# anything else: EXIT_BAD_INPUT
EXIT_CODES = ((Diverged, EXIT_DIVERGED), (DiskError, EXIT_DISK), (OutOfMemory, EXIT_MEMORY))


def failure(err: Exception, resume_hint: str = "run the same command again to continue") -> tuple[int, str]:
    """(exit code, one line) of an error that ends a command: a stop signal's (its checkpoint saved;
    `resume_hint` says how to continue, "{run_dir}" standing for the run's directory), else "error: ..." and the
    code of `EXIT_CODES`, or 2 (bad input)."""
    if isinstance(err, Interrupted):
        return err.exit_code, f"{err}; {resume_hint.format(run_dir=err.run_dir)}"
    return next((code for kind, code in EXIT_CODES if isinstance(err, kind)), EXIT_BAD_INPUT), f"error: {err}"


def exit_code(err: Exception, resume_hint: str = "run the same command again to continue") -> int:
    """Print the one line of an error that ends a command on stderr and return its exit code (`failure`)."""
    code, line = failure(err, resume_hint)
    print(line, file=sys.stderr)
    return code


def command(main: Callable[[], int]) -> int:
    """`main()`'s exit code; a KeyboardInterrupt (Ctrl-C outside a run's `guard.StopSignals`, which saves a
    checkpoint instead) is one line on stderr and `EXIT_ON_SIGNAL[SIGINT]` (130), without a traceback.

    The objects alive when `main` ends are then frozen (`gc.freeze`): the process is about to exit, and the
    interpreter's last garbage collection over the millions of objects of JAX, MuJoCo and Orbax would lengthen every
    command's exit (docs/performance.md, "The main command"). Exit handlers still run and files still close."""
    try:
        return main()
    except KeyboardInterrupt:
        print("\nstopped by Ctrl-C (SIGINT)", file=sys.stderr)
        return EXIT_ON_SIGNAL[signal.SIGINT]
    finally:
        gc.freeze()


def _bool(text: str) -> bool:
    if text.lower() not in ("1", "true", "yes", "0", "false", "no"):
        raise argparse.ArgumentTypeError(f"{text!r}: must be true or false")
    return text.lower() in ("1", "true", "yes")


def choices() -> dict[str, tuple[str, ...]]:
    """The names that --env and --agent take: the registered tasks and agents."""
    return {"env": envs_mjx.names(), "agent": tuple(AGENTS)}


def task_preset(env: str, agent: str) -> dict[str, dict[str, Any]]:
    """The preset of task `env` for `agent` ({"run"|"train"|"network": {field: value}}): the env's `task.presets`,
    and its `task.image_presets` over them for an agent that learns from images (envs_mjx/task.py); none for a name
    that is not registered (the checks refuse it, `validate.check`)."""
    if env not in envs_mjx.names():
        return {}
    task = envs_mjx.task(env)
    preset = {group: dict(values) for group, values in task.presets.items()}
    if agent in AGENTS and AGENTS[agent].uses_image:
        for group, values in task.image_presets.items():
            preset[group] = {**preset.get(group, {}), **values}
    return preset


def resolve(given: dict[str, Any]) -> Config:
    """The config of a new run (`bidal_jax.config.resolve`): defaults, then its task's preset for its agent
    (`task_preset`), then `given`."""
    return config_lib.resolve(given, task_preset)


def preset_fields() -> frozenset[str]:
    """The config fields that some task's preset sets, for some agent: their default is the preset's."""
    names = choices()
    return frozenset(field for env in names["env"] for agent in names["agent"]
                     for values in task_preset(env, agent).values() for field in values)


def task_line(env: str) -> str:
    """One task's preset in a line: the default agent's epochs and what an epoch holds, and the agents whose
    epochs differ: "planar_reach       20 epochs of 160 episodes, 400 updates (proprio_baseline 40)"."""
    configs = {agent: resolve({"env": env, "agent": agent}) for agent in choices()["agent"]}
    run, train = configs[RunConfig.agent].run, configs[RunConfig.agent].train
    others = ", ".join(f"{agent} {c.run.epochs}" for agent, c in configs.items() if c.run.epochs != run.epochs)
    return (f"  {env:<19}{run.epochs} epochs of {train.cycles_per_epoch * train.num_envs:,} episodes, "
            f"{train.cycles_per_epoch * train.updates_per_cycle:,} updates" + (f" ({others})" if others else ""))


def run_description() -> str:
    """What `python -m experiments.run` does, its agents and tasks, and the presets, before its options: what a
    newcomer reads first."""
    names = choices()
    agents = ", ".join(f"{a} (the default)" if a == RunConfig.agent else a for a in names["agent"])
    return "\n".join([
        *textwrap.wrap("Train an agent on a task: DDPG + HER, and for the *_bidal agents BidAL's forward and "
                       "inverse models and their intrinsic reward. A run writes config.json, metrics.csv, "
                       "TensorBoard logs and checkpoints into --run-dir.", 78),
        "",
        *textwrap.wrap(f"agents (--agent): {agents}", 78, subsequent_indent="  "),
        f"tasks (--env), each with a preset of epochs and sizes ({RunConfig.agent}'s):",
        *(task_line(env) for env in names["env"]),
        *textwrap.wrap("A task's preset overrides the defaults below, and the options given override the "
                       "preset (its env class's `task`, envs_mjx/); --print-config prints the resolved config "
                       "without training.", 78),
    ])


def run_parser() -> argparse.ArgumentParser:
    """Options from the config dataclasses; defaults (with the env presets) are resolved after parsing. The help
    leads with what the command does, its agents and tasks and the presets (`run_description`), the options after
    them."""
    parser = argparse.ArgumentParser(prog="python -m experiments.run", usage="%(prog)s [options]",
                                     description=run_description(),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    preset, names = preset_fields(), choices()
    for group_name, cls in CONFIG_CLASSES.items():
        group = parser.add_argument_group(f"{group_name} options")
        helps = fields_help(cls)
        for f in dataclasses.fields(cls):
            kind = _bool if type(f.default) is bool else type(f.default)
            listed = f"; one of: {', '.join(names[f.name])}" if f.name in names else ""
            default = f"the task's preset, else {f.default!r}" if f.name in preset else repr(f.default)
            # None marks "not given", so that presets apply; the help shows the config default once
            group.add_argument(option(f.name), type=kind, default=None, metavar=f.name.upper(),
                               help=f"{helps[f.name]}{listed} (default: {default})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --run-dir from its latest checkpoint, with its saved config "
                        "(only --epochs, --conv-impl and --physics may change)")
    parser.add_argument("--fresh-buffer", action="store_true",
                        help="with --resume: restore all but the replay buffer, which starts empty (a checkpoint "
                        "carried without its buffer item); recorded in config.json's fresh_buffer_epochs")
    parser.add_argument("--overwrite", action="store_true",
                        help="delete a non-empty --run-dir first (after every check passed)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the effective config (presets applied) as JSON and exit")
    return parser


def parse_names(text: str, flag: str, kind: str, allowed: Sequence[str]) -> tuple[str, ...]:
    """The names of a comma list option (`--tasks a,b`), in the order given; ConfigError naming
    one that is not allowed, or an empty list."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    for name in names:
        if name not in allowed:
            raise ConfigError(f"{flag} {text}: unknown {kind} {name!r}; allowed: {', '.join(allowed)}")
    if not names:
        raise ConfigError(f"{flag} {text!r}: name at least one of {', '.join(allowed)}")
    return tuple(dict.fromkeys(names))


def start_run(
    given: dict[str, Any], *, resume: bool = False, overwrite: bool = False, quiet: bool = False, env: Any = None,
    initialize: Callable[[Any], Any] | None = None, fresh_buffer: bool = False,
) -> tuple[Config, dict[str, float]]:
    """Prepare the run `given` asks for (every check; its directory locked, and emptied with
    `overwrite`), then train it: (its config, its last metrics row). `env` defaults to one made for
    the run's agent; `initialize` (see `loop.build`) to the transfer that `init_from` asks for;
    `fresh_buffer` resumes with an empty replay buffer. The program compiles into the persistent cache
    (`cachefolder.enable`; a folder that cannot be written is one warning line, and the run goes on without it),
    so that a resumed or repeated run of a config skips XLA's compile, with one source location per operation
    (`loop.short_source_locations`). Where other processes hold its GPU, JAX takes what is free of it
    (`memory.share_gpu`, before JAX starts on the GPU: a no-op once it has). Raises what `FAILURES` names."""
    memory.share_gpu()
    cachefolder.enable()  # before anything compiles: JAX reads the setting at its first compile
    loop.short_source_locations()  # before anything is lowered
    with preflight.prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make, preset=task_preset,
                           resume=resume, overwrite=overwrite, fresh_buffer=fresh_buffer, env=env) as prepared:
        config, env = prepared.config, prepared.env
        if initialize is None and config.run.init_from:  # another run's parameters (ignored on resume)
            initialize = transfer.make_initializer(config.run, env.observation_spec.proprio_segments, envs_mjx.make)
        return config, loop.train(env, config, quiet=quiet, resume=resume, initialize=initialize,
                                  fresh_buffer=fresh_buffer, programs=prepared.programs)


def print_summary(run: RunConfig, row: dict[str, float]) -> None:
    """The final eval success of a run and where its metrics, TensorBoard logs and checkpoints are."""
    if not row:
        print(f"nothing to train: the run is at epoch {run.epochs} already (raise --epochs to continue)")
        return
    seeds = ", ".join(f"{row[k]:.3f}" for k in row if k.startswith("eval_success_seed"))
    print(
        f"final eval success {row['eval_success']:.3f} (seeds: {seeds}) after {int(row['epoch'])} epochs, "
        f"{row['env_steps_total']:.0f} env steps, {row['wall_time']:.0f} s\n"
        f"metrics: {os.path.join(run.run_dir, 'metrics.csv')}\n"
        f"tensorboard: tensorboard --logdir {os.path.join(run.run_dir, 'tb')}\n"
        f"checkpoint: {os.path.join(run.run_dir, 'checkpoints')}"
    )
