"""The outer training loop that every command line and experiment calls (DESIGN.md, `loop.py`).

    run, train_cfg, net = prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make)
    row = train(envs_mjx.make(run.env, render=...), run, train_cfg, net)

`prepare` checks everything before anything is compiled or written: the configs
(`validate.check`), the run directory (a new run never mixes into an existing one;
`overwrite` deletes only what a run writes), a resumed run's checkpoint config, what the
env must offer, whether the training state fits in the device's memory and one checkpoint of
it on the disk; then it locks the run directory (`rundir.hold`, process 0), which `train`
releases when it ends: a second run, resumed run or experiment on it is refused. `train` runs
the jitted epoch in Python: metrics (metrics.csv and TensorBoard), Orbax checkpoints (the
latest two and the best), SIGINT/SIGTERM (save after the epoch in flight), and the
divergence guard (a non-finite metric or parameter stops the run without saving it).
Errors are exceptions whose message is one line: `ConfigError` (`rundir.RunDirInUse` among
them), `CheckpointError` (bad input, nothing written), `Diverged`, `Interrupted` (a checkpoint
was saved), `rundir.DiskError` (no space for one checkpoint at start, or a write failed).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import checkpoint, config as config_lib, multihost, rundir, transfer, validate
from bidal_jax.checkpoint import CheckpointError
from bidal_jax.config import NetworkConfig, RunConfig, TrainConfig
from bidal_jax.validate import ConfigError, option

EXIT_ON_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}
# fields whose value on resume may differ from the checkpoint's
RESUME_MAY_CHANGE = ("epochs", "run_dir")
# what a run writes into its directory; overwrite deletes nothing else
RUN_FILES = frozenset(
    {"config.json", "metrics.csv", "metrics.csv.tmp", "config.json.tmp", "tb", "checkpoints", rundir.LOCK_FILE}
)
# share of the device's memory the training state may take (the rest: activations, copies)
MEMORY_SHARE = 0.9

Configs = tuple[RunConfig, TrainConfig, NetworkConfig]


class Diverged(Exception):
    """A non-finite metric or parameter; the message names the epoch, quantity and seed."""


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived; a checkpoint was saved after the epoch in flight."""

    def __init__(self, signum: int, epoch: int, directory: str):
        super().__init__(f"interrupted: saved checkpoint at epoch {epoch} in {directory}")
        self.exit_code = EXIT_ON_SIGNAL[signum]


# ----- preparing a run: every check, nothing written ------------------------------------


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
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
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


def resumed_configs(run_dir: str, given: dict[str, Any]) -> Configs:
    """The config of the run in `run_dir`: its latest checkpoint's, with `given["epochs"]` if
    given; any other given field that differs from the checkpoint's is refused. Reads only."""
    ckpt_dir = os.path.join(run_dir, "checkpoints")
    if not os.path.isdir(run_dir):
        raise CheckpointError(f"--resume: run directory {run_dir} does not exist")
    step = checkpoint.latest_step(ckpt_dir)
    if step is None:
        raise CheckpointError(f"--resume: no checkpoint in {ckpt_dir} (to start the run again, use --overwrite)")
    where = f"checkpoint {step} in {ckpt_dir}"
    try:
        run, train_cfg, net = config_lib.from_dict(checkpoint.read_config(ckpt_dir, step), where)
    except config_lib.ConfigFormatError as err:
        raise CheckpointError(str(err)) from err
    saved = config_lib.to_dict(run, train_cfg, net)  # with the defaults of fields newer than the checkpoint
    _check_config_json(run_dir, saved, where)
    for values in saved.values():
        for field, value in values.items():
            if field in given and field not in RESUME_MAY_CHANGE and given[field] != value:
                raise ConfigError(
                    f"{option(field)} {given[field]} differs from the checkpoint's {value}; "
                    "a resumed run keeps its config (only --epochs may change)"
                )
    run = dataclasses.replace(run, run_dir=run_dir, epochs=given.get("epochs", run.epochs))
    if run.epochs < step:
        raise ConfigError(f"--epochs {run.epochs}: must be at least the checkpoint's epoch {step}")
    return run, train_cfg, net


