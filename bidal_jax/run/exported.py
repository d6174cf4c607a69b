"""The epoch program kept across processes: `jax.export` of the traced and lowered epoch, saved in the
persistent compilation cache's folder under a key over everything the program is traced from.

The persistent compilation cache (`cachefolder.enable`) spares a second process of a config
XLA's compile, not the tracing and lowering of the epoch before it (tens of seconds for a NICOL program).
With the program saved, a second process of the same program (a resumed run, a repeated one, the next
seed of a grid) deserialises it instead, and XLA finds its compiled form in the cache.

The key (`program_key`) hashes what the program is traced from: the config's fields that shape it (all
but where a run writes, how long it runs and where it starts from), the env's physics fingerprint
(`Env.physics_id`), the source of the packages that trace it and of the models (`source_digest`), the
versions of the libraries that trace and lower it and of everything they require, and of JAX's device
plugins (`library_versions`), and the devices. Any change is another program. One device and one env shard
only: other layouts are traced as before, and so is a program `jax.export` refuses (e.g. a custom call
without a stability guarantee, as MuJoCo Warp's).

A saved file (`pack`) starts with a header holding its key, the length and the sha256 of the serialised
program after it, so that a program is only ever loaded for its own key: a file of another key copied into
place, a file cut short (a process killed mid-write, a full disk) or otherwise damaged is traced anew and
saved again, with a line saying why (`unpack`). Several processes of one program (a grid's cells) may save
it at once: each writes a temporary file of its own in the same folder and renames it into place, so that a
reader sees one whole file or none. A program that cannot be saved (a read-only folder, a full disk) costs
its run nothing but the saving: one warning line (`cachefolder.warn`), and the next run traces it again.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.resources
import json
import os
import re
import uuid
from typing import Any, Callable

import jax

from bidal_jax.config import Config
from bidal_jax.run import cachefolder, memory
from bidal_jax.run.runfiles import write_atomic

PACKAGES = ("bidal_jax", "envs_mjx")  # the packages the program is traced from, and the models (envs_mjx.assets)
# the libraries that trace and lower the program; `library_versions` adds what they require, and JAX's plugins
LIBRARIES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "flax", "optax", "chex", "numpy")
MAGIC = b"bidal-jax epoch program 1\n"  # a saved file's first line; its second: "<key> <bytes> <sha256>\n"
# run fields that do not shape the program: where it writes, how long it runs, what state it starts from
RUN_FIELDS_OUTSIDE = ("seed", "epochs", "checkpoint_every", "run_dir", "target_success", "init_from", "init_parts",
                      "init_normaliser")


@functools.cache
def source_digest() -> str:
    """sha256 over the Python source of `PACKAGES` and the MJCF models (`files_digest`)."""
    roots = [importlib.resources.files(name) for name in PACKAGES] + [importlib.resources.files("envs_mjx.assets")]
    return files_digest([str(root) for root in roots])


def files_digest(roots: list[str]) -> str:
    """sha256 over the .py and .xml files under each folder of `roots`, each named by its path in its root."""
    digest = hashlib.sha256()
    for base in roots:
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


def _requires(library: str) -> list[str]:
    """The distributions `library` requires whatever extras it is installed with (a requirement that holds only
    for an extra is left out; one for another platform is kept, and reads "absent")."""
    try:
        requirements = importlib.metadata.requires(library) or []
    except importlib.metadata.PackageNotFoundError:
        return []
    return [re.match(r"\s*[A-Za-z0-9][A-Za-z0-9._-]*", name).group(0).strip()
            for name, _, marker in (r.partition(";") for r in requirements) if "extra" not in marker]


@functools.cache
def library_versions() -> dict[str, str]:
    """Distribution -> version of `LIBRARIES`, of every distribution they require in turn, and of JAX's device
    plugins (the distributions of the `jax_plugins` entry points: jax-cuda12-plugin, ...): a new version of any
    of them may trace or lower the program otherwise."""
    plugins = [ep.dist.name for ep in importlib.metadata.entry_points(group="jax_plugins") if ep.dist]
    versions: dict[str, str] = {}
    todo = [*LIBRARIES, *plugins]
    while todo:
        name = re.sub(r"[-_.]+", "-", todo.pop()).lower()
        if name not in versions:
            versions[name] = _version(name)
            todo += _requires(name)
    return dict(sorted(versions.items()))


def program_key(config: Config, physics_id: str, devices: list) -> str:
    """The key of the epoch program of `config` on an env of physics `physics_id` laid out on `devices`."""
    fields = config.to_dict()
    fields["run"] = {k: v for k, v in fields["run"].items() if k not in RUN_FIELDS_OUTSIDE}
    what = {
        "config": fields, "physics": physics_id, "source": source_digest(),
        "libraries": library_versions(),
        "devices": [f"{d.platform}:{d.device_kind}" for d in devices], "x64": bool(jax.config.jax_enable_x64),
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:32]


def folder() -> str | None:
    """Where programs are saved: `programs/` in the persistent compilation cache's folder; None without one."""
    cache = jax.config.jax_compilation_cache_dir
    return os.path.join(cache, "programs") if cache else None


