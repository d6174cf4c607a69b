"""Device memory (bidal_jax/run/memory.py): a run whose epoch cannot fit the device stops before it trains with one
line saying what to reduce: from its shapes before anything compiles (the floor: sizes far beyond a GPU, which XLA's
GPU compiler may not survive), else from the compiled program's own estimate; running out all the same while
compiling or in an epoch, or XLA's autotuner failing for want of memory, ends the run in one line with exit 6, and
its last checkpoint resumes. A GPU that another process holds: JAX takes what is free of it, and a run that does not
fit there is refused at its start in one line (exit 6) saying what is free, what it needs and how to share the GPU.
On a CPU, with the device's size, the GPU's driver or the compiled epoch patched."""

import os
import re
import shutil
import subprocess
import sys
import types

import jax
import pytest

import envs_mjx
from bidal_jax.config import AGENTS, ConfigError
from bidal_jax.run import checkpoint, loop, memory
from experiments import cli, run
from experiments.cli import resolve
from tests.helpers import FINISHED, FINISHED_EPOCHS, TINY, rows, snapshot

MiB, GiB = 2**20, 2**30
H100 = int(0.75 * 80e9)  # what JAX takes of an 80 GB H100 by default
EXHAUSTED = "RESOURCE_EXHAUSTED: Out of memory while trying to allocate 1.50GiB."
AUTOTUNER = "INTERNAL: Failed to get configs for: 2 out of 851 instructions"
SHARED = "GPU 0 is shared: other processes hold 60.0 GiB of its 80.0 GiB"
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
    """A batch that the state's estimate cannot see (the state does not hold it), and whose floor fits (about 47 MB
    for 15,000 transitions): its compiled epoch's working memory (XLA's estimate, about 80 MB) is more than the
    device's, refused in one line before the first epoch, with exit 2."""
    monkeypatch.setattr(memory, "device_memory", lambda: 64 * MiB)  # the state (about 1 MiB) fits
    run_dir = tmp_path / "run"
    assert run.main([*TINY, "--batch-size", "15000", "--epochs", "2", "--run-dir", str(run_dir)]) == 2
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


def test_an_autotuning_failure_while_compiling_is_one_line_and_exit_6(tmp_path, monkeypatch, capsys):
    """XLA's GPU autotuner tries its kernels in the memory JAX leaves free: where it can try none, one line says so
    (not the autotuner's stack), exit 6; on a GPU that other processes hold, the line is the one that says what is
    free and how to share the GPU."""
    def autotuner_fails(*args, **kwargs):
        raise jax.errors.JaxRuntimeError(AUTOTUNER)

    monkeypatch.setattr(loop, "_compile", autotuner_fails)
    assert run.main([*TINY, "--epochs", "2", "--run-dir", str(tmp_path / "a")]) == 6
    err = capsys.readouterr().err
    assert error_lines(err) == [f"error: XLA's autotuner could not try the kernels of the program while compiling and "
                                f"starting the training program ({AUTOTUNER}): it runs them in the GPU memory beside "
                                f"JAX's share; {REDUCE}, or give JAX a smaller share of the GPU "
                                "(XLA_PYTHON_CLIENT_MEM_FRACTION, now 0.75); no checkpoint was saved"]
    assert "Traceback" not in err
    monkeypatch.setattr(memory, "shared_gpu_line", lambda needed=None: SHARED)
    assert run.main([*TINY, "--epochs", "2", "--run-dir", str(tmp_path / "b")]) == 6
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith("error: XLA's autotuner could not try") and line.endswith(
        f"; {SHARED}; no checkpoint was saved")


def test_running_out_beside_another_process_says_how_to_share_the_gpu(monkeypatch):
    """A GPU taken by another process mid-run: the epoch's RESOURCE_EXHAUSTED names the last good checkpoint and,
    instead of what to reduce, that the GPU is shared (`shared_gpu_line`)."""
    err = jax.errors.JaxRuntimeError(EXHAUSTED)
    monkeypatch.setattr(memory, "shared_gpu_line", lambda needed=None: SHARED)
    assert str(memory.ran_out("training epoch 3", err, "the last good checkpoint is epoch 2 in DIR")) == (
        f"out of device memory while training epoch 3 ({EXHAUSTED}); {SHARED}; the last good checkpoint is epoch 2 "
        "in DIR")
    assert cli.failure(memory.ran_out("training epoch 3", err, "x"))[0] == cli.EXIT_MEMORY


