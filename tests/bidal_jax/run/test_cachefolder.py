"""The compilation cache's folder (bidal_jax/run/cachefolder.py): ours, else JAX's, else the default; a folder that
cannot be written (read-only, a full disk, a file in its place) lets the run go on uncached with one warning line,
and so do JAX's failures to keep each program and the traced program's failed save."""

import errno
import os
import subprocess
import sys
import warnings

import jax
import pytest

from bidal_jax.run import cachefolder, exported
from tests.helpers import REPO, TINY

WARNING = "warning: the compilation cache folder {} is not usable ({}); the run goes on, and the programs it could " \
    "not keep are compiled again by the next run"


@pytest.fixture
def fresh(monkeypatch):
    """This process has given no cache warning yet."""
    monkeypatch.setattr(cachefolder, "_warned", [])


@pytest.mark.parametrize(
    "ours, jaxs, expected", [("/a", "/b", "/a"), ("", "/b", "/b"), ("", "", "~/.cache/bidal_jax/xla")]
)
def test_the_cache_folder_is_ours_else_jaxs_else_the_default(monkeypatch, ours, jaxs, expected):
    for name, value in (("BIDAL_JAX_CACHE", ours), ("JAX_COMPILATION_CACHE_DIR", jaxs)):
        monkeypatch.setenv(name, value) if value else monkeypatch.delenv(name, raising=False)
    assert cachefolder.resolve() == os.path.expanduser(expected)


def test_a_folder_is_usable_when_a_file_can_be_written_into_it(tmp_path):
    assert cachefolder.problem(str(tmp_path / "new" / "xla")) is None
    assert os.listdir(tmp_path / "new" / "xla") == []  # the probe is gone
    (tmp_path / "file").write_text("not a folder")
    assert cachefolder.problem(str(tmp_path / "file" / "xla")) == "Not a directory"


@pytest.mark.parametrize("code, words", [(errno.EROFS, "Read-only file system"), (errno.ENOSPC,
                                                                                    "No space left on device")])
def test_a_read_only_or_full_folder_is_not_usable(tmp_path, monkeypatch, code, words):
    def refuse(path, mode="r", *args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(cachefolder, "open", refuse, raising=False)
    assert cachefolder.problem(str(tmp_path)) == words
    assert os.listdir(tmp_path) == []


def test_an_unusable_folder_switches_the_cache_off_with_one_warning(tmp_path, monkeypatch, fresh):
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("BIDAL_JAX_CACHE", str(tmp_path / "file" / "xla"))
    kept = jax.config.jax_compilation_cache_dir
    lines = []
    try:
        cachefolder.enable(lines.append)
        cachefolder.enable(lines.append)
        folder = jax.config.jax_compilation_cache_dir
        programs = exported.folder()
    finally:
        jax.config.update("jax_compilation_cache_dir", kept)
    assert folder is None and programs is None  # no cache, no saved program
    assert lines == [WARNING.format(tmp_path / "file" / "xla", "Not a directory")]


def test_jaxs_failures_to_keep_programs_and_a_failed_save_are_one_warning(tmp_path, monkeypatch, fresh):
    """A disk that fills while the run compiles: JAX warns for each program it cannot keep (and, later, for each
    entry it cannot read back), the traced program's save fails; the run shows one line."""
    lines = []
    cachefolder.fold_jax_warnings(str(tmp_path), lines.append)
    cachefolder.fold_jax_warnings(str(tmp_path), lines.append)  # once only
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        for name in ("jit_init", "jit_epoch", "jit_where"):
            warnings.warn(f"Error writing persistent compilation cache entry for '{name}': OSError: [Errno 28] No "
                          "space left on device")
        warnings.warn("Error reading persistent compilation cache entry for 'jit_init': ValueError: truncated")
        cachefolder.warn(str(tmp_path / "programs"), "No space left on device", lines.append)
    assert lines == [WARNING.format(tmp_path, "OSError: [Errno 28] No space left on device")]
    with pytest.warns(UserWarning, match="another warning"):  # others pass as before
        warnings.warn("another warning")


@pytest.mark.slow
def test_a_run_with_a_cache_folder_it_cannot_write_trains_uncached_with_one_warning(tmp_path):
    """The command line, with its cache folder under a file (unwritable, for root too): it trains, exit 0, and its
    stderr holds one warning line and none of JAX's warnings about cache entries."""
    (tmp_path / "file").write_text("not a folder")
    env = {**os.environ, "BIDAL_JAX_CACHE": str(tmp_path / "file" / "xla")}
    done = subprocess.run([sys.executable, "-m", "experiments.run", *TINY, "--epochs", "1", "--run-dir",
                           str(tmp_path / "run")], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    warned = [line for line in done.stderr.splitlines() if "warning" in line.lower()]
    assert warned == [WARNING.format(tmp_path / "file" / "xla", "Not a directory")], done.stderr
    assert "Traceback" not in done.stderr and os.path.isfile(tmp_path / "run" / "metrics.csv")
