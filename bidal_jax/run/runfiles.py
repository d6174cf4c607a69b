"""A run's files read one way and written one way, so that damage or a failed write ends a command in one line.

Reading (config.json, metrics.csv; every command that reads run folders comes here, through
`experiments.report.load_run`, `loop` and `preflight`): `read_json(path)` and `read_csv(path)` turn
a file that is missing, of the wrong type (a directory), unreadable (permissions, I/O), binary
(NUL bytes, not UTF-8) or malformed into `RunFileError`, a `ConfigError` (exit 2) whose one line
names the file and what is wrong with it. `check_run_files(run_dir)`: a resumed run's files read and can be
written, before anything is compiled (`preflight.prepare`).

Writing: `write_atomic(path, text)` writes through `PATH.tmp` and deletes it when the write fails, so a
failure leaves no temporary file that refuses the same command again ("exists and is not empty");
`rundir.disk_errors` and `rundir.writing` map the disk and permission failures of every writer to one
`DiskError` line (exit 4). `check_output_dir(directory, flag)` refuses a command's output folder that is
missing or not writable before any work is done (exit 2). `close_quietly(*closers)` closes what an error
on its way out leaves open, its own errors dropped: a cleanup never masks the first error.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
from typing import Any, Callable

from bidal_jax.config import ConfigError
from bidal_jax.run.rundir import DiskError

TMP_SUFFIX = ".tmp"


class RunFileError(ConfigError):
    """A run file that cannot be read: missing, of the wrong type, unreadable or damaged; one line naming it."""


def read_text(path: str) -> str:
    """The UTF-8 text of the file `path`; RunFileError for a missing, non-regular, unreadable or binary file."""
    if os.path.isdir(path):
        raise RunFileError(f"{path}: is a directory, not a file")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise RunFileError(f"{path}: no such file") from None
    except OSError as err:
        raise RunFileError(f"{path}: cannot be read ({err.strerror or err})") from None
    nul = data.find(b"\0")
    if nul >= 0:
        raise RunFileError(f"{path}: damaged: it holds NUL bytes (the first at byte {nul}), not text")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RunFileError(f"{path}: damaged: not UTF-8 text (byte {err.start})") from None


def read_json(path: str) -> dict[str, Any]:
    """The JSON object in the file `path` (a config.json); RunFileError for anything else (`read_text`)."""
    text = read_text(path)
    try:
        value = json.loads(text)
    except ValueError as err:
        raise RunFileError(f"{path}: damaged: not JSON ({err})") from None
    if not isinstance(value, dict):
        raise RunFileError(f"{path}: damaged: a JSON {type(value).__name__}, not an object")
    return value


def read_csv(path: str) -> tuple[list[str], list[dict[str, str]], int]:
    """(header, rows, how many rows were cut short) of the CSV file `path` (a metrics.csv); a row cut short
    (by a kill mid-write: missing values) is left out of the rows. RunFileError for a file that is not CSV
    text (`read_text`)."""
    text = read_text(path)
    try:
        reader = csv.DictReader(io.StringIO(text, newline=""))
        rows = list(reader)
    except csv.Error as err:
        raise RunFileError(f"{path}: damaged: not CSV ({err})") from None
    complete = [row for row in rows if None not in row.values()]
    return list(reader.fieldnames or []), complete, len(rows) - len(complete)


def number(path: str, row: dict[str, str], column: str) -> float:
    """The value of `column` in a row of the CSV file `path` as a float; RunFileError naming both if it
    is missing or not a number."""
    try:
        return float(row[column])
    except KeyError:
        raise RunFileError(f"{path}: damaged: no column {column!r}") from None
    except (TypeError, ValueError):
        raise RunFileError(f"{path}: damaged: {column} {row[column]!r} is not a number") from None


def write_atomic(path: str, text: str | bytes, tmp: str | None = None) -> None:
    """Write `text` (or bytes) to `path` through `tmp` (default `PATH.tmp`; one of its own for each of several
    processes that may write `path` at once): a reader never sees half of it, and a failed write (no space,
    permissions) deletes the temporary file before its error goes on."""
    tmp = tmp or path + TMP_SUFFIX
    try:
        with open(tmp, "wb") if isinstance(text, bytes) else open(tmp, "w", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def check_output_dir(directory: str, flag: str) -> None:
    """Refuse (ConfigError, exit 2) an output folder that does not exist, is not a folder or cannot be
    written: before the work, not after it. `flag` names the option that chose it; "" is the working folder."""
    directory = directory or "."
    if not os.path.isdir(directory):
        what = "is not a folder" if os.path.exists(directory) else "does not exist"
        raise ConfigError(f"{flag}: the folder {directory} {what}; create it or name another")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag}: the folder {directory} is not writable (permission denied)")


def first_line(err: BaseException, limit: int | None = None) -> str:
    """The first non-empty line of an error's message (its type's name for an empty one), cut to `limit`
    characters, the last three "...", where it is longer."""
    line = next((s.strip() for s in str(err).splitlines() if s.strip()), type(err).__name__)
    return line if limit is None or len(line) <= limit else line[: limit - 3] + "..."


def close_quietly(*closers: Callable[[], Any]) -> None:
    """Call every closer, dropping their errors: what an error on its way out leaves open is closed without
    a second error (e.g. the disk still full while TensorBoard flushes) masking the first."""
    for close in closers:
        with contextlib.suppress(Exception):
            close()


def check_run_files(run_dir: str) -> None:
    """A resumed run's files, before anything is compiled: its metrics.csv must read as CSV (`read_csv`;
    RunFileError, exit 2, naming a damaged one or a folder in its place), config.json must not be a folder, and
    the run must be able to append to metrics.csv and replace config.json (DiskError, exit 4, naming the path)."""
    metrics_csv, config_json = os.path.join(run_dir, "metrics.csv"), os.path.join(run_dir, "config.json")
    if os.path.lexists(metrics_csv):
        read_csv(metrics_csv)
    if os.path.isdir(config_json):
        raise RunFileError(f"{config_json}: is a directory, not a file")
    for path in (run_dir, *(p for p in (metrics_csv,) if os.path.lexists(p))):
        if not os.access(path, os.W_OK):
            raise DiskError(f"permission denied: {path} cannot be written; fix its permissions and resume")
