"""The training loop that every command line and experiment calls.

    with preflight.prepare(given, env_names=envs_mjx.names(), make_env=envs_mjx.make) as prepared:
        row = loop.train(prepared.env, prepared.config, prepared.programs)

`train` runs the jitted epoch of the programs it is given (`train.make_train`, laid out by `devices`, built once by
`make_programs`) in Python, calling after each epoch its callbacks, as Brax's `progress_fn`: the metrics writer
(`metrics_writer`: metrics.csv and TensorBoard, `metrics`), then the checkpoints (`Checkpoints`: Orbax, the latest
two and the best, `checkpoint`; each written while the next epochs train, but the run's last, which is on disk
before `train` returns or raises). Around them: SIGINT/SIGTERM (save after the epoch in flight) and the divergence
guard (a non-finite metric or parameter stops the run without saving it; `guard`), inside the run directory's lock
that `preflight.prepare` holds. A run resumed with `fresh_buffer` restores all but the replay buffer, which starts
empty; config.json's "fresh_buffer_epochs" records after which epochs.
Errors are exceptions whose message is one line: `CheckpointError` (bad input, nothing written),
`ConfigError` (an epoch program larger than the device's memory, `memory.check_program`: refused before it
trains), `Diverged`, `Interrupted` (a checkpoint was saved), `rundir.DiskError` (a write failed for want of disk),
`memory.OutOfMemory` (the device ran out of memory all the same while the program compiled or trained, or XLA's GPU
autotuner had no memory to try its kernels in, or a GPU that another process holds has too little free for the
compiled epoch; the last good checkpoint is kept).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import math
import os
import sys
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from bidal_jax.config import Config
from bidal_jax.run import checkpoint, exported, memory, multihost, rundir, runfiles
from bidal_jax.run.devices import device_layout, make_seeded, seed_sharding, use_physics, warp_problem
from bidal_jax.run.guard import Diverged, Interrupted, StopSignals, divergence, finite_flags, guarded
from bidal_jax.run.metrics import MetricsLog, epoch_row, write_atomic
from bidal_jax.train import make_train


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class Programs(NamedTuple):
    """A run's jitted programs and where they run (`devices.device_layout`); built once per run (`make_programs`)."""

    init: Callable
    epoch: Callable
    sharding: Any  # where the training state lives (for jax.device_put)
    devices: list
    shards: int  # env shards per seed
    seed: int  # the first seed's
    seeds: int

    def keys(self) -> jax.Array:
        """The seeds' keys."""
        return jax.random.split(jax.random.PRNGKey(self.seed), self.seeds)

    def abstract_state(self) -> Any:
        """The shapes and dtypes of the seeds' whole training state, from `jax.eval_shape` of `init`: nothing is
        allocated or compiled (the memory and disk checks, a transfer's plan, a restore)."""
        return jax.eval_shape(self.init, jax.ShapeDtypeStruct((self.seeds, 2), jnp.uint32))


def make_programs(env, config: Config) -> Programs:
    """The programs of the run `config` on `env`: laid out on devices (`devices.device_layout`), with `env` stepping
    on the physics engine the run asks for, sized for the worlds of one device (`devices.use_physics`: before
    anything is traced); traced and compiled only when called."""
    run = config.run
    devices, shards = device_layout(run.seeds, config.train, run.env_shards)
    use_physics(env, config, devices, shards)
    init, epoch = make_seeded(*make_train(env, config, shards), devices, shards)
    return Programs(init, epoch, seed_sharding(devices, shards), devices, shards, run.seed, run.seeds)


def restore_state(env, config: Config, step: int | None = None):
    """(whole training state, its epoch) of a checkpoint of `run.run_dir` (the latest by default),
    placed on this process's devices (whatever device count wrote it); compiles nothing."""
    return _restore(config.run.run_dir, make_programs(env, config), step)


