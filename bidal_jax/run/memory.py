"""Device memory: whether a run fits on its devices, checked before anything compiles and again once compiled, and
the run that runs out anyway.

Before training, a run is refused with one line saying what to reduce (`ConfigError`, exit 2, nothing trained):
- `check_state`: its training state (`jax.eval_shape`, before anything compiles: `preflight.prepare`) needs more
  than `MEMORY_SHARE` of a device's memory (`device_memory`);
- `check_floor`: the state and the least working memory its epoch can have (`floor`, from the shapes of the config,
  the env and the state alone: the batch of an update, the envs of a rollout, their camera's rays and records) need
  more than that share. It runs before XLA sees the program, whose compiler on a GPU may crash on sizes far beyond
  the device (a segmentation fault, an autotuner failure) rather than report them;
- `check_program`: its compiled epoch needs more, at once, than that share: the state it takes, the working
  memory of its rollouts and updates, and the outputs that do not reuse the state's buffers (`program_bytes`, from
  XLA's `memory_analysis()` of the compiled program; e.g. a batch too large for the device whose floor fits).
On a GPU a device's memory is the share JAX takes of it (75 % unless `XLA_PYTHON_CLIENT_MEM_FRACTION` says
otherwise, `gpu_fraction`); below 90 % the line also says to give JAX more (`more_of_the_gpu`).

A GPU that other processes hold: a command line calls `share_gpu` before JAX starts its GPU backend. Where JAX's
share of the GPU is not free (another run holds it), JAX takes what is free instead, less room for XLA's autotuner
(`HEADROOM`), and says so in a line; a run that does not fit in it is refused at its start (`OutOfMemory`, exit 6,
`shared_gpu_line`: the memory free, what the run needs, how to share a GPU). The GPU's free memory is NVML's
(`pynvml`, where installed) or `nvidia-smi`'s (`gpus`, a child process that `subprocess` starts without a
fork of this process, so JAX's threads raise no fork warning).

What XLA still cannot allocate while a program compiles or runs (its estimate is not the allocator's, other
processes share the device) raises `RESOURCE_EXHAUSTED` (`exhausted`), and its GPU autotuner fails where the memory
JAX leaves free is too small to try its kernels in (`autotuning`); `out_of_memory` and `ran_out` turn either into
`OutOfMemory`, one line naming what ran out, what to reduce (or how to share the GPU where another process holds it)
and the last good checkpoint, with its own exit code (`experiments.cli`). `tree_bytes` is what a state's arrays
take, whole (the device check's and the disk's).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import subprocess
import sys
from typing import Any, Callable, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax.config import Config, ConfigError
from bidal_jax.networks import parse_strides
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
# JAX's variables of its share of a GPU: the documented one, and its newer name (JAX refuses both at once)
FRACTION_VARIABLES = ("XLA_PYTHON_CLIENT_MEM_FRACTION", "XLA_CLIENT_MEM_FRACTION")
# how XLA names an allocation that failed (the status code; the allocators' own words)
EXHAUSTED = ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory")
# how XLA's GPU autotuner says it could try none of a kernel's candidates (it runs them in the memory JAX leaves)
AUTOTUNING = ("Failed to get configs", "No candidates could be compiled", "Autotuning failed", "autotuner")
# what a GPU shared with another process keeps free beside JAX's share (`share_gpu`): the autotuner's trials and
# this process's CUDA context; JAX's share stands where this many bytes stay free beside it, else JAX takes what is
# free less this many bytes, or this part of the free memory if more
HEADROOM, HEADROOM_SHARE = 2 * 2**30, 0.2
# bytes other processes may hold on a GPU before it counts as shared (their CUDA contexts alone stay below it)
OTHERS_HOLD = 2 * 2**30
GPU_QUERY = ["nvidia-smi", "--query-gpu=index,uuid,memory.free,memory.total", "--format=csv,noheader,nounits"]


class OutOfMemory(Exception):
    """A device ran out of memory while the run compiled or trained, or has too little free for it at its start
    (another process holds it); one line."""


def device_memory() -> int:
    """Bytes of memory of this process's first device: the accelerator's limit, or the host's RAM on a CPU."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"])
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def gpu_fraction() -> float:
    """The share of a GPU's memory JAX takes: its variable's (`FRACTION_VARIABLES`), else `DEFAULT_GPU_FRACTION`."""
    given = next((os.environ[name] for name in FRACTION_VARIABLES if os.environ.get(name)), None)
    return DEFAULT_GPU_FRACTION if given is None else float(given)


