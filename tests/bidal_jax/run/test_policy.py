"""A trained policy loads without its replay buffer (bidal_jax/run/policy.py), and the best
checkpoint is kept beside the latest two and selected by "best"."""

import os
import shutil

import jax
import numpy as np
import pytest

from bidal_jax.run import checkpoint
from bidal_jax.run.policy import load_policy
from tests.helpers import FINISHED_EPOCHS as EPOCHS


def test_load_policy_never_reads_the_buffer(finished, tmp_path):
    run_dir, _ = finished
    copy = str(tmp_path / "no_buffer")
    shutil.copytree(run_dir, copy)
    for step in checkpoint.steps(os.path.join(copy, "checkpoints")):
        shutil.rmtree(os.path.join(copy, "checkpoints", str(step), "buffer"))
    trained, original = load_policy(copy), load_policy(run_dir)
    for a, b in zip(jax.tree.leaves(trained.params), jax.tree.leaves(original.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert set(trained.params.params) == {"actor"}  # the proprio baseline has no encoder; no critic is read
    # the whole training state (for resuming) does need the buffer
    with pytest.raises(checkpoint.CheckpointError, match="has no replay buffer.*--resume --fresh-buffer"):
        checkpoint.read_metadata(os.path.join(copy, "checkpoints"))


def test_the_best_checkpoint_is_kept_beside_the_latest_two_and_selected_by_best(finished):
    run_dir, rows = finished
    success = {int(r["epoch"]): float(r["eval_success"]) for r in rows}
    best = max(success, key=lambda e: (success[e], e))
    ckpt_dir = os.path.join(run_dir, "checkpoints")
    assert set(checkpoint.steps(ckpt_dir)) == {EPOCHS - 1, EPOCHS, best}
    assert checkpoint.resolve_step(ckpt_dir, "best") == best
    assert load_policy(run_dir, "best").step == best
    with pytest.raises(checkpoint.CheckpointError, match="'last': must be a step number or 'best'"):
        checkpoint.resolve_step(ckpt_dir, "last")
