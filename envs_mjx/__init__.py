"""MJX environments of the paper's tasks, behind one registry (docs/design.md).

    env = envs_mjx.make("planar_reach", render=False)
    state = jax.jit(env.reset)(key)
    state = jax.jit(env.step)(state, action)
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
from typing import Any


def _import_without(module: str, noise: re.Pattern) -> None:
    """Import `module`, dropping the lines it prints to stdout that fully match `noise`; any
    other output passes through unchanged, also when the import fails."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            importlib.import_module(module)
    finally:
        lines = captured.getvalue().splitlines(keepends=True)
        sys.stdout.write("".join(line for line in lines if not noise.fullmatch(line.rstrip("\n"))))


# MuJoCo picks its OpenGL backend once, on import, from MUJOCO_GL; its default (GLFW) needs a
# display. On a headless Linux machine default to EGL, so that offscreen rendering
# (envs_mjx.gym's render) works, where an EGL library is installed (without one, mujoco's import
# itself would fail); an explicit MUJOCO_GL, or mujoco imported earlier, wins.
_HEADLESS = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
if _HEADLESS and "mujoco" not in sys.modules and ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")

class _WithoutWarp(importlib.abc.MetaPathFinder):
    """An import hook that finds no `warp` package (warp-lang), as if it were not installed."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name == "warp" or name.startswith("warp."):
            raise ModuleNotFoundError("No module named 'warp'", name="warp")


# mujoco.mjx imports its optional MuJoCo Warp backend on import, which costs seconds where warp-lang is installed
# (CUDA's start-up) though most runs step MJX's JAX physics: it is imported here without warp-lang, and
# `enable_warp` imports Warp when an env first steps on it (`Env.use_backend`). mujoco.mjx then prints "Failed to
# import warp: No module named 'warp'" and the same for mujoco_warp, which is expected: exactly those two lines are
# dropped.
_WARP_ABSENT = re.compile(r"Failed to import (warp|mujoco_warp): No module named 'warp'")
if "mujoco.mjx" not in sys.modules:
    _HOOKS = [] if "warp" in sys.modules else [_WithoutWarp()]
    sys.meta_path[:0] = _HOOKS
    try:
        _import_without("mujoco.mjx", _WARP_ABSENT)
    finally:
        for _hook in _HOOKS:
            sys.meta_path.remove(_hook)


def enable_warp() -> None:
    """Give mujoco.mjx its MuJoCo Warp backend, which it was imported without (above): import warp-lang, then run
    again the import-time code of the mujoco.mjx modules that bind Warp's names on import (its `warp` package, the
    types of its Warp data and its io module; reloaded in place, so that the functions mujoco.mjx exports see the
    new names). ImportError where warp-lang is not installed."""
    import mujoco.mjx.warp as mjx_warp

    if mjx_warp.WARP_INSTALLED:
        return
    import warp  # noqa: F401 - an ImportError here, not a message printed by mujoco.mjx
    from mujoco.mjx._src import io as mjx_io
    from mujoco.mjx.warp import types as mjx_warp_types

    for module in (mjx_warp_types, mjx_warp, mjx_io):
        importlib.reload(module)

from envs_mjx.base import Env, ObservationSpec, State  # noqa: E402 - after the quiet mjx import above

# XLA:CPU flags, read once when the CPU backend starts, so they are set here, on import,
# before the first computation. With its default fusion emitters XLA:CPU compiles MJX
# steps in time that grows exponentially with the depth of the kinematic tree (the
# nine-level NICOL arm: over ten times as long per step function); without them its
# concurrency-optimised scheduler deadlocks nicol's step at 256 envs on 2 cores. Neither
# flag affects GPUs; on planar/ur5 they cost <20 % of CPU physics throughput. XLA aborts
# on flags it does not know, and newer releases dropped the first one, so they are set
# only for the jaxlib they were measured with (the version pinned in pyproject.toml).
# LLVM's optimisation level 1 instead of 2 cuts XLA:CPU's compile of an epoch by a third to a
# half, and its init's more, with no measured loss of speed; the backend flag is global, so it
# is set only where no GPU plugin is installed.
_CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_enable_concurrency_optimized_scheduler=false")
_CPU_ONLY_FLAGS = ("--xla_backend_optimization_level=1",)
_FLAGS_JAXLIB = "0.10.2"


def _gpu_plugin_installed() -> bool:
    """A jax-cuda plugin is installed: its module `jax_plugins.xla_cuda*` (found without importing
    it, and without reading every installed distribution's metadata on each import)."""
    spec = importlib.util.find_spec("jax_plugins")
    locations = spec.submodule_search_locations if spec else None
    return any(m.name.startswith("xla_cuda") for m in pkgutil.iter_modules(locations or []))


if importlib.metadata.version("jaxlib") == _FLAGS_JAXLIB:
    for _flag in _CPU_FLAGS + (() if _gpu_plugin_installed() else _CPU_ONLY_FLAGS):
        if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
            os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flag}".strip()

# name -> "module:Class", imported lazily so that building one env never loads the others. A new task is its
# module (its class, model and `task`: presets, budget, contract) and one line here (docs/usage.md)
_REGISTRY: dict[str, str] = {
    "planar_reach": "envs_mjx.planar_reach:PlanarReach",
    "ur5_reach": "envs_mjx.ur5_reach:UR5Reach",
    "nicol_slide": "envs_mjx.nicol:NicolSlide",
    "nicol_lift": "envs_mjx.nicol:NicolLift",
    "nicol_lift_reduced": "envs_mjx.nicol:NicolLiftReduced",
    "nicol_slide_ee": "envs_mjx.nicol:NicolSlideEE",
    "nicol_slide_ee_obj": "envs_mjx.nicol:NicolSlideEEObj",
}


def register(name: str, target: str) -> None:
    """Register an env class or factory function given as "module:name" under `name`."""
    _REGISTRY[name] = target


def names() -> tuple[str, ...]:
    """The registered environment names."""
    return tuple(_REGISTRY)


def _registered(name: str) -> Any:
    """The class or factory registered as `name`, imported, not called; ValueError for an unknown name."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown env {name!r}; valid envs: {', '.join(names())}")
    module_name, class_name = _REGISTRY[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def make(name: str, **overrides: Any) -> Env:
    """Build the environment `name`; keyword overrides go to its constructor."""
    return _registered(name)(**overrides)


def task(name: str) -> Any:
    """What the task `name` declares beside its dynamics (its class's `task`, an `envs_mjx.task.Task`: presets,
    learning-curve budget, contract), without building it; a registered factory without one declares nothing."""
    return getattr(_registered(name), "task", Env.task)


__all__ = ["Env", "ObservationSpec", "State", "make", "names", "register", "task"]
