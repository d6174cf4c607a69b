"""Evaluate a trained run: `python -m experiments.evaluate --run-dir runs/ur5 [--checkpoint N|best]`.

Restores only what acting needs (`bidal_jax.run.policy.load_policy`: parameters and
normalisers; the replay buffer is never read), runs `--episodes` deterministic episodes
per seed and prints each seed's success with a 95 % Wilson interval, and the mean over
seeds with a 95 % Student-t interval over the seeds clipped to [0, 1] (Wilson's over the episodes when there
is one seed). By default the episodes are drawn from the checkpoint's own evaluation key, so with
`--episodes` equal to the run's `eval_envs` the printed success is the one the run logged
for that epoch; `--seed S` draws other episodes.

A run trained with observation noise (paper Sec. IV-B, Eq. 9: `noise_segments`, κ per seed) is
evaluated under it, as training's evaluation is: κ and σ are restored from the checkpoint
(`bidal_jax.run.policy.load_noise`) and each step's noise is drawn as in training, so the logged success is
reproduced too. `--clean` evaluates without noise; `--kappa K` under the run's σ scaled by K instead
of the run's κ (how far a policy trained at one noise level holds at others); the output says which. The
video's agent sees clean observations.

`--video out.mp4` also renders `--video-episodes` episodes of seed 0 with MuJoCo's own
renderer (offscreen, `--video-size` 320x240 by default) beside the agent's 42×42 view. MuJoCo's half is lit for
people (`lit`): a headlight and a light floor on a copy of the model that only the video draws, so that the
agent's camera (which reads geom colours, not lights) and the physics' fingerprint stay as they are; it also draws
the goal markers the agent's frames leave out (`envs_mjx.base.MARKER_GROUP`, NICOL's).

Exit codes: 0 done; 2 bad input: an option, a checkpoint, a --video or --json folder that does not exist or
cannot be written, or a machine where MuJoCo cannot render a --video (each refused before the evaluation runs); 4
writing --json or --video failed (no space, quota, read-only file system, permission denied); 130 stopped by Ctrl-C.
Each failure is one `error: ...` line on stderr.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys

import jax
import numpy as np

import envs_mjx
from bidal_jax import noise
from bidal_jax.config import ConfigError
from bidal_jax.run import rundir, runfiles
from bidal_jax.run.checkpoint import CheckpointError
from bidal_jax.run.policy import TrainedPolicy, evaluate_seeds, load_noise, load_policy
from envs_mjx.base import MARKER_GROUP
from experiments import cli
from experiments.stats import mean_interval, wilson_interval


def with_kappa(noise_state: noise.NoiseState | None, kappa: float) -> noise.NoiseState:
    """`noise_state` (κ [S], σ [S, F] of a run) with every seed's κ set to `kappa`, σ kept. Raises ValueError
    when `kappa` is negative or not finite, or the run has no noise state (no σ to scale)."""
    if not math.isfinite(kappa) or kappa < 0:
        raise ValueError(f"--kappa {kappa}: must be a finite number >= 0 (e.g. 0.3 for 30 % of σ)")
    if noise_state is None:
        raise ValueError("--kappa: the run trained without observation noise, so it has no σ to scale; "
                         "allowed only for a run trained with --noise-segments")
    return noise_state.replace(kappa=np.full_like(np.asarray(noise_state.kappa), kappa))


def _kappas(noise_state: noise.NoiseState) -> str:
    return ", ".join(f"{k:g}" for k in np.unique(np.asarray(noise_state.kappa)))


def noise_line(trained: TrainedPolicy, noise_state: noise.NoiseState | None, clean: bool,
               run_noise: noise.NoiseState | None = None) -> str:
    """What the evaluated agents observed: the run's noise (κ per seed, σ restored), clean observations, or
    (`run_noise`: the run's own noise state, given when --kappa replaced its κ) the run's σ with another κ."""
    if not noise.parse_segments(trained.config.train.noise_segments):
        return "observations: clean (the run trained without observation noise)"
    if clean:
        return f"observations: clean (--clean; the run trained with noise on {trained.config.train.noise_segments})"
    where = f"on {trained.config.train.noise_segments}, σ restored from checkpoint {trained.step} (paper Eq. 9)"
    if run_noise is not None:
        return (f"observations: noisy with κ {_kappas(noise_state)} (--kappa; the run trained with κ "
                f"{_kappas(run_noise)}) {where}")
    return f"observations: noisy as in training's evaluation, κ {_kappas(noise_state)} {where}"


# the video's lighting: a headlight of this ambient, diffuse and specular light, and the floor (planes darker than
# FLOOR_RGBA) drawn in this light gray; the tasks' own colours are dark so that the agent's camera sees contrast
HEADLIGHT = (0.4, 0.8, 0.1)
FLOOR_RGBA = (0.4, 0.4, 0.44, 1.0)


def lit(model):
    """A copy of the MuJoCo `model` lit for a person's eyes, as the Playground's and dm_control's renders are:
    a headlight (`HEADLIGHT`) and a light floor (`FLOOR_RGBA`); only what is drawn differs."""
    import mujoco

    model = copy.copy(model)
    headlight = model.vis.headlight
    headlight.active = 1
    headlight.ambient[:], headlight.diffuse[:], headlight.specular[:] = HEADLIGHT
    for geom in np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE):
        rgba = model.mat_rgba[model.geom_matid[geom]] if model.geom_matid[geom] >= 0 else model.geom_rgba[geom]
        if rgba[:3].mean() < np.mean(FLOOR_RGBA[:3]):
            model.geom_matid[geom], model.geom_rgba[geom] = -1, FLOOR_RGBA
    return model


def open_renderer(model, size: tuple[int, int], path: str):
    """MuJoCo's offscreen renderer of `model` (`lit`) at `size` (width, height), made before the evaluation so
    that a machine without an OpenGL platform is refused first: ConfigError naming the cause (MuJoCo raises
    `mujoco.FatalError`, or its GL bindings another error, as the platform goes)."""
    import mujoco

    try:
        return mujoco.Renderer(lit(model), size[1], size[0])
    except Exception as err:
        cause = str(err).strip() or repr(err)
        raise ConfigError(f"--video {path}: MuJoCo cannot render on this machine ({cause}); "
                          "set MUJOCO_GL to egl or osmesa where one is installed, or leave out --video") from None


def render_video(env, trained: TrainedPolicy, key: jax.Array, episodes: int, path: str, renderer,
                 quiet: bool = False) -> int:
    """Write `episodes` episodes of seed 0 to `path`: MuJoCo's render by `renderer` (`open_renderer`, closed
    here) beside the agent's 42×42 view scaled to the same height. Returns the number of frames written."""
    import imageio.v2 as imageio
    import mujoco
    from tqdm import tqdm

    height = renderer.height
    policy = trained.policy(0)
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    act = jax.jit(policy)
    model, data = env.mj_model, mujoco.MjData(env.mj_model)
    shown = mujoco.MjvOption()
    shown.geomgroup[MARKER_GROUP] = 1
    scale = max(1, height // env.observation_spec.image_shape[0])
    frames = 0

    def frame(state) -> np.ndarray:
        for name in ("qpos", "qvel", "mocap_pos", "mocap_quat"):
            getattr(data, name)[:] = np.asarray(getattr(state.data, name)[0])
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera=env.camera_name, scene_option=shown)
        view = np.asarray(state.obs["image"][0]).repeat(scale, 0).repeat(scale, 1)
        view = np.pad(np.repeat(view, 3, axis=2), ((0, height - view.shape[0]), (0, 0), (0, 0)))
        return np.concatenate([renderer.render(), view], axis=1)

    # imageio-ffmpeg starts ffmpeg with a `preexec_fn` (a process group of its own, away from Ctrl-C), which forks
    # this multithreaded process (JAX's threads: a deadlock risk, which JAX warns of); without one, subprocess starts
    # ffmpeg with no Python in the child (vfork and exec). ffmpeg then sees Ctrl-C too, and closes the file.
    os.environ["IMAGEIO_FFMPEG_NO_PREVENT_SIGINT"] = "1"
    try:
        with rundir.writing(path), imageio.get_writer(path, fps=round(1 / 0.04), macro_block_size=1) as writer:
            keys = jax.random.split(key, episodes)
            for i in tqdm(range(episodes), desc="video", unit="episode", disable=quiet):
                state = reset(keys[i][None])
                writer.append_data(frame(state))
                frames += 1
                for _ in range(env.episode_length):
                    state = step(state, act(state.obs, None))
                    writer.append_data(frame(state))
                    frames += 1
    finally:
        renderer.close()
    return frames


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m experiments.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run-dir", required=True, help="the run's directory (with checkpoints/ and config.json)")
    parser.add_argument("--checkpoint", default=None, help="a checkpoint step, or 'best' (default: the latest)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per seed")
    parser.add_argument(
        "--seed", type=int, default=None, help="draw episodes from this seed (default: the checkpoint's evaluation key)"
    )
    parser.add_argument("--video", default="", help="also write a video of seed 0's episodes to this .mp4")
    parser.add_argument("--video-episodes", type=int, default=2, help="episodes in the video")
    parser.add_argument("--video-size", default="320x240", help="MuJoCo render size WIDTHxHEIGHT (at least 320x240)")
    parser.add_argument(
        "--clean",
        action="store_true",
        help="evaluate without the run's observation noise "
        "(default: a run trained with noise is evaluated under it, as training's evaluation is)",
    )
    parser.add_argument(
        "--kappa",
        type=float,
        default=None,
        help="evaluate under the run's σ scaled by this noise coefficient (κ of Eq. 9, e.g. 0.3) instead of "
        "the run's κ; for a run trained with observation noise",
    )
    parser.add_argument("--json", default="", help="also write the results to this JSON file")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _video_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--video-size {text!r}: must be WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 320 or height < 240:
        raise ValueError(f"--video-size {text}: must be at least 320x240")
    return width, height


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.episodes < 1 or args.video_episodes < 1:
            raise ValueError(
                f"--episodes {args.episodes} / --video-episodes {args.video_episodes}: must be positive integers"
            )
        if args.clean and args.kappa is not None:
            raise ValueError("--clean and --kappa: give one (--clean is the same as --kappa 0)")
        if args.video and not args.video.endswith(".mp4"):
            raise ValueError(f"--video {args.video}: must name an .mp4 file")
        size = _video_size(args.video_size)
        for flag, path in (("--video", args.video), ("--json", args.json)):
            if path:  # refused before the evaluation, not after it
                runfiles.check_output_dir(os.path.dirname(path), flag)
        if not os.path.isdir(args.run_dir):
            raise ValueError(f"--run-dir {args.run_dir}: no such directory")
        trained = load_policy(args.run_dir, args.checkpoint)
        run_noise = None if args.clean else load_noise(args.run_dir, trained)
        noise_state = run_noise if args.kappa is None else with_kappa(run_noise, args.kappa)
    except (ValueError, CheckpointError) as err:
        return cli.exit_code(err)
    try:
        return _evaluate(args, trained, noise_state, run_noise, size)
    except (ConfigError, rundir.DiskError) as err:
        return cli.exit_code(err)


