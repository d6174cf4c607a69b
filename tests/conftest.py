"""Test configuration: the test processes set up as the command lines' (`experiments.start_process`: XLA:CPU flags,
MuJoCo's OpenGL backend), JAX's persistent compilation cache, so that reruns skip compiles, and the fixtures that
several test modules share."""

import experiments  # noqa: F401 - first, before anything imports MuJoCo: it sets up the process

# isort: split
import contextlib
import csv
import json
import os
import types

import jax
import pytest

import envs_mjx
from bidal_jax.run import loop, preflight, rundir
from experiments import cli, run
from tests.helpers import FINISHED

# per user, not per checkout, so that a fresh clone (CI's) finds what earlier runs on the machine compiled (about a
# third of the suite's time); $BIDAL_JAX_TEST_CACHE chooses another folder
CACHE = os.environ.get("BIDAL_JAX_TEST_CACHE") or os.path.join(
    os.environ.get("XDG_CACHE_HOME") or os.path.expanduser(os.path.join("~", ".cache")), "bidal_jax", "tests")
os.environ.setdefault("BIDAL_JAX_CACHE", CACHE)  # the runs' own cache (`cachefolder.enable`)
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


# ----- paper experiments (experiments/paper/grid.py) without training ----------------------------------------


TODAY = "0123456789abcdef"  # the physics fingerprint (`Env.physics_id`) of every env of `no_nicol` and test_claims


def write_fake_run(run_dir: str, env: str, rows, checkpoint_epoch: int | None, agent: str = "multimodal_bidal",
                   compile_seconds: float | None = None, physics: list[str] | None = None,
                   given: dict | None = None, buffer: bool = True) -> None:
    """A run directory as `loop.train` writes it (config.json, metrics.csv), with an (empty) checkpoint
    step unless `checkpoint_epoch` is None, holding an (empty) replay buffer item unless `buffer` is False (a
    checkpoint whose buffer was deleted). `rows`: per epoch, each seed's eval success; every
    epoch is 100 env steps per seed and 10 s of wall time. With `compile_seconds`, metrics.csv has
    `wall_time_with_compile` (`wall_time` plus them); without, it is a run recorded before that column. With
    `physics`, config.json records those physics fingerprints; without, it is a run recorded before them. With
    `given` (config fields, e.g. an arm's `given`), config.json holds the whole config they resolve to, as a run
    writes it; without, only the run's env, agent and seeds (every other field takes its default when read)."""
    seeds = len(rows[0])
    step = None if checkpoint_epoch is None else os.path.join(run_dir, "checkpoints", str(checkpoint_epoch))
    os.makedirs(run_dir if step is None else os.path.join(step, "buffer") if buffer else step)
    with open(os.path.join(run_dir, "config.json"), "w") as f:
        config = {"run": {"env": env, "agent": agent, "seeds": seeds}, "train": {}, "network": {}}
        if given is not None:
            config = cli.resolve({**given, "env": env, "agent": agent, "seeds": seeds, "run_dir": run_dir}).to_dict()
        json.dump(config | ({"physics": physics} if physics is not None else {}), f)
    with open(os.path.join(run_dir, "metrics.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        with_compile = [] if compile_seconds is None else ["wall_time_with_compile"]
        writer.writerow(["epoch", "eval_success", *(f"eval_success_seed{i}" for i in range(seeds)), "env_steps_total",
                         "wall_time", *with_compile])
        for epoch, success in enumerate(rows, start=1):
            times = [10.0 * epoch] + ([] if compile_seconds is None else [10.0 * epoch + compile_seconds])
            writer.writerow([epoch, sum(success) / seeds, *success, 100 * seeds * epoch, *times])


@pytest.fixture
def fake_run():
    """`write_fake_run`: a hand-written run directory."""
    return write_fake_run


@pytest.fixture
def no_nicol(monkeypatch):
    """Envs that only tell their episode length and physics (`TODAY`), and a record of the runs prepared and
    trained."""
    calls, delete_run_dir = [], rundir.delete_run_dir
    monkeypatch.setattr(envs_mjx, "make", lambda name, **kw: types.SimpleNamespace(
        episode_length=50, observation_spec=types.SimpleNamespace(proprio_segments=()), physics_id=TODAY))

    @contextlib.contextmanager
    def prepare(given, resume, overwrite, env=None, **kwargs):
        calls.append(("prepare", given["run_dir"], resume, overwrite))
        if overwrite:
            delete_run_dir(given["run_dir"])
        yield preflight.Prepared(cli.resolve(given), env or envs_mjx.make(given["env"]), None)

    def train(env, config, *, resume, initialize, **kwargs):
        # a run without a checkpoint was emptied first (but for its lock, which a real prepare took)
        run_dir = config.run.run_dir
        assert resume or not os.path.exists(run_dir) or set(os.listdir(run_dir)) <= {".lock"}
        calls.append(("train", run_dir, resume, initialize is not None))
        return {}

    monkeypatch.setattr(preflight, "prepare", prepare)
    monkeypatch.setattr(loop, "train", train)
    return calls


@pytest.fixture(scope="session")
def finished(tmp_path_factory):
    """A finished tiny run (`helpers.FINISHED`) with a checkpoint saved after every epoch, and its metrics rows."""
    run_dir = str(tmp_path_factory.mktemp("finished") / "run")
    assert run.main([*FINISHED, "--run-dir", run_dir]) == 0
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return run_dir, list(csv.DictReader(f))
