"""Configuration: frozen dataclasses, one per concern; `resolve` lays a task's preset and the options given over them.

Every field carries its documentation in `metadata["help"]`, which is also what the
command line shows for it (`python -m experiments.run --help`), and the rule of its valid
values in `metadata["rule"]`, beside it (`bidal_jax.run.validate` reads them). Command lines
only override fields; nothing mutates a config after construction (use `dataclasses.replace`).
A run's three configs travel together as one `Config`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from bidal_jax.agents import AGENTS, Agent, get  # noqa: F401 - AGENTS re-exported for the command lines
from bidal_jax.networks import CONVS, FUSED_IMPL, parse_strides


class ConfigError(ValueError):
    """A config value that a run cannot use; the message is one line."""


def option(field: str) -> str:
    """The command-line option of a config field: `num_envs` -> `--num-envs`."""
    return "--" + field.replace("_", "-")


@dataclasses.dataclass(frozen=True)
class Rule:
    """The valid values of a config field: its type, a predicate, and the words that say what is allowed."""

    kind: type
    allowed: Callable[[Any], bool]
    what: str


def text(what: str) -> Rule:
    """Any string (its meaning is checked elsewhere, e.g. an env name against the registry)."""
    return Rule(str, lambda v: True, what)


def one_of(values: tuple[str, ...]) -> Rule:
    """The rule of a field that takes one of `values`, each named in its message."""
    return Rule(str, lambda v: v in values, "one of " + ", ".join(values))


def _strides(v: str) -> bool:
    try:
        parse_strides(v)
    except ValueError:
        return False
    return True


def _name_list(v: str) -> bool:
    names = [name.strip() for name in v.split(",")]
    return all(name.isidentifier() for name in names) and len(set(names)) == len(names)


CONV_IMPLS = (*CONVS, FUSED_IMPL)  # NetworkConfig.conv_impl: "patch", "banded", "toeplitz", "pallas"
# conv implementations of earlier versions, each the same function of the same parameters as "patch" (`recorded`)
REMOVED_CONV_IMPLS = ("taps", "native", "stacked")
VISION_DTYPES = ("float32", "bfloat16")  # NetworkConfig.vision_dtype
INIT_NORMALISERS = ("fresh", "inherit")  # RunConfig.init_normaliser
NOISE_VARIANTS = ("derived", "literal", "noisy_goal")  # TrainConfig.noise_variant (bidal_jax/noise.py)
TARGET_ENCODERS = ("target", "online")  # TrainConfig.target_encoder (bidal_jax/losses.py)
PHYSICS = ("jax", "warp", "auto")  # RunConfig.physics (bidal_jax/run/devices.py, physics_engine)
POSITIVE_INT = Rule(int, lambda v: v >= 1, "a positive integer")
POSITIVE = Rule(float, lambda v: v > 0, "a positive number")
NON_NEGATIVE = Rule(float, lambda v: v >= 0, "a number >= 0")
PROBABILITY = Rule(float, lambda v: 0 <= v <= 1, "a probability in [0, 1]")


def doc(default: Any, help: str, rule: Rule) -> Any:  # noqa: A002 - "help" reads best at call sites
    """A dataclass field with a default, its documentation and the rule of its valid values."""
    return dataclasses.field(default=default, metadata={"help": help, "rule": rule})


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Sizes of the networks (paper Sec. III-B and III-C)."""

    conv_channels: int = doc(16, "channels of each of the four conv layers of the vision branch", POSITIVE_INT)
    conv_strides: str = doc(
        "3,2,2,1",
        "strides of the vision branch's four 3×3 conv layers, comma-separated (the first unpadded, the others "
        "'same'-padded): 3,2,2,1 maps 42×42 to 14, 7, 4, 4 (a 4×4 map: where things are survives; 3,2,2,2 "
        "ends at 2×2; docs/deviations.md); 2,2,1,1 to 20, 10, 10, 10",
        Rule(str, _strides, "four comma-separated positive integers, e.g. 3,2,2,1"),
    )
    conv_impl: str = doc(
        "patch",
        "how the vision branch's convs are computed, the same function and parameters either way (so runs of "
        "either compare and resume alike): 'patch' (strided slices and one matmul: the fast form on a CPU) or "
        "'banded' (input rows times band matrices of the kernel: the fast form on a GPU, the NICOL presets'; "
        "docs/performance.md, 'Image updates') or 'toeplitz' (banded, but a small layer, the last two of the default "
        "strides, as one matmul of the whole frame by the conv's full matrix: no windows gathered) or 'pallas' (the "
        "first three convs and ELUs in one fused kernel, activations kept on chip, the fourth as toeplitz: "
        "bidal_jax/encoder_kernel.py; a GPU compiles it, a CPU interprets it slowly; a first stride of 3 and 16 or "
        "more channels, a power of two)",
        one_of(CONV_IMPLS),
    )
    vision_dtype: str = doc(
        "float32",
        "the dtype the vision branch computes in: float32, or bfloat16 (mixed precision: its convs and dense "
        "layer in bfloat16, parameters, gradients, optimiser state and every other network in float32; about "
        "half the memory traffic of the image updates; docs/performance.md, 'Image updates')",
        one_of(VISION_DTYPES),
    )
    vision_features: int = doc(64, "width of the dense layer that ends the vision branch", POSITIVE_INT)
    proprio_features: int = doc(64, "width of the proprio branch's dense layer", POSITIVE_INT)
    latent_size: int = doc(50, "size of the latent state φ(s) of the multimodal encoder", POSITIVE_INT)
    embed_size: int = doc(64, "width of the UVFA embeddings ψ(s) and η(g)", POSITIVE_INT)
    hidden_size: int = doc(128, "width of the actor's and critic's hidden layers", POSITIVE_INT)
    hidden_layers: int = doc(2, "number of hidden layers of the actor and the critic", POSITIVE_INT)
    model_hidden_size: int = doc(128, "hidden width of the forward model f and inverse model g", POSITIVE_INT)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The DDPG + HER learner and the BidAL models (paper Sec. III-C, Eqs. 4, 5, 8)."""

    num_envs: int = doc(16, "parallel environments in each rollout of a cycle", POSITIVE_INT)
    cycles_per_epoch: int = doc(10, "rollout/update cycles in one epoch", POSITIVE_INT)
    updates_per_cycle: int = doc(40, "gradient updates after each cycle's rollout", POSITIVE_INT)
    batch_size: int = doc(256, "transitions per gradient update", POSITIVE_INT)
    buffer_episodes: int = doc(4096, "replay capacity in episodes (a multiple of num_envs)", POSITIVE_INT)
    gamma: float = doc(
        0.98, "discount γ; the critic target is clipped to [r_min/(1-γ), 0] (losses.min_reward)",
        Rule(float, lambda v: 0 < v < 1, "in (0, 1)"),
    )
    tau: float = doc(
        0.05, "Polyak rate of the target networks, applied after every gradient update",
        Rule(float, lambda v: 0 < v <= 1, "in (0, 1]"),
    )
    actor_lr: float = doc(1e-3, "Adam learning rate of the actor", POSITIVE)
    critic_lr: float = doc(1e-3, "Adam learning rate of the critic, encoder, forward and inverse models", POSITIVE)
    action_l2: float = doc(1.0, "weight of the actor's action L2 penalty", NON_NEGATIVE)
    noise_eps: float = doc(0.2, "std of the Gaussian exploration noise on actions", NON_NEGATIVE)
    random_eps: float = doc(0.3, "probability of a uniformly random exploration action", PROBABILITY)
    exploration_starts: float = doc(
        0.0,
        "fraction of training episodes begun by the env's exploration_reset (nicol_lift: the cube already held); "
        "evaluation always begins from reset. The lifting tasks' preset is 0.5, HER's pick-and-place protocol "
        "(the paper is silent; docs/deviations.md), 0 their labelled plain variant; other tasks have no such start",
        PROBABILITY,
    )
    obs_noise: float = doc(
        0.0,
        "κ of the observation noise s + κ·N(0, σ), σ the interquartile range of each feature over the clean "
        "history (paper Eq. 9); it is data in the training state, so one compiled program serves every κ",
        NON_NEGATIVE,
    )
    noise_segments: str = doc(
        "",
        "comma-separated proprio segments that get observation noise (the paper's: ee_pos,ee_rot,obj_pos); "
        "empty: no noise code at all",
        text("comma-separated proprio segment names"),
    )
    noise_variant: str = doc(
        "derived",
        "where the observation noise reaches: 'derived' (the noise segments and every feature the env derives "
        "from them, e.g. obj_rel_pos = obj_pos - ee_pos, as from estimated poses), 'literal' (the noise segments "
        "alone, the paper's literal reading) or 'noisy_goal' ('derived', and the achieved goal the agent stores "
        "and relabels with is the noisy estimate too); rewards and success are always judged on the true state",
        one_of(NOISE_VARIANTS),
    )
    her_k: int = doc(
        4, "HER 'future' relabelling ratio k: a goal is relabelled with prob. 1 - 1/(1+k)",
        Rule(int, lambda v: v >= 0, "an integer >= 0"),
    )
    intrinsic_lambda: float = doc(
        0.1, "λ of the intrinsic reward r_i = -λ/2 ||f(φ(s),a) - φ(s')||² (Eq. 4); the paper leaves it open: 0.1 "
        "learned fastest of 0, 0.1, 0.3 and 1 over nicol_slide and nicol_lift (docs/deviations.md, the λ sweep)",
        NON_NEGATIVE,
    )
    target_encoder: str = doc(
        "online",
        "the φ(s_{t+1}) of the critic's target (Eq. 8): 'target' (a Polyak-averaged copy φ' of the encoder, as the "
        "critic and actor have theirs) or 'online' (the online encoder's φ(s_{t+1}), stopped: the one the forward "
        "and inverse models read, so a BidAL update encodes each frame once, as DrQ-v2 does); the paper is silent "
        "(docs/deviations.md)",
        one_of(TARGET_ENCODERS),
    )
    sample_run: int = doc(
        1,
        "consecutive steps of one episode per sampled run: a batch is batch_size / sample_run runs, whose "
        "transitions share their frames, so an image update encodes 1 + 1/sample_run frames a transition instead "
        "of 2; a run starts uniformly in [0, T - sample_run], so each episode's first and last sample_run - 1 "
        "steps are drawn less often. 1: independent transitions, HER's draw (docs/deviations.md)",
        POSITIVE_INT,
    )
    forward_weight: float = doc(
        1.0, "weight of the forward-model loss (Eq. 3) in the representation loss",
        NON_NEGATIVE,
    )
    inverse_weight: float = doc(
        1.0, "weight of the inverse-model loss (Eq. 5) in the representation loss",
        NON_NEGATIVE,
    )
    clip_obs: float = doc(5.0, "normalised proprio and goals are clipped to ±clip_obs", POSITIVE)
    eval_envs: int = doc(64, "deterministic evaluation episodes after each epoch", POSITIVE_INT)
    grad_clip: float = doc(10.0, "global gradient-norm clip of every optimiser", POSITIVE)


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """One run: which task, which agent, how long, where to write."""

    env: str = doc("planar_reach", "environment name", text("an env name"))
    agent: str = doc("multimodal_bidal", "agent name", text("an agent name"))
    seeds: int = doc(1, "seeds trained together as one vmapped program", POSITIVE_INT)
    seed: int = doc(
        0, "first random seed; seeds use seed, seed+1, ...",
        Rule(int, lambda v: 0 <= v < 2**32, "an integer in [0, 2^32)"),
    )
    epochs: int = doc(20, "training epochs", POSITIVE_INT)
    checkpoint_every: int = doc(5, "save a checkpoint every K epochs (and at the end)", POSITIVE_INT)
    env_shards: int = doc(
        1,
        "at most this many devices split each seed's envs (of the devices the seeds leave free; gradients "
        "averaged across them); 1: none. Tested on CPU devices; also runs on GPUs (docs/usage.md: Several devices)",
        POSITIVE_INT,
    )
    physics: str = doc(
        "jax",
        "the physics engine: 'jax' (MJX's JAX implementation, on any device), 'warp' (MuJoCo Warp: a run on one "
        "NVIDIA GPU with the warp-lang package, pip install 'bidal-jax[warp]') or 'auto' (warp where that holds, "
        "else jax; the NICOL presets'); one model, so runs of either compare and resume alike",
        one_of(PHYSICS),
    )
    run_dir: str = doc("", "run directory; default runs/<env>-<agent>-<time>", text("a path"))
    target_success: float = doc(0.0, "stop early once the mean eval success reaches this (0: never)", PROBABILITY)
    init_from: str = doc(
        "",
        "RUN_DIR or RUN_DIR:CHECKPOINT (step or best) whose parameters start this run (transfer, paper Sec. IV-C; "
        "bidal_jax/run/transfer.py); empty: a fresh start. A resumed run continues its own checkpoint",
        text("RUN_DIR or RUN_DIR:CHECKPOINT"),
    )
    init_parts: str = doc(
        "encoder,forward,inverse",
        "comma-separated networks that --init-from restores, into the online and target networks (optimisers start "
        "fresh); the encoder brings its normalisers, its proprio rows matched by segment name",
        Rule(str, _name_list, "comma-separated network names without repeats, e.g. encoder,forward,inverse"),
    )
    init_normaliser: str = doc(
        "fresh",
        "the proprio normaliser of a run started by --init-from: fresh (zero counts: the statistics of this run's "
        "task alone, the encoder's weights still the source's) or inherit (the source's statistics and counts, "
        "its rows matched by segment name, continued here; docs/deviations.md, Transfer normaliser)",
        one_of(INIT_NORMALISERS),
    )


def fields_help(cls: type) -> dict[str, str]:
    """Field name -> documentation of a config dataclass."""
    return {f.name: f.metadata.get("help", "") for f in dataclasses.fields(cls)}


CONFIG_CLASSES: dict[str, type] = {"run": RunConfig, "train": TrainConfig, "network": NetworkConfig}


class ConfigFormatError(ValueError):
    """A stored config (config.json, a checkpoint's) that this version cannot read."""


@dataclasses.dataclass(frozen=True)
class Config:
    """A run's three configs as one value; its JSON form is {"run": {...}, "train": {...}, "network": {...}}."""

    run: RunConfig = RunConfig()
    train: TrainConfig = TrainConfig()
    network: NetworkConfig = NetworkConfig()

    @property
    def agent(self) -> Agent:
        """The agent `run.agent` (`bidal_jax.agents`): its algorithm family and what it observes; ValueError for
        an unknown name."""
        return get(self.run.agent)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The configs as JSON-ready {"run": {...}, "train": {...}, "network": {...}}."""
        return {name: dataclasses.asdict(getattr(self, name)) for name in CONFIG_CLASSES}

    @classmethod
    def from_dict(cls, cfg: dict, where: str) -> Config:
        """The inverse of `to_dict`; fields newer than `cfg` take what a run without them did (`recorded`). Raises
        ConfigFormatError naming `where` for a dict that is not such a config."""
        try:
            return cls(**{name: group(**recorded(name, cfg[name])) for name, group in CONFIG_CLASSES.items()})
        except (KeyError, TypeError) as err:
            raise ConfigFormatError(f"{where} has a config this version cannot read ({err})") from err


def recorded(group: str, fields: Any) -> Any:
    """A config group's `fields` as a run recorded them (config.json, a checkpoint's), read as this version runs
    them: fields the record is older than take what its run did where that is not their default (a transfer run,
    `init_from`, older than `init_normaliser` inherited its source's proprio normaliser; a run older than
    `target_encoder` read the target encoder), and a conv implementation removed since (`REMOVED_CONV_IMPLS`) reads
    as "patch", which computes the same function of the same parameters, so that its runs still resume, evaluate
    and report. Other fields newer than the record take their defaults, as they did."""
    if not isinstance(fields, dict):
        return fields
    if group == "run" and fields.get("init_from") and "init_normaliser" not in fields:
        return {**fields, "init_normaliser": "inherit"}
    if group == "train" and "target_encoder" not in fields:  # older runs' critic targets read the target encoder
        return {**fields, "target_encoder": "target"}
    if group == "network" and fields.get("conv_impl") in REMOVED_CONV_IMPLS:
        return {**fields, "conv_impl": "patch"}
    return fields


def resolve(given: dict[str, Any], preset: Callable[[str, str], dict[str, dict[str, Any]]]) -> Config:
    """The config of a new run: defaults, then `preset(env, agent)` ({"run"|"train"|"network": {field: value}}: the
    run's task's overrides for its agent, which the command lines read from the env, `experiments.cli.task_preset`),
    then `given` (field name -> value, e.g. from the command line; unknown names are ignored). ConfigError for a
    preset that names a group or field these configs lack."""
    run = RunConfig(**{f.name: given[f.name] for f in dataclasses.fields(RunConfig) if f.name in given})
    preset = preset(run.env, run.agent)
    unknown = [f"{name}.{field}" for name, values in preset.items() for field in values
               if name not in CONFIG_CLASSES or field not in {f.name for f in dataclasses.fields(CONFIG_CLASSES[name])}]
    if unknown:
        raise ConfigError(f"the task's preset sets {', '.join(unknown)}, not a config field; fields by group: "
                          "python -m experiments.run --help")
    groups = {}
    for name, group in CONFIG_CLASSES.items():
        fields = {f.name: given[f.name] for f in dataclasses.fields(group) if f.name in given}
        groups[name] = group(**{**preset.get(name, {}), **fields})
    return Config(**groups)
