"""The epoch program kept across processes: `jax.export` of the traced and lowered epoch, saved in the
persistent compilation cache's folder under a key over everything the program is traced from.

The persistent compilation cache (`loop.enable_compilation_cache`) spares a second process of a config
XLA's compile, not the tracing and lowering of the epoch before it (tens of seconds for a NICOL program).
With the program saved, a second process of the same program (a resumed run, a repeated one, the next
seed of a grid) deserialises it instead, and XLA finds its compiled form in the cache.

The key (`program_key`) hashes what the program is traced from: the config's fields that shape it (all
but where a run writes, how long it runs and where it starts from), the env's physics fingerprint
(`Env.physics_id`), the source of the packages that trace it and of the models, the versions of the
libraries that trace and lower it, and the devices. Any change is another program. One device and one env
shard only: other layouts are traced as before, and so is a program `jax.export` refuses (e.g. a custom
call without a stability guarantee, as MuJoCo Warp's). A saved program that cannot be read is traced and
saved again; one that cannot be saved (a full disk) costs its run nothing but the saving.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.resources
import json
import os
from typing import Any, Callable

import jax

from bidal_jax.config import Config
from bidal_jax.run import memory
from bidal_jax.run.runfiles import write_atomic

PACKAGES = ("bidal_jax", "envs_mjx")  # the packages the program is traced from, and the models (envs_mjx.assets)
LIBRARIES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "flax", "optax", "chex", "numpy")
# run fields that do not shape the program: where it writes, how long it runs, what state it starts from
RUN_FIELDS_OUTSIDE = ("seed", "epochs", "checkpoint_every", "run_dir", "target_success", "init_from", "init_parts",
                      "init_normaliser")


@functools.cache
def source_digest() -> str:
    """sha256 over the Python source of `PACKAGES` and the MJCF models, each file named by its path."""
    digest = hashlib.sha256()
    roots = [importlib.resources.files(name) for name in PACKAGES] + [importlib.resources.files("envs_mjx.assets")]
    for root in roots:
        base = str(root)
        for folder, dirs, files in sorted(os.walk(base, followlinks=True)):
            dirs.sort()
            for name in sorted(f for f in files if f.endswith((".py", ".xml"))):
                path = os.path.join(folder, name)
                digest.update(os.path.relpath(path, base).encode() + b"\0")
                with open(path, "rb") as f:
                    digest.update(f.read())
    return digest.hexdigest()


def _version(library: str) -> str:
    try:
        return importlib.metadata.version(library)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


def program_key(config: Config, physics_id: str, devices: list) -> str:
    """The key of the epoch program of `config` on an env of physics `physics_id` laid out on `devices`."""
    fields = config.to_dict()
    fields["run"] = {k: v for k, v in fields["run"].items() if k not in RUN_FIELDS_OUTSIDE}
    what = {
        "config": fields, "physics": physics_id, "source": source_digest(),
        "libraries": {name: _version(name) for name in LIBRARIES},
        "devices": [f"{d.platform}:{d.device_kind}" for d in devices], "x64": bool(jax.config.jax_enable_x64),
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:32]


def folder() -> str | None:
    """Where programs are saved: `programs/` in the persistent compilation cache's folder; None without one."""
    cache = jax.config.jax_compilation_cache_dir
    return os.path.join(cache, "programs") if cache else None


def _load(path: str, avals: list) -> Any:
    """The program saved at `path` if it can be read and takes `avals`; else None."""
    try:
        with open(path, "rb") as f:
            program = jax.export.deserialize(bytearray(f.read()))
    except Exception:  # missing, unreadable, truncated or from another serialisation version: trace it anew
        return None
    return program if [(tuple(a.shape), a.dtype) for a in program.in_avals] == avals else None


def _save(path: str, program: Any, log: Callable[[str], None]) -> None:
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        # several processes of one program (a grid's cells) may save it at once: a temporary file each
        write_atomic(path, bytes(program.serialize()), tmp=f"{path}.{os.getpid()}.tmp")
    except OSError as err:
        log(f"the traced program was not saved ({err.strerror or err}); a later run traces it again")


def compile_epoch(epoch: Callable, state: Any, path: str,
                  log: Callable[[str], None]) -> tuple[Callable, bool, Any]:
    """(the compiled `epoch` as `epoch(state) -> (state, metrics)`, whether it was loaded from `path`, the compiled
    program's `memory_analysis()`): the program saved at `path`, else `epoch` traced with `jax.export` and saved
    there. Its input state is donated,
    as `epoch`'s (`devices.make_seeded`). Raises what `jax.export` raises for a program it cannot export."""
    leaves, treedef = jax.tree.flatten(state)
    avals = [(tuple(x.shape), x.dtype) for x in leaves]
    program = _load(path, avals)
    loaded = program is not None
    if not loaded:
        def flat(*xs):
            new, metrics = epoch(jax.tree.unflatten(treedef, xs))
            return jax.tree.leaves(new), metrics

        program = jax.export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(*a) for a in avals])
        _save(path, program, log)

    def epoch_program(*xs):
        return program.call(*xs)

    epoch_program.__name__ = "epoch"  # jit_epoch, as the traced program is named, in the cache and in profiles
    compiled = jax.jit(epoch_program, donate_argnums=tuple(range(len(leaves)))).lower(*leaves).compile()

    def run(state: Any) -> tuple[Any, dict]:
        new, metrics = compiled(*jax.tree.leaves(state))
        return jax.tree.unflatten(treedef, new), metrics

    return run, loaded, memory.analysis(compiled)
