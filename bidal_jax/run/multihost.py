"""One run over several processes (one per host, or one per GPU), through `jax.distributed`.

`initialize()` starts JAX's distributed runtime when the environment asks for it
(`distributed_args`), before anything touches a device; every command line and experiment
script calls it first. Then `jax.devices()` lists the devices of every process, the seed
axis spans them (`devices.seed_devices`), and each process runs the same program on its own
seeds. What the loop needs around that, each the plain single-process operation when there
is one process (no collective runs, nothing changes):

- `to_host`: arrays spanning processes (metrics, flags) as numpy arrays, on every process;
- `host_parts`: a large state's values one seed at a time (the checkpoint digest);
- `largest`: the largest of each process's integer (a stop signal that one process received);
- `is_main`: process 0, which alone writes the run's files (Orbax checkpoints are written by
  every process: each its own shards, process 0 the metadata);
- `barrier`: wait until every process has arrived.

Every process must call the collective ones (`to_host`, `host_parts`, `largest`,
`barrier`) with the same arrays, in the same order.
"""

from __future__ import annotations

import functools
import os
from typing import Any, Iterator, Mapping

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from bidal_jax.config import ConfigError

# an explicit launch: the coordinator's host:port (read by jax.distributed itself), the process
# count and this process's index (read here: JAX 0.10 reads neither from the environment)
COORDINATOR, PROCESSES, PROCESS_ID = "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"
# launchers whose coordinator, process count and index jax.distributed detects itself: the
# variables its detection requires, and the one holding the process count
SLURM = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_NTASKS", "SLURM_PROCID", "SLURM_LOCALID")
SLURM_PROCESSES = "SLURM_NTASKS"
OPEN_MPI = ("OMPI_MCA_orte_hnp_uri", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK", "OMPI_COMM_WORLD_LOCAL_RANK")
OPEN_MPI_PROCESSES = "OMPI_COMM_WORLD_SIZE"


def _count(environ: Mapping[str, str], name: str, low: int) -> int:
    """The integer `environ[name]`, at least `low`; ConfigError otherwise."""
    text = environ[name]
    if not text.strip().isdigit() or int(text) < low:
        raise ConfigError(f"{name}={text!r}: must be an integer of at least {low}")
    return int(text)


def _launched_tasks(environ: Mapping[str, str]) -> int | None:
    """The task count of a SLURM step or an Open MPI launch (what jax.distributed detects), or None."""
    for required, count in ((SLURM, SLURM_PROCESSES), (OPEN_MPI, OPEN_MPI_PROCESSES)):
        if all(name in environ for name in required):
            return _count(environ, count, 1)
    return None


def distributed_args(environ: Mapping[str, str]) -> dict[str, Any] | None:
    """The keyword arguments of `jax.distributed.initialize` that `environ` asks for; None for one process.

    - `JAX_NUM_PROCESSES` or `JAX_PROCESS_ID` set: an explicit launch, which needs all three of
      `JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID`; cluster detection is off,
      so each process sees all of its host's devices (or those of `JAX_LOCAL_DEVICE_IDS`, read by JAX);
    - a SLURM step or an Open MPI launch of several tasks: no arguments, JAX detects the coordinator,
      count and index (and gives each task the GPU of its local rank unless `JAX_LOCAL_DEVICE_IDS` is set);
    - else None: one task of a launcher, or no launcher.

    Raises ConfigError for a partial or malformed explicit launch.
    """
    if PROCESSES in environ or PROCESS_ID in environ:
        missing = [name for name in (COORDINATOR, PROCESSES, PROCESS_ID) if name not in environ]
        if missing:
            raise ConfigError(f"{missing[0]} is not set: a launch of several processes sets "
                              f"{COORDINATOR}, {PROCESSES} and {PROCESS_ID}")
        processes, process_id = _count(environ, PROCESSES, 1), _count(environ, PROCESS_ID, 0)
        if process_id >= processes:
            raise ConfigError(f"{PROCESS_ID}={process_id}: must be below {PROCESSES}={processes}")
        if processes == 1:
            return None
        return {"coordinator_address": environ[COORDINATOR], "num_processes": processes, "process_id": process_id,
                "cluster_detection_method": "deactivate"}
    tasks = _launched_tasks(environ)
    if tasks is None and COORDINATOR in environ:
        raise ConfigError(f"{COORDINATOR} is set without {PROCESSES} and {PROCESS_ID} (nor a SLURM or Open MPI launch)")
    return {} if tasks is not None and tasks > 1 else None


def initialize(environ: Mapping[str, str] = os.environ) -> None:
    """`jax.distributed.initialize` with `distributed_args(environ)`, unless None or already done.
    Must run before anything touches a device. Raises ConfigError as `distributed_args`."""
    args = distributed_args(environ)
    if args is not None and not jax.distributed.is_initialized():
        jax.distributed.initialize(**args)


def several() -> bool:
    """Whether this process is one of several (`initialize` started them); touches no device."""
    return jax.distributed.is_initialized() and jax.process_count() > 1


def is_main() -> bool:
    """Whether this is process 0 (or the only one), which writes the run's files."""
    return not several() or jax.process_index() == 0


def _spans_processes(x: Any) -> bool:
    return isinstance(x, jax.Array) and not x.is_fully_addressable


def to_host(tree: Any) -> Any:
    """The tree's arrays as numpy arrays on this host, whole: `jax.device_get`, but for arrays that
    span processes, which are gathered from every process (each leaf whole on every device for a
    moment: for small arrays; see `host_parts` for large ones)."""
    if not any(_spans_processes(x) for x in jax.tree.leaves(tree)):
        return jax.device_get(tree)
    return jax.tree.map(
        lambda x: multihost_utils.process_allgather(x, tiled=True) if _spans_processes(x) else jax.device_get(x), tree
    )


def _index(tree: Any, i: jax.Array) -> Any:
    return jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, i, keepdims=False), tree)


@functools.lru_cache(maxsize=None)
def _replicated_index(mesh: Mesh):
    """`_index` jitted to give its slices whole on every device of `mesh`."""
    return jax.jit(_index, out_shardings=NamedSharding(mesh, PartitionSpec()))


def host_parts(tree: Any) -> Iterator[Any]:
    """The tree's values on this host, in parts: the whole tree (`jax.device_get`) when this process
    holds all of it, else the slices of every leaf's leading (seed) axis, one seed at a time, gathered
    from the processes that hold them (so that a large state never lies whole on one device; one
    compiled program per tree structure)."""
    spanning = [x for x in jax.tree.leaves(tree) if _spans_processes(x)]
    if not spanning:
        yield jax.device_get(tree)
        return
    index = _replicated_index(spanning[0].sharding.mesh)
    for i in range(spanning[0].shape[0]):
        yield jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), index(tree, np.int32(i)))


def largest(value: int) -> int:
    """The largest of every process's `value` (every process calls it); with one process, `value`."""
    if not several():
        return value
    return int(np.max(multihost_utils.process_allgather(np.int32(value))))


def barrier(name: str) -> None:
    """Wait until every process reaches the barrier `name`; with one process, return at once."""
    if several():
        multihost_utils.sync_global_devices(name)