def _restore(run_dir: str, programs: Programs, step: int | None = None, fresh_buffer: bool = False):
    """(state, epoch) of a checkpoint, placed like the program's; with `fresh_buffer`, the buffer is the empty one
    of the program's `init` (its seeds' and env shards' layout) and the checkpoint's is not read."""
    abstract = programs.abstract_state()
    empty = programs.init(programs.keys()).buffer if fresh_buffer else None
    state, _, step = checkpoint.restore(
        os.path.join(run_dir, "checkpoints"), abstract, step, programs.shards, buffer=empty
    )
    return jax.device_put(state, programs.sharding), step


def build(
    env, config: Config, programs: Programs, resume: bool, log: Callable = _log, initialize: Callable | None = None,
    fresh_buffer: bool = False,
):
    """(compiled epoch, state to start from, its epoch, env shards): a new state, or the latest checkpoint's
    (with `fresh_buffer`, all of it but the replay buffer, which starts empty); writes nothing.

    `initialize(state) -> state` edits a new run's initial state (e.g. parameters restored
    from another run for transfer); a resumed run continues its checkpoint as it is.
    Compilation is reported through `log` (stderr by default): a line when it starts, one with its duration.
    `programs`: the run's, built once (`preflight.prepare`, `make_programs`); nothing is built here.
    """
    run = config.run
    start = time.time()
    shards = f", envs split {programs.shards} ways" if programs.shards > 1 else ""
    train = config.train
    runs = train.batch_size // train.sample_run
    if run.env_shards > programs.shards and math.gcd(train.num_envs, train.eval_envs, runs) % run.env_shards:
        # fewer splits than asked because the sizes do not divide: say so, rather than leave devices idle unexplained
        shards += (f"{', not split' if programs.shards == 1 else ''} (--env-shards {run.env_shards}: a split divides "
                   f"--num-envs {train.num_envs}, --eval-envs {train.eval_envs} and the batch's {runs} runs)")
    engine = ", physics on MuJoCo Warp" if env.backend == "warp" else ""
    if env.backend == "jax" and run.physics == "auto" and programs.devices[0].platform == "gpu":
        engine = f", physics on MJX-JAX: MuJoCo Warp not used, {warp_problem(programs.devices)}"
    log(
        f"compiling the training program ({run.env}, {run.agent}, {run.seeds} seed(s) on "
        f"{len(programs.devices)} device(s){shards}{engine}) ..."
    )
    if resume:
        state, step = _restore(run.run_dir, programs, fresh_buffer=fresh_buffer)
        if fresh_buffer:
            log(f"resuming epoch {step} with an empty replay buffer (--fresh-buffer: the checkpoint's is not restored)")
        compiled = _compile(programs, config, env, state, log, resume=True)
    else:
        (state, compiled), step = _initial_state_and_epoch(programs, config, env, log), 0
        if initialize is not None:  # its leaves may come from elsewhere: place them on the run's devices
            state = jax.device_put(initialize(state), programs.sharding)
    log(f"compiled in {time.time() - start:.1f} s")
    return compiled, state, step, programs.shards


def _initial_state_and_epoch(programs: Programs, config: Config, env, log: Callable) -> tuple[Any, Callable]:
    """(a new run's initial state, the compiled epoch). The state's program (the seeds' keys and `init`) compiles
    and runs in a second thread while this one traces the epoch and XLA compiles it for the state's shapes and
    shardings (`abstract_state`), which is all compiling needs: a start waits for the longer of the two, not their
    sum, and the init is short beside the epoch's trace and compile;
    on accelerators that thread then compiles what the checkpoints run (`checkpoint.compile_for`), and MuJoCo
    Warp's kernels (`Env.compile_physics`), which would otherwise be built in the first epoch, after XLA's compile.
    The programs are the same, so is what they compute."""
    def initial_state():
        state = programs.init(programs.keys())
        checkpoint.compile_for(state)
        env.compile_physics()
        return state

    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        initial = pool.submit(initial_state)
        compiled = _compile(programs, config, env, programs.abstract_state(), log)
        return initial.result(), compiled


