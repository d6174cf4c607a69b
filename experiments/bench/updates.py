"""How fast the learner's gradient updates run alone, without physics: variants side by side.

    python -m experiments.bench.updates --env nicol_lift --agent multimodal_bidal --seeds 5 \\
        --variant preset net.conv_impl=patch net.conv_impl=banded [--updates 200] [--profile DIR]

Builds the preset's `init` and learner (`bidal_jax.train.make_learner`) as a run builds them, fills each seed's
replay buffer (zeros, but full, so that batches are drawn from all of it) and times `--updates` gradient updates
of all seeds at once: a jitted `lax.scan` of `update` under the seed `vmap`, as an epoch's cycle runs them. No
env step is traced, so a variant compiles in seconds where an image agent's epoch takes minutes. Each `--variant`
holds overrides of the preset as `experiments.bench.sweep` reads them (`k=v,net.k=v`). Per variant it prints the
compilation's seconds, XLA's cost estimate of one update (FLOPs and bytes accessed), the warm milliseconds per update
of all seeds (median of `--repeats` calls) and the speed-up over the first variant; `--profile DIR` also traces
one warm call per variant and prints the kernels (device events) per update, the kernels' time per part of the
update (each network's forward and backward pass, the optimiser, replay sampling: `tracing.component`) and the
largest kernels; `--json FILE` writes each variant's row there (its milliseconds per update and, with `--profile`,
each part's device milliseconds per update), which `experiments.bench.roofline` sets beside each part's floor.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

import envs_mjx
from bidal_jax.config import AGENTS, ConfigError
from bidal_jax.run import validate
from bidal_jax.train import Shards, make_learner, make_train
from experiments.bench.programs import full_buffer, parse_variant, program_config, timed
from experiments.bench.tracing import print_components, print_summary, traced


def update_program(name: str, agent: str, seeds: int, updates: int, variant: str):
    """(the seeds' compiled program `run(ts, keys) -> (ts, metrics)` of `updates` gradient updates each, its
    input state, its keys, the compile seconds) of `agent`'s preset on env `name` with `variant`'s overrides."""
    train, network, _ = parse_variant(variant)
    config = program_config(name, agent, train, network)
    env = envs_mjx.make(name, render=config.agent.uses_image)
    init, _ = make_train(env, config)
    update = make_learner(env, config, Shards(1)).update

    def run(ts, key):
        return jax.lax.scan(update, ts, jax.random.split(key, updates))

    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    ts = jax.jit(jax.vmap(lambda key: full_buffer(init(key))))(keys)
    start = time.perf_counter()
    compiled = jax.jit(jax.vmap(run), donate_argnums=0).lower(ts, keys).compile()
    return compiled, ts, keys, time.perf_counter() - start


def per_update_cost(compiled) -> tuple[float, float]:
    """XLA's estimate of (FLOPs, bytes accessed) of one update of all seeds (NaN where it gives none): XLA's cost
    analysis counts a loop's body once, so the program's figures are one update's. Its bytes count every operand
    each fused kernel reads, an upper bound of the memory traffic."""
    cost = compiled.cost_analysis()
    cost = (cost[0] if cost else {}) if isinstance(cost, list) else (cost or {})
    return cost.get("flops", float("nan")), cost.get("bytes accessed", float("nan"))


def measure(name: str, agent: str, seeds: int, updates: int, repeats: int, variant: str, profile: str,
            depth: int = 0) -> dict:
    """Compile and time one variant (`update_program`): a row of the table, with the profile's summary rows (its
    parts to the networks' submodules `depth` deep)."""
    compiled, ts, keys, compile_s = update_program(name, agent, seeds, updates, variant)
    flops, bytes_accessed = per_update_cost(compiled)
    holder = {"state": ts}  # each call donates the state it is given and returns the next

    def call():
        holder["state"], metrics = compiled(holder["state"], keys)
        return jax.block_until_ready(metrics)

    seconds = timed(call, repeats)["warm_seconds"]
    row = {"variant": variant, "compile_s": compile_s, "gflop": flops / 1e9, "gb": bytes_accessed / 1e9,
           "ms": 1e3 * seconds / updates, "trace": [], "parts": []}
    if profile:
        out = os.path.join(profile, variant.replace("/", "_").replace(",", "_"))
        _, row["trace"], row["parts"] = traced(call, out, hlo_text=compiled.as_text(), depth=depth)
    return row