def more_of_the_gpu() -> str:
    """What to add to a refusal when JAX holds less of a GPU than it may: "; or give JAX more of the GPU's memory
    (XLA_PYTHON_CLIENT_MEM_FRACTION, now F)" on a GPU whose fraction is below `FULL_GPU_FRACTION`; "" elsewhere
    (a CPU's limit is its RAM)."""
    if jax.local_devices()[0].platform != "gpu":  # the device `device_memory` measures
        return ""
    fraction = gpu_fraction()
    if fraction >= FULL_GPU_FRACTION:
        return ""
    return f"; or give JAX more of the GPU's memory (XLA_PYTHON_CLIENT_MEM_FRACTION, now {fraction:g})"


RESUME_ELSEWHERE = "a resumed run keeps its checkpoint's config: resume it on a device with more memory"


def check_state(needed: int, available: int, seeds: int, resume: bool = False) -> None:
    """Refuse a training state whose share on one device (`needed` bytes) cannot fit in `MEMORY_SHARE` of that
    device's memory (`available` bytes); a `resume`d run (its checkpoint's config) is to resume on a larger one."""
    if needed > MEMORY_SHARE * available:
        advice = RESUME_ELSEWHERE if resume else "use fewer seeds, envs or --buffer-episodes"
        raise ConfigError(
            f"--seeds {seeds}: the training state needs {needed / GIB:,.1f} GiB, more than {MEMORY_SHARE:.0%} of the "
            f"device's {available / GIB:,.1f} GiB; {advice}{more_of_the_gpu()}"
        )


# ----- the least working memory of an epoch, from shapes ----------------------------------------------------------


class Floor(NamedTuple):
    """Bytes one device needs at least while a run's epoch trains (`floor`): its share of the training `state`, and
    the working memory beside it of the `update` phase (a cycle's recorded episodes and a gradient update's batch)
    and of the `rollout` phase (the widest rollout's records and one env step of its envs), both for the device's
    seeds; the epoch holds the state and the larger of the two."""

    state: int
    update: int
    rollout: int

    @property
    def needed(self) -> int:
        return self.state + max(self.update, self.rollout)


