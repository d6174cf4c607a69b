"""Configuration: frozen dataclasses, one per concern, with agent presets by name.

Every field carries its documentation in `metadata["help"]`, which is also what the
command line shows for it (`experiments/run.py --help`). Command lines only override
fields; nothing mutates a config after construction (use `dataclasses.replace`).
"""

from __future__ import annotations

import dataclasses
from typing import Any


def doc(default: Any, help: str) -> Any:  # noqa: A002 - "help" reads best at call sites
    """A dataclass field with a default and its documentation."""
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class AgentSpec:
    """What an agent observes and whether it learns the BidAL forward/inverse models."""

    uses_image: bool
    uses_proprio: bool
    bidal: bool


AGENTS: dict[str, AgentSpec] = {
    "proprio_baseline": AgentSpec(uses_image=False, uses_proprio=True, bidal=False),
    "visual_baseline": AgentSpec(uses_image=True, uses_proprio=False, bidal=False),
    "multimodal_baseline": AgentSpec(uses_image=True, uses_proprio=True, bidal=False),
    "visual_bidal": AgentSpec(uses_image=True, uses_proprio=False, bidal=True),
    "multimodal_bidal": AgentSpec(uses_image=True, uses_proprio=True, bidal=True),
}


def agent_spec(name: str) -> AgentSpec:
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(AGENTS)}")
    return AGENTS[name]


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Sizes of the networks (paper Sec. III-B and III-C)."""

    conv_channels: int = doc(16, "channels of each of the four conv layers of the vision branch")
    conv_strides: str = doc(
        "3,2,2,2",
        "strides of the vision branch's four 3×3 conv layers, comma-separated (the first unpadded, the others "
        "'same'-padded): 3,2,2,2 maps 42×42 to 14, 7, 4, 2; 2,2,1,1 to 20, 10, 10, 10",
    )
    vision_features: int = doc(64, "width of the dense layer that ends the vision branch")
    proprio_features: int = doc(64, "width of the proprio branch's dense layer")
    latent_size: int = doc(50, "size of the latent state φ(s) of the multimodal encoder")
    embed_size: int = doc(64, "width of the UVFA embeddings ψ(s) and η(g)")
    hidden_size: int = doc(128, "width of the actor's and critic's hidden layers")
    hidden_layers: int = doc(2, "number of hidden layers of the actor and the critic")
    model_hidden_size: int = doc(128, "hidden width of the forward model f and inverse model g")


def parse_strides(text: str) -> tuple[int, ...]:
    """`NetworkConfig.conv_strides` as integers: "3,2,2,2" -> (3, 2, 2, 2); ValueError if it is not
    four positive integers."""
    strides = tuple(int(part) for part in text.split(","))
    if len(strides) != 4 or min(strides) < 1:
        raise ValueError(f"{text!r}: not four positive integers")
    return strides


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The DDPG + HER learner and the BidAL models (paper Sec. III-C, Eqs. 4, 5, 8)."""

    num_envs: int = doc(16, "parallel environments in each rollout of a cycle")
    cycles_per_epoch: int = doc(10, "rollout/update cycles in one epoch")
    updates_per_cycle: int = doc(40, "gradient updates after each cycle's rollout")
    batch_size: int = doc(256, "transitions per gradient update")
    buffer_episodes: int = doc(4096, "replay capacity in episodes (a multiple of num_envs)")
    gamma: float = doc(0.98, "discount γ; the critic target is clipped to [r_min/(1-γ), 0] (losses.min_reward)")
    tau: float = doc(0.05, "Polyak rate of the target networks, applied after every gradient update")
    actor_lr: float = doc(1e-3, "Adam learning rate of the actor")
    critic_lr: float = doc(1e-3, "Adam learning rate of the critic, encoder, forward and inverse models")
    action_l2: float = doc(1.0, "weight of the actor's action L2 penalty")
    noise_eps: float = doc(0.2, "std of the Gaussian exploration noise on actions")
    random_eps: float = doc(0.3, "probability of a uniformly random exploration action")
    exploration_starts: float = doc(
        0.0,
        "fraction of training episodes begun by the env's exploration_reset (nicol_lift: the cube "
        "already held, as HER's pick-and-place); evaluation always begins from reset. The paper uses "
        "none (0, the default); 0.5 is the labelled 'held starts' variant of lifting",
    )
    obs_noise: float = doc(
        0.0,
        "κ of the observation noise s + κ·N(0, σ), σ the interquartile range of each feature over the clean "
        "history (paper Eq. 9); it is data in the training state, so one compiled program serves every κ",
    )
    noise_segments: str = doc(
        "",
        "comma-separated proprio segments that get observation noise (the paper's: ee_pos,ee_rot,obj_pos); "
        "empty: no noise code at all",
    )
    her_k: int = doc(4, "HER 'future' relabelling ratio k: a goal is relabelled with prob. 1 - 1/(1+k)")
    intrinsic_lambda: float = doc(0.1, "λ of the intrinsic reward r_i = -λ/2 ||f(φ(s),a) - φ(s')||² (Eq. 4)")
    forward_weight: float = doc(1.0, "weight of the forward-model loss (Eq. 3) in the representation loss")
    inverse_weight: float = doc(1.0, "weight of the inverse-model loss (Eq. 5) in the representation loss")
    clip_obs: float = doc(5.0, "normalised proprio and goals are clipped to ±clip_obs")
    eval_envs: int = doc(64, "deterministic evaluation episodes after each epoch")
    grad_clip: float = doc(10.0, "global gradient-norm clip of every optimiser")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """One run: which task, which agent, how long, where to write."""

    env: str = doc("planar_reach", "environment name")
    agent: str = doc("multimodal_bidal", "agent name")
    seeds: int = doc(1, "seeds trained together as one vmapped program")
    seed: int = doc(0, "first random seed; seeds use seed, seed+1, ...")
    epochs: int = doc(20, "training epochs")
    checkpoint_every: int = doc(5, "save a checkpoint every K epochs (and at the end)")
    env_shards: int = doc(
        1,
        "at most this many devices split each seed's envs (of the devices the seeds leave free; gradients "
        "averaged across them); 1: none. Tested on CPU devices; also runs on GPUs (README: Several devices)",
    )
    run_dir: str = doc("", "run directory; default runs/<env>-<agent>-<time>")
    target_success: float = doc(0.0, "stop early once the mean eval success reaches this (0: never)")
    init_from: str = doc(
        "",
        "RUN_DIR or RUN_DIR:CHECKPOINT (step or best) whose parameters start this run (transfer, paper Sec. IV-C; "
        "bidal_jax/transfer.py); empty: a fresh start. A resumed run continues its own checkpoint",
    )
    init_parts: str = doc(
        "encoder,forward,inverse",
        "comma-separated networks that --init-from restores, into the online and target networks (optimisers start "
        "fresh); the encoder brings its normalisers, its proprio rows matched by segment name",
    )


