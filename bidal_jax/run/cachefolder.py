"""The folder of JAX's persistent compilation cache, which also keeps the traced epoch programs (`exported`): where
it is, whether it can be written, and one warning line when it cannot.

`enable` switches the cache on in `resolve()`'s folder before anything compiles (JAX fixes the folder at a
process's first compile; switched on later, it was silently ignored wherever `$JAX_COMPILATION_CACHE_DIR` was set).
A folder that cannot be written (a read-only file system, a full disk, no permission, a file in its place) is
found then, by writing a small file into it (`problem`): the run goes on without the cache, compiling its programs
as a first run does and keeping none of them, after one warning line (`warn`). A write that fails later (the disk
filling while the run compiles) is that one line too: JAX's own warning for each program it could not keep or read
back, and the traced program's failed save, are folded into it (`fold_jax_warnings`). The cache never stops a run.
"""

from __future__ import annotations

import contextlib
import os
import sys
import uuid
import warnings
from typing import Callable

import jax

# the words that begin JAX's warnings for a cache entry it could not write or read back
JAX_CACHE_ERRORS = ("Error writing persistent compilation cache entry",
                    "Error reading persistent compilation cache entry")
PROBE_BYTES = 2**20  # what `problem` writes: a disk without room for it has none for a program either
_warned: list[str] = []  # the one warning of this process, once given


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def resolve() -> str:
    """The cache's folder: `$BIDAL_JAX_CACHE`, else JAX's own `$JAX_COMPILATION_CACHE_DIR`, else
    ~/.cache/bidal_jax/xla."""
    return (os.environ.get("BIDAL_JAX_CACHE") or os.environ.get("JAX_COMPILATION_CACHE_DIR")
            or os.path.join(os.path.expanduser("~"), ".cache", "bidal_jax", "xla"))


def problem(folder: str) -> str | None:
    """Why `folder` cannot hold the cache (the OS's words, e.g. "Read-only file system"), or None: it is created
    if missing, and a file of `PROBE_BYTES` is written into it and deleted."""
    probe = os.path.join(folder, f".probe-{os.getpid()}-{uuid.uuid4().hex}")
    try:
        os.makedirs(folder, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(bytes(PROBE_BYTES))
        os.remove(probe)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.remove(probe)
        return err.strerror or str(err)
    return None


def warn(folder: str, reason: str, log: Callable[[str], None] = _log) -> None:
    """The one warning line of this process about the cache (later calls print nothing): `folder` failed
    (`reason`, e.g. "No space left on device"), and the run goes on."""
    if not _warned:
        _warned.append(reason)
        log(f"warning: the compilation cache folder {folder} is not usable ({reason}); the run goes on, and the "
            "programs it could not keep are compiled again by the next run")


def fold_jax_warnings(folder: str, log: Callable[[str], None] = _log) -> None:
    """From now on, JAX's warnings about cache entries it could not write or read back (`JAX_CACHE_ERRORS`, one per
    program, with a line of source each) are the one line of `warn`; other warnings are shown as before."""
    shown = warnings.showwarning
    if getattr(shown, "folds_cache_warnings", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if text.startswith(JAX_CACHE_ERRORS):
            warn(folder, text.split("': ", 1)[-1], log)  # "Error writing ... for 'jit_f': OSError: ..."
            return
        shown(message, category, filename, lineno, file, line)

    show.folds_cache_warnings = True
    warnings.showwarning = show


def enable(log: Callable[[str], None] = _log) -> None:
    """Switch JAX's persistent compilation cache on in `resolve()`'s folder, keeping every program however fast it
    compiled; or, where that folder cannot be written (`problem`), off, with one warning line (`warn`). Call it
    before anything compiles.

    Every program is kept: besides the run's programs, building the env (the camera's static image, MJX's data)
    and the seeds' keys run some sixty operations one by one, each its own small compile, together a noticeable part
    of every start on a CPU; read back, they take a fraction of that."""
    folder = resolve()
    reason = problem(folder)
    if reason is not None:
        warn(folder, reason, log)
        jax.config.update("jax_compilation_cache_dir", None)  # no cache: nor a saved program (`exported.folder`)
        return
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    fold_jax_warnings(folder, log)
