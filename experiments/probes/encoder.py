"""What a trained encoder's φ(s) holds: a linear probe of the frozen encoder for the hand's and the cube's positions.

The pixel agents' ladder (`experiments.paper.ladder`) asks what the visual agents fail to extract on NICOL. This
probe answers it for a trained encoder (paper Eq. 1, `networks.Encoder`), frozen: ridge regression from features of
a frame to the true `obj_pos` and `ee_pos` (the cube's centre and the hand's grasp point, metres), fitted on frames
of some scripted nicol_slide episodes and tested on the frames of others: R² and RMSE (cm) per axis.

- Frames (`slide_frames`): scripted grasp and push episodes with Gaussian action noise
  (`experiments.probes.phases.nicol_rollouts`), so that the hand and the cube spread over the table; every frame of
  every episode, its image and its true proprio. The last `HELD_OUT` share of the episodes is held out: frames of one
  episode are alike, so train and test never share an episode.
- Features (`features`), two sets per encoder: `phi`, φ(s) itself, what the actor, critic and BidAL's models read
  (from the image alone for the visual agents; from the image and the agent's proprio, normalised by its run's
  normaliser, for the multimodal ones); and `image`, the vision branch's output (its dense layer, before the fusion
  with proprio): what the image alone gives the encoder, separable in every agent.
- Ridge (`ridge_probe`): features standardised by the training frames; the penalty chosen from `ALPHAS` by the error
  on the last `HELD_OUT` share of the training episodes, then refitted on all of them (closed form). An axis along
  which the held-out target hardly varies (std below `MIN_SPREAD`: the height of a cube that slides) gets no R²,
  only its RMSE.
- Against the same architecture randomly initialised (`random_encoder`: the agent's own init, `Networks.init`, with
  fixed keys, and the trained run's normaliser): what the architecture and the frames give without learning.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import noise, normalizer
from bidal_jax.config import Config
from bidal_jax.networks import Encoder, VisionBranch
from bidal_jax.run.policy import load_policy
from experiments.probes import phases

TARGETS = ("obj_pos", "ee_pos")  # what the probe reads: proprio segments of 3 coordinates (m)
FEATURES = ("phi", "image")  # φ(s), and the vision branch's output
HELD_OUT = 0.2  # share of the episodes tested on (and of the training episodes the penalty is chosen on)
ALPHAS = tuple(10.0 ** k for k in range(-3, 5))  # ridge penalties tried, on standardised features
RANDOM_KEY = 1000  # the random encoders' keys: RANDOM_KEY + seed index
BATCH = 1024  # frames encoded at once
MIN_SPREAD = 0.005  # m: a held-out target axis with a smaller std gets no R² (`r2`)


class Frames(NamedTuple):
    """Frames of scripted episodes: images [N, 42, 42, 1] uint8, true proprio [N, D] of `spec`, episode index [N]."""

    image: np.ndarray
    proprio: np.ndarray
    episode: np.ndarray
    spec: object  # the frames' env's ObservationSpec


class Encoding(NamedTuple):
    """An agent's encoder for every seed: its config, parameters [S, ...] and proprio normaliser [S, ...]."""

    config: Config
    params: dict
    proprio_norm: normalizer.NormalizerState

    @property
    def seeds(self) -> int:
        return int(self.proprio_norm.count.shape[0])


