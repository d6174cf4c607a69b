"""The run directory's guards (`bidal_jax/run/rundir.py`): one run at a time in a directory (a second
one exits 2 naming the holder, writing nothing; a lock left by a SIGKILLed process blocks
nothing), a full disk while saving a checkpoint ends the run with one line and exit 4 and a later
resume continues from the last good checkpoint, a disk without room for one checkpoint is refused
at start, and loading a policy logs no Orbax warning."""

import csv
import errno
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import namedtuple

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

import envs_mjx
from bidal_jax.run import checkpoint, preflight, rundir
from bidal_jax.run.metrics import MetricsLog
from bidal_jax.run.policy import load_policy
from experiments import cli, run
from tests.helpers import REPO, TINY

# a process that holds the lock of the directory argv[1] until it is killed
HOLDER = ("import sys, time; from bidal_jax.run import rundir; rundir.hold(sys.argv[1]); print('held', flush=True); "
          "time.sleep(600)")


def hold_elsewhere(run_dir) -> subprocess.Popen:
    """A process that holds `run_dir`'s lock (returned once it does)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(run_dir)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def snapshot(root) -> dict:
    """Every file under `root` with its content."""
    return {os.path.join(d, n): open(os.path.join(d, n), "rb").read() for d, _, names in os.walk(root) for n in names}


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "error: " in line]


def test_a_run_on_a_directory_in_use_exits_2_naming_the_holder_and_writes_nothing(tmp_path):
    run_dir = tmp_path / "run"
    holder = hold_elsewhere(run_dir)
    try:
        (run_dir / "metrics.csv").write_text("epoch,eval_success\n1,0.5\n")  # the holder's files
        before = snapshot(run_dir)
        result = subprocess.run([sys.executable, "-m", "experiments.run", *TINY, "--epochs", "1", "--run-dir",
                                 str(run_dir)], cwd=REPO, capture_output=True, text=True, timeout=300)
        assert result.returncode == 2, result.stderr
        (line,) = error_lines(result.stderr)
        assert f"run directory {run_dir} is in use by another run" in line and f"PID {holder.pid}" in line, line
        assert "host " in line
        assert snapshot(run_dir) == before
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_left_by_a_sigkilled_process_does_not_block_the_next_run(tmp_path):
    run_dir = tmp_path / "run"
    holder = hold_elsewhere(run_dir)
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert os.listdir(run_dir) == [rundir.LOCK_FILE]  # its file stays; its lock went with it
    given = {"env": "planar_reach", "agent": "proprio_baseline", "num_envs": 4, "buffer_episodes": 8,
             "eval_envs": 4, "run_dir": str(run_dir)}
    with preflight.prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make,
                           preset=cli.task_preset):  # checks, then locks
        assert f"PID {os.getpid()}" in (run_dir / rundir.LOCK_FILE).read_text()
    assert os.listdir(run_dir) == []  # released when the block ends


def test_hold_is_refused_while_another_process_holds_and_taken_after(tmp_path):
    holder = hold_elsewhere(tmp_path)
    with pytest.raises(rundir.RunDirInUse, match=f"PID {holder.pid}"):
        rundir.hold(str(tmp_path))
    holder.kill()
    holder.wait()
    rundir.hold(str(tmp_path))
    rundir.release(str(tmp_path))


def test_disk_errno_finds_os_errors_and_tensorstore_codes():
    assert rundir.disk_errno(OSError(errno.ENOSPC, "No space left on device")) == errno.ENOSPC
    tensorstore = ValueError("RESOURCE_EXHAUSTED: Error writing \"a/0\": Failed to write 918328 bytes to file 7: "
                             "No space left on device [os_error_code='28']")
    try:
        raise RuntimeError("save failed") from tensorstore
    except RuntimeError as wrapped:
        assert rundir.disk_errno(wrapped) == errno.ENOSPC
    assert rundir.disk_errno(OSError(errno.EROFS, "Read-only file system")) == errno.EROFS
    assert rundir.disk_errno(OSError(errno.ENOENT, "No such file")) is None
    assert rundir.disk_errno(ValueError("os_error_code='2'")) is None


@pytest.fixture
def full_disk_at_checkpoint_2(monkeypatch):
    """Saving checkpoint 2 fails with ENOSPC once Orbax has started writing it (its temporary directory exists)."""
    save = ocp.JsonCheckpointHandler._save_fn

    async def failing(self, x, directory):
        if f"2{ocp.path.step.TMP_DIR_SUFFIX}" in str(directory):
            raise OSError(errno.ENOSPC, "No space left on device")
        return await save(self, x, directory)

    monkeypatch.setattr(ocp.JsonCheckpointHandler, "_save_fn", failing)
    return monkeypatch


def test_a_full_disk_while_saving_a_checkpoint_ends_with_one_line_and_the_run_resumes(
    tmp_path, full_disk_at_checkpoint_2, capsys
):
    run_dir = tmp_path / "run"
    ckpt_dir = run_dir / "checkpoints"
    assert run.main([*TINY, "--epochs", "3", "--checkpoint-every", "1", "--run-dir", str(run_dir)]) == cli.EXIT_DISK
    err = capsys.readouterr().err
    (line,) = error_lines(err)
    assert line.startswith(f"error: no space left on device while saving checkpoint 2 in {ckpt_dir} (needs about ")
    assert line.endswith(f"MB); the last good checkpoint is epoch 1 in {ckpt_dir}")
    assert "Traceback" not in err
    assert sorted(os.listdir(ckpt_dir)) == ["1"]  # the unfinished save is deleted
    assert not (run_dir / rundir.LOCK_FILE).exists()  # released

    full_disk_at_checkpoint_2.undo()  # space was freed
    assert run.main(["--resume", "--run-dir", str(run_dir), "--quiet"]) == 0
    assert checkpoint.latest_step(str(ckpt_dir)) == 3


def test_a_checkpoint_is_written_while_the_next_epoch_trains_and_holds_its_own_epoch(tmp_path, monkeypatch):
    """Checkpoint 1 is written in the background: its save waits (up to a minute) for epoch 2's metrics, which a
    save that blocked the loop would never let come; and it holds epoch 1's state, not the donated one after."""
    run_dir = tmp_path / "run"
    ckpt_dir = str(run_dir / "checkpoints")
    trained_2, threads = threading.Event(), []
    write, save = MetricsLog.write, checkpoint.save

    def writing(self, row):
        write(self, row)
        trained_2.set() if row["epoch"] == 2 else None

    def saving(mngr, step, *args, **kwargs):
        threads.append(threading.current_thread().name)
        if step == 1 and not trained_2.wait(timeout=60):
            raise AssertionError("epoch 2 did not train while checkpoint 1 was written")
        save(mngr, step, *args, **kwargs)

    monkeypatch.setattr(MetricsLog, "write", writing)
    monkeypatch.setattr(checkpoint, "save", saving)
    assert run.main([*TINY, "--epochs", "3", "--checkpoint-every", "1", "--run-dir", str(run_dir)]) == 0
    with open(run_dir / "metrics.csv") as f:
        steps = [float(row["env_steps_total"]) for row in csv.DictReader(f)]
    kept, leaf = checkpoint.steps(ckpt_dir), {"env_steps": checkpoint.read_metadata(ckpt_dir)["state"]["env_steps"]}
    saved = [float(np.sum(checkpoint.restore_partial(ckpt_dir, e, leaf)["env_steps"])) for e in kept]
    assert kept[-1] == 3 and len(kept) >= 2 and saved == [steps[e - 1] for e in kept]
    assert threads == ["checkpoint 1", "checkpoint 2", "MainThread"]  # the run's last save before it ends


