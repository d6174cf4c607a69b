"""Transfer of a learned representation into a new run (paper Sec. IV-C).

The paper pre-trains multimodal BidAL on sliding and re-uses its representation, the
encoder φ and the forward and inverse models f and g, to learn lifting with reduced
proprioception faster. A run starts from another run's parameters through two config
fields: `init_from` ("RUN_DIR" or "RUN_DIR:CHECKPOINT", a step or "best"; default the
latest checkpoint) and `init_parts` (the parameter subtrees to restore, default
"encoder,forward,inverse").

What is restored, from the source's `params` only, with Orbax partial restore (the
replay buffer, optimiser states and target networks of the source are never read, so a
checkpoint whose buffer files were deleted still serves):

- the named subtrees, into both the online and the target networks (a fresh run's
  targets equal its online networks); all other networks keep their fresh
  initialisation and every optimiser starts fresh (Adam moments zero, step 0);
- the proprio normaliser only with `init_normaliser` "inherit": then, with an encoder
  that reads proprio, the statistics it was trained with (count, mean, M2, std), whose
  running statistics continue from the source's counts. By default ("fresh") the run's
  proprio normaliser starts afresh (zero counts): it measures the target task's own
  observations from its first rollout, where the source's counts (millions of slide
  steps) would hold its mean and std near sliding's for the whole run, while the
  encoder's weights still come from the source. The goal normaliser is never carried:
  goals reach only the actor and critic (UVFA's η), which start fresh, and the goal
  distributions differ (sliding's goals lie on the table, lifting's 5-25 cm above it:
  sliding's height spread, at the normaliser's floor, would clip every lift goal);
- the layer whose rows are the proprio features (the family's `proprio_kernel`, DDPG's
  encoder's proprio layer) maps its input rows by segment name: the target's proprio
  segments must be a subset of the source's (same names and sizes, any order) and the
  target row of a feature is the source row of that feature.
  An inherited proprio normaliser's per-feature statistics are mapped alike.

Seeds: seed i of the new run starts from seed i of the source, so that S seeds of a
transfer experiment are S independent replications of pre-training and transfer; the
source must have at least as many seeds (extra source seeds are not used).

Everything else must match by name and shape: a subtree the source or the new run lacks,
a leaf of another shape or dtype, a target segment the source lacks. `check` (called by
`preflight.prepare`, before anything is compiled or written) and the initializer refuse them
with a one-line `CheckpointError` naming the leaf and both shapes.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import agents, noise, normalizer
from bidal_jax.config import Config, ConfigError, ConfigFormatError, RunConfig
from bidal_jax.run import checkpoint
from bidal_jax.run.checkpoint import CheckpointError, leaf_name

Segments = Sequence[tuple[str, int]]


def row_mapped(kernel: str) -> frozenset[str]:
    """The leaves whose first per-seed axis is the proprio feature axis: the state's `kernel` (the family's
    `proprio_kernel`) and the proprio normaliser's per-feature fields."""
    fields = normalizer.FEATURE_FIELDS + normalizer.LEGACY_FEATURE_FIELDS
    return frozenset({kernel, *(f"proprio_norm/{k}" for k in fields)})


def parse_init_from(text: str) -> tuple[str, str | None]:
    """"RUN_DIR" -> (RUN_DIR, None: the latest checkpoint); "RUN_DIR:7" or "RUN_DIR:best" -> (RUN_DIR, "7" | "best")."""
    run_dir, sep, step = text.rpartition(":")
    if sep and run_dir and (step.isdigit() or step == "best"):
        return run_dir, step
    return text, None


def parse_parts(text: str) -> tuple[str, ...]:
    """"encoder, forward,inverse" -> ("encoder", "forward", "inverse")."""
    return tuple(name.strip() for name in text.split(","))


def row_map(source: Segments, target: Segments) -> np.ndarray:
    """The source proprio row of each target proprio feature, in the target's order.

    Raises ValueError when a target segment is missing from the source or has another size.
    """
    sizes = dict(source)
    for name, size in target:
        if name in sizes and sizes[name] != size:
            raise ValueError(f"proprio segment {name} has {sizes[name]} features in the source, {size} in this run")
    return noise.feature_indices(tuple(source), tuple(name for name, _ in target))


@dataclasses.dataclass(frozen=True)
class Plan:
    """What a transfer reads and where it goes; built by `plan` after every check."""

    directory: str  # the source's checkpoints
    step: int
    parts: tuple[str, ...]
    wanted: dict  # the source's state metadata to restore (params subtrees, normalisers)
    rows: np.ndarray | None  # source proprio rows of this run's features, when the encoder reads proprio
    seeds: int  # this run's seeds: seed i from the source's seed i
    mapped: frozenset[str]  # the leaves whose rows `rows` maps (`row_mapped`)


