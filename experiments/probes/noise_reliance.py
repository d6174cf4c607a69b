"""Which proprio features does a trained policy read? Observation noise on chosen segments at evaluation.

The robustness experiment (paper Sec. IV-B, Eq. 9, Table II) noises `ee_pos`, `ee_rot` and `obj_pos`.
On NICOL the proprio vector carries the hand and the cube a second time, clean: the joint angles `q`
fix the hand's pose and `obj_rel_pos` is the cube minus the hand. This probe evaluates a run's
deterministic policies with Eq. 9's noise on each `--groups` group of segments in turn, at each
`--kappas` κ: s + κ·N(0, σ) on the group's features. σ is each feature's interquartile range over the
policy's own clean episodes (the first `--episodes` of each seed, from its evaluation key), the same
for every group, so that the groups compare on one scale. The run's own σ (from its replay window) is
not used: it covers only the segments it trained with. A policy that holds when the paper's segments
are noised but fails once `q` and `obj_rel_pos` are noised as well reads the hand and the cube from
the clean copies.

    python -m experiments.probes.noise_reliance --run-dir results/noise/multimodal_bidal-kappa15 \\
        --kappas 0.15,1 --groups "ee_pos,ee_rot,obj_pos;obj_rel_pos,q;ee_pos,ee_rot,obj_pos,obj_rel_pos,q"

Prints the clean success and a markdown table (one row per group, one column per κ): the mean success
over seeds with its 95 % Student-t interval over seeds (clipped to [0, 1]); `--out` also writes it to a
file. Exit codes: 0 done; 2 bad input (one `error: ...` line).
"""

from __future__ import annotations

import argparse
import math
import sys

import chex
import jax
import numpy as np

import envs_mjx
from bidal_jax import acting, noise
from bidal_jax.run.checkpoint import CheckpointError
from bidal_jax.run.policy import TrainedPolicy, evaluate_seeds, load_noise, load_policy
from experiments import cli
from experiments.stats import mean_interval

PAPER_GROUP = "ee_pos,ee_rot,obj_pos"
DEFAULT_GROUPS = f"{PAPER_GROUP};obj_rel_pos,q;{PAPER_GROUP},obj_rel_pos,q"
cell = "{:.3f} ({:.3f}-{:.3f})".format


def parse_groups(text: str, proprio_segments: tuple[tuple[str, int], ...]) -> list[tuple[str, ...]]:
    """"a,b;c" -> [("a", "b"), ("c",)]; raises ValueError for an empty group or a segment the env lacks."""
    groups = [noise.parse_segments(part) for part in text.split(";")]
    if not groups or any(not group for group in groups):
        raise ValueError(f"--groups {text!r}: must be ';'-separated groups of ','-separated segments, none empty")
    for group in groups:
        noise.feature_indices(proprio_segments, group)  # names the unknown segment
    return groups


def parse_kappas(text: str) -> list[float]:
    """"0.15,1" -> [0.15, 1.0]; raises ValueError unless each is a finite number > 0."""
    try:
        kappas = [float(part) for part in text.split(",")]
    except ValueError:
        kappas = []
    if not kappas or any(not math.isfinite(k) or k <= 0 for k in kappas):
        raise ValueError(f"--kappas {text!r}: must be a comma list of finite numbers > 0, e.g. 0.15,1")
    return kappas


def clean_episodes(env, trained: TrainedPolicy, keys: jax.Array, episodes: int) -> tuple[np.ndarray, np.ndarray]:
    """(σ [S, D], success [S, episodes]) of `episodes` clean episodes of each seed's deterministic policy from
    its key: per proprio feature the interquartile range over every step (Eq. 9's σ, on the policy's own
    states), and each episode's success, the episodes `evaluate_seeds` runs without noise."""

    def one(params, key):
        policy = acting.make_policy(trained.networks, trained.config, params)
        final, proprio = acting.rollout(env, policy, key, episodes, record=lambda step: step.obs["proprio"])
        flat = proprio.reshape(-1, proprio.shape[-1])
        return noise.interquartile_range(flat, np.ones(flat.shape[0], bool)), final.metrics["success"]

    sigma, success = jax.jit(jax.vmap(one))(trained.params, keys)
    return np.asarray(sigma), np.asarray(success)


