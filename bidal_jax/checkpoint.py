"""Orbax checkpoints of the whole `TrainState` plus the run's config (DESIGN.md).

A checkpoint directory `<run>/checkpoints/<epoch>/` holds three items: `state` (all
parameters, optimiser states, targets, normalisers, replay buffer, rng, counters),
`config` (the run's config as JSON) and `digest` (a CRC-32 per state leaf, as JSON).

Crash safety: Orbax writes each step to `<epoch>.orbax-checkpoint-tmp/` and renames it
when complete, so a process killed at any moment (even mid-save) leaves the previous
checkpoint intact; the step listing ignores unfinished temporary directories and a
writing `manager` deletes them. Damage is detected, never restored silently: Orbax and
TensorStore reject truncated or missing files, and the digest catches flipped bytes,
which they would load without complaint. Every failure is a `CheckpointError` whose
message says which checkpoint and what is wrong with it.

`restore_subtrees` lifts named parameter subtrees (encoder, forward, inverse, ...) out
of a checkpoint for transfer.
"""

from __future__ import annotations

import os
import zlib
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp


class CheckpointError(Exception):
    """A checkpoint that cannot be used: missing, damaged, or written for another run."""


def _handlers() -> dict[str, ocp.CheckpointHandler]:
    return {
        "state": ocp.StandardCheckpointHandler(),
        "config": ocp.JsonCheckpointHandler(),
        "digest": ocp.JsonCheckpointHandler(),
    }


def manager(directory: str, max_to_keep: int = 2) -> ocp.CheckpointManager:
    """A writing manager; creates `directory` and removes unfinished saves left in it."""
    return ocp.CheckpointManager(
        os.path.abspath(directory),
        options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True, cleanup_tmp_directories=True),
        item_handlers=_handlers(),
    )


def leaf_name(path: tuple) -> str:
    """A pytree key path as `params/actor/...`."""
    return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k)))) for k in path)


def digest(state: Any) -> dict[str, int]:
    """Leaf name -> CRC-32 of its bytes (on the host)."""
    leaves = jax.tree_util.tree_flatten_with_path(jax.device_get(state))[0]
    return {leaf_name(path): zlib.crc32(np.ascontiguousarray(leaf)) for path, leaf in leaves}


def save(mngr: ocp.CheckpointManager, step: int, state: Any, config: dict) -> None:
    """Save `state`, `config` and the state's digest as `step`; wait until it is on disk."""
    mngr.save(
        step,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state),
            config=ocp.args.JsonSave(config),
            digest=ocp.args.JsonSave({"crc32": digest(state)}),
        ),
    )
    mngr.wait_until_finished()


def steps(directory: str) -> list[int]:
    """The complete checkpoints in `directory`, oldest first (unfinished saves are not listed)."""
    if not os.path.isdir(directory):
        return []
    return sorted(ocp.path.step.checkpoint_steps(directory))


def latest_step(directory: str) -> int | None:
    found = steps(directory)
    return found[-1] if found else None


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
    for _ in range(16):  # bounded: a chain may loop
        inner = err.__cause__ or err.__context__
        if inner is None:
            break
        err = inner
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
        raise CheckpointError(f"checkpoint {step} in {directory} has no readable config (it holds {type(config).__name__})")
    return config


def _check_structure(saved: Any, target: Any, where: str) -> None:
    """Raise unless the saved state's leaves have the target's names, shapes and dtypes."""
    have = {leaf_name(p): leaf for p, leaf in jax.tree_util.tree_flatten_with_path(saved)[0]}
    want = {leaf_name(p): leaf for p, leaf in jax.tree_util.tree_flatten_with_path(target)[0]}
    missing, extra = sorted(set(want) - set(have)), sorted(set(have) - set(want))
    if missing or extra:
        raise CheckpointError(
            f"{where} holds a state of another shape: "
            + "; ".join(filter(None, [missing and f"missing {missing[:3]}", extra and f"unexpected {extra[:3]}"]))
        )
    for name, leaf in want.items():
        if tuple(have[name].shape) != tuple(leaf.shape) or np.dtype(have[name].dtype) != np.dtype(leaf.dtype):
            raise CheckpointError(
                f"{where} holds a state of another shape: {name} is {tuple(have[name].shape)} {np.dtype(have[name].dtype)}, "
                f"this config needs {tuple(leaf.shape)} {np.dtype(leaf.dtype)}"
            )


def restore(directory: str, abstract_state: Any, step: int | None = None) -> tuple[Any, dict, int]:
    """Restore (state, config, step) shaped like `abstract_state` (latest step by default); reads only.

    Checks the saved leaves' names, shapes and dtypes against `abstract_state` before
    reading any array, and the restored bytes against the saved digest afterwards.
    """
    path, step = _step_dir(directory, step)
    where = f"checkpoint {step} in {directory}"
    reader = ocp.Checkpointer(ocp.CompositeCheckpointHandler(**_handlers()))
    target = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
    try:
        items = reader.metadata(path).item_metadata
        saved = items["state"]
    except Exception as err:
        raise CheckpointError(f"{where} is damaged: its metadata cannot be read ({_reason(err)})") from err
    if saved is None:
        raise CheckpointError(f"{where} is damaged: it has no state")
    _check_structure(saved, target, where)
    args = {"state": ocp.args.StandardRestore(target), "config": ocp.args.JsonRestore()}
    if "digest" in items:  # checkpoints written before digests existed have none
        args["digest"] = ocp.args.JsonRestore()
    try:
        restored = reader.restore(path, args=ocp.args.Composite(**args))
    except Exception as err:
        raise CheckpointError(f"{where} is damaged: {_reason(err)}") from err
    if "digest" in args:
        expected = (restored["digest"] or {}).get("crc32", {})
        bad = [name for name, crc in digest(restored["state"]).items() if expected.get(name) != crc]
        if bad:
            raise CheckpointError(f"{where} is corrupted: {', '.join(bad[:3])} does not match its saved checksum")
    return restored["state"], restored["config"], step


def restore_subtrees(directory: str, abstract_state: Any, names: tuple[str, ...], step: int | None = None) -> dict:
    """The parameter subtrees `names` of a checkpoint, e.g. ("encoder", "forward", "inverse")."""
    state, _, _ = restore(directory, abstract_state, step)
    missing = [n for n in names if n not in state.params]
    if missing:
        raise CheckpointError(f"checkpoint has no parameter subtrees {missing}; it has {sorted(state.params)}")
    return {n: state.params[n] for n in names}