def _compile(programs: Programs, config: Config, env, state, log: Callable, resume: bool = False) -> Callable:
    """The compiled epoch for `state` (arrays, or their shapes, dtypes and shardings): through `exported` where it
    applies (one device, one env shard, one process, a persistent compilation cache; a line says when the traced
    program was loaded), else traced and compiled. ConfigError when it needs more of a device's memory than the
    device has (`memory.check_program`; a `resume`d run is told to resume on a larger device): refused before it
    trains."""
    where = exported.folder()
    compiled = None
    if where and len(programs.devices) == 1 and programs.shards == 1 and jax.process_count() == 1 \
            and env.backend == "jax":  # jax.export refuses MuJoCo Warp's custom calls
        key = exported.program_key(config, env.physics_id, programs.devices)
        try:
            compiled, loaded, stats = exported.compile_epoch(programs.epoch, state, where, key, log)
            if loaded:
                log(f"the traced epoch program loaded from {exported.path_of(where, key)}")
        except Exception as err:  # a program jax.export refuses: traced as before
            if memory.device_failure(err):  # out of memory, or no memory to autotune in: the same again if traced
                raise
            log(f"the epoch is traced in this process ({type(err).__name__}: {runfiles.first_line(err, 120)})")
    if compiled is None:
        compiled = programs.epoch.lower(state).compile()
        stats = memory.analysis(compiled)
    memory.check_program(stats, memory.device_memory(), resume)
    return compiled


def _recorded(run_dir: str, key: str, resume: bool) -> list:
    """The list `key` of a resumed run's config.json (empty for a new run, or a missing or damaged copy:
    what came before is unknown)."""
    if resume:
        try:
            return list(runfiles.read_json(os.path.join(run_dir, "config.json")).get(key, []))
        except (runfiles.RunFileError, TypeError):
            pass
    return []


def history_record(run_dir: str, key: str, value: str, resume: bool) -> list[str]:
    """config.json's list `key`, in order: a resumed run keeps its earlier values and adds `value` if it differs
    from the last. Keys: "physics", the fingerprints (`Env.physics_id`) of the physics the run has trained on (a
    run resumed after a model change records two); "physics_engine", the engines it stepped on (jax, warp);
    "hardware", the machines its processes ran on (`hardware`)."""
    earlier = _recorded(run_dir, key, resume)
    return earlier if earlier[-1:] == [value] else [*earlier, value]


def hardware() -> str:
    """The machine this process trains on, as config.json's "hardware" records it: "<devices> × <device kind>",
    e.g. "1 × cpu", or on GPUs their count and model as JAX names them (all processes' devices, with several
    hosts)."""
    return f"{jax.device_count()} × {jax.devices()[0].device_kind}"


def fresh_buffer_record(run_dir: str, epoch: int, resume: bool, fresh_buffer: bool) -> list[int]:
    """config.json's "fresh_buffer_epochs": the epochs after which a resume started with an empty replay
    buffer (`--fresh-buffer`), in order: a resumed run keeps its earlier ones and adds `epoch` with `fresh_buffer`."""
    earlier = _recorded(run_dir, "fresh_buffer_epochs", resume)
    return [*earlier, epoch] if fresh_buffer else earlier


def _last_good(saved: int | None, ckpt_dir: str) -> str:
    return f"the last good checkpoint is epoch {saved} in {ckpt_dir}" if saved else "no checkpoint was saved"


