"""Train an agent on a task: `python -m experiments.run --env ur5_reach`.

Every field of the run, learner and network configs is an option (`--help` lists them
with their documentation). Per-epoch metrics go to `<run-dir>/metrics.csv` and
TensorBoard (`<run-dir>/tb`); Orbax checkpoints of the whole training state go to
`<run-dir>/checkpoints` every K epochs and at the end.

Runs survive interruption and refuse bad input:

- `--resume` continues the run in `--run-dir` from its latest checkpoint with the
  checkpoint's config; only `--epochs` (not below the checkpoint's epoch), `--run-dir`
  and `--quiet` may be given with other values. metrics.csv is cut back to the
  checkpoint's epoch and appended to; TensorBoard purges the later steps.
- Ctrl-C (SIGINT) or SIGTERM lets the epoch in flight finish, saves a checkpoint and
  exits; a second signal exits at once (the latest complete checkpoint stays loadable,
  as it does after SIGKILL).
- A non-empty run directory is only continued (`--resume`) or deleted first
  (`--overwrite`, only once every check passed, and only if it holds nothing but what
  a run writes).
- Configs and checkpoints are checked before anything is compiled or written.
- A non-finite metric or parameter stops the run without saving the bad state.

Exit codes: 0 done; 2 bad command line, config or checkpoint (one `error: ...` line on
stderr, nothing written); 3 diverged; 130 stopped by SIGINT, 143 by SIGTERM (a
checkpoint was saved).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import shutil
import signal
import sys
import threading
import time

from bidal_jax.checkpoint import CheckpointError
from bidal_jax.config import NetworkConfig, RunConfig, TrainConfig, env_preset, fields_help
from bidal_jax.validate import ConfigError, option

CONFIG_CLASSES = {"run": RunConfig, "train": TrainConfig, "network": NetworkConfig}
EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 3
EXIT_ON_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}
# options whose value on --resume may differ from the checkpoint's
RESUME_MAY_CHANGE = ("epochs", "run_dir")
# what a run writes into its directory; --overwrite deletes nothing else
RUN_FILES = frozenset({"config.json", "metrics.csv", "metrics.csv.tmp", "config.json.tmp", "tb", "checkpoints"})


class Diverged(Exception):
    """A non-finite metric or parameter; the message names the epoch, quantity and seed."""


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived; a checkpoint was saved after the epoch in flight."""

    def __init__(self, signum: int, epoch: int, directory: str):
        super().__init__(f"interrupted: saved checkpoint at epoch {epoch} in {directory}")
        self.exit_code = EXIT_ON_SIGNAL[signum]


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
                group.add_argument(option(f.name), type=lambda s: s.lower() in ("1", "true", "yes"), help=helps[f.name])
            else:
                # defaults are resolved after parsing (env presets); None marks "not given"
                group.add_argument(option(f.name), type=kind, default=None, help=f"{helps[f.name]} (default: {f.default})")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--resume", action="store_true",
        help="continue the run in --run-dir from its latest checkpoint, with its saved config (only --epochs may change)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="delete a non-empty --run-dir first (after every check passed)"
    )
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


def configs_from_dict(cfg: dict, where: str) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """The inverse of `config_dict`, for a config read from a checkpoint."""
    try:
        return tuple(cls(**cfg[name]) for name, cls in CONFIG_CLASSES.items())  # type: ignore[return-value]
    except (KeyError, TypeError) as err:
        raise CheckpointError(f"{where} has a config this version cannot read ({err})") from err


def _config_differences(saved: dict, other: dict) -> list[tuple[str, str, object, object]]:
    """(group, field, saved value, other value) for each field that differs, but for those that may change."""
    return [
        (group, field, value, other.get(group, {}).get(field))
        for group, values in saved.items()
        for field, value in values.items()
        if field not in RESUME_MAY_CHANGE and other.get(group, {}).get(field) != value
    ]


def _check_config_json(run_dir: str, saved: dict, where: str) -> None:
    """Refuse a checkpoint whose config differs from the run's config.json (one from another run)."""
    path = os.path.join(run_dir, "config.json")
    try:
        with open(path) as f:
            recorded = json.load(f)
    except (OSError, ValueError):
        return  # a missing or damaged copy is rewritten from the checkpoint's config
    differences = _config_differences(saved, recorded)
    if differences:
        group, field = differences[0][:2]
        what = {"env": "another env", "agent": "another agent"}.get(field) or (
            "another network shape" if group == "network" else f"another {group} config"
        )
        listed = ", ".join(f"{f} {s!r}" for _, f, s, _ in differences)
        recorded_values = ", ".join(f"{o!r}" for *_, o in differences)
        raise CheckpointError(
            f"{where} was written for {what}: it has {listed} where the run's config.json has {recorded_values}"
        )


