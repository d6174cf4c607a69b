"""Train an agent on a task: `python -m experiments.run --env ur5_reach`.

Every field of the run, learner and network configs is an option (`--help` lists them
with their documentation). Per-epoch metrics go to `<run-dir>/metrics.csv` and
TensorBoard (`<run-dir>/tb`); Orbax checkpoints of the whole training state go to
`<run-dir>/checkpoints` every K epochs and at the end.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import sys
import time

from bidal_jax.config import NetworkConfig, RunConfig, TrainConfig, env_preset, fields_help

CONFIG_CLASSES = {"run": RunConfig, "train": TrainConfig, "network": NetworkConfig}


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.run",
        description="Train DDPG + HER (+ BidAL forward/inverse models) on an MJX task.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    for group_name, cls in CONFIG_CLASSES.items():
        group = parser.add_argument_group(f"{group_name} options")
        helps = fields_help(cls)
        for f in dataclasses.fields(cls):
            kind = type(f.default)
            if kind is bool:
                group.add_argument(_option(f.name), type=lambda s: s.lower() in ("1", "true", "yes"), help=helps[f.name])
            else:
                # defaults are resolved after parsing (env presets); None marks "not given"
                group.add_argument(_option(f.name), type=kind, default=None, help=f"{helps[f.name]} (default: {f.default})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def configs_from_args(args: argparse.Namespace) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """The three configs: defaults, then the env's preset, then what the command line gave."""
    given = {k: v for k, v in vars(args).items() if v is not None}
    run = RunConfig(**{f.name: given[f.name] for f in dataclasses.fields(RunConfig) if f.name in given})
    preset = env_preset(run.env, run.agent)
    train_kw = {**preset.get("train", {}), **{f.name: given[f.name] for f in dataclasses.fields(TrainConfig) if f.name in given}}
    net_kw = {**preset.get("network", {}), **{f.name: given[f.name] for f in dataclasses.fields(NetworkConfig) if f.name in given}}
    run_kw = {**preset.get("run", {}), **{f.name: given[f.name] for f in dataclasses.fields(RunConfig) if f.name in given}}
    return RunConfig(**run_kw), TrainConfig(**train_kw), NetworkConfig(**net_kw)


def config_dict(run: RunConfig, train: TrainConfig, net: NetworkConfig) -> dict:
    return {"run": dataclasses.asdict(run), "train": dataclasses.asdict(train), "network": dataclasses.asdict(net)}


class MetricsLog:
    """metrics.csv (one row per epoch, seed means plus per-seed eval success) and TensorBoard."""

    def __init__(self, run_dir: str):
        from tensorboardX import SummaryWriter

        self.path = os.path.join(run_dir, "metrics.csv")
        self.writer = SummaryWriter(os.path.join(run_dir, "tb"))
        self.fields: list[str] | None = None

    def write(self, row: dict[str, float]) -> None:
        if self.fields is None:
            self.fields = list(row)
            with open(self.path, "w", newline="") as f:
                csv.DictWriter(f, self.fields).writeheader()
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.fields).writerow(row)
        for key, value in row.items():
            if key != "epoch":
                self.writer.add_scalar(key, value, int(row["epoch"]))
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def epoch_row(epoch: int, metrics: dict, wall: float, epoch_seconds: float, steps_before: float) -> dict[str, float]:
    import numpy as np

    row = {"epoch": epoch}
    for key, value in sorted(metrics.items()):
        row[key] = float(np.mean(value))
    for i, value in enumerate(np.atleast_1d(metrics["eval_success"])):
        row[f"eval_success_seed{i}"] = float(value)
    steps = float(np.sum(metrics["env_steps"]))
    row["env_steps_total"] = steps
    row["wall_time"] = wall
    row["env_steps_per_second"] = (steps - steps_before) / max(epoch_seconds, 1e-9)
    return row


def train(run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, quiet: bool = False) -> dict[str, float]:
    """Run the training loop; returns the last epoch's metrics row."""
    import jax
    from tqdm import tqdm

    import envs_mjx
    from bidal_jax import checkpoint
    from bidal_jax.config import agent_spec
    from bidal_jax.train import make_seeded, make_train

    spec = agent_spec(run.agent)
    env = envs_mjx.make(run.env, render=spec.uses_image)
    init, epoch = make_seeded(*make_train(env, spec, net, train_cfg))
    os.makedirs(run.run_dir, exist_ok=True)
    cfg = config_dict(run, train_cfg, net)
    with open(os.path.join(run.run_dir, "config.json"), "w") as f:
        json.dump(cfg, f, indent=2)
    log = MetricsLog(run.run_dir)
    ckpt_dir = os.path.join(run.run_dir, "checkpoints")
    mngr = checkpoint.manager(ckpt_dir)

    start = time.time()
    state = init(jax.random.split(jax.random.PRNGKey(run.seed), run.seeds))
    row: dict[str, float] = {}
    steps_before = 0.0
    bar = tqdm(range(1, run.epochs + 1), desc=f"{run.env}/{run.agent}", disable=quiet, unit="epoch")
    for e in bar:
        t = time.time()
        state, metrics = epoch(state)
        metrics = jax.device_get(metrics)
        row = epoch_row(e, metrics, time.time() - start, time.time() - t, steps_before)
        steps_before = row["env_steps_total"]
        log.write(row)
        bar.set_postfix(eval_success=f"{row['eval_success']:.2f}", train_success=f"{row['train_success']:.2f}")
        done = run.target_success > 0 and row["eval_success"] >= run.target_success
        if e % run.checkpoint_every == 0 or e == run.epochs or done:
            checkpoint.save(mngr, e, state, cfg)
        if done:
            break
    bar.close()
    log.close()
    mngr.close()
    return row


def enable_compilation_cache() -> None:
    """JAX's persistent compilation cache, so that a second run of a config skips compiling."""
    import jax

    cache = os.environ.get("BIDAL_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "bidal_jax", "xla"))
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    enable_compilation_cache()
    run, train_cfg, net = configs_from_args(args)
    if not run.run_dir:
        run = dataclasses.replace(run, run_dir=os.path.join("runs", f"{run.env}-{run.agent}-{time.strftime('%Y%m%d-%H%M%S')}"))
    row = train(run, train_cfg, net, quiet=args.quiet)
    print(
        f"final eval success {row['eval_success']:.3f} (seeds: "
        + ", ".join(f"{row[k]:.3f}" for k in row if k.startswith("eval_success_seed"))
        + f") after {int(row['epoch'])} epochs, {row['env_steps_total']:.0f} env steps, {row['wall_time']:.0f} s\n"
        f"metrics: {os.path.join(run.run_dir, 'metrics.csv')}\n"
        f"tensorboard: tensorboard --logdir {os.path.join(run.run_dir, 'tb')}\n"
        f"checkpoint: {os.path.join(run.run_dir, 'checkpoints')}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
