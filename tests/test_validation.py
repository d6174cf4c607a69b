"""Bad input is refused clearly: bad command lines and bad checkpoints each get one `error:`
line naming the bad value, exit code 2 and an untouched run directory; a run whose loss or
parameters stop being finite stops with exit code 3 and keeps its last good checkpoint."""

import dataclasses
import glob
import hashlib
import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from bidal_jax import checkpoint, config as config_lib, loop, validate
from bidal_jax.config import NetworkConfig, RunConfig, TrainConfig
from experiments import run

TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "2", "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--quiet",
]


def snapshot(root) -> dict | None:
    """Every path under `root` with its mtime, size and content hash (None if `root` does not exist); not
    `root`'s own mtime, which a run refused after it locked the directory changes (it adds and deletes `.lock`)."""
    if not os.path.exists(root):
        return None
    found = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = os.path.join(dirpath, name)
            st = os.stat(path)
            content = hashlib.sha1(open(path, "rb").read()).hexdigest() if name in filenames else None
            found[os.path.relpath(path, root)] = (st.st_mtime_ns, st.st_size, content)
    return found


def main_exit_code(argv) -> int:
    try:
        return run.main(argv)
    except SystemExit as exit_:  # argparse's own errors
        return exit_.code


def assert_refused(argv, run_dir, expected: list, capsys) -> None:
    """main(argv) exits 2 with one `error:` line holding every `expected` string (a tuple: one of
    its strings), and leaves `run_dir` as it was."""
    before = snapshot(run_dir)
    assert main_exit_code(argv) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error: " in line]
    assert len(errors) == 1, err
    for text in expected:
        assert any(t in errors[0] for t in ((text,) if isinstance(text, str) else text)), (text, errors[0])
    assert snapshot(run_dir) == before


BAD_COMMAND_LINES = {
    "unknown env": (["--env", "nope"], ["--env 'nope'", "valid: planar_reach", "ur5_reach"]),
    "unknown agent": (["--agent", "nope"], ["--agent 'nope'", "proprio_baseline", "multimodal_bidal"]),
    "zero envs": (["--num-envs", "0"], ["--num-envs 0", "positive integer"]),
    "negative batch": (["--batch-size", "-1"], ["--batch-size -1", "positive integer"]),
    "zero epochs": (["--epochs", "0"], ["--epochs 0", "positive integer"]),
    "zero seeds": (["--seeds", "0"], ["--seeds 0", "positive integer"]),
    "negative seed": (["--seed", "-3"], ["--seed -3", "[0, 2^32)"]),
    "zero cycles": (["--cycles-per-epoch", "0"], ["--cycles-per-epoch 0"]),
    "zero updates": (["--updates-per-cycle", "0"], ["--updates-per-cycle 0"]),
    "zero eval envs": (["--eval-envs", "0"], ["--eval-envs 0"]),
    "zero hidden size": (["--hidden-size", "0"], ["--hidden-size 0", "positive integer"]),
    "three conv strides": (["--conv-strides", "2,2,1"], ["--conv-strides 2,2,1", "four comma-separated positive integers"]),
    "zero conv stride": (["--conv-strides", "2,0,1,1"], ["--conv-strides 2,0,1,1", "four comma-separated"]),
    "zero actor lr": (["--actor-lr", "0"], ["--actor-lr 0.0", "positive number"]),
    "negative critic lr": (["--critic-lr", "-0.001"], ["--critic-lr -0.001", "positive number"]),
    "nan lr": (["--critic-lr", "nan"], ["--critic-lr nan", "positive number, not nan"]),
    "gamma one": (["--gamma", "1"], ["--gamma 1.0", "(0, 1)"]),
    "gamma zero": (["--gamma", "0"], ["--gamma 0.0", "(0, 1)"]),
    "tau zero": (["--tau", "0"], ["--tau 0.0", "(0, 1]"]),
    "tau above one": (["--tau", "1.5"], ["--tau 1.5", "(0, 1]"]),
    "probability above one": (["--random-eps", "1.5"], ["--random-eps 1.5", "[0, 1]"]),
    "exploration starts above one": (["--exploration-starts", "1.5"], ["--exploration-starts 1.5", "[0, 1]"]),
    "exploration starts the env lacks": (["--exploration-starts", "0.5"], ["--exploration-starts 0.5", "env planar_reach", "must be 0"]),
    "negative target success": (["--target-success", "-0.1"], ["--target-success -0.1", "[0, 1]"]),
    "negative noise": (["--noise-eps", "-0.2"], ["--noise-eps -0.2", ">= 0"]),
    "negative her k": (["--her-k", "-1"], ["--her-k -1", ">= 0"]),
    "zero grad clip": (["--grad-clip", "0"], ["--grad-clip 0.0"]),
    "buffer not a multiple of envs": (["--buffer-episodes", "10"], ["--buffer-episodes 10", "multiple of --num-envs 4"]),
    "zero checkpoint interval": (["--checkpoint-every", "0"], ["--checkpoint-every 0", "positive integer"]),
    "resume and overwrite": (["--resume", "--overwrite"], ["--resume and --overwrite"]),
    "not an integer (argparse)": (["--num-envs", "four"], ["--num-envs", "'four'"]),
    "state larger than the device's memory": (["--seeds", "100000000"], ["--seeds 100000000", "GiB", "fewer seeds"]),
}


