"""Bad input is refused before anything is written (bidal_jax/run/preflight.py, validate.py): bad
command lines and bad checkpoints each get one `error:` line naming the bad value, exit code 2 and
an untouched run directory."""

import glob
import json
import os
import shutil

import pytest

from experiments import run
from tests.helpers import TINY, assert_refused

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
    "three conv strides": (
        ["--conv-strides", "2,2,1"],
        ["--conv-strides 2,2,1", "four comma-separated positive integers"],
    ),
    "zero conv stride": (["--conv-strides", "2,0,1,1"], ["--conv-strides 2,0,1,1", "four comma-separated"]),
    "unknown conv implementation": (["--conv-impl", "fft"], ["--conv-impl fft", "one of patch, banded"]),
    "zero actor lr": (["--actor-lr", "0"], ["--actor-lr 0.0", "positive number"]),
    "negative critic lr": (["--critic-lr", "-0.001"], ["--critic-lr -0.001", "positive number"]),
    "nan lr": (["--critic-lr", "nan"], ["--critic-lr nan", "positive number, not nan"]),
    "gamma one": (["--gamma", "1"], ["--gamma 1.0", "(0, 1)"]),
    "gamma zero": (["--gamma", "0"], ["--gamma 0.0", "(0, 1)"]),
    "tau zero": (["--tau", "0"], ["--tau 0.0", "(0, 1]"]),
    "tau above one": (["--tau", "1.5"], ["--tau 1.5", "(0, 1]"]),
    "probability above one": (["--random-eps", "1.5"], ["--random-eps 1.5", "[0, 1]"]),
    "exploration starts above one": (["--exploration-starts", "1.5"], ["--exploration-starts 1.5", "[0, 1]"]),
    "exploration starts the env lacks": (
        ["--exploration-starts", "0.5"],
        ["--exploration-starts 0.5", "env planar_reach", "must be 0"],
    ),
    "negative target success": (["--target-success", "-0.1"], ["--target-success -0.1", "[0, 1]"]),
    "negative noise": (["--noise-eps", "-0.2"], ["--noise-eps -0.2", ">= 0"]),
    "negative her k": (["--her-k", "-1"], ["--her-k -1", ">= 0"]),
    "zero grad clip": (["--grad-clip", "0"], ["--grad-clip 0.0"]),
    "buffer not a multiple of envs": (
        ["--buffer-episodes", "10"],
        ["--buffer-episodes 10", "multiple of --num-envs 4"],
    ),
    "runs that do not divide the batch": (["--sample-run", "3"], ["--sample-run 3", "divide --batch-size"]),
    "runs longer than the episodes": (["--sample-run", "64", "--batch-size", "64"],
                                      ["--sample-run 64", "env planar_reach", "must be at most"]),
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
    "other network shape": (
        _config_json("network", "hidden_size", 64),
        [],
        ["another network shape", "hidden_size 128", "64"],
    ),
    "state of another shape": (_both_configs("network", "hidden_size", 64), [], ["another shape", "128", "64"]),
    "env option differs": (_no_change, ["--env", "ur5_reach"], ["--env ur5_reach differs", "planar_reach"]),
    "agent option differs": (
        _no_change,
        ["--agent", "visual_bidal"],
        ["--agent visual_bidal differs", "proprio_baseline"],
    ),
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


def test_resume_may_change_how_the_convs_are_computed_and_the_engine(good_run, capsys):
    """--conv-impl computes the same function with the same parameters and --physics steps the same model: a
    resumed run may switch them."""
    assert run.main(["--print-config", "--resume", "--run-dir", str(good_run), "--conv-impl", "banded",
                     "--physics", "auto"]) == 0
    resumed = json.loads(capsys.readouterr().out)
    assert (resumed["network"]["conv_impl"], resumed["run"]["physics"]) == ("banded", "auto")
    saved = json.loads((good_run / "config.json").read_text())
    assert (saved["network"]["conv_impl"], saved["run"]["physics"]) == ("patch", "jax")


def test_resume_of_a_missing_run_dir_is_refused(tmp_path, capsys):
    run_dir = tmp_path / "none"
    assert_refused(["--resume", "--run-dir", str(run_dir)], run_dir, ["does not exist"], capsys)
    assert not run_dir.exists()