def check_run_dir(run_dir: str, overwrite: bool) -> None:
    """A new run never mixes into an existing one; overwrite only deletes what a run writes."""
    if os.path.exists(run_dir) and not os.path.isdir(run_dir):
        raise ConfigError(f"--run-dir {run_dir}: is a file, not a directory")
    entries = sorted(e for e in os.listdir(run_dir) if e != rundir.LOCK_FILE) if os.path.isdir(run_dir) else []
    if entries and not overwrite:
        raise ConfigError(
            f"--run-dir {run_dir}: exists and is not empty; use --resume to continue its run or --overwrite to delete it"
        )
    foreign = [e for e in entries if e not in RUN_FILES]
    if foreign:
        raise ConfigError(f"--overwrite: refusing to delete {run_dir}: it holds {foreign[0]!r}, which a run does not write")


def state_bytes(env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig) -> int:
    """Bytes of the seeds' whole training state (replay buffer included), from `jax.eval_shape`: nothing is allocated."""
    from bidal_jax.train import make_train

    init, _ = make_train(env, config_lib.agent_spec(run.agent), net, train_cfg)
    keys = jax.ShapeDtypeStruct((run.seeds, 2), jnp.uint32)
    return rundir.tree_bytes(jax.eval_shape(jax.vmap(init), keys))


def device_memory() -> int:
    """Bytes of memory of this process's first device: the accelerator's limit, or the host's RAM on a CPU."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"])
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(needed: int, available: int, seeds: int) -> None:
    """Refuse a training state whose share on one device (`needed` bytes) cannot fit in
    `MEMORY_SHARE` of that device's memory."""
    if needed > MEMORY_SHARE * available:
        gib = 2.0**30
        raise ConfigError(
            f"--seeds {seeds}: the training state needs {needed / gib:,.1f} GiB, more than {MEMORY_SHARE:.0%} of the "
            f"device's {available / gib:,.1f} GiB; use fewer seeds, envs or --buffer-episodes"
        )


def prepare(
    given: dict[str, Any],
    *,
    env_names: Iterable[str],
    make_env: Callable[..., Any],
    resume: bool = False,
    overwrite: bool = False,
) -> Configs:
    """The configs of the run that `given` (field -> value, e.g. a command line) asks for, after
    every check; compiles and writes nothing. Raises ConfigError or CheckpointError.

    With several processes, each checks (the same files: the same outcome) and they wait for
    each other at the end, so that no process writes before every one has checked."""
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite exclude each other: continue the run or delete it")
    if resume and not given.get("run_dir"):
        raise ConfigError("--resume needs --run-dir, the directory of the run to continue")
    env_names = tuple(env_names)
    if given.get("run_dir"):  # a directory in use is refused before any other check names it
        _main_decides(lambda: rundir.check_not_in_use(given["run_dir"]), f"run directory {given['run_dir']}")

    def check(configs: Configs) -> None:
        validate.check(*configs, env_names=env_names)

    configs = config_lib.resolve(given)
    check(configs)  # the values given
    if resume:
        configs = resumed_configs(given["run_dir"], given)
        check(configs)  # the checkpoint's
    else:
        run = configs[0]
        if not run.run_dir:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            run = dataclasses.replace(run, run_dir=os.path.join("runs", f"{run.env}-{run.agent}-{stamp}"))
        check_run_dir(run.run_dir, overwrite)
        configs = (run, *configs[1:])
    # what the env must offer and whether the state fits (builds the env and traces init, no compile)
    env = make_env(configs[0].env, render=False)
    validate.check_env_support(configs[1], env)
    from bidal_jax.train import device_layout

    whole = state_bytes(env, *configs)  # every seed's: what a checkpoint holds
    check_memory(whole // len(device_layout(configs[0].seeds, configs[1], configs[0].env_shards)[0]), device_memory(),
                 configs[0].seeds)
    rundir.check_space(configs[0].run_dir, whole)
    if configs[0].init_from and not resume:  # a resumed run continues its own checkpoint
        transfer.check(env, *configs, make_env=make_env)
    lock(configs[0].run_dir, resume, overwrite)
    multihost.barrier("bidal_jax.loop.prepare")
    return configs


def _main_decides(check: Callable[[], None], what: str) -> None:
    """Run `check` on process 0 only (the one that locks and writes); every process raises if it
    raised a ConfigError (process 0 that one, the others one naming `what`). Every process calls it."""
    refused = None
    if multihost.is_main():
        try:
            check()
        except ConfigError as err:
            refused = err
    if multihost.largest(int(refused is not None)):
        raise refused or ConfigError(f"{what}: refused by process 0 (see its error)")