def _refuse_changed_options(args: argparse.Namespace, saved: dict) -> None:
    given = {k: v for k, v in vars(args).items() if v is not None}
    for group, values in saved.items():
        for field, value in values.items():
            if field in given and field not in RESUME_MAY_CHANGE and given[field] != value:
                raise ConfigError(
                    f"{option(field)} {given[field]} differs from the checkpoint's {value}; "
                    "a resumed run keeps its config (only --epochs may change)"
                )


def resumed_configs(args: argparse.Namespace) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """The config of the run to resume: the latest checkpoint's, with the new --epochs; reads only."""
    from bidal_jax import checkpoint

    ckpt_dir = os.path.join(args.run_dir, "checkpoints")
    if not os.path.isdir(args.run_dir):
        raise CheckpointError(f"--resume: run directory {args.run_dir} does not exist")
    step = checkpoint.latest_step(ckpt_dir)
    if step is None:
        raise CheckpointError(f"--resume: no checkpoint in {ckpt_dir} (to start the run again, use --overwrite)")
    where = f"checkpoint {step} in {ckpt_dir}"
    saved = checkpoint.read_config(ckpt_dir, step)
    run, train_cfg, net = configs_from_dict(saved, where)
    saved = config_dict(run, train_cfg, net)  # with the defaults of fields newer than the checkpoint
    _check_config_json(args.run_dir, saved, where)
    _refuse_changed_options(args, saved)
    run = dataclasses.replace(run, run_dir=args.run_dir, epochs=run.epochs if args.epochs is None else args.epochs)
    if run.epochs < step:
        raise ConfigError(f"--epochs {run.epochs}: must be at least the checkpoint's epoch {step}")
    return run, train_cfg, net


def _check_run_dir(run_dir: str, overwrite: bool) -> None:
    """A new run never mixes into an existing one; --overwrite only deletes what a run writes."""
    if os.path.exists(run_dir) and not os.path.isdir(run_dir):
        raise ConfigError(f"--run-dir {run_dir}: is a file, not a directory")
    entries = sorted(os.listdir(run_dir)) if os.path.isdir(run_dir) else []
    if entries and not overwrite:
        raise ConfigError(
            f"--run-dir {run_dir}: exists and is not empty; use --resume to continue its run or --overwrite to delete it"
        )
    foreign = [e for e in entries if e not in RUN_FILES]
    if foreign:
        raise ConfigError(f"--overwrite: refusing to delete {run_dir}: it holds {foreign[0]!r}, which a run does not write")


def prepare(args: argparse.Namespace) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """Every check of the command line, configs and run directory; compiles and writes nothing."""
    import jax

    import envs_mjx
    from bidal_jax import validate

    if args.resume and args.overwrite:
        raise ConfigError("--resume and --overwrite exclude each other: continue the run or delete it")
    if args.resume and not args.run_dir:
        raise ConfigError("--resume needs --run-dir, the directory of the run to continue")

    def check(configs: tuple[RunConfig, TrainConfig, NetworkConfig]) -> None:
        validate.check(*configs, env_names=envs_mjx.names(), device_count=jax.device_count())

    configs = configs_from_args(args)
    check(configs)  # the values given on the command line
    if args.resume:
        configs = resumed_configs(args)
        check(configs)  # the checkpoint's
    else:
        run = configs[0]
        if not run.run_dir:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            run = dataclasses.replace(run, run_dir=os.path.join("runs", f"{run.env}-{run.agent}-{stamp}"))
        _check_run_dir(run.run_dir, args.overwrite)
        configs = (run, *configs[1:])
    # what the env must offer, checked once on the configs the run will use (builds the env, no compile)
    validate.check_env_support(configs[1], envs_mjx.make(configs[0].env, render=False))
    return configs


def _write_atomic(path: str, text: str) -> None:
    with open(path + ".tmp", "w", newline="") as f:
        f.write(text)
    os.replace(path + ".tmp", path)


