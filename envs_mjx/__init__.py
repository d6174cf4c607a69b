"""MJX environments of the paper's tasks, behind one registry (docs/design.md).

    env = envs_mjx.make("planar_reach", render=False)
    state = jax.jit(env.reset)(key)
    state = jax.jit(env.step)(state, action)

Importing the package changes nothing in the process (no environment variable, no output). A program of its own
that renders on a machine without a display sets `MUJOCO_GL=egl` (or osmesa) before MuJoCo is imported; the
project's command lines do (`experiments.start_process`).
"""

from __future__ import annotations

import importlib
from typing import Any

from envs_mjx.base import Env, ObservationSpec, State, enable_warp  # noqa: F401 - the package's API

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


def lineage(name: str) -> tuple[str, ...]:
    """`name` and the envs its class derives from, nearest first: a labelled variant (nicol_slide_ee,
    nicol_lift_reduced) keeps its base task's dynamics, starts and goals, so the base's figures of the task (its
    floor, its measured epoch) are the variant's; (`name`,) for a registered factory and for a name the registry
    lacks (a run of a task no longer registered), which derive from nothing."""
    found = getattr(_registered(name), "__mro__", ()) if name in _REGISTRY else ()
    derived = (c.__dict__.get("name") for c in found)
    return tuple(dict.fromkeys([name, *(n for n in derived if n in _REGISTRY)]))


__all__ = ["Env", "ObservationSpec", "State", "lineage", "make", "names", "register", "task"]
