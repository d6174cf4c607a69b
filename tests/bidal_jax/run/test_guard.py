"""The divergence guard (bidal_jax/run/guard.py): what is not finite is named by epoch, quantity and
seed; a run whose parameters stop being finite stops with exit code 3 and keeps its last good checkpoint."""

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax.run import checkpoint, guard, loop
from experiments import run
from tests.helpers import TINY, restored_state


def test_divergence_names_epoch_quantity_and_seed():
    metrics = {"actor_loss": np.array([0.1, 0.2]), "critic_loss": np.array([0.3, np.nan])}
    assert guard.divergence(metrics, {}) == "critic_loss is nan (seed 1)"
    flags = {"params/actor": np.array([True, True]), "params/critic": np.array([False, True])}
    assert (
        guard.divergence({"critic_loss": np.array([0.3, 0.1])}, flags)
        == "parameters params/critic are not finite (seed 0)"
    )
    no_flags = {"params/actor": np.array([True, True])}
    assert guard.divergence({"critic_loss": np.array([0.3, 0.1])}, no_flags) is None


def test_finite_flags_per_group_and_seed_on_host_arrays():
    groups = {
        "params/critic": {"w": np.array([[1.0, np.inf], [2.0, 3.0]], np.float32), "step": np.array([1, 2])},
        "goal_norm": {"count": np.array([4, 5])},  # no floating leaf: not checked
    }
    flags = guard.finite_flags(groups)
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
    state, step = restored_state(run_dir)
    assert step == 2
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(state.params))
