"""The epoch program kept across processes (bidal_jax/run/exported.py): a second run of a config loads the traced
program instead of tracing it and trains the same numbers; the key follows what shapes the program; a damaged
saved program is traced and saved again."""

import dataclasses
import os

import pytest

from bidal_jax.config import resolve
from bidal_jax.run import exported
from experiments import run
from tests.helpers import TINY, rows

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