class Checkpoints:
    """The run's checkpoints, a callback of the loop: `checkpoints(e, state, row, last)` after epoch `e` saves one every
    `checkpoint_every` epochs, written while the next epochs train (`checkpoint.save_in_background`), and the run's
    `last` epoch on disk before the loop ends. `saved`: the epoch of the last checkpoint on disk, which the error lines
    name (`last_good`); `size`: what one needs on the disk, as the disk errors say it. `background` False saves each
    in place before the next epoch: MuJoCo Warp captures its solver's CUDA graphs on the stream the epoch runs on, and
    a save's transfers from another thread during that capture make it fail ("capturing stream has unjoined work")."""

    def __init__(self, ckpt_dir: str, cfg: dict, shards: int, every: int, saved: int | None, size: str,
                 background: bool = True):
        self.dir, self.cfg, self.shards, self.every, self.saved, self.size = ckpt_dir, cfg, shards, every, saved, size
        self.background = background
        self.pending: checkpoint.Pending | None = None  # the checkpoint being written while the next epochs train
        self.manager = checkpoint.manager(ckpt_dir)

    def last_good(self) -> str:
        return _last_good(self.saved, self.dir)

    def finish(self) -> None:
        """Wait for the checkpoint being written, if any: then it is the last on disk; its failure is raised as
        `rundir.disk_errors` words it."""
        if self.pending is None:
            return
        with rundir.disk_errors(f"saving checkpoint {self.pending.step} in {self.dir} (needs about {self.size})",
                                self.last_good()):
            self.pending.wait()
        self.saved, self.pending = self.pending.step, None

    def __call__(self, e: int, state: Any, row: dict[str, float], last: bool) -> None:
        if e % self.every and not last:
            return
        self.finish()
        with rundir.disk_errors(f"saving checkpoint {e} in {self.dir} (needs about {self.size})", self.last_good()):
            if last or not self.background:  # on disk before the run ends, or before its next epoch
                checkpoint.save(self.manager, e, state, self.cfg, row["eval_success"], self.shards)
                self.saved = e
            else:
                self.pending = checkpoint.save_in_background(self.manager, e, state, self.cfg, row["eval_success"],
                                                             self.shards)

    def abandon(self) -> None:
        """On an error that ends the loop: the checkpoint being written is finished first (then it is the last good
        one); its own errors never mask that one."""
        if self.pending is not None:
            with contextlib.suppress(Exception):
                self.pending.wait()
                self.saved = self.pending.step

    def close(self) -> None:
        self.manager.close()


def metrics_writer(log: MetricsLog, run_dir: str, checkpoints: Checkpoints) -> Callable[[int, dict], None]:
    """The loop's progress callback: `write(e, row)` adds epoch `e`'s row to metrics.csv and TensorBoard (`log`); a
    failed write is one `DiskError` line naming the last good checkpoint."""

    def write(e: int, row: dict[str, float]) -> None:
        with rundir.disk_errors(f"writing the metrics of epoch {e} in {run_dir}", checkpoints.last_good()):
            log.write(row)

    return write