@pytest.mark.parametrize("case", list(BAD_COMMAND_LINES))
def test_bad_command_line_is_refused_before_anything_is_written(case, tmp_path, capsys):
    extra, expected = BAD_COMMAND_LINES[case]
    run_dir = tmp_path / "run"
    assert_refused([*TINY, "--run-dir", str(run_dir), *extra], run_dir, expected, capsys)
    assert not run_dir.exists()


def test_resume_needs_a_run_dir(capsys, tmp_path):
    assert_refused(["--resume", "--quiet"], tmp_path / "none", ["--resume needs --run-dir"], capsys)


def test_every_config_field_has_a_rule():
    fields = {f.name for cls in (RunConfig, TrainConfig, NetworkConfig) for f in dataclasses.fields(cls)}
    assert fields == set(validate.RULES)


def test_existing_run_dir_is_neither_mixed_into_nor_blindly_deleted(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.csv").write_text("epoch\n1\n")
    argv = [*TINY, "--run-dir", str(run_dir)]
    assert_refused(argv, run_dir, [str(run_dir), "not empty", "--resume", "--overwrite"], capsys)
    (run_dir / "notes.txt").write_text("mine")
    assert_refused([*argv, "--overwrite"], run_dir, ["refusing to delete", "'notes.txt'"], capsys)
    assert_refused([*argv, "--overwrite", "--gamma", "2"], run_dir, ["--gamma 2.0"], capsys)


@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    """A finished 2-epoch run with checkpoints at epochs 1 and 2."""
    run_dir = tmp_path_factory.mktemp("good") / "run"
    assert run.main([*TINY, "--epochs", "2", "--checkpoint-every", "1", "--run-dir", str(run_dir)]) == 0
    return run_dir


def _largest_state_file(run_dir) -> str:
    return max(glob.glob(f"{run_dir}/checkpoints/2/state/**/d/*", recursive=True), key=os.path.getsize)


def _truncate(run_dir) -> None:
    path = _largest_state_file(run_dir)
    data = open(path, "rb").read()
    open(path, "wb").write(data[: len(data) // 2])


def _flip_bytes(run_dir) -> None:
    path = _largest_state_file(run_dir)
    data = bytearray(open(path, "rb").read())
    middle = len(data) // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    open(path, "wb").write(bytes(data))


def _edit_json(path, group, field, value) -> None:
    with open(path) as f:
        config = json.load(f)
    config[group][field] = value
    with open(path, "w") as f:
        json.dump(config, f)


def _config_json(group, field, value):
    return lambda run_dir: _edit_json(run_dir / "config.json", group, field, value)


def _both_configs(group, field, value):
    def edit(run_dir):
        _edit_json(run_dir / "config.json", group, field, value)
        _edit_json(run_dir / "checkpoints" / "2" / "config" / "metadata", group, field, value)

    return edit


def _garbage_config(run_dir) -> None:
    (run_dir / "checkpoints" / "2" / "config" / "metadata").write_text("{not json")


def _no_change(run_dir) -> None:
    pass


BAD_CHECKPOINTS = {
    "missing": (lambda d: shutil.rmtree(d / "checkpoints"), [], ["no checkpoint in", "checkpoints"]),
    "truncated file": (_truncate, [], ["checkpoint 2 in", "is damaged"]),
    # flipped bytes of compressed data either fail to decompress or decompress to other values
    "corrupted bytes": (_flip_bytes, [], ["checkpoint 2 in", ("is damaged", "does not match its saved checksum")]),
    "unreadable config": (_garbage_config, [], ["checkpoint 2 in", "no readable config"]),
    "other env": (_config_json("run", "env", "ur5_reach"), [], ["another env", "'planar_reach'", "'ur5_reach'"]),
    "other agent": (_config_json("run", "agent", "visual_bidal"), [], ["another agent", "'visual_bidal'"]),
    "other network shape": (_config_json("network", "hidden_size", 64), [], ["another network shape", "hidden_size 128", "64"]),
    "state of another shape": (_both_configs("network", "hidden_size", 64), [], ["another shape", "128", "64"]),
    "env option differs": (_no_change, ["--env", "ur5_reach"], ["--env ur5_reach differs", "planar_reach"]),
    "agent option differs": (_no_change, ["--agent", "visual_bidal"], ["--agent visual_bidal differs", "proprio_baseline"]),
    "network option differs": (_no_change, ["--hidden-size", "64"], ["--hidden-size 64 differs", "128"]),
    "learner option differs": (_no_change, ["--gamma", "0.9"], ["--gamma 0.9 differs", "0.98"]),
    "epochs below the checkpoint": (_no_change, ["--epochs", "1"], ["--epochs 1", "checkpoint's epoch 2"]),
}


@pytest.mark.parametrize("case", list(BAD_CHECKPOINTS))
def test_bad_checkpoint_is_refused_and_left_alone(case, good_run, tmp_path, capsys):
    damage, extra, expected = BAD_CHECKPOINTS[case]
    run_dir = tmp_path / "run"
    shutil.copytree(good_run, run_dir)
    damage(run_dir)
    assert_refused(["--resume", "--run-dir", str(run_dir), "--quiet", *extra], run_dir, expected, capsys)


def test_resume_of_a_missing_run_dir_is_refused(tmp_path, capsys):
    run_dir = tmp_path / "none"
    assert_refused(["--resume", "--run-dir", str(run_dir)], run_dir, ["does not exist"], capsys)
    assert not run_dir.exists()


def test_divergence_names_epoch_quantity_and_seed():
    metrics = {"actor_loss": np.array([0.1, 0.2]), "critic_loss": np.array([0.3, np.nan])}
    assert loop.divergence(metrics, {}) == "critic_loss is nan (seed 1)"
    flags = {"params/actor": np.array([True, True]), "params/critic": np.array([False, True])}
    assert loop.divergence({"critic_loss": np.array([0.3, 0.1])}, flags) == "parameters params/critic are not finite (seed 0)"
    assert loop.divergence({"critic_loss": np.array([0.3, 0.1])}, {"params/actor": np.array([True, True])}) is None


def test_finite_flags_per_group_and_seed_on_host_arrays():
    groups = {
        "params/critic": {"w": np.array([[1.0, np.inf], [2.0, 3.0]], np.float32), "step": np.array([1, 2])},
        "goal_norm": {"count": np.array([4, 5])},  # no floating leaf: not checked
    }
    flags = loop.finite_flags(groups)
    assert list(flags) == ["params/critic"] and flags["params/critic"].tolist() == [False, True]


def test_non_finite_parameters_stop_the_run_and_keep_the_last_good_checkpoint(tmp_path, monkeypatch, capsys):
    real_build = loop.build

    def poisoning_build(*args, **kwargs):
        """The real program, but the 3rd epoch returns a NaN in the critic."""
        epoch, state, step, shards = real_build(*args, **kwargs)
        calls = []

        def poisoned(state):
            state, metrics = epoch(state)
            calls.append(None)
            if len(calls) == 3:
                critic = jax.tree.map(lambda x: x.at[0].set(jnp.nan), state.params["critic"])
                state = state.replace(params={**state.params, "critic": critic})
            return state, metrics

        return poisoned, state, step, shards

    monkeypatch.setattr(loop, "build", poisoning_build)
    run_dir = tmp_path / "run"
    ckpt_dir = run_dir / "checkpoints"
    argv = [*TINY, "--epochs", "5", "--checkpoint-every", "2", "--run-dir", str(run_dir)]
    assert run.main(argv) == 3
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert err == [
        "error: diverged at epoch 3: parameters params/critic are not finite (seed 0); "
        f"the last good checkpoint is epoch 2 in {ckpt_dir}"
    ]
    assert checkpoint.latest_step(ckpt_dir) == 2
    saved = checkpoint.read_config(ckpt_dir)
    run_cfg, train_cfg, net = config_lib.from_dict(saved, "test")
    env = envs_mjx.make(run_cfg.env, render=False)
    state, step = loop.restore_state(env, dataclasses.replace(run_cfg, run_dir=str(run_dir)), train_cfg, net)
    assert step == 2
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(state.params))
