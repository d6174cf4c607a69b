"""The run directory's guards: one writer at a time, a new run into an empty directory, enough disk for a
checkpoint, and disk failures reported in one line.

- `hold(run_dir)` takes an exclusive advisory lock (`fcntl.flock`) on `RUN_DIR/.lock` for this
  process, holding "host H, PID P" for the message of a run refused because of it, until
  `release(run_dir)` or the process ends: the kernel drops the lock of a process that dies, even
  by SIGKILL, so a lock file left behind never blocks (it is not a lock, only a file). Another
  process's `hold` raises `RunDirInUse` at once (it waits for nothing and writes nothing).
  `release` deletes the lock file before it unlocks; `hold` checks that the file it locked is
  still the one at the path, so two processes never both hold one directory. `lock_file` and
  `unlock_file` are that lock on any file (a grid's `--out`: `experiments.cluster`).
- `check_run_dir(run_dir, overwrite)`: a new run never mixes into an existing one (an `overwrite` deletes only
  what a run writes, `RUN_FILES`); `lock(run_dir, resume, overwrite)`: a run's directory held for a block
  (`hold`, the new run's directory checked again under it and, with `overwrite`, emptied, then `release`),
  process 0 deciding for every process (`main_decides`).
- `check_space(directory, needed)` refuses (`DiskError`) a run whose file system has less free
  space than one checkpoint needs (`with_margin`: its arrays' bytes, uncompressed, plus a margin).
- `disk_errors(what, last_good)`: a block whose disk failure (no space, quota, read-only file
  system, I/O error, permission denied; an `OSError`, or a TensorStore error naming the OS error
  code, as Orbax raises it) becomes one `DiskError` line, "no space left on device while WHAT; LAST_GOOD".
  `writing(path)` is that block for a command's output file (a table, figure, video, JSON), any
  other `OSError` of which becomes a `ConfigError` line naming the path.
  Meanwhile the reports of that failure by Orbax's background threads and pending writes (absl
  and asyncio log records with tracebacks, exceptions of callbacks into a closed event loop) are
  dropped; after a disk error they stay dropped, since the process is about to end on it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import shutil
import socket
import sys
from typing import Callable, Iterator

from bidal_jax.config import ConfigError
from bidal_jax.run import multihost

LOCK_FILE = ".lock"
# what a run writes into its directory; overwrite deletes nothing else
RUN_FILES = frozenset(
    {"config.json", "metrics.csv", "metrics.csv.tmp", "config.json.tmp", "tb", "checkpoints", LOCK_FILE}
)
# the disk failures that end a run with one line, and how that line names them
DISK_ERRNOS = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EIO: "input/output error",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
}
# how TensorStore (under Orbax) names the OS error of a failed write
OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")
# free space a checkpoint needs beyond its arrays' bytes: a share of them, plus the small items
MARGIN_SHARE, MARGIN_BYTES = 0.05, 2**20
# the loggers through which Orbax's background threads and pending writes report a failed save
BACKGROUND_LOGGERS = ("absl", "asyncio")
# this process's locks: the run directory's real path -> the locked file's descriptor
_held: dict[str, int] = {}


class RunDirInUse(ConfigError):
    """The run directory is locked by another process; the message names its host and PID."""


class DiskError(Exception):
    """A write failed for want of disk (or the disk failed), or a checkpoint cannot fit; one line."""


# ----- the lock ----------------------------------------------------------------------------------


def _same_file(fd: int, path: str) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def _holder(fd: int) -> str:
    """Who holds the lock file `fd` (closed here), as it says: "host H, PID P"."""
    holder = os.read(fd, 256).decode(errors="replace").strip() or "which has not written its host and PID yet"
    os.close(fd)
    return holder


def _run_dir_in_use(run_dir: str) -> Callable[[str], RunDirInUse]:
    return lambda holder: RunDirInUse(f"run directory {run_dir} is in use by another run ({holder}); "
                                      "wait until it ends or use another directory")


def check_not_in_use(run_dir: str) -> None:
    """RunDirInUse naming the holder if another process holds `run_dir`'s lock; reads only (a run
    refused for being in use learns it before any other check of the directory)."""
    try:
        fd = os.open(os.path.join(run_dir, LOCK_FILE), os.O_RDONLY)
    except OSError:
        return  # no lock file: nobody holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _run_dir_in_use(run_dir)(_holder(fd)) from None
    os.close(fd)  # unlocks


def lock_file(path: str, in_use: Callable[[str], Exception]) -> int:
    """The descriptor of `path`, created if need be, exclusively locked for this process and holding "host H, PID
    P"; `in_use(holder)` is raised, at once, while another process holds it (`holder`: what its file says). An
    OSError when it cannot be created."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise in_use(_holder(fd)) from None
        if _same_file(fd, path):
            break
        os.close(fd)  # its holder deleted it between our open and lock: lock the file now at the path
    os.ftruncate(fd, 0)
    os.write(fd, f"host {socket.gethostname()}, PID {os.getpid()}\n".encode())
    return fd


