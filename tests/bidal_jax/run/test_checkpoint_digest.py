"""A checkpoint's digest: CRC-32 on the host where the state lies on CPUs, the weighted word sums
(`checkpoint.wsum_digest`) computed where the state lies on accelerators, each checked when restored."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bidal_jax.run import checkpoint
from experiments import run
from tests.helpers import TINY

ARRAYS = {
    "frames": np.random.default_rng(0).integers(0, 256, (3, 4, 5), dtype=np.uint8),
    "weights": np.random.default_rng(1).standard_normal((3, 7)).astype(np.float32),
    "half": np.random.default_rng(2).standard_normal((3, 2)).astype(jnp.bfloat16),
    "done": np.random.default_rng(3).random((3, 6)) > 0.5,
    "steps": np.arange(3, dtype=np.int32) - 1,
}


def _sums(leaf: np.ndarray, offset: int = 0) -> tuple[int, int]:
    weighted, total = jax.device_get(checkpoint._sums([leaf], [np.uint32(offset)]))[0]
    return int(weighted), int(total)


def _by_definition(leaf: np.ndarray) -> int:
    """Σ w_i·(2i+1) and Σ w_i mod 2^32 over the words of `leaf`, written out in Python integers."""
    words = np.ascontiguousarray(leaf).view({1: np.uint8, 2: np.uint16, 4: np.uint32}[leaf.dtype.itemsize])
    words = [int(w) for w in words.reshape(-1)]
    weighted = sum(w * (2 * i + 1) for i, w in enumerate(words)) % 2**32
    return weighted << 32 | sum(words) % 2**32


@pytest.mark.parametrize("name", sorted(ARRAYS))
def test_the_word_sums_are_their_definition_whole_and_summed_one_seed_at_a_time(name):
    """The sums of a leaf equal their definition, and so do those of its seed rows summed with their offsets (how a
    state spanning processes is digested, `multihost.host_parts`)."""
    leaf = ARRAYS[name]
    assert checkpoint.wsum_digest({name: leaf}) == {name: _by_definition(leaf)}
    weighted = total = 0
    for seed in range(leaf.shape[0]):
        w, t = _sums(leaf[seed], offset=seed * leaf[seed].size)
        weighted, total = (weighted + w) % 2**32, (total + t) % 2**32
    assert weighted << 32 | total == _by_definition(leaf)


def test_any_one_word_changed_or_two_words_swapped_changes_the_word_sums():
    frames = ARRAYS["frames"]
    expected = checkpoint.wsum_digest({"f": frames})
    for index in np.ndindex(frames.shape):
        for delta in (1, 128, 255):
            changed = frames.copy()
            changed[index] = (int(changed[index]) + delta) % 256
            assert checkpoint.wsum_digest({"f": changed}) != expected, (index, delta)
    flat = frames.reshape(-1)
    first, second = np.flatnonzero(flat != flat[0])[0], 0
    swapped = flat.copy()
    swapped[[first, second]] = swapped[[second, first]]
    assert checkpoint.wsum_digest({"f": swapped.reshape(frames.shape)}) != expected


def test_the_digest_is_crc32_on_cpus_and_the_word_sums_on_accelerators(monkeypatch):
    state = {name: jnp.asarray(leaf) for name, leaf in ARRAYS.items()}
    assert checkpoint.digest(state) == {"crc32": checkpoint.crc32_digest(state)}
    monkeypatch.setattr(jax.Device, "platform", "gpu", raising=False)
    assert checkpoint.digest(state) == {"wsum": checkpoint.wsum_digest(state)}


def test_a_checkpoint_with_word_sums_restores_and_fails_its_checksum_when_an_array_differs(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    monkeypatch.setattr(checkpoint, "digest", lambda state: {"wsum": checkpoint.wsum_digest(state)})
    assert run.main([*TINY, "--epochs", "1", "--run-dir", str(run_dir)]) == 0
    ckpt_dir = str(run_dir / "checkpoints")
    wanted = {"env_steps": checkpoint.read_metadata(ckpt_dir)["state"]["env_steps"]}
    steps = checkpoint.restore_partial(ckpt_dir, 1, wanted)["env_steps"]
    path = os.path.join(ckpt_dir, "1", "digest", "metadata")  # the JSON item as Orbax writes it
    with open(path) as f:
        saved = json.load(f)
    assert "crc32" not in saved and saved["wsum"]["env_steps"] == checkpoint.wsum_digest({"env_steps": steps})[
        "env_steps"]
    saved["wsum"]["env_steps"] ^= 1 << 40
    with open(path, "w") as f:
        json.dump(saved, f)
    with pytest.raises(checkpoint.CheckpointError, match="env_steps does not match its saved checksum"):
        checkpoint.restore_partial(ckpt_dir, 1, wanted)


def _compiles(action) -> list[str]:
    """The compilations (XLA's, or reads of the persistent cache in their place) that `action()` makes."""
    events, listening = [], [True]
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, *args, **kwargs: events.append(name) if listening[0] else None)
    try:
        action()
    finally:
        listening[0] = False
    return [name for name in events if "backend_compile" in name or "cache_retrieval" in name]


def test_what_a_save_runs_on_accelerators_is_compiled_beforehand(monkeypatch):
    """`compile_for` leaves nothing for the first save to compile (on CPUs it compiles nothing: they digest with
    CRC-32)."""
    state = {"a": jnp.zeros((3, 11), jnp.float32), "b": jnp.zeros((3, 13, 2), jnp.uint8)}  # shapes of no other test
    monkeypatch.setattr(checkpoint, "_on_accelerators", lambda state: True)
    checkpoint.compile_for(state)
    assert _compiles(lambda: (checkpoint.digest(state), checkpoint._copy(state))) == []
    assert _compiles(lambda: checkpoint.digest({"a": jnp.zeros((3, 17), jnp.float32)}))  # what it looks for
