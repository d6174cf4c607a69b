"""Orbax checkpoints of the whole `TrainState` plus the run's config.

A checkpoint directory `<run>/checkpoints/<epoch>/` holds four items: `state` (all
parameters, optimiser states, targets, normalisers, rng, counters), `buffer` (the replay
buffer, kept apart so that acting and transfer never read it and it can be deleted),
`config` (the run's config as JSON) and `digest` (a checksum per state leaf, as JSON: `digest`).
A manager keeps the latest two checkpoints and the best one by evaluation success
(`resolve_step(directory, "best")` finds it).

Crash safety: Orbax writes each step to `<epoch>.orbax-checkpoint-tmp/` and renames it
when complete, so a process killed at any moment (even mid-save) leaves the previous
checkpoint intact; the step listing ignores unfinished temporary directories and a
writing `manager` deletes them. A save that fails (e.g. the disk is full) deletes its own at once
and raises from `save`. `save_in_background` saves a copy of the state made on its devices in a
thread, so that training goes on while it is written; its failure is raised where it is waited for
(`Pending.wait`: the loop's next save, or the run's end).
Damage is detected, never restored silently: Orbax and
TensorStore reject truncated or missing files, and the digest catches flipped bytes,
which they would load without complaint. Every failure is a `CheckpointError` whose
message says which checkpoint and what is wrong with it.

`restore_partial` reads only named leaves (e.g. the acting parameters and normalisers)
with Orbax partial restore, checked against the digest like a full restore. Readers open only the
items they need, each with its own handler (no warning about the manager's `metrics` item).
A checkpoint carried without its `buffer` item restores only with another buffer given in its
place (`restore(..., buffer=...)`: a run resumed with `--fresh-buffer`).
A checkpoint whose Adam moments were saved per parameter array (before `train.optimizer` raveled each
network group's parameters into one vector) restores with them raveled in the parameters' order.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import threading
import time
import zlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from bidal_jax import replay
from bidal_jax.run import multihost, rundir


class CheckpointError(Exception):
    """A checkpoint that cannot be used: missing, damaged, or written for another run."""


BEST_METRIC = "eval_success"
ARRAY_ITEMS = ("state", "buffer")
# seconds to wait for each of the threads of a failed save before deleting what it wrote
SAVE_THREADS_TIMEOUT = 30.0
# seconds a failed save's directory must stay gone after its removal (`remove_failed`)
SETTLE_SECONDS = 1.0


def _handlers(partial: bool = False) -> dict[str, ocp.CheckpointHandler]:
    """The items' handlers; a partial restore reads `state` with the PyTree handler it was saved in."""
    return {
        "state": ocp.PyTreeCheckpointHandler() if partial else ocp.StandardCheckpointHandler(),
        "buffer": ocp.StandardCheckpointHandler(),
        "config": ocp.JsonCheckpointHandler(),
        "digest": ocp.JsonCheckpointHandler(),
    }


def manager(directory: str, keep_latest: int = 2) -> ocp.CheckpointManager:
    """A writing manager that keeps the `keep_latest` newest checkpoints and the best one
    (highest `eval_success` given to `save`); creates `directory` and removes unfinished saves."""
    policy = ocp.checkpoint_managers.AnyPreservationPolicy([
        ocp.checkpoint_managers.LatestN(n=keep_latest),
        ocp.checkpoint_managers.BestN(get_metric_fn=_best_metric, n=1, keep_checkpoints_without_metrics=False),
    ])
    # best_fn makes the manager write each step's metrics to disk, so the best survives a resume
    options = ocp.CheckpointManagerOptions(
        preservation_policy=policy, best_fn=_best_metric, create=True, cleanup_tmp_directories=True,
        enable_async_checkpointing=False,
    )
    return ocp.CheckpointManager(os.path.abspath(directory), options=options, item_handlers=_handlers())


def _best_metric(metrics: dict) -> float:
    return metrics[BEST_METRIC]


def leaf_name(path: tuple) -> str:
    """A pytree key path as `params/actor/...`."""
    return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k)))) for k in path)


def digest(state: Any) -> dict:
    """The digest item of a checkpoint of `state`: {"wsum": `wsum_digest`} where the state lies whole in this
    process on GPUs (or other accelerators), so that its gigabytes of replay frames are not read back to the host
    for it (CRC-32 of a NICOL state's gigabytes was most of a save; docs/performance.md, "What a checkpoint costs");
    else {"crc32": `crc32_digest`}, which a CPU computes some ten times faster."""
    return {"wsum": wsum_digest(state)} if _on_accelerators(state) else {"crc32": crc32_digest(state)}