def unlock_file(path: str, fd: int) -> None:
    """Delete the lock file `path` that `lock_file` locked as `fd`, then unlock it."""
    with contextlib.suppress(OSError):
        os.unlink(path)
    os.close(fd)


def hold(run_dir: str) -> None:
    """Lock `run_dir` (created if missing) for this process until `release` or its end; nothing when
    this process holds it already. RunDirInUse naming the holder; ConfigError if it cannot be created."""
    key = os.path.realpath(run_dir)
    if key in _held:
        return
    try:
        os.makedirs(run_dir, exist_ok=True)
        _held[key] = lock_file(os.path.join(run_dir, LOCK_FILE), _run_dir_in_use(run_dir))
    except RunDirInUse:
        raise
    except OSError as err:
        raise ConfigError(f"run directory {run_dir}: cannot create its lock file ({err.strerror})") from None


def release(run_dir: str) -> None:
    """Delete `run_dir`'s lock file and unlock it, if this process holds it."""
    fd = _held.pop(os.path.realpath(run_dir), None)
    if fd is not None:
        unlock_file(os.path.join(run_dir, LOCK_FILE), fd)


# ----- a run's directory: new, in use by nobody, emptied --------------------------------------------------


def main_decides(check: Callable[[], None], what: str) -> None:
    """Run `check` on process 0 only (the one that locks and writes); every process raises if it
    raised a ConfigError (process 0 that one, the others one naming `what`). Every process calls it."""
    refused = None
    if multihost.is_main():
        try:
            check()
        except ConfigError as err:
            refused = err
    if multihost.largest(int(refused is not None)):
        raise refused or ConfigError(f"{what}: refused by process 0 (see its error)")


def check_run_dir(run_dir: str, overwrite: bool) -> None:
    """A new run never mixes into an existing one; overwrite only deletes what a run writes (`RUN_FILES`)."""
    if os.path.exists(run_dir) and not os.path.isdir(run_dir):
        raise ConfigError(f"--run-dir {run_dir}: is a file, not a directory")
    entries = sorted(e for e in os.listdir(run_dir) if e != LOCK_FILE) if os.path.isdir(run_dir) else []
    if entries and not overwrite:
        raise ConfigError(
            f"--run-dir {run_dir}: exists and is not empty; use --resume to continue its run "
            "or --overwrite to delete it"
        )
    foreign = [e for e in entries if e not in RUN_FILES]
    if foreign:
        raise ConfigError(
            f"--overwrite: refusing to delete {run_dir}: it holds {foreign[0]!r}, which a run does not write"
        )


@contextlib.contextmanager
def lock(run_dir: str, resume: bool, overwrite: bool) -> Iterator[None]:
    """Hold `run_dir`'s lock for the block (process 0; `hold`, then `release`), the one owner of the lock
    of a run: a new run's directory is checked again under it (a run that ended meanwhile may have filled
    it) and, with `overwrite`, emptied (`delete_run_dir`); every process waits for the others before the
    block. Every process raises when process 0 is refused: RunDirInUse or ConfigError."""

    def take() -> None:
        hold(run_dir)
        try:
            if not resume:
                check_run_dir(run_dir, overwrite)
        except ConfigError:
            release(run_dir)
            raise

    main_decides(take, f"run directory {run_dir}")
    try:
        if overwrite:
            delete_run_dir(run_dir)
        multihost.barrier("bidal_jax.run.preflight.prepare")
        yield
    finally:
        if multihost.is_main():
            release(run_dir)


