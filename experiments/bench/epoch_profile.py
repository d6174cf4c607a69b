"""Where a training epoch's time goes: a JAX profiler trace of one warm epoch, summarised.

    python -m experiments.bench.epoch_profile --env nicol_slide --agent multimodal_bidal --seeds 1
    python -m experiments.bench.epoch_profile --env planar_reach --seeds 3 --out runs/profile/planar
    python -m experiments.bench.epoch_profile --env nicol_lift --agent multimodal_bidal --seeds 5 \
        --variant net.vision_dtype=bfloat16

Builds the preset's training program as `experiments.bench.throughput --devices 1` does (with a `--variant`'s
overrides, as `experiments.bench.sweep` reads them), runs two epochs (compilation, then a warm epoch, whose
untraced time it prints at once), then traces a third with `jax.profiler.trace` (the trace, with a Perfetto
JSON copy, stays in `--out` for TensorBoard or ui.perfetto.dev) and prints the device's time per part of the
epoch (physics, camera, the policy in rollouts, replay, each network's forward and backward pass in the
updates, the optimiser, evaluation: `tracing.component`), then, per device stream and host thread, the seconds
its events add up to, how many there are, and its largest operations.
On a GPU the event count of the compute stream is the number of kernels an epoch launches: when
it, rather than the work per kernel, sets the epoch's time, more seeds per device cost little and
more devices gain little (docs/performance.md, "Where the time goes").
"""

from __future__ import annotations

import argparse
import os
import time

import jax

import envs_mjx
from bidal_jax.config import AGENTS, PHYSICS, ConfigError
from bidal_jax.run import validate
from experiments.bench.programs import parse_variant, seeded_program
from experiments.bench.tracing import print_components, print_summary, traced


def profile_epoch(name: str, agent: str, seeds: int, out: str, top: int = 10,
                  variant: str = "preset", physics: str = "preset") -> tuple[float, list[dict], list[dict]]:
    """(the traced epoch's wall seconds, `summarise(..., top)` of its trace, `by_component` of it), written to
    `out`, of the preset with `variant`'s overrides (`programs.parse_variant`) on the physics engine `physics`
    (`seeded_program`'s backend); prints the compiling and the warm epoch's seconds."""
    train, network, options = parse_variant(variant)
    init, epoch, *_ = seeded_program(name, agent, seeds, backend=physics, train=train, network=network,
                                     options=options)
    state = init(jax.random.split(jax.random.PRNGKey(0), seeds))
    start = time.perf_counter()
    compiled = epoch.lower(state).compile()  # its HLO text names the kernels' parts
    for label in ("first epoch (compilation included)", "warm epoch, untraced"):
        state, metrics = compiled(state)
        jax.block_until_ready(metrics)
        print(f"{label}: {time.perf_counter() - start:.2f} s", flush=True)
        start = time.perf_counter()
    return traced(lambda: compiled(state)[1], out, top, compiled.as_text())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench.epoch_profile", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--env", default="planar_reach", choices=envs_mjx.names())
    parser.add_argument("--agent", default="proprio_baseline", choices=list(AGENTS))
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--top", type=int, default=10, help="largest operations shown per stream or thread")
    parser.add_argument("--streams", type=int, default=6, help="streams and threads shown, largest first")
    parser.add_argument("--variant", default="preset", help="k=v,net.k=v,opt.k=v overrides of the preset "
                        "(as experiments.bench.sweep's --variant)")
    parser.add_argument("--physics", default="preset", choices=["preset", *PHYSICS],
                        help="the physics engine (RunConfig.physics); preset: the preset's")
    parser.add_argument("--out", default="", help="trace folder (default: runs/profile/ENV-AGENT-SEEDS)")
    args = parser.parse_args(argv)
    out = args.out or os.path.join("runs", "profile", f"{args.env}-{args.agent}-{args.seeds}")
    try:
        validate.check_field("seeds", args.seeds)
        wall, rows, parts = profile_epoch(args.env, args.agent, args.seeds, out, args.top, args.variant, args.physics)
    except ConfigError as err:  # a bad seed count, variant or engine for these devices: one line
        raise SystemExit(f"error: {err}") from err
    device = jax.devices()[0]
    print(
        f"{args.env} {args.agent} ({args.variant}), {args.seeds} seed(s) on {device.platform} ({device.device_kind}): "
        f"traced epoch {wall:.2f} s (profiling slows it); trace in {out}"
    )
    print_components(parts, wall)
    print_summary(rows, args.streams)


if __name__ == "__main__":
    main()