def per_update(parts: list[dict], updates: int) -> list[dict]:
    """`by_component`'s rows of a traced call of `updates` updates, per update: milliseconds (as "seconds", the
    unit `print_components` is told) and events."""
    return [{**r, "seconds": 1e3 * r["seconds"] / updates, **{key: r[key] / updates for key in ("events", "inherited")}}
            for r in parts]


def kernels_per_update(trace: list[dict], updates: int) -> float | None:
    """Events of the busiest device stream of a traced call, per update (None without a device stream)."""
    streams = [r for r in trace if r["process"].startswith("/device:")]
    return max(r["events"] for r in streams) / updates if streams else None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench.updates", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="nicol_lift", choices=envs_mjx.names())
    parser.add_argument("--agent", default="multimodal_bidal", choices=list(AGENTS))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=200, help="gradient updates per timed call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per variant (after one warm-up)")
    parser.add_argument("--variant", nargs="+", default=["preset"],
                        help="k=v,net.k=v overrides of the preset, one per variant (as experiments.bench.sweep's)")
    parser.add_argument("--profile", default="", help="trace one warm call per variant into this folder")
    parser.add_argument("--json", default="", help="write each variant's row here: ms per update, and with "
                        "--profile each part's device ms per update")
    parser.add_argument("--depth", type=int, default=0, help="with --profile: the parts name the networks' "
                        "submodules this deep (2: the encoder's conv layers, Encoder/VisionBranch_0/PatchConv_1)")
    args = parser.parse_args(argv)
    bad = [f"--{field} {getattr(args, field)}: a positive integer is allowed" for field in ("updates", "repeats")
           if getattr(args, field) < 1]
    if args.depth < 0:
        bad.append(f"--depth {args.depth}: a number >= 0 is allowed")
    if bad:
        raise SystemExit(f"error: {bad[0]}")
    try:
        validate.check_field("seeds", args.seeds)
        rows = [measure(args.env, args.agent, args.seeds, args.updates, args.repeats, v, args.profile, args.depth)
                for v in args.variant]
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from err
    device = jax.devices()[0]
    print(f"{args.env} {args.agent}, {args.seeds} seed(s), {args.updates} updates a call, on {device.platform} "
          f"({device.device_kind}); ms: warm milliseconds per update of all seeds, median of {args.repeats}")
    print("\n| variant | compile (s) | GFLOP / update | GB accessed / update | ms / update | speed-up "
          "| kernels / update |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        kernels = kernels_per_update(row["trace"], args.updates)
        print(f"| {row['variant']} | {row['compile_s']:.1f} | {row['gflop']:.2f} | {row['gb']:.2f} | {row['ms']:.3f} "
              f"| {rows[0]['ms'] / row['ms']:.2f}× | {'–' if kernels is None else f'{kernels:.0f}'} |")
    for row in filter(lambda row: row["parts"], rows):
        print(f"\n## {row['variant']}")
        print_components(per_update(row["parts"], args.updates), row["ms"], "ms per update")
        print_summary([r for r in row["trace"] if r["process"].startswith("/device:")], 2)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump([{"env": args.env, "agent": args.agent, "seeds": args.seeds, "updates": args.updates,
                        "variant": row["variant"], "device_kind": device.device_kind, "ms": row["ms"],
                        "parts": [{"component": r["component"], "ms": r["seconds"], "events": r["events"]}
                                  for r in per_update(row["parts"], args.updates)]} for row in rows], f, indent=1)


if __name__ == "__main__":
    main()