def _on_accelerators(state: Any) -> bool:
    """Whether `state` lies whole in this process on devices other than CPUs."""
    leaves = jax.tree.leaves(state)
    return bool(leaves) and all(
        isinstance(x, jax.Array) and x.is_fully_addressable and all(d.platform != "cpu" for d in x.devices())
        for x in leaves
    )


def compile_for(state: Any) -> None:
    """Compile the programs that a save of `state` runs on its accelerators (`_copy`, `_sums`: seconds for a
    NICOL state), so that its first save does not wait for them; `loop.build` calls it beside the
    epoch's compile. Nothing on CPUs, whose digest is CRC-32 and whose cores the epoch's compile keeps busy."""
    if _on_accelerators(state):
        leaves = jax.tree.leaves(state)
        _copy.lower(state).compile()
        _sums.lower(leaves, [np.uint32(0)] * len(leaves)).compile()


def wsum_digest(state: Any) -> dict[str, int]:
    """Leaf name -> two sums of the leaf's bytes read as words w_0 … w_{n-1} in C order (a 1- or 2-byte value is a
    word, a 4-byte value one, an 8-byte value two), modulo 2^32: Σ w_i·(2i+1) in the high 32 bits, Σ w_i in the low.
    Any one word changed changes the first (its odd weight is invertible modulo 2^32), as any one byte changed
    changes a CRC-32. Computed where the leaves lie (`_sums`), or where a state spans processes on this process's
    default device from its host parts (`multihost.host_parts`, one seed at a time), to the same numbers."""
    paths, _ = jax.tree_util.tree_flatten_with_path(state)
    names, leaves, count = [leaf_name(path) for path, _ in paths], [leaf for _, leaf in paths], len(paths)
    whole = all(not isinstance(x, jax.Array) or x.is_fully_addressable for x in leaves)
    parts = [leaves] if whole else (jax.tree.leaves(part) for part in multihost.host_parts(state))
    weighted, total, offset = [0] * count, [0] * count, [0] * count
    for part in parts:
        sums = jax.device_get(_sums(part, [np.uint32(o % 2**32) for o in offset]))
        for i, (leaf, (w, t)) in enumerate(zip(part, sums)):
            weighted[i], total[i] = (weighted[i] + int(w)) % 2**32, (total[i] + int(t)) % 2**32
            offset[i] += int(np.size(leaf)) * (2 if leaf.dtype.itemsize == 8 else 1)
    return {name: w << 32 | t for name, w, t in zip(names, weighted, total)}


@jax.jit
def _sums(leaves: list[jax.Array], offsets: list[jax.Array]) -> list[tuple[jax.Array, jax.Array]]:
    """`wsum_digest`'s two sums of each leaf whose words follow `offsets` words (uint32) already summed: a word's
    index is its offset plus its flat index from each axis's iota, modulo 2^32; the products are summed, not
    stored. 1- and 2-byte values are widened, 8-byte ones split into two words (low first, as a little-endian
    view)."""
    def sums(leaf, offset):
        kind = {1: jnp.uint8, 2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint32}[leaf.dtype.itemsize]
        words = (leaf.astype(kind) if leaf.dtype == bool else jax.lax.bitcast_convert_type(leaf, kind))
        words = words.astype(jnp.uint32)
        index, stride = jnp.broadcast_to(offset, words.shape), 1
        for axis in reversed(range(words.ndim)):
            index = index + jax.lax.broadcasted_iota(jnp.uint32, words.shape, axis) * jnp.uint32(stride % 2**32)
            stride *= words.shape[axis]
        return jnp.sum(words * (2 * index + 1), dtype=jnp.uint32), jnp.sum(words, dtype=jnp.uint32)

    return [sums(leaf, offset) for leaf, offset in zip(leaves, offsets)]


def crc32_digest(state: Any) -> dict[str, int]:
    """Leaf name -> CRC-32 of its bytes, read on the host in parts (`multihost.host_parts`: the whole state, or one
    seed at a time from a state spanning processes, which all digest it)."""
    names = [leaf_name(path) for path, _ in jax.tree_util.tree_flatten_with_path(state)[0]]
    crcs = [0] * len(names)
    for part in multihost.host_parts(state):
        crcs = [zlib.crc32(np.ascontiguousarray(leaf), crc) for leaf, crc in zip(jax.tree.leaves(part), crcs)]
    return dict(zip(names, crcs))