def _leaves(tree: Any) -> dict[str, Any]:
    return {leaf_name(path): leaf for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _compare(where: str, saved: dict, target: dict, rows: np.ndarray | None, mapped: frozenset[str]) -> None:
    """Refuse unless the source's leaves `saved` match this run's `target` by name, per-seed shape and
    dtype; row-mapped leaves are compared after the mapping."""
    have, want = _leaves(saved), _leaves(target)
    unmatched = sorted(set(have) ^ set(want))
    if unmatched:
        name = unmatched[0]
        owner, other = ("the source", "this run") if name in have else ("this run", "the source")
        shape = tuple((have[name] if name in have else want[name]).shape[1:])
        raise CheckpointError(f"{where}: {owner} has {name} ({shape} per seed), {other} has none")
    for name, leaf in want.items():
        source_shape = tuple(have[name].shape[1:])
        expected = (len(rows), *source_shape[1:]) if name in mapped else source_shape
        if expected != tuple(leaf.shape[1:]) or np.dtype(have[name].dtype) != np.dtype(leaf.dtype):
            raise CheckpointError(
                f"{where}: {name} is {source_shape} {np.dtype(have[name].dtype)} per seed in the source, "
                f"this run needs {tuple(leaf.shape[1:])} {np.dtype(leaf.dtype)}"
            )


def plan(run: RunConfig, target: Any, segments: Segments, make_env: Callable[..., Any]) -> Plan:
    """Check that `run.init_from` can start `run`, whose (abstract) initial state is `target` (seed axis
    first) and whose proprio segments are `segments`; reads only the source's config and array
    metadata. `make_env(name, render=False)` builds the source's env (for its segments).
    Raises CheckpointError with one line."""
    where = f"--init-from {run.init_from}"
    run_dir, step_text = parse_init_from(run.init_from)
    if not os.path.isdir(run_dir):
        raise CheckpointError(f"{where}: run directory {run_dir} does not exist")
    directory = os.path.join(run_dir, "checkpoints")
    try:
        step = checkpoint.resolve_step(directory, step_text)
        source = Config.from_dict(checkpoint.read_config(directory, step), f"checkpoint {step} in {directory}").run
        saved = checkpoint.read_metadata(directory, step, ("state",))["state"]
    except (CheckpointError, ConfigFormatError) as err:
        raise CheckpointError(f"{where}: {err}") from err
    seeds = int(target.env_steps.shape[0])
    if source.seeds < seeds:
        raise CheckpointError(
            f"--seeds {seeds}: the source {run_dir} has {source.seeds} seed(s); seed i starts from the source's "
            f"seed i, so the source needs at least {seeds}"
        )
    parts = parse_parts(run.init_parts)
    owners = ((target.params, f"this run's agent {run.agent}"), (saved["params"], f"the source ({source.agent})"))
    for name in parts:
        for networks, whose in owners:
            if name not in networks:
                raise CheckpointError(
                    f"--init-parts {run.init_parts}: {whose} has no {name}; it has {', '.join(sorted(networks))}"
                )
    # the source's leaves to read, and this run's leaves that receive them
    wanted = {"params": {name: saved["params"][name] for name in parts}}
    receiving = {"params": {name: target.params[name] for name in parts}}
    rows, kernel = None, f"params/{agents.get(run.agent).family.proprio_kernel}"
    mapped = row_mapped(kernel)
    if kernel in _leaves(receiving):
        try:
            source_segments = make_env(source.env, render=False).observation_spec.proprio_segments
        except ValueError as err:  # an env no longer registered
            raise CheckpointError(f"{where}: {err}") from err
        try:
            rows = row_map(source_segments, segments)
        except ValueError as err:
            raise CheckpointError(f"{where}: this run's env {run.env} does not fit {source.env}'s: {err}") from err
        saved_size, env_size = int(saved["proprio_norm"]["mean"].shape[-1]), sum(size for _, size in source_segments)
        if saved_size != env_size:
            raise CheckpointError(
                f"{where}: the source's proprio has {saved_size} features, env {source.env}'s segments now "
                f"{env_size}: the env changed since the source was trained"
            )
        if run.init_normaliser == "inherit":
            wanted["proprio_norm"], receiving["proprio_norm"] = saved["proprio_norm"], target.proprio_norm
    _compare(where, wanted, receiving, rows, mapped)
    return Plan(directory, step, parts, wanted, rows, seeds, mapped)


def apply(p: Plan, state: Any, restored: dict) -> Any:
    """`state` (a new run's initial TrainState) with the restored source leaves put in (pure)."""

    def select(path, x):
        x = jnp.asarray(x)[: p.seeds]
        return x[:, p.rows] if leaf_name(path) in p.mapped else x

    new = jax.tree_util.tree_map_with_path(select, restored)
    norms = {"proprio_norm": normalizer.from_saved(new["proprio_norm"])} if "proprio_norm" in new else {}
    return state.replace(
        params={**state.params, **new["params"]},
        # copies: the epoch donates its input, and one buffer cannot be donated twice
        target_params={**state.target_params, **jax.tree.map(jnp.copy, new["params"])},
        **norms,
    )


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def make_initializer(
    run: RunConfig, segments: Segments, make_env: Callable[..., Any], log: Callable[[str], None] = _log
) -> Callable[[Any], Any]:
    """`initialize(state) -> state` for `loop.train`: the transfer `run.init_from` asks for, into a new
    run's initial state (checked again on the real state, then restored). Raises CheckpointError."""

    def initialize(state):
        p = plan(run, state, segments, make_env)
        restored = checkpoint.restore_partial(p.directory, p.step, p.wanted)
        names = [*p.parts, *(k for k in p.wanted if k != "params")]
        log(f"transfer: restored {', '.join(names)} from checkpoint {p.step} in {p.directory} (seed i from seed i)")
        return apply(p, state, restored)

    return initialize


def check(config: Config, target: Any, segments: Segments, make_env: Callable[..., Any]) -> Plan:
    """The checks of `plan` for a run about to start (`preflight.prepare`), whose abstract initial state
    (`loop.Programs.abstract_state`) is `target`; compiles nothing. Raises ConfigError when the source is
    the run's own directory, else as `plan`."""
    run = config.run
    source_dir = parse_init_from(run.init_from)[0]
    if os.path.realpath(source_dir) == os.path.realpath(run.run_dir):
        raise ConfigError(f"--init-from {run.init_from}: is this run's own --run-dir; the source must be another run")
    return plan(run, target, segments, make_env)
