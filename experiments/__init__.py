"""The command lines, grouped by role: `run`, `evaluate` and `plot` here (with `cli` and `report`,
what they share), the paper's experiments in `paper/`, benchmarks in `bench/`, probes in `probes/`
(docs/usage.md lists every command).

This package is where the project's processes start: `python -m experiments.run` imports it before its
module, a grid's Ray workers import it to run a cell, and the tests import it first (tests/conftest.py).
`start_process` sets, once, what those processes need before any of their modules imports MuJoCo or JAX starts
a backend: the XLA:CPU flags measured for the installed jaxlib, MuJoCo's OpenGL backend on a headless machine,
MuJoCo MJX's import without MuJoCo Warp (given to it when an env steps on Warp)
and its two lines about Warp, and for a command line XLA's C++ logs off. The
libraries, `envs_mjx` and `bidal_jax`, change nothing on import (tests/test_import_effects.py); docs/design.md
("Versions and process settings") says what each setting does.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import importlib
import importlib.abc
import importlib.metadata
import importlib.util
import io
import os
import pkgutil
import re
import sys

# XLA:CPU flags by the jaxlib release (major.minor) they were measured with: (flags for every machine, flags only
# where no GPU plugin is installed). XLA aborts on a flag it does not know and releases drop flags, so a release
# not listed here gets none; measure one (experiments.bench.compile_time --xla-option) before adding it.
XLA_FLAGS_BY_JAXLIB = {
    "0.10": (("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_enable_concurrency_optimized_scheduler=false"),
             ("--xla_backend_optimization_level=1",)),
}
# the environment this process started with, before `start_process`: what a command hands to a run of another
# checkout, which sets up its own process (experiments.bench.success)
CALLER_ENVIRONMENT = dict(os.environ)
# mujoco.mjx tries its optional Warp backend on import and prints these when Warp is absent, which is expected
# where the envs run on MJX's JAX backend
WARP_ABSENT = re.compile(r"Failed to import (warp|mujoco_warp): No module named 'warp'")


def xla_flags(jaxlib: str, gpu_plugin: bool) -> tuple[str, ...]:
    """The XLA flags measured for jaxlib version `jaxlib` ("0.10.2"), with or without a GPU plugin installed."""
    every, cpu_only = XLA_FLAGS_BY_JAXLIB.get(".".join(jaxlib.split(".")[:2]), ((), ()))
    return every + (() if gpu_plugin else cpu_only)


def with_flags(current: str, flags: tuple[str, ...]) -> str:
    """`current` XLA_FLAGS with each of `flags` whose name it does not set already (the caller's value wins)."""
    for flag in flags:
        if flag.split("=")[0] not in current:
            current = f"{current} {flag}".strip()
    return current


def gpu_plugin_installed() -> bool:
    """A jax-cuda plugin is installed: its module `jax_plugins.xla_cuda*` (found without importing it, and
    without reading every installed distribution's metadata)."""
    spec = importlib.util.find_spec("jax_plugins")
    locations = spec.submodule_search_locations if spec else None
    return any(m.name.startswith("xla_cuda") for m in pkgutil.iter_modules(locations or []))


def import_without(module: str, noise: re.Pattern) -> None:
    """Import `module`, dropping the lines it prints to stdout that fully match `noise`; any other output passes
    through unchanged, also when the import fails."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            importlib.import_module(module)
    finally:
        lines = captured.getvalue().splitlines(keepends=True)
        sys.stdout.write("".join(line for line in lines if not noise.fullmatch(line.rstrip("\n"))))


class WithoutWarp(importlib.abc.MetaPathFinder):
    """An import hook that finds no `warp` package (warp-lang), as if it were not installed."""

    def find_spec(self, name: str, path=None, target=None) -> None:
        if name == "warp" or name.startswith("warp."):
            raise ModuleNotFoundError("No module named 'warp'", name="warp")


def import_mjx_without_warp() -> None:
    """Import mujoco.mjx without its optional MuJoCo Warp backend, which costs seconds of CUDA start-up where
    warp-lang is installed though most runs step MJX's JAX physics; `envs_mjx.enable_warp` gives it Warp when an env
    first steps on it. mujoco.mjx then prints its two lines about an absent Warp, which are dropped."""
    hooks = [] if "warp" in sys.modules else [WithoutWarp()]
    sys.meta_path[:0] = hooks
    try:
        import_without("mujoco.mjx", WARP_ABSENT)
    finally:
        for hook in hooks:
            sys.meta_path.remove(hook)


def start_process() -> None:
    """Set up this process for the project's programs (the module docstring); what the caller's environment sets
    already wins. Idempotent."""
    # `python -m experiments.<command>` (Python names the module "-m" while it imports this package to find it):
    # XLA's and absl's C++ logs (the GPU autotuner's dumps, rematerialization warnings) stay off the terminal, since
    # every failure is one `error:` line; set before JAX loads. TF_CPP_MIN_LOG_LEVEL=0 shows them.
    if sys.argv[:1] == ["-m"]:
        os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    # XLA reads XLA_FLAGS once, when its first backend starts: before anything computes
    flags = xla_flags(importlib.metadata.version("jaxlib"), gpu_plugin_installed())
    os.environ["XLA_FLAGS"] = with_flags(os.environ.get("XLA_FLAGS", ""), flags)
    # MuJoCo picks its OpenGL backend once, on import; its default (GLFW) needs a display. On a headless Linux
    # machine with an EGL library, EGL renders offscreen (evaluate --video, envs_mjx.gym's render)
    headless = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if headless and "mujoco" not in sys.modules and ctypes.util.find_library("EGL"):
        os.environ.setdefault("MUJOCO_GL", "egl")
    if "mujoco.mjx" not in sys.modules:
        import_mjx_without_warp()


start_process()
