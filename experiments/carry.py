"""Carry a stopped run to another machine or a later process: `python -m experiments.carry --run-dir RUN --out DEST`.

A run that outlasts the machine it trains on (a machine's or a cluster job's time limit) stops with SIGTERM (its epoch
in flight finishes and a checkpoint is saved) and continues elsewhere. Its replay buffer is most of a checkpoint
(841 MB of a 5-seed nicol_slide image run's, against 7-9 MB for all the rest), too much to move or commit, so
this copies what the run needs without it into DEST:

- everything in RUN but its checkpoints (config.json, metrics.csv, tb/);
- its latest checkpoint alone, without its `buffer` item.

DEST continues with `python -m experiments.run --resume --fresh-buffer --run-dir DEST` (the buffer starts empty: a
deviation from the uninterrupted run, recorded in config.json's `fresh_buffer_epochs`); a paper experiment whose
folder holds such a run resumes it so by itself (`experiments.paper.grid`) and names it below its table.

Refused with one `error: ...` line and exit 2, nothing written: a RUN that another process trains (stop it
first), a RUN without a finished checkpoint, a DEST that exists. The copy is made in DEST's sibling
`DEST.carry-tmp` and renamed to DEST when whole, so a disk that fails (exit 4) leaves no partial DEST.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

from bidal_jax.config import ConfigError
from bidal_jax.run import checkpoint, rundir
from bidal_jax.run.checkpoint import CheckpointError
from experiments import cli, report

TMP_SUFFIX = ".carry-tmp"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.carry", description=__doc__.split("\n\n")[0], allow_abbrev=False
    )
    parser.add_argument("--run-dir", required=True, help="the stopped run to carry")
    parser.add_argument("--out", required=True, help="the folder to write (must not exist)")
    return parser


def folder_bytes(path: str) -> int:
    """Bytes of the files under `path`."""
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(path) for f in files)


def finished(run_dir: str) -> bool:
    """Whether the run's metrics.csv reaches the epochs of its config.json (`report.load_run`; False for a folder it
    cannot read as a run, e.g. one without epochs yet)."""
    try:
        run = report.load_run(run_dir)
    except report.RunError:
        return False
    return run["epoch"][-1] >= run["config"]["run"]["epochs"]


def keeps_checkpoint(run_dir: str) -> bool:
    """Whether a results folder keeps the run's latest checkpoint, carried without its buffer: while the run is
    unfinished, so that a later process continues it; and when it is a transfer experiment's finished source
    (`experiments.paper.transfer_learning`: OUT/source) whose transfer arm (OUT/transfer) has not started, since
    that arm starts from the source's parameters (a started arm resumes from its own checkpoint)."""
    if not finished(run_dir):
        return True
    run_dir = os.path.normpath(run_dir)
    arm = os.path.join(os.path.dirname(run_dir), "transfer")
    return os.path.basename(run_dir) == "source" and not os.path.isdir(os.path.join(arm, "checkpoints")) \
        and not finished(arm)


def carry(run_dir: str, dest: str) -> int:
    """Copy `run_dir` into `dest` but for its checkpoints, and its latest checkpoint without the replay buffer;
    the latest checkpoint's epoch. ConfigError / CheckpointError (nothing written) for a run in use, without a
    checkpoint or an existing `dest`; DiskError when a write fails (the partial copy is deleted)."""
    if not os.path.isdir(run_dir):
        raise ConfigError(f"--run-dir {run_dir}: no such directory")
    rundir.check_not_in_use(run_dir)
    directory = os.path.join(run_dir, "checkpoints")
    step = checkpoint.latest_step(directory)
    if step is None:
        raise CheckpointError(f"no checkpoint in {directory}: nothing to resume from")
    if os.path.lexists(dest):
        raise ConfigError(f"--out {dest} exists; name a folder that does not (nothing is overwritten)")
    tmp, latest = dest.rstrip(os.sep) + TMP_SUFFIX, os.path.join(directory, str(step))
    shutil.rmtree(tmp, ignore_errors=True)  # a copy of ours that an earlier failure left
    try:
        with rundir.disk_errors(f"copying {run_dir} to {tmp}", f"{dest} was not written"):
            shutil.copytree(run_dir, tmp, ignore=shutil.ignore_patterns("checkpoints", rundir.LOCK_FILE))
            shutil.copytree(latest, os.path.join(tmp, "checkpoints", str(step)),
                            ignore=lambda where, _: ["buffer"] if where == latest else [])
            os.rename(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return step


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        step = carry(args.run_dir, args.out)
    except (ConfigError, CheckpointError, rundir.DiskError) as err:
        return cli.exit_code(err)
    print(f"carried {args.run_dir} to {args.out}: checkpoint {step} without its replay buffer, "
          f"{rundir.megabytes(folder_bytes(args.out))}\n"
          f"continue it with: python -m experiments.run --resume --fresh-buffer --run-dir {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
