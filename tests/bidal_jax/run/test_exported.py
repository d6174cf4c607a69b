"""The epoch program kept across processes (bidal_jax/run/exported.py): a second run of a config loads the traced
program instead of tracing it and trains the same numbers; the key follows what shapes the program; a damaged
saved program is traced and saved again. Under faults: two processes saving one program at once leave one whole
file; a file of another key, or cut short, is traced anew; the key covers the source and every library the program
is traced with; a program that cannot be saved is one warning line."""

import dataclasses
import errno
import os
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bidal_jax.run import cachefolder, exported
from experiments import run
from experiments.cli import resolve
from tests.helpers import REPO, TINY, rows

LOADED = "the traced epoch program loaded from"


@pytest.fixture
def programs(tmp_path, monkeypatch):
    """A folder of its own for the saved programs (the persistent cache's is shared between test runs)."""
    folder = tmp_path / "programs"
    monkeypatch.setattr(exported, "folder", lambda: str(folder))
    return folder


def train(run_dir, capsys) -> str:
    """stderr of a tiny 2-epoch run into `run_dir`."""
    assert run.main([*TINY, "--epochs", "2", "--run-dir", str(run_dir)]) == 0
    return capsys.readouterr().err


def test_a_second_run_loads_the_traced_program_and_trains_the_same(programs, tmp_path, capsys, monkeypatch):
    first = train(tmp_path / "a", capsys)
    saved = os.listdir(programs)
    assert len(saved) == 1 and saved[0].startswith("epoch-") and LOADED not in first, first

    def no_tracing(*args, **kwargs):
        raise AssertionError("the epoch was exported again")

    monkeypatch.setattr(exported.jax.export, "export", no_tracing)
    second = train(tmp_path / "b", capsys)
    assert LOADED in second and os.listdir(programs) == saved
    assert rows(tmp_path / "a") == rows(tmp_path / "b")


def test_a_damaged_program_is_traced_and_saved_again(programs, tmp_path, capsys):
    train(tmp_path / "a", capsys)
    (path,) = programs.iterdir()
    path.write_bytes(b"not a program")
    assert LOADED not in train(tmp_path / "b", capsys)
    assert path.stat().st_size > 1000
    assert rows(tmp_path / "a") == rows(tmp_path / "b")


def test_the_key_follows_what_shapes_the_program():
    config = resolve({"env": "planar_reach", "agent": "proprio_baseline"})
    devices = [type("Device", (), {"platform": "cpu", "device_kind": "cpu"})()]
    key = exported.program_key(config, "physics", devices)

    def changed(group, **fields):
        return dataclasses.replace(config, **{group: dataclasses.replace(getattr(config, group), **fields)})

    for same in (changed("run", epochs=7, run_dir="elsewhere", seed=3, checkpoint_every=2),):
        assert exported.program_key(same, "physics", devices) == key
    for other in (changed("train", batch_size=64), changed("network", vision_dtype="bfloat16"),
                  changed("run", seeds=2), changed("run", agent="multimodal_bidal")):
        assert exported.program_key(other, "physics", devices) != key
    assert exported.program_key(config, "other physics", devices) != key


# ----- a saved program under faults: concurrent saves, another key's file, a cut file, another source or library ---


def tiny_epoch():
    """A small epoch-like program and its state: `compile_epoch` takes any `epoch(state) -> (state, metrics)`."""
    def epoch(state):
        return {"x": state["x"] + 1.0}, {"sum": state["x"].sum()}

    return jax.jit(epoch), {"x": jnp.zeros(3)}


def compile_tiny(folder, key, log):
    """`compile_epoch` of `tiny_epoch` under `key` in `folder`: (whether it was loaded, the result of one epoch)."""
    epoch, state = tiny_epoch()
    run_epoch, loaded, _ = exported.compile_epoch(epoch, state, str(folder), key, log)
    new, _ = run_epoch(state)
    return loaded, np.asarray(new["x"])


SAVER = """
import os, sys, time, types
from bidal_jax.run import exported
path, key, size, times, go = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
payload = bytes([int(key[-1], 16)]) * size
program = types.SimpleNamespace(serialize=lambda: payload)
print("ready", flush=True)
while not os.path.exists(go):
    time.sleep(0.01)
for _ in range(times):
    exported._save(path, key, program, lambda line: print(line, file=sys.stderr, flush=True))
"""