def train(
    env, config: Config, programs: Programs, *, quiet: bool = False, resume: bool = False,
    initialize: Callable | None = None, fresh_buffer: bool = False,
) -> dict[str, float]:
    """Run the training loop in `run.run_dir` (from its latest checkpoint with `resume`; with
    `fresh_buffer` too, an empty replay buffer instead of the checkpoint's); returns
    the last epoch's metrics row (empty when the run is already at `run.epochs`). `initialize`
    edits a new run's initial state (see `build`); `programs` are the run's, built once (`preflight.prepare`):
    the loop trains what it is given.

    Runs inside the run directory's lock (`preflight.prepare`'s, which holds it until the run ends).
    Raises CheckpointError (before writing anything) when the checkpoint cannot be
    restored, Diverged on a non-finite metric or parameter, Interrupted after saving on
    SIGINT/SIGTERM, rundir.DiskError when a write fails for want of disk (the unfinished
    checkpoint is deleted: the last good one is what a resumed run continues).

    With several processes (`bidal_jax.run.multihost`), every process calls it: the seeds span every
    process's devices, the checkpoints are written by all, config.json, the metrics and the progress
    bar by process 0 only; a signal to any process stops all after the same epoch.
    """
    begun = time.time()  # the clock of wall_time_with_compile
    run = config.run
    ckpt_dir = os.path.join(run.run_dir, "checkpoints")
    main = multihost.is_main()
    with StopSignals(ckpt_dir) as stop:
        resumed = checkpoint.latest_step(ckpt_dir) if resume else None
        with memory.out_of_memory("compiling and starting the training program", lambda: _last_good(resumed, ckpt_dir)):
            epoch, state, start_epoch, shards = build(env, config, programs, resume, initialize=initialize,
                                                      fresh_buffer=fresh_buffer)
        cfg = {
            **config.to_dict(),
            "physics": history_record(run.run_dir, "physics", env.physics_id, resume),
            "physics_engine": history_record(run.run_dir, "physics_engine", env.backend, resume),
            "hardware": history_record(run.run_dir, "hardware", hardware(), resume),
            "fresh_buffer_epochs": fresh_buffer_record(run.run_dir, start_epoch, resume, fresh_buffer),
        }
        saved = start_epoch if resume else None
        size = rundir.megabytes(rundir.with_margin(memory.tree_bytes(state)))
        with rundir.disk_errors(f"writing the run's files in {run.run_dir}", _last_good(saved, ckpt_dir)):
            if main:
                os.makedirs(run.run_dir, exist_ok=True)
                write_atomic(os.path.join(run.run_dir, "config.json"), json.dumps(cfg, indent=2))
            log = MetricsLog(run.run_dir, resume_epoch=start_epoch if resume else None, writes=main)
            checkpoints = Checkpoints(ckpt_dir, cfg, shards, run.checkpoint_every, saved, size,
                                      background=env.backend != "warp")
        # the loop's callbacks after each epoch: the metrics writer with its row, then (unless the run diverged) the
        # checkpoints with its state
        progress = metrics_writer(log, run.run_dir, checkpoints)

        row = log.last_row
        wall_before = row.get("wall_time", 0.0)
        # (a run resumed from metrics written before this column: its time so far without compiling)
        compiled_before = row.get("wall_time_with_compile", wall_before)
        steps_before = float(np.sum(multihost.to_host(state.env_steps)))
        start = time.time()
        bar = tqdm(range(start_epoch + 1, run.epochs + 1), desc=f"{run.env}/{run.agent}", disable=quiet or not main,
                   unit="epoch", initial=start_epoch, total=run.epochs)
        e = start_epoch
        try:
            for e in bar:
                t = time.time()
                state, metrics = epoch(state)
                metrics = multihost.to_host(metrics)
                now = time.time()
                row = epoch_row(e, metrics, now - t, steps_before, wall_before + now - start,
                                compiled_before + now - begun)
                steps_before = row["env_steps_total"]
                progress(e, row)
                bad = divergence(metrics, finite_flags(multihost.to_host(guarded(state))))
                if bad:
                    checkpoints.finish()
                    raise Diverged(f"diverged at epoch {e}: {bad}; {checkpoints.last_good()}")
                bar.set_postfix(eval_success=f"{row['eval_success']:.2f}", train_success=f"{row['train_success']:.2f}")
                done = run.target_success > 0 and row["eval_success"] >= run.target_success
                # read once: a signal arriving after this waits for the next epoch; one process's stops all
                signum = multihost.largest(stop.signum or 0) or None
                checkpoints(e, state, row, last=bool(e == run.epochs or done or signum))
                if signum:
                    raise Interrupted(signum, e, run.run_dir)
                if done:
                    break
        except BaseException as err:
            checkpoints.abandon()
            runfiles.close_quietly(bar.close, log.close, checkpoints.close)
            if memory.device_failure(err):  # the device ran out of memory: one line, the last good checkpoint kept
                raise memory.ran_out(f"training epoch {e}", err, checkpoints.last_good()) from None
            raise
        with rundir.disk_errors(f"closing the run's files in {run.run_dir}", checkpoints.last_good()):
            bar.close()
            log.close()
            checkpoints.close()
    return row


def short_source_locations() -> None:
    """Programs lowered with one source location per operation (its own line) instead of JAX's default, the whole
    Python stack (`jax_include_full_tracebacks_in_locations`); a user's $JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS
    wins. Only the programs' metadata shrinks (what they compute is the same): the main command's compiled epoch
    is about a quarter less HLO text, which XLA:CPU compiles sooner. The ops' names
    shrink too, to the innermost `jit` and the op ("vmap(jit(step))/mul"), without the `jax.named_scope`s by which
    a profile attributes kernels (experiments/bench/tracing.py), so the profiling benches do not call it. Call it
    before anything is lowered."""
    if "JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS" not in os.environ:
        jax.config.update("jax_include_full_tracebacks_in_locations", False)