def slide_frames(env, episodes: int, key: jax.Array) -> Frames:
    """Every frame of `episodes` scripted episodes of the NICOL env `env` (`phases.nicol_rollouts`, action noise
    `phases.SCRIPT_NOISE`), simulated `phases.FRAME_CHUNK` episodes at a time."""
    (image, proprio), _ = phases.chunked_rollouts(env, episodes, key, lambda s: (s.obs["image"], s.obs["proprio"]))
    return Frames(image, proprio, np.arange(len(image)) // env.episode_length, env.observation_spec)


def load_encoder(run_dir: str, checkpoint_step: int | str | None = None) -> Encoding:
    """The trained encoder of a run (its latest checkpoint, or step N, or "best"), every seed, with Orbax partial
    restore of what acting reads (`bidal_jax.run.policy.load_policy`). Raises `CheckpointError`; ValueError for an
    agent without an encoder."""
    trained = load_policy(run_dir, checkpoint_step)
    if "encoder" not in trained.params.params:
        raise ValueError(f"{run_dir}: {trained.config.run.agent} has no encoder to probe")
    return Encoding(trained.config, trained.params.params["encoder"], trained.params.proprio_norm)


def random_encoder(like: Encoding, env) -> Encoding:
    """`like`'s architecture randomly initialised: its agent's own init (`Networks.init`) with keys `RANDOM_KEY` +
    seed index, for the sizes of its env `env`; the same proprio normaliser."""
    spec = env.observation_spec
    networks = like.config.agent.networks(like.config.network, spec.proprio_size, spec.goal_size, env.action_size,
                                          spec.image_shape)
    keys = jnp.arange(like.seeds) + RANDOM_KEY
    params = jax.jit(jax.vmap(lambda k: networks.init(jax.random.PRNGKey(k))["encoder"]))(keys)
    return like._replace(params=params)


@functools.lru_cache(maxsize=None)
def _encode(config: Config):
    """The jitted features of one seed's encoder: (params, normaliser, images, proprio) -> {"phi", "image"}."""
    encoder = Encoder(config.network, config.agent.uses_proprio)

    @jax.jit
    def encode(params, norm, image, proprio):
        proprio = normalizer.normalize(norm, proprio, config.train.clip_obs)
        phi, found = encoder.apply(params, image, proprio, mutable=["intermediates"],
                                   capture_intermediates=lambda module, _: isinstance(module, VisionBranch))
        (branch,) = jax.tree.leaves(found["intermediates"])
        return {"phi": phi, "image": branch}

    return encode


def features(encoding: Encoding, frames: Frames, segments: tuple[str, ...]) -> dict[str, np.ndarray]:
    """{"phi": [S, N, latent], "image": [S, N, vision_features]}: each seed's features of every frame, its encoder
    reading the proprio `segments` (the agent's env's, in order) of the frames' true proprio."""
    rows = noise.feature_indices(frames.spec.proprio_segments, segments)
    encode = _encode(encoding.config)
    out = {name: [] for name in FEATURES}
    for seed in range(encoding.seeds):
        params, norm = jax.tree.map(lambda x: x[seed], (encoding.params, encoding.proprio_norm))
        parts = [encode(params, norm, frames.image[i:i + BATCH], frames.proprio[i:i + BATCH, rows])
                 for i in range(0, len(frames.image), BATCH)]
        for name in FEATURES:
            out[name].append(np.concatenate([np.asarray(p[name], np.float64) for p in parts]))
    return {name: np.stack(values) for name, values in out.items()}


def split(episode: np.ndarray, share: float = HELD_OUT) -> tuple[np.ndarray, np.ndarray]:
    """(first, last) masks of frames [N] by episode: the last `share` of the episodes (at least one) is `last`."""
    episodes = np.unique(episode)
    held = max(1, int(round(len(episodes) * share)))
    if held >= len(episodes):
        raise ValueError(f"{len(episodes)} episode(s): too few to hold out {share:.0%} and keep some to fit")
    last = np.isin(episode, episodes[-held:])
    return ~last, last


def ridge_fit(x: np.ndarray, y: np.ndarray, alpha: float):
    """The ridge regression of y [N, T] on x [N, F], standardised by x's mean and std: a function x -> ŷ."""
    mean, std = x.mean(0), x.std(0) + 1e-8
    z = (x - mean) / std
    offset = y.mean(0)
    weights = np.linalg.solve(z.T @ z + alpha * np.eye(z.shape[1]), z.T @ (y - offset))
    return lambda new: ((new - mean) / std) @ weights + offset


def r2(pred: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The coefficient of determination per column [T]: 1 − residual / total sum of squares about y's mean; NaN for
    a column whose std is below `MIN_SPREAD` (e.g. the height of a cube that stays on the table), where it says
    nothing."""
    total = ((y - y.mean(0)) ** 2).sum(0)
    return np.where(y.std(0) < MIN_SPREAD, np.nan, 1.0 - ((y - pred) ** 2).sum(0) / np.maximum(total, 1e-12))


def ridge_probe(x: np.ndarray, y: np.ndarray, episode: np.ndarray) -> dict[str, np.ndarray]:
    """The probe of targets y [N, T] from features x [N, F]: the penalty of `ALPHAS` whose fit on the first training
    episodes errs least on the last ones, refitted on all training episodes, scored on the held-out episodes
    (`split`): {"r2" [T], "rmse" [T] (y's unit), "alpha"}."""
    chex.assert_equal_shape_prefix([x, y], 1)
    train, test = split(episode)
    fit, check = split(episode[train])
    x_train, y_train = x[train], y[train]
    errors = [np.mean((ridge_fit(x_train[fit], y_train[fit], a)(x_train[check]) - y_train[check]) ** 2)
              for a in ALPHAS]
    alpha = ALPHAS[int(np.argmin(errors))]
    pred = ridge_fit(x_train, y_train, alpha)(x[test])
    return {"r2": r2(pred, y[test]), "rmse": np.sqrt(((pred - y[test]) ** 2).mean(0)), "alpha": alpha}


def probe(encoding: Encoding, frames: Frames, segments: tuple[str, ...]) -> dict:
    """Each seed's probe of every `TARGETS` segment from every `FEATURES` set of `encoding` on `frames` (its encoder
    reading the proprio `segments`): {feature set: {target: {"r2": [S][3], "rmse_cm": [S][3]}}}, JSON-ready (an R²
    that `r2` leaves undefined is None)."""
    found = features(encoding, frames, segments)
    out = {}
    for name, x in found.items():
        out[name] = {}
        for target in TARGETS:
            y = frames.proprio[:, frames.spec.segment_slice(target)].astype(np.float64)
            seeds = [ridge_probe(x_seed, y, frames.episode) for x_seed in x]
            out[name][target] = {"r2": [[None if np.isnan(v) else round(float(v), 4) for v in s["r2"]] for s in seeds],
                                 "rmse_cm": [(100 * s["rmse"]).round(3).tolist() for s in seeds]}
    return out