def noise_on(sigma: np.ndarray, proprio_segments: tuple[tuple[str, int], ...], group: tuple[str, ...],
             kappa: float) -> noise.NoiseState:
    """The noise state (κ [S], σ [S, F]) of `group`'s features, σ taken from `sigma` [S, D]."""
    chex.assert_rank(sigma, 2)
    indices = noise.feature_indices(proprio_segments, group)
    return noise.NoiseState(kappa=np.full(sigma.shape[0], kappa, np.float32), sigma=sigma[:, indices])


def sigma_ratio(sigma: np.ndarray, proprio_segments: tuple[tuple[str, int], ...], trained: TrainedPolicy,
                run_noise: noise.NoiseState | None) -> str:
    """A line comparing `sigma` [S, D] with the σ the run trained with (its replay window's, restored from the
    checkpoint) on the run's noise segments: the mean, min and max over seeds and features of their ratio."""
    if run_noise is None:
        return "(the run trained without observation noise: no σ of its own to compare)\n"
    segments = noise.parse_segments(trained.config.train.noise_segments)
    run_sigma = np.asarray(run_noise.sigma)
    ratio = sigma[:, noise.feature_indices(proprio_segments, segments)] / np.where(run_sigma > 0, run_sigma, np.nan)
    return (f"σ here / the run's σ on {', '.join(segments)}: mean {np.nanmean(ratio):.2f} "
            f"(min {np.nanmin(ratio):.2f}, max {np.nanmax(ratio):.2f})\n")


def table(rows: dict[str, list[tuple[float, float, float]]], kappas: list[float]) -> str:
    """Markdown: one row per group, one column per κ (each row's cells in `kappas`' order): "mean (low-high)"."""
    lines = ["| noised segments | " + " | ".join(f"κ {k:g}" for k in kappas) + " |",
             "| --- |" + " --- |" * len(kappas)]
    for group, by_kappa in rows.items():
        lines.append(f"| {group} | " + " | ".join(cell(*interval) for interval in by_kappa) + " |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m experiments.probes.noise_reliance",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--run-dir", required=True, help="the run's directory (with checkpoints/ and config.json)")
    parser.add_argument("--checkpoint", default=None, help="a checkpoint step, or 'best' (default: the latest)")
    parser.add_argument("--episodes", type=int, default=64, help="episodes per seed, for σ and each cell")
    parser.add_argument("--kappas", default="0.15,1", help="comma list of κ > 0")
    parser.add_argument("--groups", default=DEFAULT_GROUPS, help="';'-separated groups of ','-separated "
                        f"proprio segments, each noised on its own (default {DEFAULT_GROUPS!r})")
    parser.add_argument("--out", default="", help="also write the table to this file")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.episodes < 1:
            raise ValueError(f"--episodes {args.episodes}: must be a positive integer")
        kappas = parse_kappas(args.kappas)
        trained = load_policy(args.run_dir, args.checkpoint)
        env = envs_mjx.make(trained.config.run.env, render=trained.config.agent.uses_image)
        segments = env.observation_spec.proprio_segments
        groups = parse_groups(args.groups, segments)
        run_noise = load_noise(args.run_dir, trained)
    except (ValueError, CheckpointError) as err:
        return cli.exit_code(err)
    keys = trained.eval_key
    sigma, clean_success = clean_episodes(env, trained, keys, args.episodes)
    scale = sigma_ratio(sigma, segments, trained, run_noise)
    clean = mean_interval(clean_success)
    rows = {", ".join(group): [mean_interval(evaluate_seeds(env, trained, keys, args.episodes,
                                                            noise_on(sigma, segments, group, k), group))
                               for k in kappas]
            for group in groups}
    run = trained.config.run
    text = (f"{run.env} / {run.agent}, checkpoint {trained.step} of {args.run_dir}, {args.episodes} episodes per "
            f"seed, {trained.seeds} seed(s); σ from the policy's clean episodes; mean success (95 % t-interval "
            f"over seeds)\n{scale}\nclean: {cell(*clean)}\n\n{table(rows, kappas)}\n")
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
