"""A refusal ends a paper experiment's command (experiments/paper/{curves,noise_robustness,transfer_learning,
lambda_sweep}.py): a grid refused before its cells start (a --ray-address nothing answers, an --out another grid
holds) exits 2 with its error as the last line of its output, and goes on to no table or plot, even where run
folders with epochs would make one: curves as a command line (its output's order), each experiment in this
process."""

import os
import socket
import subprocess
import sys

import pytest

import envs_mjx
from experiments import cluster
from experiments.paper import curves, lambda_sweep, noise_robustness
from experiments.paper import transfer_learning as transfer
from tests.conftest import TODAY, write_fake_run
from tests.helpers import REPO

CURVES = ["-m", "experiments.paper.curves", "--tasks", "planar_reach", "--agents", "proprio_baseline", "--seeds",
          "1", "--epochs", "1", "--num-envs", "4", "--buffer-episodes", "8", "--batch-size", "8", "--eval-envs", "4",
          "--quiet", "--ray"]


def command_lines(argv: list[str]) -> tuple[int, list[str]]:
    """(exit code, the non-empty lines of stdout and stderr together, in order) of `python ARGV`."""
    done = subprocess.run([sys.executable, *argv], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, timeout=300, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    return done.returncode, [line for line in done.stdout.splitlines() if line.strip()]


def finished_run(out, physics: str = TODAY) -> None:
    """A finished run of `CURVES` in `out` on `physics`, from which a report would write a table."""
    write_fake_run(str(out / "planar_reach" / "proprio_baseline"), "planar_reach", [(0.5,)], None,
                   agent="proprio_baseline", physics=[physics],
                   given={"epochs": 1, "num_envs": 4, "buffer_episodes": 8, "batch_size": 8, "eval_envs": 4})


@pytest.fixture(scope="module")
def today() -> str:
    """planar_reach's physics today, which a command line's run folders must have not to be stale."""
    return envs_mjx.make("planar_reach", render=False).physics_id


def test_curves_refused_for_an_address_nothing_answers_ends_on_that_line(tmp_path, today):
    out = tmp_path / "curves"
    finished_run(out, today)
    with socket.socket() as s:  # a port that nothing listens on
        s.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{s.getsockname()[1]}"
        code, lines = command_lines([*CURVES, "--ray-address", address, "--out", str(out)])
    assert code == 2, lines[-5:]
    assert lines[-1].startswith(f"error: --ray-address {address}: nothing answers at {address}")
    assert not (out / "table.md").exists() and not any("nothing to plot" in line for line in lines)


@pytest.mark.parametrize("experiment, argv", [
    (transfer, ["--seeds", "2", "--epochs", "3", "--source-epochs", "2", "--quiet"]),
    (lambda_sweep, ["--lambdas", "0.1", "--quiet"]),
    (noise_robustness, ["--env", "planar_reach", "--noise-segments", "q", "--agents", "proprio_baseline", "--runs",
                        "1", "--epochs", "1", "--quiet"]),
    (curves, ["--tasks", "planar_reach", "--agents", "proprio_baseline", "--seeds", "1", "--epochs", "1",
              "--quiet"]),
], ids=["transfer_learning", "lambda_sweep", "noise_robustness", "curves"])
def test_every_experiment_refused_for_a_held_out_writes_no_results(experiment, argv, tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    with cluster.holding(str(out)):
        assert experiment.main([*argv, "--ray", "--out", str(out)]) == 2
    printed = capsys.readouterr()
    assert printed.err.splitlines()[-1].startswith(f"error: --out {out}: another grid trains into it")
    assert "nothing to plot" not in printed.out and "written to" not in printed.out
    assert no_nicol == [] and sorted(os.listdir(out)) == []  # the grid's lock file is gone with its holder
