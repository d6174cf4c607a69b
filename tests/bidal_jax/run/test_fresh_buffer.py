"""Resuming without the replay buffer: a run directory carried without its checkpoints' `buffer`
items resumes with `--resume --fresh-buffer` from an empty buffer (recorded in config.json), and
without the flag is refused with one line that names the flag."""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

import envs_mjx
from bidal_jax.config import Config
from bidal_jax.run import checkpoint, loop
from experiments import run
from tests.helpers import TINY, assert_refused, restored_state

SEEDS, EPOCHS = 2, 2
# room for two epochs of episodes (4 envs × 2 cycles each), so that a refilled buffer holds fewer than the saved one
CARRIED = [*TINY, "--seeds", str(SEEDS), "--buffer-episodes", "16", "--checkpoint-every", "1"]
EPOCH_EPISODES = 8


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A run of EPOCHS epochs of SEEDS seeds, checkpointed after every epoch, buffer full."""
    run_dir = tmp_path_factory.mktemp("trained") / "run"
    assert run.main([*CARRIED, "--epochs", str(EPOCHS), "--run-dir", str(run_dir)]) == 0
    return run_dir


def carried(trained, tmp_path):
    """A copy of the `trained` run whose latest checkpoint lacks its buffer item, as carried between machines."""
    run_dir = tmp_path / "run"
    shutil.copytree(trained, run_dir)
    shutil.rmtree(run_dir / "checkpoints" / str(EPOCHS) / "buffer")
    return run_dir


def test_fresh_buffer_resumes_from_the_checkpoint_with_an_empty_buffer(trained, tmp_path, capsys):
    run_dir = carried(trained, tmp_path)
    saved = Config.from_dict(checkpoint.read_config(str(run_dir / "checkpoints")), str(run_dir))
    config = dataclasses.replace(saved, run=dataclasses.replace(saved.run, run_dir=str(run_dir)))
    lines = []
    env = envs_mjx.make("planar_reach", render=False)
    _, state, step, _ = loop.build(env, config, loop.make_programs(env, config), resume=True,
                                   log=lines.append, fresh_buffer=True)
    expected, _ = restored_state(trained)
    assert step == EPOCHS and any("empty replay buffer" in line for line in lines), lines
    for name in ("params", "target_params", "opt_state", "proprio_norm", "key", "env_steps", "epoch"):
        for a, b in zip(jax.tree.leaves(getattr(state, name)), jax.tree.leaves(getattr(expected, name)), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b)), name
    assert np.asarray(expected.buffer.size).tolist() == [2 * EPOCH_EPISODES] * SEEDS
    assert np.asarray(state.buffer.size).tolist() == np.asarray(state.buffer.position).tolist() == [0] * SEEDS
    for a, b in zip(jax.tree.leaves(state.buffer), jax.tree.leaves(expected.buffer), strict=True):
        assert (a.shape, a.dtype) == (b.shape, b.dtype)
        assert not np.any(np.asarray(a))

    # the command line continues to the next epoch: one epoch's episodes in the buffer, recorded in config.json
    assert run.main(["--resume", "--fresh-buffer", "--run-dir", str(run_dir), "--epochs", str(EPOCHS + 1),
                     "--quiet"]) == 0
    assert "empty replay buffer" in capsys.readouterr().err
    resumed, step = restored_state(run_dir)
    assert step == EPOCHS + 1
    assert np.asarray(resumed.buffer.size).tolist() == [EPOCH_EPISODES] * SEEDS
    before, recorded = (json.loads((d / "config.json").read_text()) for d in (trained, run_dir))
    assert before["fresh_buffer_epochs"] == [] and recorded["fresh_buffer_epochs"] == [EPOCHS]
    # the flag is no config field: the configs are the run's, but for the epochs and the copy's directory
    assert (recorded["train"], recorded["network"]) == (before["train"], before["network"])
    assert recorded["run"] == {**before["run"], "epochs": EPOCHS + 1, "run_dir": str(run_dir)}

    # a later resume (its checkpoint has a buffer again) keeps the record
    assert run.main(["--resume", "--run-dir", str(run_dir), "--epochs", str(EPOCHS + 2), "--quiet"]) == 0
    assert json.loads((run_dir / "config.json").read_text())["fresh_buffer_epochs"] == [EPOCHS]


def test_resume_without_a_buffer_is_refused_naming_the_flag(trained, tmp_path, capsys):
    run_dir = carried(trained, tmp_path)
    argv = ["--resume", "--run-dir", str(run_dir), "--epochs", str(EPOCHS + 1), "--quiet"]
    assert_refused(argv, run_dir, [f"checkpoint {EPOCHS} in", "--resume --fresh-buffer", "empty replay buffer"],
                   capsys)


def test_fresh_buffer_needs_resume(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert_refused([*TINY, "--fresh-buffer", "--run-dir", str(run_dir)], run_dir, ["--fresh-buffer needs --resume"],
                   capsys)


def test_fresh_buffer_record_keeps_a_resumed_runs_history(tmp_path):
    assert loop.fresh_buffer_record(str(tmp_path), 3, resume=True, fresh_buffer=True) == [3]
    (tmp_path / "config.json").write_text(json.dumps({"fresh_buffer_epochs": [2]}))
    assert loop.fresh_buffer_record(str(tmp_path), 5, resume=True, fresh_buffer=True) == [2, 5]
    assert loop.fresh_buffer_record(str(tmp_path), 5, resume=True, fresh_buffer=False) == [2]
    assert loop.fresh_buffer_record(str(tmp_path), 0, resume=False, fresh_buffer=False) == []
