"""Seeds sharded over devices (jax.sharding): 4 seeds on 4 (CPU) devices give the metrics of the
same 4 seeds on one device, and a checkpoint written on 4 devices resumes on 1. One seed's envs
split over 4 devices (shard_map) keep one set of parameters and resume on 1 device."""

import os
import subprocess
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bidal_jax.config import TrainConfig
from bidal_jax.run.devices import device_layout, over_seeds, seed_devices
from experiments import run
from tests.helpers import REPO, assert_same_metrics, rows
from tests.helpers import SHARDED as TINY


def test_seeds_spread_over_as_many_devices_as_divide_them():
    devices = [types.SimpleNamespace(process_index=0, name=f"d{i}") for i in range(4)]
    assert seed_devices(8, devices) == devices
    assert seed_devices(6, devices) == devices[:2]
    assert seed_devices(1, devices) == devices[:1]
    assert seed_devices(5, devices) == devices[:1]


@pytest.mark.parametrize("seeds", [1, 3])
def test_over_seeds_maps_the_seed_axis_and_runs_one_seed_on_its_row(seeds):
    """Each seed's result is `fn` of its row, with the axis kept; one seed reaches `fn` without vmap's batching."""
    batched = []

    def fn(state, key):
        batched.append("Batch" in type(state["x"]).__name__)  # vmap's tracer
        return {"x": state["x"] * 2 + jax.random.uniform(key)}, state["x"].sum()

    state = {"x": jnp.arange(seeds * 4, dtype=jnp.float32).reshape(seeds, 4)}
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    out, total = jax.jit(over_seeds(fn))(state, keys)
    assert out["x"].shape == (seeds, 4) and total.shape == (seeds,)
    for i in range(seeds):
        row, row_total = fn({"x": state["x"][i]}, keys[i])
        np.testing.assert_allclose(out["x"][i], row["x"], rtol=1e-6)
        np.testing.assert_allclose(total[i], row_total, rtol=1e-6)
    assert batched[0] is (seeds > 1)


def test_devices_the_seeds_leave_split_their_envs():
    devices = [types.SimpleNamespace(process_index=0, name=f"d{i}") for i in range(4)]
    config = TrainConfig(num_envs=16, eval_envs=64, batch_size=256)
    assert device_layout(1, config, 4, devices) == (devices, 4)
    assert device_layout(2, config, 4, devices) == (devices, 2)
    assert device_layout(3, config, 4, devices) == (devices, 4)  # 3 seeds on one row of 4 shards
    assert device_layout(4, config, 4, devices) == (devices, 1)
    assert device_layout(1, TrainConfig(num_envs=6, eval_envs=64, batch_size=256), 4, devices) == (devices[:2], 2)
    assert device_layout(1, TrainConfig(num_envs=16, noise_segments="joint_pos"), 4, devices) == (devices[:1], 1)
    two_hosts = [types.SimpleNamespace(process_index=p, name=f"d{p}{i}") for p in (0, 1) for i in (0, 1)]
    assert device_layout(2, config, 2, two_hosts) == (two_hosts, 2)
    assert device_layout(1, config, 1, devices) == (devices[:1], 1)  # the default: no env shards
    assert device_layout(1, config, 2, devices) == (devices[:2], 2)
    # each shard draws whole runs of transitions: 256 / 128 = 2 runs
    assert device_layout(1, TrainConfig(num_envs=16, eval_envs=64, batch_size=256, sample_run=128), 4,
                         devices) == (devices[:2], 2)


@pytest.mark.slow
def test_four_seeds_on_four_devices_match_one_device_and_resume_on_one(tmp_path, capsys):
    sharded, single = str(tmp_path / "sharded"), str(tmp_path / "single")
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"}
    proc = subprocess.run([sys.executable, "-m", "experiments.run", *TINY, "--epochs", "2", "--run-dir", sharded],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "4 seed(s) on 4 device(s)" in proc.stderr
    assert jax.device_count() == 1
    assert run.main([*TINY, "--epochs", "2", "--run-dir", single]) == 0
    assert_same_metrics(sharded, single)
    # the 4-device checkpoint continues on this 1-device process
    assert run.main(["--resume", "--run-dir", sharded, "--epochs", "3", "--quiet"]) == 0
    assert "on 1 device(s)" in capsys.readouterr().err
    assert [r["epoch"] for r in rows(sharded)] == [1.0, 2.0, 3.0]


ENV_SHARDS = """
import jax, numpy as np
import envs_mjx
from bidal_jax.config import Config, RunConfig, TrainConfig
from bidal_jax.run.devices import device_layout, make_seeded
from bidal_jax.train import make_train
config = TrainConfig(num_envs=4, cycles_per_epoch=2, updates_per_cycle=2, batch_size=8, buffer_episodes=8, eval_envs=4)
devices, shards = device_layout(1, config, 4)
assert shards == 4, shards
env = envs_mjx.make("planar_reach", render=False)
config = Config(RunConfig(agent="proprio_baseline"), config)
init, epoch = make_seeded(*make_train(env, config, shards), devices, shards)
state, _ = epoch(init(jax.random.split(jax.random.PRNGKey(0), 1)))
for leaf in jax.tree.leaves(state.params):  # averaged gradients: every shard holds the same parameters
    copies = [np.asarray(s.data) for s in leaf.addressable_shards]
    assert len(copies) == 4 and all((c == copies[0]).all() for c in copies)
blocks = [np.asarray(b.data) for b in state.buffer.episodes["proprio"].addressable_shards]
assert [b.shape[1] for b in blocks] == [2] * 4 and not (blocks[0] == blocks[1]).all()  # each shard's own episodes
"""


@pytest.mark.slow
def test_one_seeds_envs_split_over_four_devices_share_parameters_and_resume_on_one(tmp_path, capsys):
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"}
    proc = subprocess.run(
        [sys.executable, "-c", ENV_SHARDS], cwd=REPO, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    run_dir = str(tmp_path / "split")
    one_seed = [*TINY[:-4], "--seeds", "1", "--checkpoint-every", "1", "--env-shards", "4"]
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.run", *one_seed, "--epochs", "2", "--run-dir", run_dir],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "1 seed(s) on 4 device(s), envs split 4 ways" in proc.stderr
    # its buffer, kept in 4 blocks, continues in one (replay.relayout)
    assert run.main(["--resume", "--run-dir", run_dir, "--epochs", "3", "--quiet"]) == 0
    assert "1 seed(s) on 1 device(s))" in capsys.readouterr().err
    assert [r["epoch"] for r in rows(run_dir)] == [1.0, 2.0, 3.0]
