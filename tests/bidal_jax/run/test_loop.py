"""Resuming: a stopped and resumed run equals one that never stopped, bit for bit; SIGKILL at
any moment (mid-save included) leaves a checkpoint to resume from; SIGINT and SIGTERM save
one and exit with 130 and 143. A new run's state and epoch, built side by side (`loop.build`), are the
programs' own, bit for bit; the settings a command compiles with."""

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
import types

import jax
import mujoco
import numpy as np
import pytest

import envs_mjx
from bidal_jax.config import ConfigError, TrainConfig
from bidal_jax.run import checkpoint, devices, loop
from envs_mjx import base
from experiments import cli, run
from tests.helpers import REPO, restored_state

TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "2", "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--quiet",
]
EPOCHS = 6
# the only columns that may differ between runs
TIMING = ("wall_time", "wall_time_with_compile", "env_steps_per_second")
TMP_SUFFIX = ".orbax-checkpoint-tmp"


def metric_rows(run_dir) -> list[dict[str, str]]:
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return [{k: v for k, v in row.items() if k not in TIMING} for row in csv.DictReader(f)]


def assert_same_run(run_dir, reference) -> None:
    assert metric_rows(run_dir) == metric_rows(reference)
    (state, step), (expected, expected_step) = restored_state(run_dir), restored_state(reference)
    assert step == expected_step == EPOCHS
    names = [checkpoint.leaf_name(p) for p, _ in jax.tree_util.tree_flatten_with_path(expected)[0]]
    for name, a, b in zip(names, jax.tree.leaves(state), jax.tree.leaves(expected)):
        assert np.array_equal(np.asarray(a), np.asarray(b)), name


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """A run of EPOCHS epochs that never stopped."""
    run_dir = tmp_path_factory.mktemp("straight") / "run"
    assert run.main([*TINY, "--checkpoint-every", "1", "--epochs", str(EPOCHS), "--run-dir", str(run_dir)]) == 0
    return run_dir