class MetricsLog:
    """metrics.csv (one row per epoch, seed means plus per-seed eval success) and TensorBoard.

    With `resume_epoch`, the rows after that epoch (written after the checkpoint, before
    the run stopped) are dropped from the CSV and purged from TensorBoard; new rows are appended.
    """

    def __init__(self, run_dir: str, resume_epoch: int | None = None):
        from tensorboardX import SummaryWriter

        self.path = os.path.join(run_dir, "metrics.csv")
        self.fields: list[str] | None = None
        self.last_row: dict[str, float] = {}
        if resume_epoch is not None and os.path.exists(self.path):
            self._truncate(resume_epoch)
        purge = None if resume_epoch is None else resume_epoch + 1
        self.writer = SummaryWriter(os.path.join(run_dir, "tb"), purge_step=purge)

    def _truncate(self, epoch: int) -> None:
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
        if not reader.fieldnames:
            return
        self.fields = list(reader.fieldnames)
        # a row cut short by a kill has missing (None) values
        kept = [r for r in rows if None not in r.values() and float(r["epoch"]) <= epoch]
        if len(kept) < len(rows):
            with open(self.path + ".tmp", "w", newline="") as f:
                writer = csv.DictWriter(f, self.fields)
                writer.writeheader()
                writer.writerows(kept)
            os.replace(self.path + ".tmp", self.path)
        self.last_row = {k: float(v) for k, v in kept[-1].items()} if kept else {}

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
        self.last_row = row

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


def finite_flags(state) -> dict:
    """Per seed, whether each parameter group holds only finite values: {"params/actor": bool[S], ...}.

    Cheap enough to run (jitted) after every epoch; the replay buffer is not scanned.
    """
    import jax
    import jax.numpy as jnp

    groups = {
        **{f"params/{k}": v for k, v in state.params.items()},
        **{f"target_params/{k}": v for k, v in state.target_params.items()},
        **{f"opt_state/{k}": v for k, v in state.opt_state.items()},
        "proprio_norm": state.proprio_norm,
        "goal_norm": state.goal_norm,
    }
    flags = {}
    for name, tree in groups.items():
        leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
        if leaves:
            flags[name] = jnp.stack([jnp.isfinite(x).reshape(x.shape[0], -1).all(axis=1) for x in leaves]).all(axis=0)
    return flags


def divergence(metrics: dict, flags: dict) -> str | None:
    """What is not finite ("critic_loss is nan (seed 1)"), or None."""
    import numpy as np

    for key in sorted(metrics):
        values = np.atleast_1d(np.asarray(metrics[key], dtype=np.float64))
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            return f"{key} is {values[bad[0]]} (seed {bad[0]})"
    for name, ok in flags.items():
        bad = np.flatnonzero(~np.asarray(ok))
        if bad.size:
            return f"parameters {name} are not finite (seed {bad[0]})"
    return None


class StopSignals:
    """While active, a first SIGINT or SIGTERM only sets `signum`: the loop saves a checkpoint after the epoch in flight.

    A second one exits at once with the signal's exit code (`os._exit`: as safe as SIGKILL,
    which leaves the latest complete checkpoint). Handlers can only be installed in the
    main thread; elsewhere this does nothing.
    """

    def __init__(self, checkpoint_dir: str):
        self.checkpoint_dir = checkpoint_dir
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum, frame) -> None:
        if self.signum is not None:
            sys.stdout.flush()
            print(f"\naborted: the latest complete checkpoint in {self.checkpoint_dir} is kept", file=sys.stderr, flush=True)
            os._exit(EXIT_ON_SIGNAL[signum])
        self.signum = signum
        print(
            f"\n{signal.Signals(signum).name}: saving a checkpoint after the epoch in flight (send it again to abort)",
            file=sys.stderr,
        )

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in EXIT_ON_SIGNAL}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)


def build(run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, resume: bool):
    """(jitted epoch, state to start from, its epoch): a new state, or the latest checkpoint's; writes nothing."""
    import jax

    import envs_mjx
    from bidal_jax import checkpoint
    from bidal_jax.config import agent_spec
    from bidal_jax.train import make_seeded, make_train

    spec = agent_spec(run.agent)
    env = envs_mjx.make(run.env, render=spec.uses_image)
    init, epoch = make_seeded(*make_train(env, spec, net, train_cfg))
    keys = jax.random.split(jax.random.PRNGKey(run.seed), run.seeds)
    if not resume:
        return epoch, init(keys), 0
    state, _, step = checkpoint.restore(os.path.join(run.run_dir, "checkpoints"), jax.eval_shape(init, keys))
    return epoch, state, step


