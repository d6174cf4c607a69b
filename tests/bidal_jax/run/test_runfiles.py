"""A run's own files (`bidal_jax/run/runfiles.py`, `loop`, `preflight`): a resumed run whose metrics.csv is a
folder (exit 2) or cannot be written (exit 4) is refused before compiling; a disk or permission failure while
the metrics are written ends the run in one line with exit 4, even when closing TensorBoard fails again; a full
disk while config.json is written leaves no temporary file that refuses the same command; Ctrl-C while the env
is built exits 130 without a traceback."""

import errno
import os
import shutil

import pytest

import envs_mjx
from bidal_jax.run import metrics, rundir, runfiles
from experiments import cli, run
from tests.helpers import FINISHED_EPOCHS, TINY


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "error: " in line]


@pytest.fixture
def copied(finished, tmp_path):
    """A copy of the `finished` run (its checkpoints included) to resume and damage."""
    run_dir = str(tmp_path / "run")
    shutil.copytree(finished[0], run_dir)
    return run_dir


def resume(run_dir: str) -> list[str]:
    return ["--resume", "--run-dir", run_dir, "--epochs", str(FINISHED_EPOCHS + 1), "--quiet"]


def test_a_resumed_run_whose_metrics_csv_is_a_folder_is_refused_before_compiling(copied, capsys):
    path = os.path.join(copied, "metrics.csv")
    os.remove(path)
    os.mkdir(path)
    assert run.main(resume(copied)) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert error_lines(err) == [f"error: {path}: is a directory, not a file"]
    assert "compiling" not in err and "Traceback" not in err


def test_a_resumed_run_that_cannot_write_its_metrics_csv_is_refused_before_compiling(copied, capsys, monkeypatch):
    path = os.path.join(copied, "metrics.csv")
    access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: access(p, mode) and os.fspath(p) != path)
    assert run.main(resume(copied)) == cli.EXIT_DISK
    err = capsys.readouterr().err
    assert error_lines(err) == [f"error: permission denied: {path} cannot be written; fix its permissions and resume"]
    assert "compiling" not in err


@pytest.mark.parametrize("code, reason", [(errno.ENOSPC, "no space left on device"),
                                          (errno.EACCES, "permission denied")])
def test_a_failed_metrics_write_ends_in_one_line_though_closing_tensorboard_fails_again(
    copied, capsys, monkeypatch, code, reason
):
    def failing(self, *args):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(metrics.MetricsLog, "write", failing)
    monkeypatch.setattr(metrics.MetricsLog, "close", failing)  # the disk is still full when TensorBoard flushes
    assert run.main(resume(copied)) == cli.EXIT_DISK
    err = capsys.readouterr().err
    ckpt_dir = os.path.join(copied, "checkpoints")
    assert error_lines(err) == [
        f"error: {reason} while writing the metrics of epoch {FINISHED_EPOCHS + 1} in {copied}; the last good "
        f"checkpoint is epoch {FINISHED_EPOCHS} in {ckpt_dir}"]
    assert "Traceback" not in err


def test_a_full_disk_while_config_json_is_written_leaves_nothing_that_refuses_a_rerun(tmp_path, capsys, monkeypatch):
    run_dir = str(tmp_path / "run")
    real_open = open

    def full(path, mode="r", *args, **kwargs):  # the temporary file is created, then the disk is full
        f = real_open(path, mode, *args, **kwargs)
        if os.fspath(path).endswith("config.json" + runfiles.TMP_SUFFIX):
            f.write = lambda text: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device"))
        return f

    monkeypatch.setattr(runfiles, "open", full, raising=False)
    assert run.main([*TINY, "--epochs", "1", "--run-dir", run_dir]) == cli.EXIT_DISK
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: no space left on device while writing the run's files in {run_dir}; ")
    assert os.listdir(run_dir) == []  # no config.json.tmp; the lock released
    rundir.check_run_dir(run_dir, overwrite=False)  # the same command is not refused


def test_ctrl_c_while_the_env_is_built_exits_130_without_a_traceback(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(envs_mjx, "make", interrupted)
    assert cli.command(lambda: run.main([*TINY, "--epochs", "1", "--run-dir", str(tmp_path / "run")])) == 130
    err = capsys.readouterr().err
    assert err.strip() == "stopped by Ctrl-C (SIGINT)" and "Traceback" not in err


@pytest.mark.parametrize("text, why", [("[1, 2]", "damaged: a JSON list, not an object"),
                                       ('{"run": ', "damaged: not JSON (")])
def test_read_json_names_the_file_and_what_is_wrong(tmp_path, text, why):
    path = tmp_path / "config.json"
    path.write_text(text)
    with pytest.raises(runfiles.RunFileError) as raised:
        runfiles.read_json(str(path))
    assert str(raised.value).startswith(f"{path}: {why}")
