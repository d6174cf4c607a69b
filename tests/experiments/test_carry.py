"""Carrying a stopped run (experiments/carry.py): its files and latest checkpoint without the replay buffer, a copy
that `--resume --fresh-buffer` continues; a run in use, without a checkpoint, an existing destination or a failing
disk refused in one line with nothing left behind."""

import errno
import json
import os
import shutil

import pytest

from bidal_jax.run import rundir
from experiments import carry, run
from tests.helpers import FINISHED_EPOCHS, restored_state, snapshot


def refused(argv, code, expected, capsys, *paths):
    """carry.main(argv) exits `code` with one `error:` line holding `expected`, and leaves `paths` as they were."""
    before = [snapshot(p) for p in paths]
    assert carry.main(argv) == code
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and expected in errors[0], errors
    assert [snapshot(p) for p in paths] == before


def test_carry_copies_the_run_and_its_latest_checkpoint_without_the_buffer_and_it_resumes(finished, tmp_path, capsys):
    run_dir, _ = finished
    dest = tmp_path / "carried"
    before = snapshot(run_dir)
    assert carry.main(["--run-dir", run_dir, "--out", str(dest)]) == 0
    assert snapshot(run_dir) == before  # the run itself is only read
    printed = capsys.readouterr().out
    assert f"checkpoint {FINISHED_EPOCHS} without its replay buffer" in printed
    assert f"python -m experiments.run --resume --fresh-buffer --run-dir {dest}" in printed
    assert sorted(os.listdir(dest / "checkpoints")) == [str(FINISHED_EPOCHS)]  # the latest alone
    step = dest / "checkpoints" / str(FINISHED_EPOCHS)
    assert not (step / "buffer").exists() and (step / "state").is_dir()
    assert not os.path.exists(f"{dest}{carry.TMP_SUFFIX}")
    for name in ("config.json", "metrics.csv"):
        assert (dest / name).read_bytes() == open(os.path.join(run_dir, name), "rb").read()

    assert run.main(["--resume", "--fresh-buffer", "--run-dir", str(dest), "--epochs", str(FINISHED_EPOCHS + 1),
                     "--quiet"]) == 0
    _, step = restored_state(dest)
    assert step == FINISHED_EPOCHS + 1
    assert json.loads((dest / "config.json").read_text())["fresh_buffer_epochs"] == [FINISHED_EPOCHS]


def test_carry_refuses_an_existing_destination(finished, tmp_path, capsys):
    run_dir, _ = finished
    dest = tmp_path / "carried"
    dest.mkdir()
    (dest / "kept").write_text("mine")
    refused(["--run-dir", run_dir, "--out", str(dest)], 2, "exists; name a folder that does not", capsys,
            run_dir, str(dest))


def test_carry_refuses_a_run_without_a_checkpoint_or_directory(tmp_path, capsys):
    run_dir, dest = tmp_path / "run", tmp_path / "carried"
    refused(["--run-dir", str(run_dir), "--out", str(dest)], 2, "no such directory", capsys, str(dest))
    run_dir.mkdir()
    (run_dir / "config.json").write_text("{}")
    refused(["--run-dir", str(run_dir), "--out", str(dest)], 2, "nothing to resume from", capsys,
            str(run_dir), str(dest))


def test_carry_refuses_a_run_that_trains(finished, tmp_path, capsys):
    run_dir, _ = finished
    dest = tmp_path / "carried"
    rundir.hold(run_dir)  # as a run training in it holds it
    try:
        assert carry.main(["--run-dir", run_dir, "--out", str(dest)]) == 2
    finally:
        rundir.release(run_dir)
    assert "is in use" in capsys.readouterr().err and not dest.exists()


def test_a_failing_disk_leaves_no_partial_copy(finished, tmp_path, capsys, monkeypatch):
    run_dir, _ = finished
    dest = tmp_path / "carried"
    real = shutil.copytree

    def copytree(src, dst, *args, **kwargs):
        if os.path.basename(os.path.dirname(dst)) == "checkpoints":  # the run's files are copied, not its checkpoint
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(shutil, "copytree", copytree)
    refused(["--run-dir", run_dir, "--out", str(dest)], 4, "no space left on device while copying", capsys, run_dir)
    assert not dest.exists() and not os.path.exists(f"{dest}{carry.TMP_SUFFIX}")


@pytest.mark.parametrize("argv", [["--run-dir", "r"], ["--out", "o"]])
def test_both_folders_are_required(argv):
    with pytest.raises(SystemExit) as exit_:
        carry.main(argv)
    assert exit_.value.code == 2