def lock(run_dir: str, resume: bool, overwrite: bool) -> None:
    """Lock `run_dir` for this run (process 0; `rundir.hold`) and check a new run's directory again
    under the lock (a run that ended meanwhile may have filled it). Every process raises when
    process 0 is refused: RunDirInUse or ConfigError."""

    def take() -> None:
        rundir.hold(run_dir)
        try:
            if not resume:
                check_run_dir(run_dir, overwrite)
        except ConfigError:
            rundir.release(run_dir)
            raise

    _main_decides(take, f"run directory {run_dir}")


# ----- metrics --------------------------------------------------------------------------


def _write_atomic(path: str, text: str) -> None:
    with open(path + ".tmp", "w", newline="") as f:
        f.write(text)
    os.replace(path + ".tmp", path)


class MetricsLog:
    """metrics.csv (one row per epoch, seed means plus per-seed eval success) and TensorBoard.

    With `resume_epoch`, the rows after that epoch (written after the checkpoint, before
    the run stopped) are dropped from the CSV and purged from TensorBoard; new rows are appended.
    With `writes=False` (every process of a run over several but process 0) nothing is written;
    `last_row` is still the last row up to `resume_epoch`.
    """

    def __init__(self, run_dir: str, resume_epoch: int | None = None, writes: bool = True):
        self.path = os.path.join(run_dir, "metrics.csv")
        self.fields: list[str] | None = None
        self.last_row: dict[str, float] = {}
        self.writer = None
        if resume_epoch is not None and os.path.exists(self.path):
            self._truncate(resume_epoch, writes)
        if writes:
            from tensorboardX import SummaryWriter

            purge = None if resume_epoch is None else resume_epoch + 1
            self.writer = SummaryWriter(os.path.join(run_dir, "tb"), purge_step=purge)

    def _truncate(self, epoch: int, writes: bool) -> None:
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
        if not reader.fieldnames:
            return
        self.fields = list(reader.fieldnames)
        # a row cut short by a kill has missing (None) values
        kept = [r for r in rows if None not in r.values() and float(r["epoch"]) <= epoch]
        if writes and len(kept) < len(rows):
            with open(self.path + ".tmp", "w", newline="") as f:
                writer = csv.DictWriter(f, self.fields)
                writer.writeheader()
                writer.writerows(kept)
            os.replace(self.path + ".tmp", self.path)
        self.last_row = {k: float(v) for k, v in kept[-1].items()} if kept else {}

    def write(self, row: dict[str, float]) -> None:
        self.last_row = row
        if self.writer is None:
            return
        if self.fields is None:
            self.fields = list(row)
            with open(self.path, "w", newline="") as f:
                csv.DictWriter(f, self.fields).writeheader()
        # a run resumed from an older metrics.csv keeps its header: columns newer than it are left out
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.fields, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key != "epoch":
                self.writer.add_scalar(key, value, int(row["epoch"]))
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def epoch_row(epoch: int, metrics: dict, epoch_seconds: float, steps_before: float, wall: float,
              wall_with_compile: float) -> dict[str, float]:
    """One metrics.csv row: seed means of every metric, per-seed eval success, env steps, times: `wall_time`
    (`wall`: seconds of training, from when the programs were built) and `wall_time_with_compile` (seconds
    from when `train` began, building and compiling the programs included), both summed over resumed sessions."""
    row = {"epoch": epoch}
    for key, value in sorted(metrics.items()):
        row[key] = float(np.mean(value))
    for i, value in enumerate(np.atleast_1d(metrics["eval_success"])):
        row[f"eval_success_seed{i}"] = float(value)
    steps = float(np.sum(metrics["env_steps"]))
    row["env_steps_total"] = steps
    row["wall_time"] = wall
    row["wall_time_with_compile"] = wall_with_compile
    row["env_steps_per_second"] = (steps - steps_before) / max(epoch_seconds, 1e-9)
    return row


# ----- the divergence guard and signals ---------------------------------------------------


def guarded(state) -> dict:
    """The parts of a training state that the divergence guard checks, by name: {"params/actor": tree, ...};
    not the replay buffer, so that fetching them after every epoch is cheap."""
    return {
        **{f"params/{k}": v for k, v in state.params.items()},
        **{f"target_params/{k}": v for k, v in state.target_params.items()},
        **{f"opt_state/{k}": v for k, v in state.opt_state.items()},
        "proprio_norm": state.proprio_norm,
        "goal_norm": state.goal_norm,
    }


