"""Fixtures of the experiments' tests: hand-written run directories."""

import pytest

from tests.experiments.runs import RUN_A, RUN_B, write_run


@pytest.fixture
def two_runs(tmp_path):
    return write_run(tmp_path / "a", "multimodal_bidal", RUN_A), write_run(tmp_path / "b", "proprio_baseline", RUN_B)