def test_two_processes_saving_one_program_at_once_leave_one_whole_file(tmp_path):
    """Two processes save the program of one key 20 times each at once (a grid's cells starting together), while
    this one reads the file: every read is a whole program of that key, or no file yet; at the end one file, no
    temporary file left, no warning."""
    path, key, size = str(tmp_path / "programs" / "epoch-k.jax"), "0" * 31 + "7", 4 * 2**20
    go = str(tmp_path / "go")
    savers = [subprocess.Popen([sys.executable, "-c", SAVER, path, key, str(size), "20", go], cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    try:
        for saver in savers:
            assert saver.stdout.readline().strip() == "ready"
        open(go, "w").close()
        reads = 0
        while any(saver.poll() is None for saver in savers):
            try:
                with open(path, "rb") as f:
                    data = f.read()
            except FileNotFoundError:
                continue
            program, why = exported.unpack(data, key)
            assert program == bytes([7]) * size, why
            reads += 1
        errors = [saver.communicate(timeout=60)[1] for saver in savers]
    finally:
        for saver in savers:
            saver.kill()
    assert [saver.returncode for saver in savers] == [0, 0] and errors == ["", ""]
    assert reads > 0 and sorted(os.listdir(tmp_path / "programs")) == ["epoch-k.jax"]
    assert exported.unpack((tmp_path / "programs" / "epoch-k.jax").read_bytes(), key)[0] == bytes([7]) * size


def test_a_program_is_loaded_only_under_its_own_key(tmp_path):
    """A program file of another key copied into place is not loaded (its key is in the file): it is traced anew,
    with a line saying why, and saved under its own key."""
    lines = []
    assert compile_tiny(tmp_path, "a" * 32, lines.append)[0] is False
    assert compile_tiny(tmp_path, "a" * 32, lines.append)[0] is True
    shutil.copy(exported.path_of(str(tmp_path), "a" * 32), exported.path_of(str(tmp_path), "b" * 32))
    loaded, x = compile_tiny(tmp_path, "b" * 32, lines.append)
    assert loaded is False and np.array_equal(x, np.ones(3))
    assert lines == [f"the saved epoch program {exported.path_of(str(tmp_path), 'b' * 32)} is another program's "
                     f"(its key is {'a' * 12}...): traced anew"]
    assert exported.unpack(open(exported.path_of(str(tmp_path), "b" * 32), "rb").read(), "b" * 32)[0] is not None
    assert compile_tiny(tmp_path, "b" * 32, lines.append)[0] is True


@pytest.mark.parametrize("cut", ["in the first line", "in the header", "in the program", "its last byte"])
def test_a_program_cut_short_is_traced_anew_and_saved_whole(tmp_path, cut):
    key = "c" * 32
    compile_tiny(tmp_path, key, print)
    path = exported.path_of(str(tmp_path), key)
    data = open(path, "rb").read()
    keep = {"in the first line": len(exported.MAGIC) - 3, "in the header": len(exported.MAGIC) + 20,
            "in the program": len(data) // 2, "its last byte": len(data) - 1}[cut]
    with open(path, "wb") as f:
        f.write(data[:keep])
    lines = []
    loaded, x = compile_tiny(tmp_path, key, lines.append)
    assert loaded is False and np.array_equal(x, np.ones(3))
    assert len(lines) == 1 and lines[0].startswith(f"the saved epoch program {path} is ") and "traced anew" in lines[0]
    assert open(path, "rb").read() == data


def test_the_key_covers_the_source_and_every_library_the_program_is_traced_with(tmp_path, monkeypatch):
    """A changed source file, or a new version of a library the program's libraries require (ml_dtypes, under
    jax), is another key: the run traces anew instead of loading the program saved before."""
    for name, text in (("pkg/a.py", "x = 1\n"), ("pkg/sub/b.py", "y = 2\n"), ("pkg/model.xml", "<m/>"),
                       ("pkg/notes.txt", "n")):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    before = exported.files_digest([str(tmp_path / "pkg")])
    (tmp_path / "pkg" / "notes.txt").write_text("not source")
    assert exported.files_digest([str(tmp_path / "pkg")]) == before
    (tmp_path / "pkg" / "sub" / "b.py").write_text("y = 3\n")
    assert exported.files_digest([str(tmp_path / "pkg")]) != before

    config = resolve({"env": "planar_reach", "agent": "proprio_baseline"})
    devices = [type("Device", (), {"platform": "cpu", "device_kind": "cpu"})()]
    key = exported.program_key(config, "physics", devices)
    assert {"jax", "jaxlib", "ml-dtypes", "opt-einsum", "mujoco-mjx", "flax"} <= set(exported.library_versions())

    monkeypatch.setattr(exported, "source_digest", lambda: "another source")
    assert exported.program_key(config, "physics", devices) != key
    monkeypatch.undo()
    version = exported._version
    monkeypatch.setattr(exported, "_version", lambda name: "99.0" if name == "ml-dtypes" else version(name))
    exported.library_versions.cache_clear()
    try:
        other = exported.program_key(config, "physics", devices)
    finally:
        monkeypatch.undo()
        exported.library_versions.cache_clear()
    assert other != key and exported.program_key(config, "physics", devices) == key

    lines = []
    compile_tiny(tmp_path / "programs", key, lines.append)
    assert compile_tiny(tmp_path / "programs", other, lines.append)[0] is False and lines == []


def test_a_program_that_cannot_be_saved_is_one_warning_and_the_run_goes_on(tmp_path, monkeypatch):
    """A cache folder on a full disk (or read-only): the program still compiles and runs; one warning line, however
    many programs could not be saved."""
    monkeypatch.setattr(cachefolder, "_warned", [])

    def full(path, data, tmp=None):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(exported, "write_atomic", full)
    lines = []
    for key in ("d" * 32, "e" * 32):
        loaded, x = compile_tiny(tmp_path, key, lines.append)
        assert loaded is False and np.array_equal(x, np.ones(3))
    assert lines == [f"warning: the compilation cache folder {tmp_path} is not usable (No space left on device); the "
                     "run goes on, and the programs it could not keep are compiled again by the next run"]