# ----- the floor: sizes refused from their shapes, before XLA compiles -----------------------------------------


@pytest.fixture(scope="module")
def planar_floor():
    """`memory.floor` of planar_reach's preset for an agent (one seed, one device), given the config's changes."""
    envs = {image: envs_mjx.make("planar_reach", render=image) for image in (False, True)}

    def least(agent="multimodal_bidal", state=0, seeds=1, shards=1, **given):
        config = resolve({"env": "planar_reach", "agent": agent, **given})
        return memory.floor(config, envs[config.agent.uses_image], state, seeds, shards)

    return least


def test_the_floor_grows_with_the_batch_the_envs_and_the_seeds_and_shrinks_with_shards(planar_floor):
    base = planar_floor()
    assert base.state == 0 and base.update > base.rollout > 0
    double = planar_floor(batch_size=512)
    # a transition of an image agent: its two frames' conv maps dominate (more than 40 KB), and proprio's far less
    per_transition = (double.update - base.update) / 256
    assert per_transition > 40_000
    proprio = planar_floor("proprio_baseline", batch_size=512)
    assert 1_000 < (proprio.update - planar_floor("proprio_baseline").update) / 256 < per_transition / 10
    assert planar_floor(seeds=3) == (0, 3 * base.update, 3 * base.rollout)
    assert planar_floor(shards=2, num_envs=32, batch_size=512) == planar_floor(num_envs=16, batch_size=256)
    wide = planar_floor(num_envs=160, eval_envs=160)  # the camera's 84 × 84 rays of every env, and its records
    assert wide.rollout == 10 * base.rollout
    assert planar_floor(state=5).needed == 5 + base.update
    # bfloat16 vision halves the conv maps: less per frame
    assert planar_floor(vision_dtype="bfloat16").update < base.update


@pytest.mark.parametrize("batch", [4_000_000, 40_000_000, 400_000_000])
def test_batches_far_beyond_an_h100_are_refused_from_their_shapes_before_compiling(batch, tmp_path, monkeypatch,
                                                                                 capsys):
    """What segfaulted XLA's GPU compiler or failed its autotuner on an 80 GB H100 is refused in one line before
    anything compiles (compiling fails this test), exit 2, naming the batch, and nothing is written."""
    monkeypatch.setattr(memory, "device_memory", lambda: H100)

    def compiles(*args, **kwargs):
        raise AssertionError("compiled")

    monkeypatch.setattr(loop, "_compile", compiles)
    run_dir = tmp_path / "run"
    assert run.main(["--env", "planar_reach", "--batch-size", str(batch), "--run-dir", str(run_dir)]) == 2
    err = capsys.readouterr().err
    (line,) = error_lines(err)
    assert re.fullmatch(rf"error: --batch-size {batch}: the training program needs at least [\d,]+\.\d GiB of device "
                        r"memory, from its shapes before compiling \(the state 0\.4 GiB and an update's batch "
                        r"[\d,.]+ GiB\), more than 90% of the device's 55\.9 GiB; use a smaller --batch-size", line)
    assert "compiling" not in err.replace("before compiling", "") and not run_dir.exists()