def test_stopped_and_resumed_run_is_bit_identical(tmp_path, straight):
    run_dir = tmp_path / "resumed"
    assert run.main([*TINY, "--checkpoint-every", "1", "--epochs", str(EPOCHS // 2), "--run-dir", str(run_dir)]) == 0
    # what a run killed after writing a row but before saving its checkpoint leaves: a row past
    # the checkpoint, then a row cut short; resuming drops both
    path = run_dir / "metrics.csv"
    last = path.read_text().splitlines()[-1].split(",", 1)[1]
    with open(path, "a") as f:
        f.write(f"{EPOCHS // 2 + 1},{last}\n{EPOCHS // 2 + 2},0.5")
    assert run.main(["--resume", "--run-dir", str(run_dir), "--epochs", str(EPOCHS), "--quiet"]) == 0
    assert_same_run(run_dir, straight)
    # config.json records the physics and the machine the run trained on, once: the resumed part ran on the same
    physics = envs_mjx.make("planar_reach", render=False).physics_id
    recorded = json.loads((run_dir / "config.json").read_text())
    assert recorded["physics"] == [physics]
    assert recorded["hardware"] == [f"{jax.device_count()} × {jax.devices()[0].device_kind}"]
    assert recorded["physics_engine"] == ["jax"]


@pytest.mark.parametrize("key", ["physics", "physics_engine", "hardware"])
def test_history_record_keeps_a_resumed_runs_history(tmp_path, key):
    assert loop.history_record(str(tmp_path), key, "new", resume=True) == ["new"]  # no config.json: unknown history
    (tmp_path / "config.json").write_text(json.dumps({key: ["old"]}))
    assert loop.history_record(str(tmp_path), key, "new", resume=True) == ["old", "new"]
    assert loop.history_record(str(tmp_path), key, "old", resume=True) == ["old"]
    assert loop.history_record(str(tmp_path), key, "new", resume=False) == ["new"]  # a fresh start: its own


def _devices(*platforms):
    return [types.SimpleNamespace(platform=p) for p in platforms]


@pytest.mark.parametrize("warp", [True, False])
def test_physics_engine_is_warp_only_on_gpus_with_warp(monkeypatch, warp):
    monkeypatch.setattr(devices.importlib.util, "find_spec", lambda name: object() if warp else None)
    for gpus in (_devices("gpu"), _devices("gpu", "gpu")):  # several GPUs: each steps its own envs
        assert devices.physics_engine("jax", gpus) == "jax"
        assert devices.physics_engine("auto", gpus) == ("warp" if warp else "jax")
        if warp:
            assert devices.physics_engine("warp", gpus) == "warp"
        else:
            with pytest.raises(ConfigError, match="warp-lang package is not installed"):
                devices.physics_engine("warp", gpus)
    for cpus in (_devices("cpu"), _devices("cpu", "cpu")):
        assert devices.physics_engine("auto", cpus) == "jax"
        with pytest.raises(ConfigError, match=r"^--physics warp needs NVIDIA GPUs and warp-lang: this run lays "
                                              r"out \d cpu device\(s\); allowed here: jax, auto$"):
            devices.physics_engine("warp", cpus)


def test_warps_contact_buffer_is_sized_for_one_devices_envs():
    """Each device steps its seeds' share of the envs: 8 seeds of 2,560 envs on 2 devices, 1,280 each."""
    train = TrainConfig(num_envs=2560, eval_envs=128)
    assert devices.physics_worlds(8, train) == 8 * 2560
    assert devices.physics_worlds(8, train, devices=2) == 4 * 2560
    assert devices.physics_worlds(1, train, devices=2, shards=2) == 1280
    assert devices.physics_worlds(2, TrainConfig(num_envs=16, eval_envs=64), devices=4, shards=2) == 32


def test_a_run_on_two_gpus_steps_warp_sized_for_one_gpus_envs(monkeypatch):
    """`use_physics` asks the env for Warp with the worlds of one device: 8 seeds of 2,560 envs on 2 GPUs."""
    config = cli.resolve({"env": "nicol_slide", "agent": "multimodal_bidal", "seeds": 8})
    monkeypatch.setattr(devices.importlib.util, "find_spec", lambda name: object())
    asked = []
    env = types.SimpleNamespace(use_backend=lambda engine, worlds: asked.append((engine, worlds)))
    devices.use_physics(env, config, _devices("gpu", "gpu"), 1)
    assert config.run.physics == "auto" and asked == [("warp", 4 * 2560)]


def test_physics_id_follows_the_model_options():
    env = envs_mjx.make("planar_reach", render=False)
    before = env.physics_id
    assert len(before) == 16 and envs_mjx.make("planar_reach", render=False).physics_id == before
    env.set_options(iterations=env.mj_model.opt.iterations + 1)
    assert env.physics_id != before


def test_the_model_digest_is_of_the_models_numbers_not_of_its_file_format(tmp_path):
    """A model saved to MuJoCo's binary and loaded back digests as before (a release may write other bytes for the
    same model: `envs_mjx.base.model_digest`), and moving its camera by a millimetre changes the digest."""
    model = envs_mjx.make("ur5_reach", render=False).mj_model
    buffer = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    (tmp_path / "model.mjb").write_bytes(buffer.tobytes())
    reloaded = mujoco.MjModel.from_binary_path(str(tmp_path / "model.mjb"))
    assert base.model_digest(reloaded) == base.model_digest(model)
    reloaded.cam_pos[0, 0] += 1e-3
    assert base.model_digest(reloaded) != base.model_digest(model)


def start(argv, log_dir, name) -> subprocess.Popen:
    """`python -m experiments.run ARGV` in the background; its output goes to LOG_DIR/NAME.{out,err}."""
    out, err = open(log_dir / f"{name}.out", "w"), open(log_dir / f"{name}.err", "w")
    return subprocess.Popen([sys.executable, "-m", "experiments.run", *argv], cwd=REPO, stdout=out, stderr=err)


def wait_for(condition, proc: subprocess.Popen, timeout: float = 300) -> bool:
    """Poll `condition` every few ms; False if the process ended first."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if condition():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.003)
    raise TimeoutError(f"condition not met within {timeout} s")


def kill(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def unfinished_saves(ckpt_dir) -> list[str]:
    return [n for n in os.listdir(ckpt_dir) if TMP_SUFFIX in n] if os.path.isdir(ckpt_dir) else []


def test_sigkill_at_any_moment_leaves_a_checkpoint_to_resume(tmp_path, straight):
    run_dir, logs = tmp_path / "killed", tmp_path
    ckpt_dir = run_dir / "checkpoints"
    resume = ["--resume", "--run-dir", str(run_dir), "--quiet"]

    # 1. as soon as the first checkpoint is complete (deleting nothing yet, or training on)
    proc = start([*TINY, "--checkpoint-every", "1", "--epochs", str(EPOCHS), "--run-dir", str(run_dir)], logs, "first")
    assert wait_for(lambda: checkpoint.latest_step(ckpt_dir) is not None, proc)
    kill(proc)

    # 2. in the middle of a save: an unfinished temporary step directory is on disk when the kill lands
    killed_mid_save = False
    for attempt in range(3):
        proc = start(resume, logs, f"mid_save{attempt}")
        if not wait_for(lambda: bool(unfinished_saves(ckpt_dir)), proc):
            break  # the run finished first
        kill(proc)
        if unfinished_saves(ckpt_dir):
            killed_mid_save = True
            break
    assert killed_mid_save
    assert checkpoint.latest_step(ckpt_dir) is not None

    # 3. while starting up and restoring
    proc = start(resume, logs, "startup")
    time.sleep(2.0)
    kill(proc)

    # 4. to the end: the same run as one that never stopped, and no unfinished save left behind
    proc = start(resume, logs, "last")
    assert proc.wait(timeout=300) == 0, (logs / "last.err").read_text()
    assert unfinished_saves(ckpt_dir) == []
    assert_same_run(run_dir, straight)


def test_sigint_and_sigterm_save_a_checkpoint_and_exit(tmp_path):
    run_dir, logs = tmp_path / "signalled", tmp_path
    ckpt_dir = run_dir / "checkpoints"
    never = ["--epochs", "100000", "--checkpoint-every", "100000"]  # only a signal saves

    def rows() -> int:
        return len(metric_rows(run_dir)) if (run_dir / "metrics.csv").exists() else 0

    proc = start([*TINY, *never, "--run-dir", str(run_dir)], logs, "sigint")
    assert wait_for(lambda: rows() >= 1, proc)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=120) == 130
    first = checkpoint.latest_step(ckpt_dir)
    assert f"interrupted: saved checkpoint at epoch {first} in {ckpt_dir}" in (logs / "sigint.err").read_text()
    assert [int(r["epoch"]) for r in metric_rows(run_dir)] == list(range(1, first + 1))

    proc = start(["--resume", "--run-dir", str(run_dir), "--quiet"], logs, "sigterm")
    assert wait_for(lambda: rows() > first, proc)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 143
    second = checkpoint.latest_step(ckpt_dir)
    assert second > first
    assert f"interrupted: saved checkpoint at epoch {second} in {ckpt_dir}" in (logs / "sigterm.err").read_text()
    assert [int(r["epoch"]) for r in metric_rows(run_dir)] == list(range(1, second + 1))


def test_a_new_runs_state_and_epoch_built_side_by_side_are_the_programs_own(tmp_path):
    """`build` compiles the epoch for the state's shapes while the state is computed in another thread: the state
    and one epoch of it are bitwise those of the programs called one after the other."""
    given = {"env": "planar_reach", "agent": "proprio_baseline", "seeds": 2, "num_envs": 4, "cycles_per_epoch": 2,
             "updates_per_cycle": 2, "batch_size": 8, "buffer_episodes": 8, "eval_envs": 4,
             "run_dir": str(tmp_path / "run")}
    env, config = envs_mjx.make("planar_reach", render=False), cli.resolve(given)
    programs = loop.make_programs(env, config)
    expected = programs.epoch(programs.init(programs.keys()))
    epoch, state, step, _ = loop.build(env, config, programs, resume=False, log=lambda message: None)
    assert step == 0
    for a, b in zip(jax.tree.leaves(epoch(state)), jax.tree.leaves(expected)):
        assert np.array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("given, expected", [(None, False), ("1", True), ("0", False)])
def test_source_locations_are_short_unless_the_user_asks_for_tracebacks(monkeypatch, given, expected):
    name = "jax_include_full_tracebacks_in_locations"
    if given is None:
        monkeypatch.delenv(name.upper(), raising=False)
    else:
        monkeypatch.setenv(name.upper(), given)
    kept = getattr(jax.config, name)
    try:
        jax.config.update(name, given != "0")  # what JAX read from the variable at import
        loop.short_source_locations()
        setting = getattr(jax.config, name)
    finally:
        jax.config.update(name, kept)
    assert setting is expected


def test_a_new_run_compiles_the_physics_kernels_and_the_saves_beside_the_epoch(tmp_path, monkeypatch):
    """What would otherwise compile at its first use (MuJoCo Warp's kernels in the first epoch, the checkpoint's copy
    and digest at the first save) compiles in the init thread while the epoch compiles, once each."""
    calls = []
    monkeypatch.setattr(envs_mjx.base.Env, "compile_physics",
                        lambda self: calls.append(("physics", threading.current_thread().name)))
    monkeypatch.setattr(checkpoint, "compile_for",
                        lambda state: calls.append(("saves", threading.current_thread().name)))
    assert run.main([*TINY, "--epochs", "1", "--run-dir", str(tmp_path / "run")]) == 0
    assert [what for what, _ in calls] == ["saves", "physics"]
    assert all(thread != threading.main_thread().name for _, thread in calls)


@pytest.mark.parametrize("background", [True, False])
def test_checkpoints_are_written_beside_the_next_epochs_unless_warp_steps_them(tmp_path, monkeypatch, background):
    """`loop.Checkpoints`: a save in a thread while the next epochs train, or (MuJoCo Warp's physics, whose CUDA graph
    capture a save's transfers from another thread break) in place, on disk before the next epoch."""
    calls = []
    monkeypatch.setattr(loop.checkpoint, "save", lambda mngr, e, *a: calls.append(("in place", e)))
    monkeypatch.setattr(loop.checkpoint, "save_in_background",
                        lambda mngr, e, *a: calls.append(("thread", e)) or loop.checkpoint.Pending(e))
    checkpoints = loop.Checkpoints(str(tmp_path / "checkpoints"), {}, 1, 2, None, "1 MB", background=background)
    for e in (1, 2, 3):
        checkpoints(e, None, {"eval_success": 0.5}, last=e == 3)
    assert calls == [("thread" if background else "in place", 2), ("in place", 3)]
    assert checkpoints.saved == 3
    checkpoints.close()
