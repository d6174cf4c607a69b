"""Can the vision branch see what the task needs? A supervised probe of the conv encoder.

The visual agents (`visual_baseline`, `visual_bidal`) observe only the 42×42 image and the goal:
to succeed they must read from the image where the achieved goal is (the hand's xy on
planar_reach, the three joint angles on ur5_reach, the cube on NICOL) to within the task's
success threshold ε. This probe trains the agents' vision branch (`networks.VisionBranch`, four
3×3 conv layers with ELU and a dense layer, paper Sec. III-B) with a linear head by regression
on the achieved goal, with labels, from frames of the env's start states, and reports on
held-out frames: the RMSE per goal dimension (beside that of a constant prediction, the training
mean), and the share of frames whose predicted achieved goal lies within ε of the true one
("located"). A branch that cannot locate the achieved goal with supervision cannot give
the actor and critic what success needs; one that can points at the learning signal instead.

    python -m experiments.probes.vision --envs planar_reach,ur5_reach --conv-strides 3,2,2,2 2,2,1,1

`--target SEGMENT` reads a proprio segment instead of the achieved goal, e.g. the hand's grasp point
`ee_pos` on NICOL, which an image-only agent must also see to push or grasp the cube; "located" then
uses the task's ε as well. Since the hand starts every episode at rest, `--random-steps K` takes each
frame after K uniformly random actions from a start state, so that the hand is spread over the
workspace:

    python -m experiments.probes.vision --envs nicol_slide --target ee_pos --random-steps 10

`--phase contact` (NICOL) takes the frames instead from scripted grasp and push episodes
(`experiments.probes.phases`) where the hand is at the cube, the frames a hidden cube would spoil:

    python -m experiments.probes.vision --envs nicol_slide --phase contact

Frames: `--frames` start states of `env.reset` (each task draws its start, e.g. the arm's joint
angles or the cube's place, uniformly over the task's range: many distinct states, where the
frames of an episode are alike), or the states `--random-steps` random actions later; a fifth
held out. Training: Adam, `--steps` updates of `--batch` frames, on targets standardised by the
training frames' mean and std; the learning rate `--lr` falls along a cosine to `--lr-final` times
itself by the last update (1: constant). Prints a markdown table (one row per env and strides; the
env column names the target and the random steps where they are not the defaults) and writes it to
`--out`. The table also gives the share located on as many training frames as are held out: near
the held-out share, the probe underfits (more updates or a larger branch help); far above it, it
overfits (more frames help). A full-size ur5_reach run for a GPU, e.g.:

    python -m experiments.probes.vision --envs ur5_reach --conv-strides 3,2,2,1 2,2,1,1 --frames 256000 \
        --steps 50000 --lr 3e-3 --lr-final 0.1

`--supersample N` renders the frames with N² rays per pixel instead of the env's own camera setting
(`Env.camera_supersample`), to measure what a finer anti-aliased frame would give the agents.
"""

from __future__ import annotations

import argparse
import sys
import time

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

import envs_mjx
from bidal_jax.config import ConfigError, NetworkConfig, parse_strides
from bidal_jax.networks import VisionBranch
from bidal_jax.run import validate
from envs_mjx.nicol import NicolEnv
from experiments import cli
from experiments.probes import phases

PROG = "python -m experiments.probes.vision"
HELD_OUT = 0.2  # share of the frames the probe is tested on
PHASE_FRAMES_PER_EPISODE = 8  # scripted episodes run per frame asked for in a phase (`--phase`): at least this many
ACHIEVED_GOAL = "achieved_goal"  # the default target; any other is a proprio segment's name


class Probe(nn.Module):
    """The agents' vision branch and a linear head: image [B, 42, 42, 1] -> target [B, G]."""

    goal_size: int
    strides: tuple[int, ...]
    channels: int = NetworkConfig.conv_channels
    features: int = NetworkConfig.vision_features

    @nn.compact
    def __call__(self, image: jax.Array) -> jax.Array:
        return nn.Dense(self.goal_size)(VisionBranch(self.channels, self.features, self.strides)(image))


def frames(env, key: jax.Array, n: int, random_steps: int = 0,
           target: str = ACHIEVED_GOAL) -> tuple[np.ndarray, np.ndarray]:
    """(images [n, 42, 42, 1], targets [n, G]) of `n` start states of `env.reset`, each after
    `random_steps` uniformly random actions; the target is the achieved goal or the proprio segment
    named `target`."""

    def observe(k):  # the start state of key k, as without random actions; the actions' key folded from it
        actions = jax.random.uniform(jax.random.fold_in(k, 1), (random_steps, env.action_size), minval=-1.0, maxval=1.0)
        state, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), env.reset(k), actions)
        return state.obs

    obs = jax.jit(lambda keys: jax.lax.map(observe, keys, batch_size=phases.FRAME_CHUNK))(jax.random.split(key, n))
    labels = obs[ACHIEVED_GOAL] if target == ACHIEVED_GOAL else obs["proprio"][
        :, env.observation_spec.segment_slice(target)]
    chex.assert_rank(labels, 2)
    return np.asarray(obs["image"]), np.asarray(labels)