def _split(state: Any) -> tuple[dict, Any]:
    """A training state as (its fields but the buffer, as a dict; the buffer)."""
    fields = {f.name: getattr(state, f.name) for f in dataclasses.fields(state) if f.name != "buffer"}
    return fields, state.buffer


def save(
    mngr: ocp.CheckpointManager, step: int, state: Any, config: dict, eval_success: float, env_shards: int = 1,
    digested: dict | None = None,
) -> None:
    """Save `state` (buffer apart), `config` and the state's digest (`digested`, else `digest(state)`) as `step`,
    ranked by `eval_success` for the best checkpoint; wait until it is on disk. `env_shards`: how many
    shards kept the buffer (its layout, `replay.relayout`), saved beside the digest."""
    fields, buffer = _split(state)
    digested = digested or digest(state)
    running = set(threading.enumerate())
    try:
        mngr.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(fields),
                buffer=ocp.args.StandardSave(buffer),
                config=ocp.args.JsonSave(config),
                digest=ocp.args.JsonSave({**digested, "env_shards": env_shards}),
            ),
            metrics={BEST_METRIC: float(eval_success)},
        )
        mngr.wait_until_finished()
    except BaseException:
        # Orbax's threads of this save may still be writing into its directory: wait for them first
        for thread in set(threading.enumerate()) - running:
            thread.join(timeout=SAVE_THREADS_TIMEOUT)
        if multihost.is_main():
            remove_failed(str(mngr.directory), step)
        raise


@jax.jit
def _copy(tree: Any) -> Any:
    """A copy of `tree`'s arrays on their devices (the same shardings), which the caller may then donate."""
    return jax.tree.map(jnp.copy, tree)


def _memory_stats(device: jax.Device) -> dict | None:
    """The device's allocator figures (`bytes_limit`, `peak_bytes_in_use`, ...; None on a CPU)."""
    return device.memory_stats()


def _room_for_copy(state: Any) -> bool:
    """Whether each device holding `state` has room for a copy of its part beside the most it has held yet (the
    epochs' temporaries included, so the next epoch still fits beside the copy); a device that keeps no figures
    (a CPU) is taken to have room."""
    parts: dict[Any, int] = {}
    for leaf in jax.tree.leaves(state):
        for shard in leaf.addressable_shards:
            parts[shard.device] = parts.get(shard.device, 0) + shard.data.nbytes
    for device, nbytes in parts.items():
        stats = _memory_stats(device) or {}
        if "bytes_limit" in stats and stats.get("peak_bytes_in_use", 0) + nbytes > stats["bytes_limit"]:
            return False
    return True


def _copy_if_room(state: Any) -> Any | None:
    """`_copy(state)`, or None where its devices have no room for it (`_room_for_copy`, or the copy fails for
    want of memory)."""
    if not _room_for_copy(state):
        return None
    try:
        return _copy(state)
    except jax.errors.JaxRuntimeError as err:
        if "RESOURCE_EXHAUSTED" not in str(err):
            raise
        return None


@dataclasses.dataclass
class Pending:
    """A checkpoint being written by `save_in_background`: its step, its thread and what the thread raised."""

    step: int
    thread: threading.Thread | None = None
    raised: BaseException | None = None

    def wait(self) -> None:
        """Wait until the checkpoint is on disk; raise what its save raised (its unfinished files are deleted)."""
        if self.thread is not None:
            self.thread.join()
        if self.raised is not None:
            raise self.raised


def save_in_background(
    mngr: ocp.CheckpointManager, step: int, state: Any, config: dict, eval_success: float, env_shards: int = 1
) -> Pending:
    """`save` of a copy of `state` made on its devices (`_copy`: the caller may donate `state` at once) and digested
    before it returns (`digest`: on GPUs a few milliseconds), written in a thread; the next use of `mngr` must come
    after `Pending.wait`. It saves `state` itself before returning (and raises as `save` does) where its devices have
    no room for the copy, and where this process is one of several, since Orbax's multi-process saves synchronise
    the processes."""
    pending, copy = Pending(step), None if multihost.several() else _copy_if_room(state)
    if copy is None:
        save(mngr, step, state, config, eval_success, env_shards)  # its failure raised here
        return pending

    digested = digest(copy)  # here, before the next epoch is queued on the devices ahead of it

    def write() -> None:
        try:
            save(mngr, step, copy, config, eval_success, env_shards, digested)
        except BaseException as err:  # raised to whoever waits for it
            pending.raised = err

    pending.thread = threading.Thread(name=f"checkpoint {step}", target=write)
    pending.thread.start()
    return pending