def test_the_floor_refuses_rollouts_by_their_envs_and_seeds(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(memory, "device_memory", lambda: 2 * GiB)  # the state (0.8 GiB) fits
    assert run.main(["--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "200000",
                     "--buffer-episodes", "200000", "--seeds", "2", "--run-dir", str(tmp_path / "run")]) == 2
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith("error: --num-envs 200000: the training program needs at least ")
    assert "a rollout's envs" in line and line.endswith("use fewer --num-envs or --eval-envs or fewer seeds")


def test_every_preset_fits_a_cpus_memory_and_five_seeds_an_h100(monkeypatch):
    """The floor refuses nothing that trains today: every task's preset for each kind of agent, one seed within
    16 GiB of a CPU's memory, five seeds (a cell of the paper's grid) within JAX's share of an 80 GB H100; and it
    is below XLA's own estimate of the largest program the paper trains."""
    for env_name in envs_mjx.names():
        for agent in ("proprio_baseline", "multimodal_bidal"):
            config = resolve({"env": env_name, "agent": agent})
            env = envs_mjx.make(env_name, render=AGENTS[agent].uses_image)
            state = memory.tree_bytes(loop.make_programs(env, config).abstract_state())
            memory.check_floor(memory.floor(config, env, state, 1, 1), 16 * GiB, config)
            memory.check_floor(memory.floor(config, env, 5 * state, 5, 1), H100, config)
    # the paper's noise program, whose compiled epoch XLA estimated at 94.6 GiB on an H200: the floor stays below
    config = resolve({"env": "nicol_slide", "seeds": 15, "noise_segments": "ee_pos,ee_rot,obj_pos", "obs_noise": 0.1})
    env = envs_mjx.make("nicol_slide", render=True)
    state = memory.tree_bytes(loop.make_programs(env, config).abstract_state())
    assert memory.floor(config, env, state, 15, 1).needed < 94.6 * GiB / 2


def test_a_run_resumed_on_a_smaller_device_is_refused_and_its_checkpoints_kept(finished, tmp_path, monkeypatch,
                                                                               capsys):
    """A checkpoint of a device larger than this one: its config cannot change, so the line says to resume it on a
    device with more memory; exit 2, and the run folder is as it was."""
    run_dir = str(tmp_path / "run")
    shutil.copytree(finished[0], run_dir)
    before = snapshot(run_dir)
    for size, what in ((MiB, "--seeds 2: the training state needs"),  # its state (2.2 MB) does not fit
                       (2_500_000, "--batch-size 16: the training program needs at least")):  # its epoch's floor
        monkeypatch.setattr(memory, "device_memory", lambda size=size: size)
        assert run.main(["--resume", "--run-dir", run_dir, "--epochs", "6", "--quiet"]) == 2
        (line,) = error_lines(capsys.readouterr().err)
        assert line.startswith(f"error: {what}") and line.endswith(memory.RESUME_ELSEWHERE)
        assert snapshot(run_dir) == before


# ----- a GPU that other processes hold ---------------------------------------------------------------------------


SMI = "0, GPU-aaaa, 20480, 81920\n1, GPU-bbbb, 81000, 81920\n"


@pytest.fixture
def smi(monkeypatch):
    """`nvidia-smi` answers `SMI` (pynvml not installed); the fixture records its calls."""
    calls = []
    monkeypatch.setitem(sys.modules, "pynvml", None)
    monkeypatch.setattr(memory.shutil, "which", lambda name: f"/usr/bin/{name}")

    def answer(command, **kwargs):
        calls.append(command)
        return subprocess.CompletedProcess(command, 0, SMI, "")

    monkeypatch.setattr(memory.subprocess, "run", answer)
    return calls


def test_the_gpus_free_memory_is_read_for_the_gpus_cuda_sees(smi, monkeypatch):
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert memory.gpus() == [memory.Gpu("0", 20 * GiB, 80 * GiB), memory.Gpu("1", 81000 * MiB, 80 * GiB)]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "GPU-bbbb")
    assert memory.gpus() == [memory.Gpu("1", 81000 * MiB, 80 * GiB)]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    assert memory.gpus() == [memory.Gpu("0", 20 * GiB, 80 * GiB)]
    assert smi[0] == memory.GPU_QUERY
    monkeypatch.setattr(memory.shutil, "which", lambda name: None)
    assert memory.gpus() == []  # no NVIDIA tool: nothing known


