"""Learning speed of a preset and its variants on one GPU: wall-clock time (process start, compilation
included) and env steps to eval success thresholds, seeds vmapped in one program per variant.

    python -m experiments.bench.sweep --env nicol_slide --agent multimodal_bidal --seeds 5 --epochs 60 \
        --variant preset --variant updates_per_cycle=320 --variant updates_per_cycle=320,batch_size=4096 \
        --out sweep.jsonl

Each `--variant` is `preset` or comma-separated `TrainConfig` overrides of the env's preset for the agent,
`net.NAME=VALUE` `NetworkConfig` overrides (e.g. `net.hidden_size=256`) and `opt.NAME=VALUE` physics options
(e.g. `opt.iterations=10`, `envs_mjx.base.Env.set_options`); the variants run one after another in this process
(each builds, compiles and trains its own program). A JSON line per epoch: variant, the physics' fingerprint
(`Env.physics_id`) and engine, epoch, mean and per-seed eval success, env steps per seed, updates per seed, seconds
since the process started (`process_seconds`, imports and every earlier variant included) and since the variant started
(`variant_seconds`, its build and compilation included), and the epoch's mean extrinsic and intrinsic reward per
sampled transition; the report adds the area under the curve (mean success over the epochs run) and the mean
|r_i| / |r_e|, what the λ sweep (`--variant intrinsic_lambda=1`) reads. `--physics jax|warp|auto` picks the physics
engine (`RunConfig.physics`; by default the preset's, MuJoCo Warp for the NICOL tasks on one GPU with warp-lang), and
each row names the one it ran on (`engine`). `--minutes` stops a variant when its time is up, `--until S` once its
mean eval success has reached S (a time-to-success sweep needs no epochs past its last threshold).

`--ray` trains the variants at once instead, each a cell of a Ray task on its share of the machine's or cluster's
GPUs (`experiments/cluster.py`): a variant writes its rows into OUT.parts/<i>.jsonl, and once every variant has
ended they are appended to OUT in the variants' order; `process_seconds` then counts from the start of the
variant's worker process. A variant keeps no checkpoint: one whose worker dies is retried from its first epoch,
its rows rewritten.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time

PROCESS_START = time.perf_counter()

import jax  # noqa: E402 - imported after the process clock starts, so that process_seconds counts it
import numpy as np  # noqa: E402

from bidal_jax.config import PHYSICS, ConfigError  # noqa: E402
from experiments import cli, cluster  # noqa: E402
from experiments.bench.programs import parse_variant, program_config, seeded_program  # noqa: E402

THRESHOLDS = (0.5, 0.8, 0.9)
REWARDS = ("extrinsic_reward", "intrinsic_reward")


def reward_ratio(rows: list[dict]) -> float | None:
    """Mean |r_i| / |r_e| over the epochs of a variant (None without an intrinsic reward)."""
    if not rows or "intrinsic_reward" not in rows[0]:
        return None
    r_i = np.mean([abs(r["intrinsic_reward"]) for r in rows])
    r_e = np.mean([abs(r["extrinsic_reward"]) for r in rows])
    return float(r_i / max(r_e, 1e-9))


def train_variant(args, label: str, overrides: dict, network: dict, options: dict, sink) -> None:
    start = time.perf_counter()
    init, epoch, _, env, *_ = seeded_program(args.env, args.agent, args.seeds, backend=args.physics, train=overrides,
                                             network=network, options=options)
    state = init(jax.random.split(jax.random.PRNGKey(args.seed), args.seeds))
    for e in range(1, args.epochs + 1):
        state, metrics = epoch(state)
        success = np.asarray(metrics["eval_success"])
        now = time.perf_counter()
        row = {"variant": label, "overrides": overrides, "network": network, "options": options,
               "physics": env.physics_id, "engine": env.backend, "epoch": e,
               "eval_success": float(success.mean()),
               "eval_success_seeds": [round(float(s), 4) for s in success],
               "env_steps_per_seed": int(np.asarray(state.env_steps)[0]),
               "updates_per_seed": int(np.asarray(state.updates)[0]),
               # mean r_e and r_i per sampled transition (Eq. 4, 6), r_i absent without forward model
               **{k: float(np.mean(metrics[k])) for k in REWARDS if k in metrics},
               "process_seconds": now - PROCESS_START, "variant_seconds": now - start}
        sink.write(json.dumps(row) + "\n")
        sink.flush()
        print(f"{label} epoch {e}: {row['eval_success']:.3f} at {row['variant_seconds']:.0f} s", flush=True)
        if args.minutes and row["variant_seconds"] > 60 * args.minutes:
            break
        if args.until and row["eval_success"] >= args.until:
            break


def first_reach(rows: list[dict], threshold: float) -> dict | None:
    """The first epoch row whose mean eval success reaches `threshold`, or None."""
    return next((r for r in rows if r["eval_success"] >= threshold), None)


def report(paths: list[str]) -> str:
    """Markdown table: per variant, epochs run, final success, and time / env steps to each threshold."""
    by_variant: dict[str, list[dict]] = {}
    for path in paths:
        with open(path) as f:
            for line in f:
                row = json.loads(line)
                by_variant.setdefault(f"{path.split('/')[-1]}: {row['variant']}", []).append(row)
    head = ["variant", "epochs", "last-5 mean", "AUC", *(f"to {t}: s / env steps" for t in THRESHOLDS),
            "|r_i| / |r_e|", "s per epoch"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, rows in by_variant.items():
        cells = [label, str(rows[-1]["epoch"]), f"{np.mean([r['eval_success'] for r in rows[-5:]]):.3f}",
                 f"{np.mean([r['eval_success'] for r in rows]):.3f}"]
        for t in THRESHOLDS:
            hit = first_reach(rows, t)
            cells.append(f"{hit['variant_seconds']:.0f} / {hit['env_steps_per_seed']:,}" if hit else "—")
        ratio = reward_ratio(rows)
        cells.append("—" if ratio is None else f"{ratio:.3f}")
        pace = (rows[-1]["variant_seconds"] - rows[0]["variant_seconds"]) / max(len(rows) - 1, 1)
        cells.append(f"{pace:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def rows_written(path: str) -> int:
    """The rows (epochs) a variant has written into its part file so far; 0 before it has one."""
    try:
        with open(path) as f:
            return sum(1 for _ in f)
    except FileNotFoundError:
        return 0


def train_part(payload: tuple) -> tuple[int, None]:
    """A Ray task's variant (`cluster.run_cells`): `train_variant` into its part file, written afresh (a retried
    variant starts again: it has no checkpoint); exit code 0."""
    args, label, overrides, network, options, path = payload
    with open(path, "w") as sink:
        train_variant(args, label, overrides, network, options, sink)
    return 0, None


def train_on_ray(args, variants: list) -> int:
    """Every variant a cell of `cluster.run_cells`, each writing OUT.parts/<i>.jsonl; once all have ended, their
    rows are appended to OUT in the variants' order and the parts deleted; the grid's exit code."""
    parts = f"{args.out}.parts"
    os.makedirs(parts, exist_ok=True)
    paths = [os.path.join(parts, f"{i}.jsonl") for i in range(len(variants))]
    cells = [cluster.Cell(f"{i}: {label}", args.epochs, (args, label, *parsed, path),
                          lambda path=path: rows_written(path)) for i, ((label, parsed), path) in
             enumerate(zip(variants, paths))]
    code = cluster.run_cells(cells, train_part, args, args.out, lock=f"{args.out}{cluster.GRID_LOCK}")
    with open(args.out, "a") as sink:
        for path in paths:
            if os.path.exists(path):
                with open(path) as part:
                    sink.write(part.read())
    shutil.rmtree(parts)
    return code


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="nicol_slide")
    parser.add_argument("--agent", default="multimodal_bidal")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--epochs", type=int, default=50)
    parser.add_argument("--minutes", type=float, default=0.0, help="stop a variant after this many minutes (0: never)")
    parser.add_argument("--until", type=float, default=0.0,
                        help="stop a variant once its mean eval success reaches this (0: never)")
    parser.add_argument("--physics", default="preset", choices=["preset", *PHYSICS],
                        help="the physics engine (RunConfig.physics); preset: the preset's")
    parser.add_argument("--variant", action="append", default=None, help="preset, or k=v,net.k=v,opt.k=v overrides")
    parser.add_argument("--out", help="JSON-lines file, appended to")
    parser.add_argument("--report", nargs="+", help="print the table of these JSON-lines files and exit")
    cluster.add_options(parser)
    args = parser.parse_args(argv)
    if args.report:
        print(report(args.report))
        return 0
    if not 0.0 <= args.until <= 1.0:
        raise SystemExit(f"error: --until {args.until}: a success rate in [0, 1] is allowed (0: never stop early)")
    if not args.out:
        raise SystemExit("error: --out is required to train (or give --report FILES)")
    variants = [(text, parse_variant(text)) for text in (args.variant or ["preset"])]
    for text, (overrides, network, _) in variants:  # every variant's config, before the first one trains
        try:
            program_config(args.env, args.agent, overrides, network)
        except ConfigError as err:
            raise SystemExit(f"error: --variant {text}: {err}") from None
    if cluster.wanted(args):
        try:
            cluster.prepare_driver(args)
            return train_on_ray(args, variants)
        except ConfigError as err:
            return cli.exit_code(err)
    with open(args.out, "a") as sink:
        for label, (overrides, network, options) in variants:
            train_variant(args, label, overrides, network, options, sink)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
