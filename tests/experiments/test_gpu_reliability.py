"""On a GPU: sizes far beyond it are refused from their shapes before XLA compiles, sizes at its edge end in one
line at most, and two runs started on one GPU both train or the second is refused in one line (bidal_jax/run/
memory.py). Each run is a command line of its own, as a user starts it; `-s` prints what each did, for the record.
Skipped without a GPU, which a child process asks JAX about: this process starting JAX on the GPU would take 75 % of
it and make every run here one beside another process."""

import os
import subprocess
import sys
import time

import pytest

from tests.helpers import REPO

BACKEND = subprocess.run([sys.executable, "-c", "import jax; print(jax.default_backend())"], capture_output=True,
                         text=True, env={**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}).stdout.strip()
pytestmark = pytest.mark.skipif(BACKEND != "gpu", reason="needs a GPU")
# the files of XLA's C++ logs that dumped the autotuner's failures on the terminal, and its words, which a refusal
# from shapes has none of
LOGS = ("autotuner.cc", "config_selector.cc")
AUTOTUNER = (*LOGS, "autotuner", "Failed to get configs", "No candidates could be compiled")


def text(path: str) -> str:
    with open(path) as f:
        return f.read()


def start(argv: list[str], err_path: str) -> subprocess.Popen:
    """`python -m experiments.run ARGV` started, its stderr into `err_path`, its stdout into the same path + .out."""
    with open(err_path, "w") as err, open(err_path + ".out", "w") as out:
        return subprocess.Popen([sys.executable, "-m", "experiments.run", *argv, "--quiet"], cwd=REPO, stdout=out,
                                stderr=err, text=True)


def finish(process: subprocess.Popen, err_path: str, began: float, timeout: float = 900) -> tuple[int, str]:
    """(exit code, stderr) of a started run once it ends; prints both and its seconds."""
    code = process.wait(timeout=timeout)
    err = text(err_path)
    lines = [line for line in err.splitlines() if line.strip()]
    print(f"\n$ {' '.join(process.args[1:])}\nexit {code} after {time.time() - began:.0f} s; last line: "
          f"{lines[-1] if lines else ''}")
    return code, err


def errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error: ")]


@pytest.mark.parametrize("batch", [4_000_000, 40_000_000, 400_000_000])
def test_a_batch_far_beyond_the_gpu_is_refused_in_one_line_before_compiling(batch, tmp_path):
    """What segfaulted (4e7, 4e8) or died in the autotuner (4e6): exit 2, one `error:` line naming the batch, the
    last line, and no compiling, segfault or autotuner text."""
    began = time.time()
    code, err = finish(start(["--env", "planar_reach", "--batch-size", str(batch), "--run-dir",
                              str(tmp_path / "run")], str(tmp_path / "err")), str(tmp_path / "err"), began, 300)
    assert code == 2, err[-3000:]
    (line,) = errors(err)
    assert line.startswith(f"error: --batch-size {batch}: the training program needs at least ")
    assert "from its shapes before compiling" in line and err.strip().splitlines()[-1] == line
    assert "compiling the training program" not in err and "compiled in" not in err
    assert not any(word in err for word in AUTOTUNER) and "Traceback" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("batch", [100_000, 400_000])
def test_a_batch_at_the_edge_trains_or_ends_in_one_line(batch, tmp_path):
    """Batches whose floor fits the GPU (100,000: about 6 GiB; 400,000: about 21 GiB) but whose program may not (XLA's
    estimate on a CPU is about 3 times the floor): one short epoch trains (exit 0), or the run ends in one line, exit 2
    (the compiled program's estimate) or 6 (out of memory, or the autotuner without memory), no traceback or
    segfault."""
    began = time.time()
    argv = ["--env", "planar_reach", "--batch-size", str(batch), "--epochs", "1", "--cycles-per-epoch", "1",
            "--updates-per-cycle", "2", "--run-dir", str(tmp_path / "run")]
    code, err = finish(start(argv, str(tmp_path / "err")), str(tmp_path / "err"), began, 600)
    assert code in (0, 2, 6), err[-3000:]
    assert len(errors(err)) == (code != 0) and "Traceback" not in err
    assert not any(word in err for word in LOGS)  # XLA's C++ logs stay off the terminal
    if code:
        assert err.strip().splitlines()[-1] == errors(err)[0]


def test_two_runs_started_on_one_gpu_both_train_or_the_second_is_refused_in_one_line(tmp_path):
    """The issue's pair: visual_baseline and visual_bidal on nicol_slide, 3 seeds each, one epoch, the second started
    once the first has JAX's share of the GPU (its compile line): the second fits in what is free (JAX takes it, one
    line says so) and trains, or it is refused in one line saying what is free and how to share the GPU (exit 6);
    never the autotuner's dump or a traceback."""
    common = ["--env", "nicol_slide", "--seeds", "3", "--epochs", "1"]
    first_err, second_err = str(tmp_path / "first"), str(tmp_path / "second")
    began = time.time()
    first = start([*common, "--agent", "visual_baseline", "--run-dir", str(tmp_path / "a")], first_err)
    while "compiling the training program" not in text(first_err) and first.poll() is None:
        time.sleep(1)
    second = start([*common, "--agent", "visual_bidal", "--run-dir", str(tmp_path / "b")], second_err)
    (code_a, err_a), (code_b, err_b) = finish(first, first_err, began), finish(second, second_err, began)
    print(f"second run's lines about the GPU: {[line for line in err_b.splitlines() if 'GPU' in line]}")
    assert code_a == 0, err_a[-3000:]
    assert code_b in (0, 6), err_b[-3000:]
    for err in (err_a, err_b):
        assert "Traceback" not in err and not any(word in err for word in LOGS)
    if code_b:
        (line,) = errors(err_b)
        assert "GPU" in line and ("shared" in line or "XLA_PYTHON_CLIENT_MEM_FRACTION" in line), line