def test_a_copy_has_room_beside_the_devices_peak_use(monkeypatch):
    state = {"a": jax.numpy.zeros(256, jax.numpy.float32), "b": jax.numpy.zeros(256, jax.numpy.uint8)}  # 1,280 bytes
    assert checkpoint._room_for_copy(state)  # a CPU keeps no figures
    for peak, room in ((2**20 - 1280, True), (2**20 - 1279, False)):
        stats = {"bytes_limit": 2**20, "peak_bytes_in_use": peak}
        monkeypatch.setattr(checkpoint, "_memory_stats", lambda device, stats=stats: stats)
        assert checkpoint._room_for_copy(state) == room


def _out_of_memory(state):
    raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 1024 bytes.")


@pytest.mark.parametrize("short", [
    ("_memory_stats", lambda device: {"bytes_limit": 2**30, "peak_bytes_in_use": 2**30 - 1024}),  # a full device
    ("_copy", _out_of_memory),  # the copy itself fails
])
def test_a_checkpoint_is_written_before_the_next_epoch_where_the_devices_have_no_room_for_a_copy(
    tmp_path, monkeypatch, short
):
    run_dir, threads, save = tmp_path / "run", [], checkpoint.save
    monkeypatch.setattr(checkpoint, *short)
    monkeypatch.setattr(checkpoint, "save", lambda *args: (threads.append(threading.current_thread().name),
                                                           save(*args)))
    assert run.main([*TINY, "--epochs", "2", "--checkpoint-every", "1", "--run-dir", str(run_dir)]) == 0
    assert threads == ["MainThread", "MainThread"] and checkpoint.steps(str(run_dir / "checkpoints")) == [1, 2]


