"""Device memory (bidal_jax/run/memory.py): a run whose compiled epoch does not fit the device stops before it
trains with one line saying what to reduce; running out all the same while compiling or in an epoch ends the run
in one line with exit 6, and its last checkpoint resumes. On a CPU, with the device's size patched or the compiled
epoch made to raise XLA's RESOURCE_EXHAUSTED."""

import os
import re
import types

import jax
import pytest

from bidal_jax.config import ConfigError
from bidal_jax.run import checkpoint, loop, memory
from experiments import run
from tests.helpers import FINISHED, FINISHED_EPOCHS, TINY, rows

MiB = 2**20
EXHAUSTED = "RESOURCE_EXHAUSTED: Out of memory while trying to allocate 1.50GiB."
REDUCE = "use a smaller --batch-size, fewer seeds, --num-envs or --buffer-episodes"


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error: ")]


def stats(arguments: int, temp: int, outputs: int, alias: int):
    """A compiled program's `memory_analysis()`, as XLA gives it."""
    return types.SimpleNamespace(argument_size_in_bytes=arguments, temp_size_in_bytes=temp,
                                 output_size_in_bytes=outputs, alias_size_in_bytes=alias)


def test_a_program_is_its_state_its_working_memory_and_the_outputs_not_written_in_place():
    assert memory.program_bytes(stats(100, 50, 110, 100)) == (160, 50)  # outputs: 100 of 110 into the state
    assert memory.program_bytes(None) is None
    memory.check_program(stats(100, 50, 110, 100), available=180)  # 160 <= 90 % of 180
    memory.check_program(None, available=1)  # a backend without an analysis: nothing to check
    with pytest.raises(ConfigError, match=rf"needs 1\.5 GiB of device memory at once .*working memory 1\.0 GiB.*"
                                          rf"90% of the device's 1\.0 GiB; {REDUCE}$"):
        memory.check_program(stats(2**29, 2**30, 2**29, 2**29), available=2**30)


def test_a_refusal_on_a_gpu_says_to_give_jax_more_of_it_while_jax_holds_less_than_90_percent(monkeypatch):
    """JAX takes 75 % of a GPU unless told otherwise: a program refused there may fit with a larger share."""
    monkeypatch.setattr(jax, "local_devices", lambda: [types.SimpleNamespace(platform="gpu")])
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    too_large = stats(2**29, 2**30, 2**29, 2**29)
    hint = "; or give JAX more of the GPU's memory (XLA_PYTHON_CLIENT_MEM_FRACTION, now 0.75)"
    with pytest.raises(ConfigError, match=rf"{REDUCE}{re.escape(hint)}$"):
        memory.check_program(too_large, available=2**30)
    with pytest.raises(ConfigError, match=rf"--buffer-episodes{re.escape(hint)}$"):
        memory.check_state(2**30, available=2**30, seeds=5)
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.45")  # a grid's half-GPU cell
    with pytest.raises(ConfigError, match=r"XLA_PYTHON_CLIENT_MEM_FRACTION, now 0\.45\)$"):
        memory.check_program(too_large, available=2**30)
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.95")  # JAX holds nearly all of it already
    with pytest.raises(ConfigError, match=rf"{REDUCE}$"):
        memory.check_program(too_large, available=2**30)


def test_only_xlas_failure_to_allocate_is_out_of_memory():
    assert memory.exhausted(jax.errors.JaxRuntimeError(EXHAUSTED))
    assert not memory.exhausted(jax.errors.JaxRuntimeError("INTERNAL: something else"))
    assert not memory.exhausted(MemoryError("host"))


def test_an_epoch_larger_than_the_device_stops_before_training(tmp_path, monkeypatch, capsys):
    """A batch that the state's estimate cannot see (the state does not hold it): its compiled epoch's working
    memory is more than the device's, refused in one line before the first epoch, with exit 2."""
    monkeypatch.setattr(memory, "device_memory", lambda: 64 * MiB)  # the state (about 1 MiB) fits
    run_dir = tmp_path / "run"
    assert run.main([*TINY, "--batch-size", "100000", "--epochs", "2", "--run-dir", str(run_dir)]) == 2
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith("error: the training program needs ") and line.endswith(
        f"more than 90% of the device's 0.1 GiB; {REDUCE}")
    assert not os.path.exists(run_dir / "metrics.csv") and not os.path.exists(run_dir / "checkpoints")


def test_out_of_memory_while_compiling_is_one_line_and_exit_6(tmp_path, monkeypatch, capsys):
    def exhausted(*args, **kwargs):
        raise jax.errors.JaxRuntimeError(EXHAUSTED)

    monkeypatch.setattr(loop, "_compile", exhausted)
    run_dir = tmp_path / "run"
    assert run.main([*TINY, "--epochs", "2", "--run-dir", str(run_dir)]) == 6
    err = capsys.readouterr().err
    assert error_lines(err) == [f"error: out of device memory while compiling and starting the training program "
                                f"({EXHAUSTED}); {REDUCE}; no checkpoint was saved"]
    assert "Traceback" not in err and not os.path.exists(run_dir / "metrics.csv")


def test_out_of_memory_in_an_epoch_is_one_line_exit_6_and_the_last_checkpoint_resumes(finished, tmp_path,
                                                                                         monkeypatch, capsys):
    """The compiled epoch raises RESOURCE_EXHAUSTED in epoch 3 (checkpoint 2 being written meanwhile): one line
    naming the epoch and the last good checkpoint, exit 6; resumed from that checkpoint, the run ends with the rows
    of the run that never stopped."""
    build = loop.build

    def epoch_3_runs_out(*args, **kwargs):
        epoch, state, step, shards = build(*args, **kwargs)
        calls = []

        def epoch_or_out_of_memory(state):
            calls.append(state)
            if len(calls) == 3:
                raise jax.errors.JaxRuntimeError(EXHAUSTED)
            return epoch(state)

        return epoch_or_out_of_memory, state, step, shards

    monkeypatch.setattr(loop, "build", epoch_3_runs_out)
    run_dir = str(tmp_path / "run")
    assert run.main([*FINISHED, "--run-dir", run_dir]) == 6
    err = capsys.readouterr().err
    ckpt_dir = os.path.join(run_dir, "checkpoints")
    assert error_lines(err) == [f"error: out of device memory while training epoch 3 ({EXHAUSTED}); {REDUCE}; the "
                                f"last good checkpoint is epoch 2 in {ckpt_dir}"]
    assert "Traceback" not in err and checkpoint.latest_step(ckpt_dir) == 2
    monkeypatch.undo()
    assert run.main(["--resume", "--run-dir", run_dir, "--quiet"]) == 0
    assert rows(run_dir) == rows(finished[0]) and len(rows(run_dir)) == FINISHED_EPOCHS
