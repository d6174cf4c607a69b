"""What results/ may hold (.gitignore): run folders (config.json, metrics.csv), plots and tables; never a
checkpoint, a replay buffer or TensorBoard logs. A run resumes from its own run folder where it trains (a local
disk, or a path that every node of a cluster sees), so git never carries a checkpoint."""

import os
import subprocess

import pytest

from tests.helpers import REPO

pytestmark = pytest.mark.skipif(not os.path.exists(os.path.join(REPO, ".git")), reason="not a git checkout")


def git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)


def test_no_checkpoint_is_committed():
    tracked = git("ls-files").stdout.splitlines()
    assert [path for path in tracked if "checkpoints" in path.split("/")] == []


@pytest.mark.parametrize("path, ignored", [
    ("results/curves/nicol_lift/multimodal_bidal/checkpoints/40/buffer/array", True),
    ("results/curves/nicol_lift/multimodal_bidal/checkpoints/40/state/array", True),
    ("results/transfer/source/tb/events.out.tfevents", True),
    ("results/sweep.jsonl.parts/0.jsonl", True),
    ("results/curves/nicol_lift/multimodal_bidal/metrics.csv", False),
    ("results/curves/nicol_lift/multimodal_bidal/config.json", False),
    ("results/curves/table.md", False),
])
def test_gitignore_keeps_checkpoints_and_logs_out_of_results(path, ignored):
    assert (git("check-ignore", "--no-index", "-q", path).returncode == 0) == ignored
