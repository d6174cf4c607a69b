"""Command-line smoke run: `python -m experiments.run` writes metrics, TensorBoard and a checkpoint."""

import csv
import gc
import glob
import json
import os
import subprocess
import sys

import pytest

from bidal_jax.run import checkpoint
from experiments import cli, run
from tests import helpers

TINY = [
    "--env", "planar_reach", "--epochs", "2", "--checkpoint-every", "1", "--num-envs", "4",
    "--cycles-per-epoch", "2", "--updates-per-cycle", "2", "--batch-size", "8",
    "--buffer-episodes", "8", "--eval-envs", "4", "--conv-channels", "4", "--quiet",
]


@pytest.mark.slow
def test_cli_smoke_run_writes_metrics_tensorboard_and_checkpoint(tmp_path, capsys):
    run_dir = str(tmp_path / "smoke")
    assert run.main([*TINY, "--agent", "visual_bidal", "--seeds", "2", "--run-dir", run_dir]) == 0
    out = capsys.readouterr().out
    assert "final eval success" in out and run_dir in out
    with open(os.path.join(run_dir, "metrics.csv")) as f:
        rows = list(csv.DictReader(f))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    for column in ("eval_success", "train_success", "critic_loss", "actor_loss", "forward_loss", "inverse_loss",
                   "intrinsic_reward", "env_steps_total", "wall_time", "env_steps_per_second", "eval_success_seed1"):
        assert column in rows[0], column
    assert float(rows[-1]["env_steps_total"]) == 2 * 2 * 2 * 4 * 50  # epochs * cycles * seeds * envs * T
    assert any(name.startswith("events.out.tfevents") for name in os.listdir(os.path.join(run_dir, "tb")))
    assert checkpoint.latest_step(os.path.join(run_dir, "checkpoints")) == 2
    saved = checkpoint.read_config(os.path.join(run_dir, "checkpoints"))
    assert saved["run"]["agent"] == "visual_bidal" and saved["train"]["num_envs"] == 4
    with open(os.path.join(run_dir, "config.json")) as f:
        assert json.load(f) == saved


@pytest.mark.slow
def test_the_training_program_lands_in_the_runs_cache_even_where_jax_names_another(tmp_path):
    """$BIDAL_JAX_CACHE wins over JAX's own $JAX_COMPILATION_CACHE_DIR: the cache is switched on before
    anything compiles (JAX fixes the folder at a process's first compile). A fresh process, so its own first."""
    ours, jaxs = tmp_path / "ours", tmp_path / "jaxs"
    env = {**os.environ, "BIDAL_JAX_CACHE": str(ours), "JAX_COMPILATION_CACHE_DIR": str(jaxs)}
    proc = subprocess.run([sys.executable, "-m", "experiments.run", *helpers.TINY, "--epochs", "1", "--run-dir",
                           str(tmp_path / "run")], cwd=helpers.REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert glob.glob(str(ours / "jit_epoch-*")), sorted(os.listdir(ours)) if ours.exists() else "no cache folder"
    # and the small programs compiled in a fraction of a second: the seeds' keys, an env's one-by-one operations
    assert glob.glob(str(ours / "jit__threefry_split-*")), sorted(os.listdir(ours))
    assert not jaxs.exists()


def test_a_command_leaves_its_objects_frozen_for_the_exit():
    """`cli.command` freezes what is alive when its `main` returns, so that the exit skips collecting it."""
    gc.unfreeze()
    try:
        assert cli.command(lambda: 0) == 0
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_help_documents_every_option(capsys):
    with pytest.raises(SystemExit):
        run.main(["--help"])
    out = capsys.readouterr().out
    for option in (
        "--env",
        "--agent",
        "--seeds",
        "--epochs",
        "--num-envs",
        "--run-dir",
        "--gamma",
        "--intrinsic-lambda",
        "--latent-size",
        "--batch-size",
    ):
        assert option in out, option


def test_help_names_every_env_and_agent_and_each_default_once(capsys):
    import envs_mjx
    from bidal_jax.config import AGENTS

    with pytest.raises(SystemExit):
        run.main(["--help"])
    text = capsys.readouterr().out
    out = " ".join(text.split())  # argparse wraps lines
    for name in (*envs_mjx.names(), *AGENTS):
        assert name in out, name
    options = text.split("\n  --")[1:]
    assert all(option.count("(default:") <= 1 for option in options)
    assert "(default: None)" not in out and "--num-envs NUM_ENVS" in out


def test_help_opens_with_the_tasks_agents_and_presets_before_the_options():
    """What a newcomer reads first: one line of usage, then what the command does, every agent and every task with
    its preset's epochs (the first 17 lines), then that the presets override the defaults and that --print-config
    prints the resolved config, before the first option."""
    import envs_mjx
    from bidal_jax.config import AGENTS, resolve

    lines = cli.run_parser().format_help().splitlines()
    head = "\n".join(lines[:17])
    assert lines[0] == "usage: python -m experiments.run [options]"
    for name in (*envs_mjx.names(), *AGENTS):
        assert name in head, name
    for env in envs_mjx.names():
        line = next(line for line in lines if line.split()[:1] == [env])
        assert f" {resolve({'env': env}).run.epochs} epochs " in line, line
    options = lines.index("options:")
    assert options < 25 and "preset" in head and "--print-config" in "\n".join(lines[:options])


def test_the_options_a_preset_sets_say_their_default_comes_from_it():
    from bidal_jax.config import RunConfig, TrainConfig

    text = " ".join(cli.run_parser().format_help().split())
    assert f"--epochs EPOCHS training epochs (default: the task's preset, else {RunConfig.epochs})" in text
    assert f"(default: the task's preset, else {TrainConfig.num_envs})" in text
    assert f"--seeds SEEDS seeds trained together as one vmapped program (default: {RunConfig.seeds})" in text


def test_print_config_shows_the_preset_and_the_command_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run.main(["--env", "nicol_slide", "--seeds", "3", "--print-config"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["train"]["num_envs"] == 2560 and config["run"]["seeds"] == 3  # the nicol preset, then the option
    assert config["train"]["exploration_starts"] == 0.0  # faithful to the paper: no held starts by default
    assert os.listdir(tmp_path) == []