def pack(key: str, program: bytes) -> bytes:
    """The file of a program saved under `key`: `MAGIC`, a line of its key, length and sha256, the program."""
    return MAGIC + f"{key} {len(program)} {hashlib.sha256(program).hexdigest()}\n".encode() + program


def unpack(data: bytes, key: str) -> tuple[bytes | None, str]:
    """(the serialised program in a saved file's `data`, "") if the file is whole and saved under `key`, else
    (None, why not)."""
    if not data.startswith(MAGIC):
        return None, "not a saved program of this version"
    header, newline, program = data[len(MAGIC):].partition(b"\n")
    fields = header.decode(errors="replace").split()
    if not newline or len(fields) != 3 or not fields[1].isdigit():
        return None, "cut short (no whole header)"
    saved_key, size, digest = fields[0], int(fields[1]), fields[2]
    if saved_key != key:
        return None, f"another program's (its key is {saved_key[:12]}...)"
    if len(program) != size:
        return None, f"cut short ({len(program):,} of its {size:,} bytes)"
    if hashlib.sha256(program).hexdigest() != digest:
        return None, "damaged (its checksum differs)"
    return program, ""


def _load(path: str, key: str, avals: list, log: Callable[[str], None]) -> Any:
    """The program saved at `path` under `key` if it is whole and takes `avals`; else None (with a line saying why
    when a file was there)."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        return None
    except OSError as err:
        data, why = None, f"unreadable ({err.strerror or err})"
    if data is not None:
        program, why = unpack(data, key)
        if program is not None:
            try:
                loaded = jax.export.deserialize(bytearray(program))
                if [(tuple(a.shape), a.dtype) for a in loaded.in_avals] == avals:
                    return loaded
                why = "of other input shapes"
            except Exception as err:  # from another serialisation version
                why = f"not readable by this JAX ({type(err).__name__})"
    log(f"the saved epoch program {path} is {why}: traced anew")
    return None


def _save(path: str, key: str, program: Any, log: Callable[[str], None]) -> None:
    """Save `program` at `path` under `key` (`pack`) through a temporary file of this call's own in the same folder
    (several processes, or threads, may save one program at once); a failure is one warning line."""
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        write_atomic(path, pack(key, bytes(program.serialize())), tmp=f"{path}.{os.getpid()}-{uuid.uuid4().hex}.tmp")
    except OSError as err:
        cachefolder.warn(os.path.dirname(path), err.strerror or str(err), log)


def path_of(where: str, key: str) -> str:
    """The file of the program of `key` in the folder `where`."""
    return os.path.join(where, f"epoch-{key}.jax")


def compile_epoch(epoch: Callable, state: Any, where: str, key: str,
                  log: Callable[[str], None]) -> tuple[Callable, bool, Any]:
    """(the compiled `epoch` as `epoch(state) -> (state, metrics)`, whether it was loaded, the compiled program's
    `memory_analysis()`): the program saved in the folder `where` under `key`, else `epoch` traced with
    `jax.export` and saved there. Its input state is donated, as `epoch`'s (`devices.make_seeded`). Raises what
    `jax.export` raises for a program it cannot export."""
    leaves, treedef = jax.tree.flatten(state)
    avals = [(tuple(x.shape), x.dtype) for x in leaves]
    path = path_of(where, key)
    program = _load(path, key, avals, log)
    loaded = program is not None
    if not loaded:
        def flat(*xs):
            new, metrics = epoch(jax.tree.unflatten(treedef, xs))
            return jax.tree.leaves(new), metrics

        program = jax.export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(*a) for a in avals])
        _save(path, key, program, log)

    def epoch_program(*xs):
        return program.call(*xs)

    epoch_program.__name__ = "epoch"  # jit_epoch, as the traced program is named, in the cache and in profiles
    compiled = jax.jit(epoch_program, donate_argnums=tuple(range(len(leaves)))).lower(*leaves).compile()

    def run(state: Any) -> tuple[Any, dict]:
        new, metrics = compiled(*jax.tree.leaves(state))
        return jax.tree.unflatten(treedef, new), metrics

    return run, loaded, memory.analysis(compiled)
