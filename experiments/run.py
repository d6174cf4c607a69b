"""Train an agent on a task: `python -m experiments.run --env ur5_reach`.

Every field of the run, learner and network configs is an option (`--help` lists them
with their documentation, the valid envs and agents). Per-epoch metrics go to
`<run-dir>/metrics.csv` and TensorBoard (`<run-dir>/tb`); Orbax checkpoints of the whole
training state go to `<run-dir>/checkpoints` every K epochs and at the end (the latest two
and the best by eval success are kept). The loop, its checks and its outputs live in
`bidal_jax.loop`; this module is only the command line.

- `--resume` continues the run in `--run-dir` from its latest checkpoint with the
  checkpoint's config; only `--epochs` (not below the checkpoint's epoch), `--run-dir`
  and `--quiet` may be given with other values.
- Ctrl-C (SIGINT) or SIGTERM lets the epoch in flight finish, saves a checkpoint and
  exits; a second signal exits at once.
- A non-empty run directory is only continued (`--resume`) or deleted first
  (`--overwrite`, only once every check passed, and only if it holds nothing but what
  a run writes). A training state larger than the device's memory is refused, and so is
  one whose checkpoint the run directory's disk has no room for.
- One run at a time in a run directory: a run holds a lock on `<run-dir>/.lock` (host and
  PID inside) while it lives; another run, `--resume` or experiment on it is refused.
- Several processes (one per host) train one run together when the environment launches
  them: `JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID`, or a SLURM or
  Open MPI launch of several tasks (`bidal_jax.multihost`; README "Several hosts").

Exit codes: 0 done; 2 bad command line, config or checkpoint, or a run directory in use
by another run (one `error: ...` line on stderr, nothing written); 3 diverged; 4 the
disk: no room for one checkpoint at start (nothing written), or a write failed (no space,
quota, read-only file system, I/O error; the unfinished checkpoint is deleted, the last
good one is kept); 130 stopped by SIGINT, 143 by SIGTERM (a checkpoint was saved).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import envs_mjx
from bidal_jax import config as config_lib, loop, multihost, rundir, transfer
from bidal_jax.checkpoint import CheckpointError
from bidal_jax.config import AGENTS, CONFIG_CLASSES, fields_help
from bidal_jax.validate import ConfigError, option

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_DISK = 4
CHOICES = {"env": envs_mjx.names(), "agent": tuple(AGENTS)}


def _bool(text: str) -> bool:
    if text.lower() not in ("1", "true", "yes", "0", "false", "no"):
        raise argparse.ArgumentTypeError(f"{text!r}: must be true or false")
    return text.lower() in ("1", "true", "yes")


def build_parser() -> argparse.ArgumentParser:
    """Options from the config dataclasses; defaults (with the env presets) are resolved after parsing."""
    parser = argparse.ArgumentParser(
        prog="python -m experiments.run",
        description="Train DDPG + HER (+ BidAL forward/inverse models) on an MJX task. Envs: "
        + ", ".join(CHOICES["env"]) + ". Agents: " + ", ".join(CHOICES["agent"]) + ".",
        epilog="Defaults are the config's; the env presets of bidal_jax/config.py override some of them "
        "(--print-config shows the values a run would use).",
    )
    for group_name, cls in CONFIG_CLASSES.items():
        group = parser.add_argument_group(f"{group_name} options")
        helps = fields_help(cls)
        for f in dataclasses.fields(cls):
            kind = _bool if type(f.default) is bool else type(f.default)
            choices = CHOICES.get(f.name)
            listed = f"; one of: {', '.join(choices)}" if choices else ""
            # None marks "not given", so that presets apply; the help shows the config default once
            group.add_argument(option(f.name), type=kind, default=None, metavar=f.name.upper(),
                               help=f"{helps[f.name]}{listed} (default: {f.default!r})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --run-dir from its latest checkpoint, with its saved config "
                        "(only --epochs may change)")
    parser.add_argument("--overwrite", action="store_true", help="delete a non-empty --run-dir first (after every check passed)")
    parser.add_argument("--print-config", action="store_true", help="print the effective config (presets applied) as JSON and exit")
    return parser


def print_summary(run, row: dict[str, float]) -> None:
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


def _error(message: object, code: int) -> int:
    print(f"error: {message}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    given = {k: v for k, v in vars(args).items() if v is not None}
    try:
        multihost.initialize()  # several processes, when the environment launched them (README "Several hosts")
        if args.print_config:
            configs = config_lib.resolve(given)
            if args.resume and args.run_dir:
                configs = loop.resumed_configs(args.run_dir, given)
            print(json.dumps(config_lib.to_dict(*configs), indent=2))
            return 0
        run, train_cfg, net = loop.prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make,
                                           resume=args.resume, overwrite=args.overwrite)
    except (ConfigError, CheckpointError) as err:
        return _error(err, EXIT_BAD_INPUT)
    except rundir.DiskError as err:
        return _error(err, EXIT_DISK)
    if args.overwrite:
        loop.delete_run_dir(run.run_dir)
    loop.enable_compilation_cache()
    env = envs_mjx.make(run.env, render=config_lib.agent_spec(run.agent).uses_image)
    # a run with --init-from starts from another run's parameters (ignored on --resume)
    segments = env.observation_spec.proprio_segments
    initialize = transfer.make_initializer(run, segments, envs_mjx.make) if run.init_from else None
    try:
        row = loop.train(env, run, train_cfg, net, quiet=args.quiet, resume=args.resume, initialize=initialize)
    except CheckpointError as err:
        return _error(err, EXIT_BAD_INPUT)
    except loop.Diverged as err:
        return _error(err, EXIT_DIVERGED)
    except rundir.DiskError as err:
        return _error(err, EXIT_DISK)
    except loop.Interrupted as stop:
        print(f"{stop}; continue with --resume --run-dir {run.run_dir}", file=sys.stderr)
        return stop.exit_code
    print_summary(run, row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