def remove_unfinished(directory: str, step: int) -> bool:
    """Delete the unfinished save of `step` (Orbax's `<step>.orbax-checkpoint-tmp*` directories) in `directory`;
    whether there was one."""
    prefix = f"{step}{ocp.path.step.TMP_DIR_SUFFIX}"
    found = [name for name in (os.listdir(directory) if os.path.isdir(directory) else []) if name.startswith(prefix)]
    for name in found:
        shutil.rmtree(os.path.join(directory, name), ignore_errors=True)
    return bool(found)


def remove_failed(directory: str, step: int, settle: float = SETTLE_SECONDS,
                  timeout: float = SAVE_THREADS_TIMEOUT) -> None:
    """`remove_unfinished` of a failed save, again whenever its directory comes back, until it has stayed gone for
    `settle` seconds (at most `timeout`): the writes of its other items already queued in TensorStore's own threads,
    which `threading` does not list, may still create files in it after a first removal."""
    start = gone_since = time.monotonic()
    while time.monotonic() - gone_since < settle and time.monotonic() - start < timeout:
        if remove_unfinished(directory, step):
            gone_since = time.monotonic()
        time.sleep(0.02)


def steps(directory: str) -> list[int]:
    """The complete checkpoints in `directory`, oldest first (unfinished saves are not listed)."""
    if not os.path.isdir(directory):
        return []
    return sorted(ocp.path.step.checkpoint_steps(directory))


def latest_step(directory: str) -> int | None:
    found = steps(directory)
    return found[-1] if found else None


def has_buffer(directory: str, step: int | None = None) -> bool:
    """Whether a checkpoint (the latest by default) holds its replay buffer item: one without it (its buffer
    deleted) resumes only with an empty buffer (`--fresh-buffer`); CheckpointError if the step is absent."""
    path, _ = _step_dir(directory, step)
    return os.path.isdir(os.path.join(path, "buffer"))


def best_step(directory: str) -> int | None:
    """The checkpoint with the highest saved eval success (the latest of equals), or None."""
    found = steps(directory)
    if not found:
        return None
    options = ocp.CheckpointManagerOptions(read_only=True, best_fn=_best_metric)
    mngr = ocp.CheckpointManager(os.path.abspath(directory), options=options)
    try:
        ranked = [(m[BEST_METRIC], s) for s in found if (m := mngr.metrics(s)) and BEST_METRIC in m]
    finally:
        mngr.close()
    return max(ranked)[1] if ranked else None


def resolve_step(directory: str, step: int | str | None) -> int:
    """A checkpoint step from None (latest), an int (or its string) or "best"; CheckpointError if absent."""
    if step == "best":
        best = best_step(directory)
        if best is None:
            raise CheckpointError(f"no checkpoint with an eval success in {directory}")
        return best
    if isinstance(step, str):
        if not step.isdigit():
            raise CheckpointError(f"checkpoint {step!r}: must be a step number or 'best'")
        step = int(step)
    return _step_dir(directory, step)[1]


def _step_dir(directory: str, step: int | None) -> tuple[str, int]:
    found = steps(directory)
    if not found:
        raise CheckpointError(f"no checkpoint in {directory}")
    step = found[-1] if step is None else step
    if step not in found:
        raise CheckpointError(f"no checkpoint {step} in {directory}; it has {found}")
    return os.path.join(os.path.abspath(directory), str(step)), step


def _reason(err: BaseException) -> str:
    """The first line of the innermost cause: Orbax wraps TensorStore's precise message in long ones."""
    *_, err = rundir.causes(err)
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0] if lines else ''}"[:300]


def read_config(directory: str, step: int | None = None) -> dict:
    """The config stored with a checkpoint (the latest one by default); reads only."""
    path, step = _step_dir(directory, step)
    try:
        config = ocp.Checkpointer(ocp.CompositeCheckpointHandler(**_handlers())).restore(
            path, args=ocp.args.Composite(config=ocp.args.JsonRestore())
        )["config"]
    except Exception as err:  # orbax raises many types for damaged files
        raise CheckpointError(f"checkpoint {step} in {directory} has no readable config ({_reason(err)})") from err
    if not isinstance(config, dict):
        raise CheckpointError(
            f"checkpoint {step} in {directory} has no readable config (it holds {type(config).__name__})"
        )
    return config