def finite_flags(groups: dict) -> dict:
    """Per seed, whether each group of `guarded` (host arrays with a leading seed axis) holds only
    finite values: {"params/actor": bool[S], ...}. Numpy on the host: no program to compile."""
    flags = {}
    for name, tree in groups.items():
        leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
        if leaves:
            flags[name] = np.stack([np.isfinite(x).reshape(x.shape[0], -1).all(axis=1) for x in leaves]).all(axis=0)
    return flags


def divergence(metrics: dict, flags: dict) -> str | None:
    """What is not finite ("critic_loss is nan (seed 1)"), or None."""
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


# ----- building and running ---------------------------------------------------------------


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class Programs(NamedTuple):
    """A run's jitted programs and where they run (`train.device_layout`)."""

    init: Callable
    epoch: Callable
    keys: jax.Array  # the seeds' keys
    sharding: Any  # where the training state lives (for jax.device_put)
    devices: list
    shards: int  # env shards per seed


def _programs(env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig) -> Programs:
    from bidal_jax.train import device_layout, make_seeded, make_train, seed_sharding

    devices, shards = device_layout(run.seeds, train_cfg, run.env_shards)
    init, epoch = make_seeded(*make_train(env, config_lib.agent_spec(run.agent), net, train_cfg, shards), devices, shards)
    keys = jax.random.split(jax.random.PRNGKey(run.seed), run.seeds)
    return Programs(init, epoch, keys, seed_sharding(devices, shards), devices, shards)


def restore_state(env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, step: int | None = None):
    """(whole training state, its epoch) of a checkpoint of `run.run_dir` (the latest by default),
    placed on this process's devices (whatever device count wrote it); compiles nothing."""
    return _restore(run, _programs(env, run, train_cfg, net), step)


def _restore(run: RunConfig, programs: Programs, step: int | None = None):
    abstract = jax.eval_shape(programs.init, programs.keys)
    state, _, step = checkpoint.restore(os.path.join(run.run_dir, "checkpoints"), abstract, step, programs.shards)
    return jax.device_put(state, programs.sharding), step


def build(
    env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, resume: bool, log: Callable = _log,
    initialize: Callable | None = None,
):
    """(compiled epoch, state to start from, its epoch, env shards): a new state, or the latest checkpoint's; writes nothing.

    `initialize(state) -> state` edits a new run's initial state (e.g. parameters restored
    from another run for transfer); a resumed run continues its checkpoint as it is.
    Compilation is reported through `log` (stderr by default): a line when it starts, one with its duration.
    """
    programs = _programs(env, run, train_cfg, net)
    start = time.time()
    shards = f", envs split {programs.shards} ways" if programs.shards > 1 else ""
    log(f"compiling the training program ({run.env}, {run.agent}, {run.seeds} seed(s) on "
        f"{len(programs.devices)} device(s){shards}) ...")
    if resume:
        state, step = _restore(run, programs)
    else:
        state, step = programs.init(programs.keys), 0
        if initialize is not None:  # its leaves may come from elsewhere: place them on the run's devices
            state = jax.device_put(initialize(state), programs.sharding)
    compiled = programs.epoch.lower(state).compile()
    log(f"compiled in {time.time() - start:.1f} s")
    return compiled, state, step, programs.shards


def train(
    env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, *, quiet: bool = False, resume: bool = False,
    initialize: Callable | None = None,
) -> dict[str, float]:
    """Run the training loop in `run.run_dir` (from its latest checkpoint with `resume`); returns
    the last epoch's metrics row (empty when the run is already at `run.epochs`). `initialize`
    edits a new run's initial state (see `build`).

    Holds the run directory's lock (`prepare` took it; taken here if not) until it returns or raises.
    Raises CheckpointError (before writing anything) when the checkpoint cannot be
    restored, Diverged on a non-finite metric or parameter, Interrupted after saving on
    SIGINT/SIGTERM, rundir.DiskError when a write fails for want of disk (the unfinished
    checkpoint is deleted: the last good one is what a resumed run continues).

    With several processes (`bidal_jax.multihost`), every process calls it: the seeds span every
    process's devices, the checkpoints are written by all, config.json, the metrics and the progress
    bar by process 0 only; a signal to any process stops all after the same epoch.
    """
    begun = time.time()  # the clock of wall_time_with_compile
    main = multihost.is_main()
    if main:
        rundir.hold(run.run_dir)
    try:
        return _train(env, run, train_cfg, net, quiet, resume, initialize, begun)
    finally:
        if main:
            rundir.release(run.run_dir)


