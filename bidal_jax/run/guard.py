"""What stops a run: the divergence guard and the stop signals.

After every epoch the loop checks the metrics and the parameters (`guarded`, `finite_flags`,
`divergence`): a non-finite value stops the run with `Diverged`, without saving. SIGINT or
SIGTERM (`StopSignals`) lets the epoch in flight finish; the loop saves a checkpoint and
raises `Interrupted`, whose exit code is the signal's.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np

EXIT_ON_SIGNAL = {signal.SIGINT: 130, signal.SIGTERM: 143}


class Diverged(Exception):
    """A non-finite metric or parameter; the message names the epoch, quantity and seed."""


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived; a checkpoint was saved after the epoch in flight."""

    def __init__(self, signum: int, epoch: int, run_dir: str):
        super().__init__(f"interrupted: saved checkpoint at epoch {epoch} in {os.path.join(run_dir, 'checkpoints')}")
        self.exit_code = EXIT_ON_SIGNAL[signum]
        self.run_dir = run_dir


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
    """While active, a first SIGINT or SIGTERM only sets `signum`: the loop saves a checkpoint after the epoch
    in flight.

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
            print(
                f"\naborted: the latest complete checkpoint in {self.checkpoint_dir} is kept",
                file=sys.stderr,
                flush=True,
            )
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