def _named(tree: Any) -> dict[str, Any]:
    """Leaf name -> leaf of a tree, in the tree's leaf order."""
    return {leaf_name(path): leaf for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _check_structure(saved: Any, target: Any, where: str, partial: bool = False) -> None:
    """Raise unless the saved leaves have the target's names, shapes and dtypes (with `partial`,
    the saved state may hold more leaves than the target)."""
    have, want = _named(saved), _named(target)
    missing, extra = sorted(set(want) - set(have)), [] if partial else sorted(set(have) - set(want))
    if missing or extra:
        raise CheckpointError(
            f"{where} holds a state of another shape: "
            + "; ".join(filter(None, [missing and f"missing {missing[:3]}", extra and f"unexpected {extra[:3]}"]))
        )
    # the parameters first: a parameter's shape names the config field that differs (an optimiser's raveled
    # moments only their total size)
    for name in sorted(want, key=lambda name: "params" not in name.split("/")[:2]):
        leaf = want[name]
        if tuple(have[name].shape) != tuple(leaf.shape) or np.dtype(have[name].dtype) != np.dtype(leaf.dtype):
            raise CheckpointError(
                f"{where} holds a state of another shape: {name} is {tuple(have[name].shape)} "
                f"{np.dtype(have[name].dtype)}, "
                f"this config needs {tuple(leaf.shape)} {np.dtype(leaf.dtype)}"
            )


def _per_parameter_moments(saved: Any, target: Any) -> dict[str, list[str]]:
    """{target leaf: the saved leaves it ravels} where a checkpoint's optimiser state keeps Adam's moments per
    parameter array (as saved before `train.optimizer` raveled each network group's parameters into one vector)
    and the target wants one vector [seeds, n] each; {} where the structures differ otherwise, or not at all."""
    have, want = _named(saved), _named(target)
    extra = [name for name in have if name not in want]
    moments = {name: [e for e in extra if e.startswith(f"{name}/")] for name in want if name not in have}
    if not extra or not all(moments.values()) or sum(map(len, moments.values())) != len(extra):
        return {}
    for name, parts in moments.items():
        seeds, size = want[name].shape[0], want[name].shape[-1]
        if len(want[name].shape) != 2 or any(have[p].shape[0] != seeds for p in parts) \
                or sum(int(np.prod(have[p].shape[1:])) for p in parts) != size:
            return {}
    return moments


def _per_parameter_target(saved: Any, target: Any, moments: dict[str, list[str]]) -> Any:
    """The restore target of a `saved` state that keeps moments per parameter array: each saved leaf's shape and
    dtype, placed as the target leaf it is, or as the raveled moment it is part of (sharded by the seed axis)."""
    want = _named(target)
    like = {**want, **{part: want[flat] for flat, parts in moments.items() for part in parts}}
    return jax.tree_util.tree_map_with_path(
        lambda path, meta: jax.ShapeDtypeStruct(tuple(meta.shape), meta.dtype, sharding=like[leaf_name(path)].sharding),
        saved)


def _raveled_moments(restored: Any, target: Any, moments: dict[str, list[str]]) -> Any:
    """`restored` (saved per parameter) in the target's structure: each flat moment the saved moments of its
    parameters, each raveled per seed and joined in the parameters' leaf order (`optax.flatten`'s ravel)."""
    have = _named(restored)

    def leaf(path: tuple, _: Any) -> jax.Array:
        name = leaf_name(path)
        if name not in moments:
            return have[name]
        return jax.numpy.concatenate([have[p].reshape(have[p].shape[0], -1) for p in moments[name]], axis=1)

    return jax.tree_util.tree_map_with_path(leaf, target)


def restore(
    directory: str, abstract_state: Any, step: int | None = None, env_shards: int = 1, buffer: Any = None
) -> tuple[Any, dict, int]:
    """Restore (state, config, step) shaped like `abstract_state` (latest step by default); reads only.

    Checks the saved leaves' names, shapes and dtypes against `abstract_state` before
    reading any array, and the restored bytes against the saved digest afterwards. A buffer
    saved by another number of env shards is laid out for `env_shards` (`replay.relayout`).
    With `buffer` (e.g. an empty one), the state holds it instead of the saved buffer, whose
    item is neither read nor needed.
    """
    path, step = _step_dir(directory, step)
    where = f"checkpoint {step} in {directory}"
    fields, saved_buffer = _split(jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state))
    targets = {"state": fields} if buffer is not None else {"state": fields, "buffer": saved_buffer}
    saved = _metadata(path, where, tuple(targets))
    flat_moments = _per_parameter_moments(saved["state"], fields)
    if flat_moments:  # an optimiser state saved before Adam's moments were one vector per group
        targets["state"] = _per_parameter_target(saved["state"], fields, flat_moments)
    _check_structure(saved, targets, where)
    args = {name: ocp.args.StandardRestore(target) for name, target in targets.items()}
    restored = _restore_checked(path, where, {**args, "config": ocp.args.JsonRestore()})
    state = _raveled_moments(restored["state"], fields, flat_moments) if flat_moments else restored["state"]
    if buffer is None:
        saved_shards = (restored["digest"] or {}).get("env_shards", 1)  # checkpoints before env shards: 1
        buffer = replay.relayout(restored["buffer"], saved_shards, env_shards, axis=1)  # after the seed axis
    return type(abstract_state)(**state, buffer=buffer), restored["config"], step