def _last_good(saved: int | None, ckpt_dir: str) -> str:
    return f"the last good checkpoint is epoch {saved} in {ckpt_dir}" if saved else "no checkpoint was saved"


def _train(env, run: RunConfig, train_cfg: TrainConfig, net: NetworkConfig, quiet: bool, resume: bool,
           initialize: Callable | None, begun: float) -> dict[str, float]:
    """`train`'s loop, the lock held; `begun`: when `train` was called."""
    from tqdm import tqdm

    ckpt_dir = os.path.join(run.run_dir, "checkpoints")
    main = multihost.is_main()
    with StopSignals(ckpt_dir) as stop:
        epoch, state, start_epoch, shards = build(env, run, train_cfg, net, resume, initialize=initialize)
        cfg = config_lib.to_dict(run, train_cfg, net)
        saved = start_epoch if resume else None
        with rundir.disk_errors(f"writing the run's files in {run.run_dir}", _last_good(saved, ckpt_dir)):
            if main:
                os.makedirs(run.run_dir, exist_ok=True)
                _write_atomic(os.path.join(run.run_dir, "config.json"), json.dumps(cfg, indent=2))
            log = MetricsLog(run.run_dir, resume_epoch=start_epoch if resume else None, writes=main)
            mngr = checkpoint.manager(ckpt_dir)

        row = log.last_row
        wall_before = row.get("wall_time", 0.0)
        # (a run resumed from metrics written before this column: its time so far without compiling)
        compiled_before = row.get("wall_time_with_compile", wall_before)
        steps_before = float(np.sum(multihost.to_host(state.env_steps)))
        size = rundir.megabytes(rundir.with_margin(rundir.tree_bytes(state)))
        start = time.time()
        bar = tqdm(range(start_epoch + 1, run.epochs + 1), desc=f"{run.env}/{run.agent}", disable=quiet or not main,
                   unit="epoch", initial=start_epoch, total=run.epochs)
        try:
            for e in bar:
                t = time.time()
                state, metrics = epoch(state)
                metrics = multihost.to_host(metrics)
                now = time.time()
                row = epoch_row(e, metrics, now - t, steps_before, wall_before + now - start,
                                compiled_before + now - begun)
                steps_before = row["env_steps_total"]
                with rundir.disk_errors(f"writing the metrics of epoch {e} in {run.run_dir}",
                                        _last_good(saved, ckpt_dir)):
                    log.write(row)
                bad = divergence(metrics, finite_flags(multihost.to_host(guarded(state))))
                if bad:
                    raise Diverged(f"diverged at epoch {e}: {bad}; {_last_good(saved, ckpt_dir)}")
                bar.set_postfix(eval_success=f"{row['eval_success']:.2f}", train_success=f"{row['train_success']:.2f}")
                done = run.target_success > 0 and row["eval_success"] >= run.target_success
                # read once: a signal arriving after this waits for the next epoch; one process's stops all
                signum = multihost.largest(stop.signum or 0) or None
                if e % run.checkpoint_every == 0 or e == run.epochs or done or signum:
                    with rundir.disk_errors(f"saving checkpoint {e} in {ckpt_dir} (needs about {size})",
                                            _last_good(saved, ckpt_dir)):
                        checkpoint.save(mngr, e, state, cfg, row["eval_success"], shards)
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


def delete_run_dir(run_dir: str) -> None:
    """Delete what a run directory that `check_run_dir(run_dir, overwrite=True)` accepted holds, but
    its lock: process 0 deletes it, every process waits until it is gone."""
    if multihost.is_main() and os.path.isdir(run_dir):
        for name in set(os.listdir(run_dir)) - {rundir.LOCK_FILE}:
            path = os.path.join(run_dir, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
    multihost.barrier("bidal_jax.loop.delete_run_dir")


def enable_compilation_cache() -> None:
    """JAX's persistent compilation cache, so that a second run of a config skips compiling."""
    cache = os.environ.get("BIDAL_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "bidal_jax", "xla"))
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
