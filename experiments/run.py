"""Train an agent on a task: `python -m experiments.run --env ur5_reach`.

Every field of the run, learner and network configs is an option (`--help` opens with the
tasks, their presets and the agents, then lists the options with their documentation). Per-epoch metrics go to
`<run-dir>/metrics.csv` and TensorBoard (`<run-dir>/tb`); Orbax checkpoints of the whole
training state go to `<run-dir>/checkpoints` every K epochs and at the end (the latest two
and the best by eval success are kept). The checks live in `bidal_jax.run.preflight`, the
loop and its outputs in `bidal_jax.run.loop`, the options and the start of a run in
`experiments/cli.py`; this module is only the command line.

- `--resume` continues the run in `--run-dir` from its latest checkpoint with the
  checkpoint's config; only `--epochs` (not below the checkpoint's epoch), `--run-dir`,
  `--conv-impl`, `--physics` and `--quiet` may be given with other values. `--resume --fresh-buffer` restores all
  but the replay buffer, which starts empty (a checkpoint carried without its `buffer` item; a deviation
  from the uninterrupted run, recorded in config.json's `fresh_buffer_epochs`).
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
  Open MPI launch of several tasks (`bidal_jax.run.multihost`; docs/usage.md "Several hosts").

Exit codes (`cli.exit_code`): 0 done; 2 bad command line, config or checkpoint, or a run directory in use
by another run (one `error: ...` line on stderr, nothing written); 3 diverged; 4 the
disk: no room for one checkpoint at start (nothing written), or a write failed (no space,
quota, read-only file system, I/O error, permission denied; the unfinished checkpoint is deleted, the last
good one is kept); 6 out of device memory (while compiling or in an epoch, or XLA's GPU autotuner without memory
to try its kernels in: the last good checkpoint is kept; or a GPU that other processes hold with too little free
for the run); 130 stopped by SIGINT, 143 by SIGTERM (a checkpoint was saved; Ctrl-C before training
starts: nothing saved). Sizes too large for the device are refused with 2, from their shapes before anything
compiles (`bidal_jax.run.memory`). A resumed run's metrics.csv that is damaged or a folder is refused with 2, one
it cannot write with 4, before compiling. docs/usage.md lists every command's exit codes.
"""

from __future__ import annotations

import json
import sys

from bidal_jax.config import resolve
from bidal_jax.run import multihost, preflight
from experiments import cli


def main(argv: list[str] | None = None) -> int:
    args = cli.run_parser().parse_args(argv)
    given = {k: v for k, v in vars(args).items() if v is not None}
    try:
        multihost.initialize()  # several processes, when the environment launched them (docs/usage.md)
        if args.print_config:
            config = resolve(given)
            if args.resume and args.run_dir:
                config = preflight.resumed_config(args.run_dir, given)
            print(json.dumps(config.to_dict(), indent=2))
            return 0
        config, row = cli.start_run(given, resume=args.resume, overwrite=args.overwrite, quiet=args.quiet,
                                    fresh_buffer=args.fresh_buffer)
    except cli.FAILURES as err:
        return cli.exit_code(err, "continue with --resume --run-dir {run_dir}")
    cli.print_summary(config.run, row)
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