def frame_bytes(config: Config, image_shape: tuple[int, ...]) -> int:
    """Bytes of one frame in an image update, at least: the uint8 frame gathered from the buffer, the frame in the
    vision dtype, each conv layer's output map (kept for its gradient) and the vision branch's features (float32)."""
    network, pixels = config.network, math.prod(image_shape)
    size = jnp.dtype(network.vision_dtype).itemsize
    first, *rest = parse_strides(network.conv_strides)
    height, width = (image_shape[0] - 3) // first + 1, (image_shape[1] - 3) // first + 1  # unpadded 3×3
    maps = [height * width]
    for stride in rest:  # "same"-padded
        height, width = -(-height // stride), -(-width // stride)
        maps.append(height * width)
    return pixels + pixels * size + sum(maps) * network.conv_channels * size + network.vision_features * 4


def transition_bytes(config: Config, env: Any) -> int:
    """Bytes of one sampled transition in a gradient update, at least: its float32 entries (proprio and next
    proprio, goal, action, reward) and int32 indices, the critic's and the actor's embeddings and hidden layers of
    the two passes that take a gradient, and for an image agent its frames (`frame_bytes`): 1 + 1/sample_run a
    transition where the online encoder reads s_{t+1} too, else the 1 of s_t that takes a gradient."""
    train, network, spec = config.train, config.network, env.observation_spec
    entries = 2 * spec.proprio_size + spec.goal_size + env.action_size + 1 + 3
    layers = 2 * (2 * network.embed_size + network.hidden_layers * network.hidden_size)
    size = (entries + layers) * 4
    if config.agent.uses_image:
        frames = 1 + 1 / train.sample_run if train.target_encoder == "online" else 1
        size += math.ceil(frames * frame_bytes(config, spec.image_shape))
    return size


def env_bytes(config: Config, env: Any) -> tuple[int, int]:
    """(bytes of one env step, bytes of one env's recorded episode), at least: the physics state in and out of a
    step (MJX-JAX's `mjx.Data` of the env's model, twice, whichever engine steps it: MuJoCo Warp's data holds every
    world's contacts at once) and for an image agent the camera's supersampled rays (each ray's
    nearest distance, float32, and geom id, int32: `env.camera`, 84×84 rays for the 42×42 frame); the episode's
    T + 1 observations (frame, proprio, goals) and actions, twice (the rollout's records and the episodes built
    from them)."""
    from mujoco import mjx  # (MuJoCo's, loaded with the envs; not on every import of this module)

    spec = env.observation_spec
    step = 2 * tree_bytes(jax.eval_shape(lambda: mjx.make_data(env.mj_model)))  # shapes: nothing allocated
    observation = 4 * (spec.proprio_size + 2 * spec.goal_size + env.action_size)
    if config.agent.uses_image:
        step += 8 * env.camera.rays_per_side**2
        observation += math.prod(spec.image_shape)
    return step, 2 * (env.episode_length + 1) * observation


def floor(config: Config, env: Any, state: int, seeds: int, shards: int) -> Floor:
    """The least memory one device of a run needs while its epoch trains (`Floor`), from shapes alone, before
    anything compiles: its `state` bytes; and per seed of its `seeds`, for its 1/`shards` of the envs and the batch
    (`train.make_train`): a gradient update's batch × `transition_bytes` beside a cycle's recorded episodes, or the
    widest rollout's envs (a cycle's, or the evaluation's where it is a rollout of its own) × one env step beside
    their recorded episodes (`env_bytes`).

    A floor, not XLA's estimate: it counts the tensors that must exist at once (each the output of a matmul or a
    gather, or kept for a gradient) and no copy, temporary or fusion choice of the compiler's. XLA's
    `memory_analysis()` of the compiled epoch is 1.7 to 10 times it where it grows with the sizes (XLA:CPU's):
    planar_reach multimodal_bidal, 193 KB a transition of the batch against the floor's 62 KB, 857 KB an env of
    its rollout against 244 KB; proprio_baseline 5.2 KB a transition against 3.1 KB; nicol_slide multimodal_bidal
    with 64 envs, 323 MB in all against 36 MB; and on a GPU, the paper's noise program (nicol_slide
    multimodal_bidal, 15 seeds) 94.6 GiB in all against the floor's 33 GiB. So the floor refuses no
    program that XLA's estimate (`check_program`) would let train, and refuses in a second the sizes far beyond
    the device (planar_reach's --batch-size 4000000 needs at least 212 GiB), which XLA's GPU compiler may not
    survive to report."""
    train = config.train
    n_envs, n_eval = train.num_envs // shards, train.eval_envs // shards
    width = n_envs if n_eval % n_envs == 0 else max(n_envs, n_eval)  # evaluation chunks of the cycles' width
    step, episode = env_bytes(config, env)
    update = n_envs * episode + train.batch_size // shards * transition_bytes(config, env)
    rollout = width * (episode + step)
    return Floor(state, seeds * update, seeds * rollout)


def check_floor(least: Floor, available: int, config: Config, resume: bool = False) -> None:
    """Refuse (ConfigError, one line) a run whose `floor` on one device is more than `MEMORY_SHARE` of the device's
    `available` bytes, naming the part to reduce: the batch (--batch-size) or the envs (--num-envs, --eval-envs);
    a `resume`d run, whose config is its checkpoint's, is to resume on a device with more memory; on a GPU that
    another process holds, the line says how much is free and how to share it (`OutOfMemory`, exit 6)."""
    if least.needed <= MEMORY_SHARE * available:
        return
    train = config.train
    if least.update >= least.rollout:
        what, part = f"--batch-size {train.batch_size}", f"an update's batch {least.update / GIB:,.1f} GiB"
        reduce = "a smaller --batch-size"
    else:
        what, part = f"--num-envs {train.num_envs}", f"a rollout's envs {least.rollout / GIB:,.1f} GiB"
        reduce = "fewer --num-envs or --eval-envs"
    if config.run.seeds > 1:
        reduce += " or fewer seeds"
    taken = shared_gpu_line(least.needed)
    if taken:
        raise OutOfMemory(taken)
    advice = RESUME_ELSEWHERE if resume else f"use {reduce}"
    raise ConfigError(
        f"{what}: the training program needs at least {least.needed / GIB:,.1f} GiB of device memory, from its "
        f"shapes before compiling (the state {least.state / GIB:,.1f} GiB and {part}), more than "
        f"{MEMORY_SHARE:.0%} of the device's {available / GIB:,.1f} GiB; {advice}{more_of_the_gpu()}"
    )


# ----- a GPU that other processes share ------------------------------------------------------------------------


class Gpu(NamedTuple):
    """One GPU as its driver reports it: its index, free and total bytes."""

    index: str
    free: int
    total: int


def _visible(rows: list[tuple[str, str, int, int]]) -> list[Gpu]:
    """The GPUs of `rows` (index, uuid, free, total bytes) that this process's CUDA sees (CUDA_VISIBLE_DEVICES:
    indices or UUIDs; all where unset)."""
    wanted = os.environ.get("CUDA_VISIBLE_DEVICES")
    gpus = {index: Gpu(index, free, total) for index, _, free, total in rows}
    if wanted is None:
        return list(gpus.values())
    by_uuid = {uuid: index for index, uuid, _, _ in rows}
    names = [name.strip() for name in wanted.split(",") if name.strip()]
    return [gpus[name] for name in (by_uuid.get(n, n) for n in names) if name in gpus]


def gpus() -> list[Gpu]:
    """The GPUs this process may use with their free and total memory, from NVML (`pynvml`, where installed) or
    `nvidia-smi` (a spawned child: no fork of a threaded process); [] without an NVIDIA driver or tool."""
    try:
        import pynvml
    except ImportError:
        pynvml = None
    try:
        if pynvml is not None:
            pynvml.nvmlInit()
            try:
                rows = []
                for i in range(pynvml.nvmlDeviceGetCount()):
                    handle = pynvml.nvmlDeviceGetHandleByIndex(i)
                    uuid, info = pynvml.nvmlDeviceGetUUID(handle), pynvml.nvmlDeviceGetMemoryInfo(handle)
                    rows.append((str(i), uuid.decode() if isinstance(uuid, bytes) else uuid, info.free, info.total))
            finally:
                pynvml.nvmlShutdown()
            return _visible(rows)
        if shutil.which(GPU_QUERY[0]) is None:
            return []
        out = subprocess.run(GPU_QUERY, capture_output=True, text=True, timeout=20, check=True).stdout
        rows = [[part.strip() for part in line.split(",")] for line in out.splitlines() if line.strip()]
        return _visible([(i, u, int(float(free)) * 2**20, int(float(total)) * 2**20) for i, u, free, total in rows])
    except Exception:  # no driver, a tool that fails or times out: nothing known
        return []


def _backend_started() -> bool:
    """Whether JAX has started its backends (a GPU's share is then taken)."""
    from jax._src import xla_bridge

    started = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(started and started())


def _may_use_gpu() -> bool:
    """Whether JAX may start a GPU backend in this process (JAX_PLATFORMS or jax_platforms allow one)."""
    platforms = (jax.config.jax_platforms or os.environ.get("JAX_PLATFORMS") or "").lower()
    return not platforms or any(name in platforms for name in ("cuda", "gpu", "rocm"))


def share_gpu(log: Callable[[str], None] = lambda line: print(line, file=sys.stderr, flush=True)) -> None:
    """Before JAX starts its GPU backend (a command line's first step, or a grid's cell's): where other processes
    hold so much of a GPU that JAX's share (`gpu_fraction` of its memory) is not free, JAX takes the memory free
    instead, less `HEADROOM` for XLA's autotuner, which runs its trials beside JAX's share (JAX would otherwise take
    all that is free, and the autotuner fail); one `log` line says so. Nothing on a CPU, without an NVIDIA tool, or
    once JAX has started."""
    if not _may_use_gpu() or _backend_started():
        return
    visible = gpus()
    if not visible:
        return
    gpu = min(visible, key=lambda g: g.free)
    fraction = gpu_fraction()
    if fraction * gpu.total <= gpu.free - HEADROOM:  # JAX's share is free (e.g. two grid cells of 0.45 each)
        return
    spare = max(HEADROOM, HEADROOM_SHARE * gpu.free)
    share = max(math.floor(100 * max(gpu.free - spare, 0) / gpu.total) / 100, 0.01)
    name = next((name for name in FRACTION_VARIABLES[::-1] if os.environ.get(name)), FRACTION_VARIABLES[0])
    os.environ[name] = f"{share:.2f}"
    log(f"GPU {gpu.index}: other processes hold {(gpu.total - gpu.free) / GIB:,.1f} GiB of its "
        f"{gpu.total / GIB:,.1f} GiB; JAX takes {share * gpu.total / GIB:,.1f} GiB of the {gpu.free / GIB:,.1f} GiB "
        f"free ({name} {fraction:g} -> {share:.2f})")


def _own_bytes() -> int:
    """Bytes this process's JAX holds on its first device (its allocator's pool, else its limit)."""
    stats = jax.local_devices()[0].memory_stats() or {}
    return int(max(stats.get("pool_bytes", 0), stats.get("bytes_reserved", 0)) or stats.get("bytes_limit", 0))


def shared_gpu_line(needed: int | None = None) -> str | None:
    """The one line of a run that its GPU has too little free memory for because other processes hold it: the GPU's
    free memory, what the run needs (`needed` bytes, where known) and how to share a GPU; None on a CPU, where no
    other process holds more than `OTHERS_HOLD` of the GPU, or where the run would not fit the GPU alone either
    (`needed` more than `MEMORY_SHARE` of `FULL_GPU_FRACTION` of it: its sizes are to reduce)."""
    if jax.local_devices()[0].platform != "gpu":
        return None
    visible = gpus()
    if not visible:
        return None
    gpu = min(visible, key=lambda g: g.free)
    others = gpu.total - gpu.free - _own_bytes()
    if others <= OTHERS_HOLD or (needed and needed > MEMORY_SHARE * FULL_GPU_FRACTION * gpu.total):
        return None
    needs = f"this run needs at least {needed / GIB:,.1f} GiB" if needed else "this run needs more"
    return (f"GPU {gpu.index} is shared: other processes hold {others / GIB:,.1f} GiB of its {gpu.total / GIB:,.1f} "
            f"GiB, {(gpu.total - others) / GIB:,.1f} GiB are left to this process, and {needs}; wait for them to end, "
            "or share the GPU between runs, each with a part of it: XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 for each of "
            "two runs started together, or a grid's --gpus-per-cell 0.5")


# ----- the compiled program's estimate, and what runs out all the same ---------------------------------------------


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


def check_program(stats: Any, available: int, resume: bool = False) -> None:
    """Refuse (ConfigError) a compiled epoch whose memory on one device (`program_bytes` of its `memory_analysis()`,
    `stats`) is more than `MEMORY_SHARE` of the device's `available` bytes; nothing when there is no analysis. A
    `resume`d run is to resume on a larger device; on a GPU that another process holds, the line says how much is
    free and how to share it (`OutOfMemory`, exit 6)."""
    sizes = program_bytes(stats)
    if sizes is not None and sizes[0] > MEMORY_SHARE * available:
        needed, working = sizes
        taken = shared_gpu_line(needed)
        if taken:
            raise OutOfMemory(taken)
        raise ConfigError(
            f"the training program needs {needed / GIB:,.1f} GiB of device memory at once (its epoch's working "
            f"memory {working / GIB:,.1f} GiB beside the state), more than {MEMORY_SHARE:.0%} of the device's "
            f"{available / GIB:,.1f} GiB; {RESUME_ELSEWHERE if resume else REDUCE}{more_of_the_gpu()}"
        )


def exhausted(err: BaseException) -> bool:
    """Whether `err` is XLA's failure to allocate device memory (a `JaxRuntimeError` of RESOURCE_EXHAUSTED)."""
    return isinstance(err, jax.errors.JaxRuntimeError) and any(word in str(err) for word in EXHAUSTED)


def autotuning(err: BaseException) -> bool:
    """Whether `err` is XLA's GPU autotuner failing to try a kernel's candidates (it runs them in the GPU memory
    that JAX's share leaves free: too little of it, or a kernel too large to try)."""
    return isinstance(err, jax.errors.JaxRuntimeError) and any(word in str(err) for word in AUTOTUNING)


def device_failure(err: BaseException) -> bool:
    """Whether `err` is the device's memory failing a program: `exhausted` or `autotuning`."""
    return exhausted(err) or autotuning(err)


def ran_out(doing: str, err: BaseException, after: str) -> OutOfMemory:
    """The `OutOfMemory` of `err` (`device_failure`): "out of device memory while DOING (XLA's first line); use ...;
    AFTER" (e.g. the last good checkpoint); on a GPU that other processes hold, what is free and how to share it
    (`shared_gpu_line`) instead of what to reduce; for the autotuner, that XLA could not try its kernels."""
    taken = shared_gpu_line()
    if autotuning(err):
        what = (f"XLA's autotuner could not try the kernels of the program while {doing} ({first_line(err, 120)}): "
                "it runs them in the GPU memory beside JAX's share")
        advice = taken or (f"{REDUCE}, or give JAX a smaller share of the GPU (XLA_PYTHON_CLIENT_MEM_FRACTION, now "
                           f"{gpu_fraction():g})")
        return OutOfMemory(f"{what}; {advice}; {after}")
    return OutOfMemory(f"out of device memory while {doing} ({first_line(err, 160)}); {taken or REDUCE}; {after}")


@contextlib.contextmanager
def out_of_memory(doing: str, after: Callable[[], str]) -> Iterator[None]:
    """A block whose device's memory failing a program (`device_failure`) raises `ran_out(doing, ..., after())`;
    other errors pass."""
    try:
        yield
    except jax.errors.JaxRuntimeError as err:
        if not device_failure(err):
            raise
        raise ran_out(doing, err, after()) from None


def tree_bytes(tree: Any) -> int:
    """Bytes of a pytree's arrays (or shape/dtype structs), whole: what a checkpoint of it writes, uncompressed."""
    return int(sum(np.prod(x.shape, dtype=np.int64) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree)))