def phase_frames(env, key: jax.Array, n: int, phase: str, target: str = ACHIEVED_GOAL) -> tuple[np.ndarray, np.ndarray]:
    """(images, targets) of at most `n` NICOL frames in `phase` of the scripted episodes
    (`experiments.probes.phases`: e.g. `contact`, the hand at the cube), in random order."""
    spec = env.observation_spec

    def record(state):
        proprio = state.obs["proprio"]
        label = state.obs[ACHIEVED_GOAL] if target == ACHIEVED_GOAL else proprio[spec.segment_slice(target)]
        return state.obs["image"], label

    key_episodes, key_order = jax.random.split(key)
    episodes = -(-n // PHASE_FRAMES_PER_EPISODE)
    (images, labels), phase_of = phases.chunked_rollouts(env, episodes, key_episodes, record)
    keep = np.flatnonzero(phase_of == phases.PHASES_NICOL.index(phase))
    order = keep[np.asarray(jax.random.permutation(key_order, len(keep)))[:n]]
    return images[order], labels[order]


def schedule(lr: float, steps: int, lr_final: float) -> optax.Schedule:
    """The learning rate of each update: `lr` falling along a cosine to `lr_final`·`lr` at update `steps`."""
    return optax.cosine_decay_schedule(lr, steps, alpha=lr_final)


def fit(model: Probe, key: jax.Array, images: np.ndarray, targets: np.ndarray, steps: int, batch: int, lr: float,
        lr_final: float = 1.0):
    """Parameters after `steps` Adam updates on the mean squared error, on random batches; the learning rate
    decays from `lr` to `lr_final`·`lr` (`schedule`)."""
    key_init, key_batches = jax.random.split(key)
    params = model.init(key_init, images[:1])
    opt = optax.adam(schedule(lr, steps, lr_final))

    # the frames are arguments of the compiled loop, not constants folded into it (hundreds of MB at full size)
    @jax.jit
    def train(p, keys, x, y):
        def loss(p, idx):
            return jnp.mean((model.apply(p, x[idx]) - y[idx]) ** 2)

        def update(carry, k):
            p, s = carry
            grads = jax.grad(loss)(p, jax.random.randint(k, (batch,), 0, len(images)))
            updates, s = opt.update(grads, s, p)
            return (optax.apply_updates(p, updates), s), None

        return jax.lax.scan(update, (p, opt.init(p)), keys)[0][0]

    return train(params, jax.random.split(key_batches, steps), jnp.asarray(images), jnp.asarray(targets))


def located(pred: np.ndarray, goals: np.ndarray, epsilon: float) -> float:
    """Share of frames whose predicted achieved goal is within ε of the true one (the success test)."""
    return float(np.mean(np.linalg.norm(pred - goals, axis=-1) < epsilon))


def probe(images: np.ndarray, goals: np.ndarray, epsilon: float, strides: tuple[int, ...], key: jax.Array,
          steps: int, batch: int, lr: float, lr_final: float = 1.0) -> dict:
    """The probe's figures on the held-out share of `frames`' (images, goals): RMSE per target
    dimension and share located within `epsilon`, of the probe and of the constant prediction; and the
    share located on as many training frames as are held out (overfitting shows as a gap)."""
    cut = int(round(len(images) * (1 - HELD_OUT)))
    (train_x, train_y), (test_x, test_y) = (images[:cut], goals[:cut]), (images[cut:], goals[cut:])
    mean, std = train_y.mean(0), train_y.std(0) + 1e-6
    model = Probe(goals.shape[-1], strides)
    params = fit(model, key, train_x, (train_y - mean) / std, steps, batch, lr, lr_final)
    apply = jax.jit(model.apply)

    def predict(x):
        return np.concatenate([np.asarray(apply(params, x[i:i + 1024])) for i in range(0, len(x), 1024)]) * std + mean

    pred = predict(test_x)
    return {
        "rmse": np.sqrt(np.mean((pred - test_y) ** 2, axis=0)),
        "constant_rmse": np.sqrt(np.mean((mean - test_y) ** 2, axis=0)),
        "located": located(pred, test_y, epsilon),
        "located_training": located(predict(train_x[:len(test_x)]), train_y[:len(test_x)], epsilon),
        "constant": located(np.broadcast_to(mean, test_y.shape), test_y, epsilon),
        "frames": (len(train_x), len(test_x)),
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument(
        "--envs", default="planar_reach,ur5_reach", help="comma list of envs (default planar_reach,ur5_reach)"
    )
    parser.add_argument(
        "--conv-strides",
        nargs="+",
        default=[NetworkConfig.conv_strides],
        help="one or more stride settings of the vision branch, e.g. 3,2,2,2 2,2,1,1",
    )
    parser.add_argument("--frames", type=int, default=16000, help="start-state frames per env, a fifth held out")
    parser.add_argument("--steps", type=int, default=3000, help="Adam updates of the probe")
    parser.add_argument("--batch", type=int, default=256, help="frames per update")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate at the first update")
    parser.add_argument(
        "--lr-final", type=float, default=1.0,
        help="the learning rate at the last update, as a share of --lr, reached along a cosine (default 1: constant)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed of the frames and the probe")
    parser.add_argument(
        "--target", default=ACHIEVED_GOAL,
        help="what the probe reads: achieved_goal (default) or a proprio segment of every env, e.g. ee_pos",
    )
    parser.add_argument(
        "--random-steps", type=int, default=0,
        help="uniformly random actions from each start state before its frame (default 0: start states)",
    )
    parser.add_argument(
        "--phase", default="", choices=("",) + phases.PHASES_NICOL,
        help="NICOL only: frames of this phase of scripted grasp and push episodes (experiments.probes.phases; "
             "e.g. contact: the hand at the cube) instead of start states",
    )
    parser.add_argument(
        "--supersample", type=int, default=0,
        help="rays per pixel along each axis of the rendered frames (default 0: the env's own, Env.camera_supersample)",
    )
    parser.add_argument("--out", default="", help="also write the table to this file")
    return parser


def checked(args: argparse.Namespace) -> tuple[list[str], list[tuple[int, ...]]]:
    """The envs and stride settings asked for; ConfigError naming a bad one."""
    envs = list(cli.parse_names(args.envs, "--envs", "env", envs_mjx.names()))
    for text in args.conv_strides:
        validate.check_field("conv_strides", text)
    strides = [parse_strides(text) for text in args.conv_strides]
    for flag, value, least in (("--frames", args.frames, 5), ("--steps", args.steps, 1), ("--batch", args.batch, 1),
                               ("--random-steps", args.random_steps, 0), ("--supersample", args.supersample, 0)):
        if value < least:
            raise ConfigError(f"{flag} {value}: must be an integer >= {least}")
    if not 0.0 <= args.lr_final <= 1.0:
        raise ConfigError(f"--lr-final {args.lr_final:g}: must be a share of --lr, between 0 and 1")
    return envs, strides


def with_supersample(env, supersample: int):
    """`env`, its camera casting `supersample`² rays per pixel where `supersample` is set (0: as built)."""
    if supersample:
        env.set_camera_supersample(supersample)
    return env


def check_target(target: str, envs: dict) -> None:
    """ConfigError unless `target` is the achieved goal or a proprio segment of every env in `envs`."""
    for name, env in envs.items():
        segments = env.observation_spec.segment_names
        if target != ACHIEVED_GOAL and target not in segments:
            raise ConfigError(
                f"--target {target}: not a proprio segment of {name}; allowed: {ACHIEVED_GOAL}, {', '.join(segments)}")


def label(name: str, target: str, random_steps: int, phase: str = "") -> str:
    """The table's env column: the env, and what the probe reads where it is not the default."""
    parts = ([] if target == ACHIEVED_GOAL else [target]) + (
        [f"after {random_steps} random actions"] if random_steps else []) + ([f"{phase} frames"] if phase else [])
    return f"{name}: {' '.join(parts)}" if parts else name


def row(name: str, env, strides: tuple[int, ...], result: dict) -> str:
    rmse = ", ".join(f"{x:.3f} ({c:.3f})" for x, c in zip(result["rmse"], result["constant_rmse"]))
    return (
        f"| {name} | {','.join(map(str, strides))} | {env.epsilon:g} | {rmse} | {result['located']:.3f} | "
        f"{result['located_training']:.3f} | {result['constant']:.3f} | "
        f"{result['frames'][0]:,} / {result['frames'][1]:,} |"
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        names, strides = checked(args)
        envs = {name: with_supersample(envs_mjx.make(name, render=True), args.supersample) for name in names}
        check_target(args.target, envs)
        if args.phase and not all(isinstance(env, NicolEnv) for env in envs.values()):
            raise ConfigError(f"--phase {args.phase}: NICOL envs only (nicol_slide, nicol_lift), not {args.envs}")
    except ConfigError as err:
        return cli.exit_code(err)
    lines = [
        f"| env | conv strides | ε | held-out RMSE per {'goal' if args.target == ACHIEVED_GOAL else args.target} "
        "dimension (constant prediction) | located (within ε) | located, training frames | "
        "constant prediction | "
        "frames train / held out |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    print("\n".join(lines), flush=True)
    key_frames, key_fit = jax.random.split(jax.random.PRNGKey(args.seed))
    for name, env in envs.items():
        start = time.time()
        if args.phase:
            images, goals = phase_frames(env, key_frames, args.frames, args.phase, args.target)
        else:
            images, goals = frames(env, key_frames, args.frames, args.random_steps, args.target)
        for s in strides:
            result = probe(images, goals, env.epsilon, s, key_fit, args.steps, args.batch, args.lr, args.lr_final)
            lines.append(row(label(name, args.target, args.random_steps, args.phase), env, s, result))
            print(f"{lines[-1]}  ({time.time() - start:.0f} s)", flush=True)
            start = time.time()
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
