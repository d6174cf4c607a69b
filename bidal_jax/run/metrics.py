"""A run's records: metrics.csv (one row per epoch) and TensorBoard, read and written through `runfiles`.

`epoch_row` turns one epoch's metrics (seed axis first) into a row: the seed means of every
metric, each seed's eval success, env steps and times. `MetricsLog` writes the rows; on
resume it drops the rows written after the checkpoint the run continues from.
"""

from __future__ import annotations

import csv
import importlib
import io
import os
import sys

import numpy as np

from bidal_jax.run.runfiles import number, read_csv, write_atomic


def _import_without_torch(module: str):
    """`module` imported with PyTorch hidden unless it is imported already: tensorboardX imports torch where it is
    installed only to accept torch tensors, which these scalars never are, and that import costs seconds of a run's
    start (docs/performance.md, "The main command")."""
    if "torch" in sys.modules:
        return importlib.import_module(module)
    sys.modules["torch"] = None  # `import torch` raises ImportError while this entry is None
    try:
        return importlib.import_module(module)
    finally:
        del sys.modules["torch"]


SummaryWriter = _import_without_torch("tensorboardX").SummaryWriter


class MetricsLog:
    """metrics.csv (one row per epoch, seed means plus per-seed eval success) and TensorBoard.

    With `resume_epoch`, the rows after that epoch (written after the checkpoint, before
    the run stopped) are dropped from the CSV and purged from TensorBoard; new rows are appended.
    With `writes=False` (every process of a run over several but process 0) nothing is written;
    `last_row` is still the last row up to `resume_epoch`.
    """

    def __init__(self, run_dir: str, resume_epoch: int | None = None, writes: bool = True):
        self.path = os.path.join(run_dir, "metrics.csv")
        self.fields: list[str] | None = None
        self.last_row: dict[str, float] = {}
        self.writer = None
        if resume_epoch is not None and os.path.exists(self.path):
            self._truncate(resume_epoch, writes)
        if writes:
            purge = None if resume_epoch is None else resume_epoch + 1
            self.writer = SummaryWriter(os.path.join(run_dir, "tb"), purge_step=purge)

    def _truncate(self, epoch: int, writes: bool) -> None:
        """Keep the rows up to `epoch` (`runfiles.read_csv`: RunFileError for a damaged file), rewriting the
        file when rows after it, or one cut short by a kill, were there."""
        fields, rows, cut = read_csv(self.path)
        if not fields:
            return
        self.fields = fields
        kept = [r for r in rows if number(self.path, r, "epoch") <= epoch]
        if writes and (cut or len(kept) < len(rows)):
            text = io.StringIO()
            writer = csv.DictWriter(text, self.fields)
            writer.writeheader()
            writer.writerows(kept)
            write_atomic(self.path, text.getvalue())
        self.last_row = {k: number(self.path, r, k) for r in kept[-1:] for k in r}

    def write(self, row: dict[str, float]) -> None:
        self.last_row = row
        if self.writer is None:
            return
        if self.fields is None:
            self.fields = list(row)
            with open(self.path, "w", newline="") as f:
                csv.DictWriter(f, self.fields).writeheader()
        # a run resumed from an older metrics.csv keeps its header: columns newer than it are left out
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.fields, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key != "epoch":
                self.writer.add_scalar(key, value, int(row["epoch"]))
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


PER_SEED = ("eval_success", "train_success")  # the metrics that metrics.csv also keeps seed by seed


def epoch_row(epoch: int, metrics: dict, epoch_seconds: float, steps_before: float, wall: float,
              wall_with_compile: float) -> dict[str, float]:
    """One metrics.csv row: seed means of every metric, per-seed eval and train success (`PER_SEED`), env steps,
    times: `wall_time` (`wall`: seconds of training, from when the programs were built) and `wall_time_with_compile`
    (seconds from when `train` began, building and compiling the programs included), both summed over the run's
    processes."""
    row = {"epoch": epoch}
    for key, value in sorted(metrics.items()):
        row[key] = float(np.mean(value))
    for key in sorted(k for k in metrics if k.startswith(PER_SEED)):  # also the goal subsets' and start kinds'
        for i, value in enumerate(np.atleast_1d(metrics[key])):
            row[f"{key}_seed{i}"] = float(value)
    steps = float(np.sum(metrics["env_steps"]))
    row["env_steps_total"] = steps
    row["wall_time"] = wall
    row["wall_time_with_compile"] = wall_with_compile
    row["env_steps_per_second"] = (steps - steps_before) / max(epoch_seconds, 1e-9)
    return row
