"""Several processes train one run (bidal_jax.run.multihost): when the environment asks for
`jax.distributed`, how the seeds spread over every process's devices, and two local processes
of 2 CPU devices each that write one run equal to a single-process run, whose checkpoint resumes
in one process, and the other way round."""

import os
import socket
import subprocess
import sys
import types

import pytest

from bidal_jax.config import ConfigError
from bidal_jax.run import multihost
from bidal_jax.run.devices import seed_devices
from bidal_jax.run.policy import load_policy
from experiments import run
from tests.helpers import REPO, assert_same_metrics, rows
from tests.helpers import SHARDED as TINY

SLURM = {"SLURM_JOB_ID": "7", "SLURM_STEP_NODELIST": "node[1-2]", "SLURM_NTASKS": "2", "SLURM_PROCID": "1",
         "SLURM_LOCALID": "0"}
OPEN_MPI = {"OMPI_MCA_orte_hnp_uri": "1.0;tcp://10.0.0.1:1", "OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "1",
            "OMPI_COMM_WORLD_LOCAL_RANK": "0"}
EXPLICIT = {"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}


def test_no_launcher_or_one_task_is_one_process():
    assert multihost.distributed_args({}) is None
    assert multihost.distributed_args({"HOME": "/root"}) is None
    assert multihost.distributed_args({**SLURM, "SLURM_NTASKS": "1"}) is None
    assert multihost.distributed_args({**OPEN_MPI, "OMPI_COMM_WORLD_SIZE": "1"}) is None
    assert multihost.distributed_args({**EXPLICIT, "JAX_NUM_PROCESSES": "1", "JAX_PROCESS_ID": "0"}) is None
    # a SLURM allocation without a step (e.g. the batch script itself) is not a launch of tasks
    assert multihost.distributed_args({k: v for k, v in SLURM.items() if k != "SLURM_STEP_NODELIST"}) is None


def test_launchers_of_several_tasks_let_jax_detect_the_rest():
    assert multihost.distributed_args(SLURM) == {}
    assert multihost.distributed_args(OPEN_MPI) == {}
    # JAX reads JAX_COORDINATOR_ADDRESS itself: with a launcher it only overrides the address
    assert multihost.distributed_args({**SLURM, "JAX_COORDINATOR_ADDRESS": "node1:1234"}) == {}


def test_explicit_launch_passes_count_and_index_and_turns_detection_off():
    expected = {"coordinator_address": "10.0.0.1:1234", "num_processes": 2, "process_id": 1,
                "cluster_detection_method": "deactivate"}
    assert multihost.distributed_args(EXPLICIT) == expected
    assert multihost.distributed_args({**SLURM, **EXPLICIT}) == expected  # explicit wins over the launcher's


@pytest.mark.parametrize("environ, message", [
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "JAX_COORDINATOR_ADDRESS is not set"),
    ({"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_NUM_PROCESSES": "2"}, "JAX_PROCESS_ID is not set"),
    ({"JAX_COORDINATOR_ADDRESS": "h:1"}, "JAX_COORDINATOR_ADDRESS is set without JAX_NUM_PROCESSES"),
    ({**EXPLICIT, "JAX_NUM_PROCESSES": "two"}, "JAX_NUM_PROCESSES='two': must be an integer of at least 1"),
    ({**EXPLICIT, "JAX_NUM_PROCESSES": "0"}, "JAX_NUM_PROCESSES='0': must be an integer of at least 1"),
    ({**EXPLICIT, "JAX_PROCESS_ID": "-1"}, "JAX_PROCESS_ID='-1': must be an integer of at least 0"),
    ({**EXPLICIT, "JAX_PROCESS_ID": "2"}, "JAX_PROCESS_ID=2: must be below JAX_NUM_PROCESSES=2"),
    ({**SLURM, "SLURM_NTASKS": "x"}, "SLURM_NTASKS='x'"),
])
def test_bad_launch_variables_are_one_line_errors(environ, message):
    with pytest.raises(ConfigError, match=message) as err:
        multihost.distributed_args(environ)
    assert "\n" not in str(err.value)


def test_one_process_is_the_main_one_and_its_helpers_are_the_plain_operations():
    assert multihost.is_main()
    assert multihost.largest(15) == 15
    multihost.barrier("alone")  # returns at once


def test_each_process_holds_an_equal_share_of_the_seeds():
    devices = [types.SimpleNamespace(process_index=p, name=f"p{p}d{i}") for p in (0, 1) for i in (0, 1)]
    assert seed_devices(4, devices) == devices
    assert seed_devices(8, devices) == devices
    assert seed_devices(2, devices) == [devices[0], devices[2]]  # one device of each process
    assert seed_devices(6, devices) == [devices[0], devices[2]]
    with pytest.raises(ConfigError, match="--seeds 3: must be a multiple of the 2 processes"):
        seed_devices(3, devices)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def launch(args: list[str], log_dir) -> list[tuple[int, str]]:
    """`python -m experiments.run ARGS` as 2 processes of 2 CPU devices each, their output in
    `log_dir`; (exit code, output) of each."""
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
           "JAX_COORDINATOR_ADDRESS": f"localhost:{free_port()}", "JAX_NUM_PROCESSES": "2"}
    log_dir.mkdir()
    logs = [log_dir / f"process{i}.log" for i in (0, 1)]
    procs = []
    try:
        for i, log in enumerate(logs):
            with open(log, "w") as f:
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "experiments.run", *args],
                        cwd=REPO,
                        env={**env, "JAX_PROCESS_ID": str(i)},
                        stdout=f,
                        stderr=subprocess.STDOUT,
                    )
                )
        codes = [p.wait(timeout=600) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    return [(code, log.read_text()) for code, log in zip(codes, logs)]


@pytest.mark.slow
def test_two_processes_write_one_run_equal_to_one_process_and_resume_across_process_counts(tmp_path, capsys):
    multi, single = tmp_path / "multi", tmp_path / "single"
    # 4 seeds over 2 processes × 2 devices: one run directory, written once
    for code, log in launch([*TINY, "--epochs", "2", "--run-dir", str(multi), "--overwrite"], tmp_path / "new"):
        assert code == 0, log[-3000:]
        assert "4 seed(s) on 4 device(s)" in log
    assert sorted(os.listdir(multi)) == ["checkpoints", "config.json", "metrics.csv", "tb"]
    assert len(os.listdir(multi / "tb")) == 1  # one TensorBoard file: process 0's
    assert [r["epoch"] for r in rows(multi)] == [1.0, 2.0]
    # the same seeds in one process on one device
    assert run.main([*TINY, "--epochs", "2", "--run-dir", str(single)]) == 0
    assert_same_metrics(multi, single)
    # the 2-process checkpoint's acting parameters load in this 1-device process (Orbax partial
    # restore, as evaluate and transfer read them); the checkpoint continues in this process, and
    # the 1-device one in 2 processes
    assert load_policy(str(multi)).step == 2
    assert run.main(["--resume", "--run-dir", str(multi), "--epochs", "3", "--quiet"]) == 0
    assert "on 1 device(s)" in capsys.readouterr().err
    for code, log in launch(["--resume", "--run-dir", str(single), "--epochs", "3", "--quiet"], tmp_path / "resumed"):
        assert code == 0, log[-3000:]
        assert "4 seed(s) on 4 device(s)" in log
    assert [r["epoch"] for r in rows(single)] == [1.0, 2.0, 3.0]
    assert_same_metrics(multi, single)