def delete_run_dir(run_dir: str) -> None:
    """Delete what a run directory that `check_run_dir(run_dir, overwrite=True)` accepted holds, but
    its lock: process 0 deletes it, every process waits until it is gone."""
    if multihost.is_main() and os.path.isdir(run_dir):
        for name in set(os.listdir(run_dir)) - {LOCK_FILE}:
            path = os.path.join(run_dir, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
    multihost.barrier("bidal_jax.run.preflight.delete_run_dir")


# ----- disk space and disk errors ----------------------------------------------------------------


def with_margin(nbytes: int) -> int:
    """Free bytes a checkpoint of `nbytes` of arrays needs (metadata, config, digest, metrics)."""
    return int(nbytes * (1 + MARGIN_SHARE)) + MARGIN_BYTES


def megabytes(nbytes: int) -> str:
    """Bytes in MB (2^20 bytes), with a decimal below 100."""
    mb = nbytes / 2**20
    return f"{mb:,.0f} MB" if mb >= 100 else f"{mb:.1f} MB"


def check_space(directory: str, nbytes: int) -> None:
    """Refuse (DiskError) when the file system of `directory` (or of its nearest existing parent)
    has not `with_margin(nbytes)` bytes free: not enough for one checkpoint of `nbytes` of arrays."""
    existing = os.path.abspath(directory)
    while not os.path.isdir(existing):
        existing = os.path.dirname(existing)
    free, needed = shutil.disk_usage(existing).free, with_margin(nbytes)
    if free < needed:
        raise DiskError(
            f"not enough space for one checkpoint in {directory}: it needs about {megabytes(needed)}, the disk has "
            f"{megabytes(free)} free; free some space or use a run directory on another disk"
        )


def causes(err: BaseException) -> Iterator[BaseException]:
    """`err`, then its causes (or contexts), outermost first; bounded: a chain may loop."""
    for _ in range(16):
        yield err
        err = err.__cause__ or err.__context__
        if err is None:
            return


def disk_errno(err: BaseException) -> int | None:
    """The `DISK_ERRNOS` code of a disk failure anywhere in `err`'s chain, or None."""
    for e in causes(err):
        if isinstance(e, OSError) and e.errno in DISK_ERRNOS:
            return e.errno
        found = OS_ERROR_CODE.search(str(e))
        if found and int(found.group(1)) in DISK_ERRNOS:
            return int(found.group(1))
    return None


class _DropDiskFailures(logging.Filter):
    """Drops log records that report a disk failure (in their message or their exception)."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return disk_errno(Exception(record.getMessage())) is None and (exc is None or disk_errno(exc) is None)


def _quiet_unraisable(previous):
    """An `sys.unraisablehook` that drops disk failures and callbacks into a closed event loop (what
    Orbax's pending writes raise once a save failed) and passes anything else to `previous`."""

    def hook(unraisable) -> None:
        exc = unraisable.exc_value
        if exc is not None and (disk_errno(exc) is not None or "Event loop is closed" in str(exc)):
            return
        previous(unraisable)

    return hook


@contextlib.contextmanager
def disk_errors(what: str, last_good: str) -> Iterator[None]:
    """Run the block; a disk failure inside becomes DiskError("<reason> while <what>; <last_good>"),
    any other exception passes. Background reports of disk failures are dropped meanwhile, and for
    good after one."""
    loggers, hook = [logging.getLogger(name) for name in BACKGROUND_LOGGERS], sys.unraisablehook
    dropping = _DropDiskFailures()
    for logger in loggers:
        logger.addFilter(dropping)
    sys.unraisablehook = _quiet_unraisable(hook)
    code = None
    try:
        yield
    except Exception as err:
        code = disk_errno(err)
        if code is None:
            raise
        raise DiskError(f"{DISK_ERRNOS[code]} while {what}; {last_good}") from None
    finally:
        if code is None:
            for logger in loggers:
                logger.removeFilter(dropping)
            sys.unraisablehook = hook


@contextlib.contextmanager
def writing(path: str) -> Iterator[None]:
    """Run a block that writes a command's output `path`: a disk or permission failure becomes DiskError
    (`disk_errors`, exit 4), any other OSError (e.g. a folder where the file should be) a ConfigError
    naming `path` (exit 2); one line each."""
    try:
        with disk_errors(f"writing {path}", "free some space or fix the permissions and run the command again"):
            yield
    except OSError as err:
        raise ConfigError(f"cannot write {path}: {err.strerror or err}") from None