def _metadata(path: str, where: str, names: tuple[str, ...] = ARRAY_ITEMS) -> dict:
    """{"state": tree, "buffer": tree} (the items `names`) of a checkpoint's array metadata (shapes, dtypes; no
    data), each read by its item's handler alone: the other items are not opened."""
    handlers, saved = _handlers(), {}
    for name in names:
        item = os.path.join(path, name)
        if not os.path.isdir(item):
            raise CheckpointError(
                f"{where} has no replay buffer (its buffer item was left out or deleted); "
                "--resume --fresh-buffer continues the run with an empty replay buffer"
                if name == "buffer" else f"{where} is damaged: it has no {name}"
            )
        try:
            saved[name] = dict(handlers[name].metadata(epath.Path(item)))
        except Exception as err:
            raise CheckpointError(f"{where} is damaged: its metadata cannot be read ({_reason(err)})") from err
    return saved


def read_metadata(directory: str, step: int | None = None, names: tuple[str, ...] = ARRAY_ITEMS) -> dict:
    """The array metadata (shape, dtype) of a checkpoint's `state` and `buffer` items (or those
    in `names`); reads no array."""
    path, step = _step_dir(directory, step)
    return _metadata(path, f"checkpoint {step} in {directory}", names)


def _restore_checked(path: str, where: str, args: dict, partial: bool = False) -> dict:
    """Restore the items `args` and check every restored array against the saved digest."""
    reader = ocp.Checkpointer(ocp.CompositeCheckpointHandler(**_handlers(partial)))
    try:
        restored = reader.restore(path, args=ocp.args.Composite(**args, digest=ocp.args.JsonRestore()))
    except Exception as err:
        raise CheckpointError(f"{where} is damaged: {_reason(err)}") from err
    saved = restored["digest"] or {}
    kind, expected = (wsum_digest, saved["wsum"]) if "wsum" in saved else (crc32_digest, saved.get("crc32", {}))
    arrays = {name: restored[name] for name in ARRAY_ITEMS if name in args}
    found = {
        **kind(arrays.get("state", {})),
        **{f"buffer/{k}": v for k, v in kind(arrays.get("buffer", {})).items()},
    }
    bad = [name for name, value in found.items() if expected.get(name) != value]
    if bad:
        raise CheckpointError(f"{where} is corrupted: {', '.join(bad[:3])} does not match its saved checksum")
    return restored


def restore_partial(directory: str, step: int | None, wanted: Any) -> dict:
    """Only the leaves of the `state` item named by `wanted` (a sub-tree of `read_metadata(...)["state"]`
    or of shape/dtype structs), with Orbax partial restore, as numpy arrays on the host (whatever
    devices and processes wrote them: every process reads them whole); the buffer is never read.

    Raises CheckpointError when a wanted leaf is missing, damaged or fails its checksum.
    """
    path, step = _step_dir(directory, step)
    where = f"checkpoint {step} in {directory}"
    # no sharding: the saved one names the writer's devices, which this process may not have
    target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), wanted)
    _check_structure(_metadata(path, where, ("state",))["state"], target, where, partial=True)
    args = ocp.args.PyTreeRestore(
        item=target, restore_args=ocp.checkpoint_utils.construct_restore_args(target), partial_restore=True
    )
    return _restore_checked(path, where, {"state": args}, partial=True)["state"]