def fields_help(cls: type) -> dict[str, str]:
    """Field name -> documentation of a config dataclass."""
    return {f.name: f.metadata.get("help", "") for f in dataclasses.fields(cls)}


# Per-env overrides of the defaults above (then the command line overrides these).
# Keys: "run", "train", "network"; values: field -> value.
ENV_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "planar_reach": {"run": {"epochs": 40}},
    "ur5_reach": {"run": {"epochs": 15}},
    # the NICOL tasks are sized for one GPU (README, "Results"): many parallel envs, big batches
    **{
        name: {
            "run": {"epochs": 100},
            "train": {
                "num_envs": 512,
                "cycles_per_epoch": 5,
                "updates_per_cycle": 80,
                "batch_size": 2048,
                "buffer_episodes": 16384,
                "eval_envs": 128,
            },
        }
        for name in ("nicol_slide", "nicol_lift", "nicol_lift_reduced")
    },
}
# Per-agent overrides of the env presets, for agents that learn from images.
IMAGE_AGENT_PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "planar_reach": {"run": {"epochs": 20}},
}


def env_preset(env: str, agent: str) -> dict[str, dict[str, Any]]:
    """The overrides for `env` (and for an image `agent` on it): {"run"|"train"|"network": {...}}."""
    preset = {k: dict(v) for k, v in ENV_PRESETS.get(env, {}).items()}
    if agent in AGENTS and AGENTS[agent].uses_image:
        for group, values in IMAGE_AGENT_PRESETS.get(env, {}).items():
            preset.setdefault(group, {}).update(values)
    return preset


CONFIG_CLASSES: dict[str, type] = {"run": RunConfig, "train": TrainConfig, "network": NetworkConfig}


class ConfigFormatError(ValueError):
    """A stored config (config.json, a checkpoint's) that this version cannot read."""


def to_dict(run: RunConfig, train: TrainConfig, network: NetworkConfig) -> dict[str, dict[str, Any]]:
    """The three configs as JSON-ready {"run": {...}, "train": {...}, "network": {...}}."""
    return {name: dataclasses.asdict(cfg) for name, cfg in zip(CONFIG_CLASSES, (run, train, network))}


def from_dict(cfg: dict, where: str) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """The inverse of `to_dict`; fields newer than `cfg` take their defaults. Raises
    ConfigFormatError naming `where` for a dict that is not such a config."""
    try:
        return tuple(cls(**cfg[name]) for name, cls in CONFIG_CLASSES.items())  # type: ignore[return-value]
    except (KeyError, TypeError) as err:
        raise ConfigFormatError(f"{where} has a config this version cannot read ({err})") from err


def resolve(given: dict[str, Any]) -> tuple[RunConfig, TrainConfig, NetworkConfig]:
    """The configs of a new run: defaults, then the env's (and image agent's) preset, then
    `given` (field name -> value, e.g. from the command line; unknown names are ignored)."""
    run = RunConfig(**{f.name: given[f.name] for f in dataclasses.fields(RunConfig) if f.name in given})
    preset = env_preset(run.env, run.agent)
    return tuple(  # type: ignore[return-value]
        cls(**{**preset.get(name, {}), **{f.name: given[f.name] for f in dataclasses.fields(cls) if f.name in given}})
        for name, cls in CONFIG_CLASSES.items()
    )