def train(
    run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, quiet: bool = False, resume: bool = False
) -> dict[str, float]:
    """Run the training loop (from the latest checkpoint with `resume`); returns the last epoch's metrics row.

    Raises CheckpointError (before writing anything) when the checkpoint cannot be
    restored, Diverged on a non-finite metric or parameter, Interrupted after saving on
    SIGINT/SIGTERM.
    """
    import jax
    import numpy as np
    from tqdm import tqdm

    from bidal_jax import checkpoint

    ckpt_dir = os.path.join(run.run_dir, "checkpoints")
    with StopSignals(ckpt_dir) as stop:
        epoch, state, start_epoch = build(run, train_cfg, net, resume)
        os.makedirs(run.run_dir, exist_ok=True)
        cfg = config_dict(run, train_cfg, net)
        _write_atomic(os.path.join(run.run_dir, "config.json"), json.dumps(cfg, indent=2))
        log = MetricsLog(run.run_dir, resume_epoch=start_epoch if resume else None)
        mngr = checkpoint.manager(ckpt_dir)
        finite = jax.jit(finite_flags)

        row = log.last_row
        wall_before = row.get("wall_time", 0.0)
        steps_before = float(np.sum(jax.device_get(state.env_steps)))
        saved = start_epoch if resume else None
        start = time.time()
        bar = tqdm(range(start_epoch + 1, run.epochs + 1), desc=f"{run.env}/{run.agent}", disable=quiet, unit="epoch",
                   initial=start_epoch, total=run.epochs)
        try:
            for e in bar:
                t = time.time()
                state, metrics = epoch(state)
                metrics = jax.device_get(metrics)
                row = epoch_row(e, metrics, wall_before + time.time() - start, time.time() - t, steps_before)
                steps_before = row["env_steps_total"]
                log.write(row)
                bad = divergence(metrics, jax.device_get(finite(state)))
                if bad:
                    last = f"the last good checkpoint is epoch {saved} in {ckpt_dir}" if saved else "no checkpoint was saved"
                    raise Diverged(f"diverged at epoch {e}: {bad}; {last}")
                bar.set_postfix(eval_success=f"{row['eval_success']:.2f}", train_success=f"{row['train_success']:.2f}")
                done = run.target_success > 0 and row["eval_success"] >= run.target_success
                signum = stop.signum  # read once: a signal arriving after this waits for the next epoch
                if e % run.checkpoint_every == 0 or e == run.epochs or done or signum:
                    checkpoint.save(mngr, e, state, cfg)
                    saved = e
                if signum:
                    raise Interrupted(signum, e, ckpt_dir)
                if done:
                    break
        finally:
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


def print_summary(run: RunConfig, row: dict[str, float]) -> None:
    if not row:
        print(f"nothing to train: the run is at epoch {run.epochs} already (raise --epochs to continue)")
        return
    print(
        f"final eval success {row['eval_success']:.3f} (seeds: "
        + ", ".join(f"{row[k]:.3f}" for k in row if k.startswith("eval_success_seed"))
        + f") after {int(row['epoch'])} epochs, {row['env_steps_total']:.0f} env steps, {row['wall_time']:.0f} s\n"
        f"metrics: {os.path.join(run.run_dir, 'metrics.csv')}\n"
        f"tensorboard: tensorboard --logdir {os.path.join(run.run_dir, 'tb')}\n"
        f"checkpoint: {os.path.join(run.run_dir, 'checkpoints')}"
    )


def _error(message: object, code: int) -> int:
    print(f"error: {message}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        run, train_cfg, net = prepare(args)
    except (ConfigError, CheckpointError) as err:
        return _error(err, EXIT_BAD_INPUT)
    if args.overwrite and os.path.isdir(run.run_dir):
        shutil.rmtree(run.run_dir)
    enable_compilation_cache()
    try:
        row = train(run, train_cfg, net, quiet=args.quiet, resume=args.resume)
    except CheckpointError as err:
        return _error(err, EXIT_BAD_INPUT)
    except Diverged as err:
        return _error(err, EXIT_DIVERGED)
    except Interrupted as stop:
        print(f"{stop}; continue with --resume --run-dir {run.run_dir}", file=sys.stderr)
        return stop.exit_code
    print_summary(run, row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
