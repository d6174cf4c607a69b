"""Device memory: whether a run's state and its epoch fit on its devices, and the run that runs out anyway.

Before training, a run is refused with one line saying what to reduce (`ConfigError`, exit 2, nothing trained):
- `check_state`: its training state (`jax.eval_shape`, before anything compiles: `preflight.prepare`) needs more
  than `MEMORY_SHARE` of a device's memory (`device_memory`);
- `check_program`: its compiled epoch needs more, at once, than that share: the state it takes, the working
  memory of its rollouts and updates, and the outputs that do not reuse the state's buffers (`program_bytes`, from
  XLA's `memory_analysis()` of the compiled program; e.g. a batch too large for the device, whose state fits).
On a GPU a device's memory is the share JAX takes of it (75 % unless `XLA_PYTHON_CLIENT_MEM_FRACTION` says
otherwise); below 90 % the line also says to give JAX more (`more_of_the_gpu`).

What XLA still cannot allocate while a program compiles or runs (its estimate is not the allocator's, other
processes share the device) raises `RESOURCE_EXHAUSTED` (`exhausted`); `out_of_memory` and `ran_out` turn it
into `OutOfMemory`, one line naming what ran out, what to reduce and the last good checkpoint, with its own exit
code (`experiments.cli`). `tree_bytes` is what a state's arrays take, whole (the device check's and the disk's).
"""

from __future__ import annotations

import contextlib
import os
from typing import Any, Callable, Iterator

import jax
import numpy as np

from bidal_jax.config import ConfigError
from bidal_jax.run.runfiles import first_line

# share of the device's memory the training state, or the whole epoch program, may take (the rest: the runtime's
# own buffers, a checkpoint's copy, fragmentation)
MEMORY_SHARE = 0.9
GIB = 2.0**30
REDUCE = "use a smaller --batch-size, fewer seeds, --num-envs or --buffer-episodes"
# the share of a GPU's memory JAX takes by default (XLA_PYTHON_CLIENT_MEM_FRACTION unset), and the most it should
# take (the rest: CUDA contexts): a refusal while JAX holds less suggests more (`more_of_the_gpu`), and a grid's
# cell given a fraction of a GPU takes that fraction of it (`experiments.cluster.worker_env`)
DEFAULT_GPU_FRACTION = 0.75
FULL_GPU_FRACTION = 0.9
# how XLA names an allocation that failed (the status code; the allocators' own words)
EXHAUSTED = ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory")


class OutOfMemory(Exception):
    """A device ran out of memory while the run compiled or trained; one line."""


def device_memory() -> int:
    """Bytes of memory of this process's first device: the accelerator's limit, or the host's RAM on a CPU."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"])
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def more_of_the_gpu() -> str:
    """What to add to a refusal when JAX holds less of a GPU than it may: "; or give JAX more of the GPU's memory
    (XLA_PYTHON_CLIENT_MEM_FRACTION, now F)" on a GPU whose fraction is below `FULL_GPU_FRACTION`; "" elsewhere
    (a CPU's limit is its RAM)."""
    if jax.local_devices()[0].platform != "gpu":  # the device `device_memory` measures
        return ""
    fraction = float(os.environ.get("XLA_PYTHON_CLIENT_MEM_FRACTION", DEFAULT_GPU_FRACTION))
    if fraction >= FULL_GPU_FRACTION:
        return ""
    return f"; or give JAX more of the GPU's memory (XLA_PYTHON_CLIENT_MEM_FRACTION, now {fraction:g})"


def check_state(needed: int, available: int, seeds: int) -> None:
    """Refuse a training state whose share on one device (`needed` bytes) cannot fit in `MEMORY_SHARE` of that
    device's memory (`available` bytes)."""
    if needed > MEMORY_SHARE * available:
        raise ConfigError(
            f"--seeds {seeds}: the training state needs {needed / GIB:,.1f} GiB, more than {MEMORY_SHARE:.0%} of the "
            f"device's {available / GIB:,.1f} GiB; use fewer seeds, envs or --buffer-episodes{more_of_the_gpu()}"
        )


def analysis(compiled: Any) -> Any:
    """XLA's `memory_analysis()` of a compiled program; None where its backend gives none."""
    try:
        return compiled.memory_analysis()
    except Exception:  # not implemented for this backend
        return None


def program_bytes(stats: Any) -> tuple[int, int] | None:
    """(bytes a compiled program holds on one device at once, the part of them that is working memory) from its
    `memory_analysis()`: its arguments, its temporaries and its outputs less those written into donated arguments'
    buffers; None where the backend gives no analysis."""
    if stats is None:
        return None
    working = int(stats.temp_size_in_bytes)
    outputs = max(int(stats.output_size_in_bytes) - int(stats.alias_size_in_bytes), 0)
    return int(stats.argument_size_in_bytes) + working + outputs, working


def check_program(stats: Any, available: int) -> None:
    """Refuse (ConfigError) a compiled epoch whose memory on one device (`program_bytes` of its `memory_analysis()`,
    `stats`) is more than `MEMORY_SHARE` of the device's `available` bytes; nothing when there is no analysis."""
    sizes = program_bytes(stats)
    if sizes is not None and sizes[0] > MEMORY_SHARE * available:
        needed, working = sizes
        raise ConfigError(
            f"the training program needs {needed / GIB:,.1f} GiB of device memory at once (its epoch's working "
            f"memory {working / GIB:,.1f} GiB beside the state), more than {MEMORY_SHARE:.0%} of the device's "
            f"{available / GIB:,.1f} GiB; {REDUCE}{more_of_the_gpu()}"
        )


def exhausted(err: BaseException) -> bool:
    """Whether `err` is XLA's failure to allocate device memory (a `JaxRuntimeError` of RESOURCE_EXHAUSTED)."""
    return isinstance(err, jax.errors.JaxRuntimeError) and any(word in str(err) for word in EXHAUSTED)


def ran_out(doing: str, err: BaseException, after: str) -> OutOfMemory:
    """The `OutOfMemory` of `err` (`exhausted`): "out of device memory while DOING (XLA's first line); use ...;
    AFTER" (e.g. the last good checkpoint)."""
    return OutOfMemory(f"out of device memory while {doing} ({first_line(err, 160)}); {REDUCE}; {after}")


@contextlib.contextmanager
def out_of_memory(doing: str, after: Callable[[], str]) -> Iterator[None]:
    """A block whose device running out of memory (`exhausted`) raises `ran_out(doing, ..., after())`; other
    errors pass."""
    try:
        yield
    except jax.errors.JaxRuntimeError as err:
        if not exhausted(err):
            raise
        raise ran_out(doing, err, after()) from None


def tree_bytes(tree: Any) -> int:
    """Bytes of a pytree's arrays (or shape/dtype structs), whole: what a checkpoint of it writes, uncompressed."""
    return int(sum(np.prod(x.shape, dtype=np.int64) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree)))