def test_a_disk_without_room_for_one_checkpoint_is_refused_at_start(tmp_path, monkeypatch, capsys):
    run_dir = tmp_path / "run"
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(rundir.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 2**19, 2**19))
    assert run.main([*TINY, "--epochs", "1", "--run-dir", str(run_dir)]) == cli.EXIT_DISK
    (line,) = error_lines(capsys.readouterr().err)
    assert f"not enough space for one checkpoint in {run_dir}: it needs about " in line
    assert "the disk has 0.5 MB free" in line
    assert not run_dir.exists()


def test_loading_a_policy_logs_no_warning(tmp_path, caplog):
    run_dir = tmp_path / "run"
    assert run.main([*TINY, "--epochs", "1", "--run-dir", str(run_dir)]) == 0
    with caplog.at_level(logging.WARNING):
        trained = load_policy(str(run_dir))
    assert trained.step == 1
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_a_save_in_place_that_fails_ends_the_run_before_the_next_epoch(tmp_path, full_disk_at_checkpoint_2, capsys):
    full_disk_at_checkpoint_2.setattr(checkpoint, "_copy", _out_of_memory)
    run_dir = tmp_path / "run"
    assert run.main([*TINY, "--epochs", "3", "--checkpoint-every", "1", "--run-dir", str(run_dir)]) == cli.EXIT_DISK
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: no space left on device while saving checkpoint 2 in {run_dir / 'checkpoints'}")
    with open(run_dir / "metrics.csv") as f:
        assert [row["epoch"] for row in csv.DictReader(f)] == ["1", "2"]  # a save in the background: 3 rows


def test_a_failed_saves_directory_written_again_after_its_removal_is_removed_again(tmp_path):
    """`checkpoint.remove_failed`: a write that lands after the first removal (TensorStore's threads finishing the
    save's other items) makes the directory come back; it is removed again, and checkpoint 1 is left alone."""
    unfinished = tmp_path / f"2{ocp.path.step.TMP_DIR_SUFFIX}"
    (tmp_path / "1").mkdir()
    unfinished.mkdir()

    def late_write():
        time.sleep(0.2)
        (unfinished / "state").mkdir(parents=True)

    writer = threading.Thread(target=late_write)
    writer.start()
    checkpoint.remove_failed(str(tmp_path), 2, settle=0.5, timeout=10)
    writer.join()
    assert sorted(os.listdir(tmp_path)) == ["1"]