def _evaluate(args: argparse.Namespace, trained: TrainedPolicy, noise_state: noise.NoiseState | None,
              run_noise: noise.NoiseState | None, size: tuple[int, int]) -> int:
    """`main` once its options and the policy are checked: evaluate, print, write --json and --video (their
    failures one line: ConfigError, `rundir.DiskError`)."""
    run = trained.config.run
    env = envs_mjx.make(run.env, render=trained.config.agent.uses_image)
    renderer = open_renderer(env.mj_model, size, args.video) if args.video else None
    if args.seed is None:
        keys = trained.eval_key
    else:
        keys = jax.random.split(jax.random.PRNGKey(args.seed), trained.seeds)
    success = evaluate_seeds(env, trained, keys, args.episodes, noise_state)
    mean, low, high = mean_interval(success)
    observed = noise_line(trained, noise_state, args.clean, None if args.kappa is None else run_noise)
    print(f"{run.env} / {run.agent}, checkpoint {trained.step}, {args.episodes} episodes per seed")
    print(observed)
    for i, row in enumerate(success):
        lo, hi = wilson_interval(int(row.sum()), row.size)
        print(f"seed {i}: success {row.mean():.3f} (95 % interval {lo:.3f}-{hi:.3f})")
    print(f"mean success {mean:.3f} (95 % interval {low:.3f}-{high:.3f}) over {trained.seeds} seed(s)")
    if args.json:
        results = {"checkpoint": trained.step, "episodes": args.episodes, "per_seed": success.mean(axis=1).tolist(),
                   "mean": mean, "interval": [low, high], "observations": observed}
        with rundir.writing(args.json):
            runfiles.write_atomic(args.json, json.dumps(results, indent=2))
    if renderer is not None:
        key = jax.random.PRNGKey(0 if args.seed is None else args.seed)
        frames = render_video(env, trained, key, args.video_episodes, args.video, renderer, args.quiet)
        print(f"video: {args.video} ({frames} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