def test_jax_takes_what_is_free_of_a_gpu_that_others_hold(smi, monkeypatch):
    """Before JAX starts on a GPU of which another process holds 60 GiB: JAX's 75 % would take all that is free and
    leave XLA's autotuner nothing, so JAX takes the 20 GiB free less room for it, and one line says so."""
    monkeypatch.setattr(memory, "_may_use_gpu", lambda: True)
    monkeypatch.setattr(memory, "_backend_started", lambda: False)
    for name in memory.FRACTION_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1")  # a GPU of its own: JAX's share is free
    lines = []
    memory.share_gpu(lines.append)
    assert lines == [] and "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")
    memory.share_gpu(lines.append)
    assert os.environ["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.20"  # (20 - 4) GiB of 80
    assert lines == ["GPU 0: other processes hold 60.0 GiB of its 80.0 GiB; JAX takes 16.0 GiB of the 20.0 GiB "
                     "free (XLA_PYTHON_CLIENT_MEM_FRACTION 0.75 -> 0.20)"]
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION")
    monkeypatch.setenv("XLA_CLIENT_MEM_FRACTION", "0.5")  # JAX's newer name: the one changed (both at once fail)
    memory.share_gpu(lines.append)
    assert os.environ["XLA_CLIENT_MEM_FRACTION"] == "0.20" and "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ
    monkeypatch.setattr(memory, "gpus", lambda: [memory.Gpu("0", 43 * GiB, 80 * GiB)])
    monkeypatch.setenv("XLA_CLIENT_MEM_FRACTION", "0.45")  # the second of two grid cells on a GPU: its share is free
    memory.share_gpu(lines.append)
    assert os.environ["XLA_CLIENT_MEM_FRACTION"] == "0.45" and len(lines) == 2
    monkeypatch.setattr(memory, "_backend_started", lambda: True)  # too late: JAX holds its share
    monkeypatch.setenv("XLA_CLIENT_MEM_FRACTION", "0.9")
    memory.share_gpu(lines.append)
    assert os.environ["XLA_CLIENT_MEM_FRACTION"] == "0.9" and len(lines) == 2


def test_a_run_that_does_not_fit_beside_another_process_is_refused_at_its_start_with_exit_6(monkeypatch):
    """JAX holds 16 GiB of a GPU whose 60 GiB another process holds (4 GiB are free): a run whose floor does not fit
    there is refused in one line saying what is left, what it needs and how to share a GPU; exit 6 (it fits once the
    GPU is free)."""
    gpu = types.SimpleNamespace(platform="gpu", memory_stats=lambda: {"bytes_limit": 16 * GiB, "pool_bytes": 16 * GiB})
    monkeypatch.setattr(jax, "local_devices", lambda: [gpu])
    monkeypatch.setattr(memory, "gpus", lambda: [memory.Gpu("0", 4 * GiB, 80 * GiB)])
    config = resolve({"env": "planar_reach"})
    least = memory.Floor(2 * GiB, 30 * GiB, GiB)
    with pytest.raises(memory.OutOfMemory) as refused:
        memory.check_floor(least, 16 * GiB, config)
    assert str(refused.value) == (
        "GPU 0 is shared: other processes hold 60.0 GiB of its 80.0 GiB, 20.0 GiB are left to this process, and this "
        "run needs at least 32.0 GiB; wait for them to end, or share the GPU between runs, each with a part of it: "
        "XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 for each of two runs started together, or a grid's --gpus-per-cell 0.5")
    assert cli.failure(refused.value)[0] == cli.EXIT_MEMORY
    memory.check_floor(memory.Floor(2 * GiB, 10 * GiB, GiB), 16 * GiB, config)  # it fits: nothing said
    with pytest.raises(ConfigError, match=r"^--batch-size 256: .* needs at least 102\.0 GiB"):  # not even alone
        memory.check_floor(memory.Floor(2 * GiB, 100 * GiB, GiB), 16 * GiB, config)


def test_envs_that_do_not_divide_across_the_devices_train_on_fewer_and_the_compile_line_says_why(monkeypatch):
    """`--env-shards 4` with 6 envs: a split must divide the envs, so 2 devices split them (`devices.device_layout`),
    and the run's compile line says why not 4, rather than leave 2 devices idle unexplained."""
    monkeypatch.setattr(loop, "_initial_state_and_epoch", lambda *args: (None, None))
    config = resolve({"env": "planar_reach", "agent": "proprio_baseline", "num_envs": 6, "eval_envs": 4,
                      "batch_size": 8, "env_shards": 4})
    programs = loop.Programs(None, None, None, [types.SimpleNamespace(platform="cpu")] * 2, 2, 0, 1)
    lines = []
    loop.build(types.SimpleNamespace(backend="jax"), config, programs, False, log=lines.append)
    assert lines[0] == ("compiling the training program (planar_reach, proprio_baseline, 1 seed(s) on 2 device(s), "
                        "envs split 2 ways (--env-shards 4: a split divides --num-envs 6, --eval-envs 4 and the "
                        "batch's 8 runs)) ...")
    lines.clear()  # 8 envs on 2 devices: as many splits as devices, nothing to say
    config = resolve({"env": "planar_reach", "agent": "proprio_baseline", "num_envs": 8, "eval_envs": 4,
                      "batch_size": 8, "env_shards": 4})
    loop.build(types.SimpleNamespace(backend="jax"), config, programs, False, log=lines.append)
    assert lines[0].endswith("1 seed(s) on 2 device(s), envs split 2 ways) ...")
