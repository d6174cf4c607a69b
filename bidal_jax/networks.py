"""Flax networks of multimodal BidAL (paper Sec. III-B, III-C; Fig. 2).

- `Encoder`: φ(s) (Eq. 1). Vision branch: four 3×3 conv layers with ELU and a dense
  layer; proprio branch: one dense layer; the branches are concatenated and one dense
  layer (LayerNorm + tanh) gives φ(s). The visual agents use the vision branch alone;
  the proprio baseline has no learned encoder (φ(s) is the normalised proprio).
- `Actor` μ(ψ(s), η(g)) and `Critic` Q(ψ(s), a, η(g)): UVFA goal embeddings (Sec. III-C.2).
- `ForwardModel` f(φ(s), a) → φ̂(s') (Eq. 2) and `InverseModel` g(φ(s), φ(s')) → â (Eq. 5),
  two dense layers each.

`make_networks` builds the set an agent of the DDPG family needs (`bidal_jax.agents.ddpg`) and returns pure
init/apply functions. The modules take a `config.NetworkConfig` (this module imports no config: the config
imports the agents, which build these networks).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import encoder_kernel
from bidal_jax.conv_matrices import same_pads, toeplitz_matrix


def parse_strides(text: str) -> tuple[int, ...]:
    """`NetworkConfig.conv_strides` as integers: "3,2,2,1" -> (3, 2, 2, 1); ValueError if it is not
    four positive integers."""
    strides = tuple(int(part) for part in text.split(","))
    if len(strides) != 4 or min(strides) < 1:
        raise ValueError(f"{text!r}: not four positive integers")
    return strides


def _width_bands(kernel: jax.Array, stride: int, width: int) -> jax.Array:
    """The convolution along one row as matrices, one per kernel row dy: [k, width·C, out_w·F] whose entry
    ((x, c), (o, f)) is kernel[dy, x − stride·o, c, f] for 0 <= x − stride·o < k, else 0."""
    k, _, channels, features = kernel.shape
    out_w = (width - k) // stride + 1
    taps = np.arange(width)[:, None, None] == stride * np.arange(out_w)[None, :, None] + np.arange(k)
    bands = jnp.einsum("xod,ydcf->yxcof", taps.astype(kernel.dtype), kernel)
    return bands.reshape(k, width * channels, out_w * features)


def _window_rows(x: jax.Array, k: int, stride: int, top: int, out_h: int) -> jax.Array:
    """The k input rows of each output row's window side by side: [B, out_h, k·W·C] of x [B, H, W·C] padded with
    `top` zero rows above and as many below as the windows reach; the zero rows are written into the windows, the
    padded frame is never built."""
    batch, height, row = x.shape
    if stride == k and top == 0 and out_h * k <= height:  # windows that tile the rows: the frame's own layout
        return x[:, : out_h * k].reshape(batch, out_h, k * row)
    zero = jnp.zeros((batch, 1, row), x.dtype)
    blocks = []
    for dy in range(k):
        rows = [dy + stride * o - top for o in range(out_h)]  # the input row of each window's place dy
        inside = [r for r in rows if 0 <= r < height]
        pieces = [zero] * sum(r < 0 for r in rows)
        if inside:
            pieces.append(x[:, inside[0] : inside[-1] + 1 : stride])
        pieces += [zero] * sum(r >= height for r in rows)
        blocks.append(jnp.concatenate(pieces, axis=1) if len(pieces) > 1 else pieces[0])
    return jnp.concatenate(blocks, axis=-1)


def _banded_conv(x: jax.Array, kernel: jax.Array, stride: int, pads: tuple[int, int, int, int]) -> jax.Array:
    """The unpadded convolution of x [B, H, W, C] zero-padded by `pads` (top, bottom, left, right) as one dense
    matmul: each output row's window of k input rows, side by side (`_window_rows`), times the band matrices of the
    k kernel rows stacked (`_width_bands`): [B·out_h, k·W·C] @ [k·W·C, out_w·F], the output rows in order. The
    padding costs no copy of the frame: its zero rows are written into the windows, and the band rows of padded
    columns are dropped. No transpose and no copy of taps: the band's zeros and the windows' overlap cost arithmetic
    instead (several times that of the convolution), which a GPU's matrix units have to spare and its memory has
    not."""
    batch, height, width, channels = x.shape
    k, features = kernel.shape[0], kernel.shape[-1]
    top, bottom, left, right = pads
    out_h = (height + top + bottom - k) // stride + 1
    bands = _width_bands(kernel, stride, width + left + right)[:, left * channels : (left + width) * channels]
    windows = _window_rows(x.reshape(batch, height, width * channels), k, stride, top, out_h)
    y = windows @ bands.reshape(k * width * channels, -1)
    return y.reshape(batch, out_h, -1, features)


def _patch_conv(x: jax.Array, kernel: jax.Array, stride: int, pads: tuple[int, int, int, int]) -> jax.Array:
    """The same convolution as `_banded_conv`, as the k² strided slices of the padded frame concatenated into
    patches [B, out_h, out_w, k²·C] and multiplied by the kernel [k²·C, F] once: no convolution op, which XLA's CPU
    backend runs slowly inside the training loop's `lax.scan`, and the least arithmetic."""
    k, _, channels, features = kernel.shape
    top, bottom, left, right = pads
    x = jnp.pad(x, ((0, 0), (top, bottom), (left, right), (0, 0)))
    out_h, out_w = (x.shape[1] - k) // stride + 1, (x.shape[2] - k) // stride + 1
    taps = [x[:, dy : dy + stride * (out_h - 1) + 1 : stride, dx : dx + stride * (out_w - 1) + 1 : stride, :]
            for dy in range(k) for dx in range(k)]
    return jnp.concatenate(taps, axis=-1) @ kernel.reshape(k * k * channels, features)


TOEPLITZ_ENTRIES = 1 << 20  # `_toeplitz_conv`: a layer's whole-frame matrix up to this size is one dense matmul


def _toeplitz_conv(x: jax.Array, kernel: jax.Array, stride: int, pads: tuple[int, int, int, int]) -> jax.Array:
    """The same convolution as `_banded_conv`, where the layer is small enough: the whole frame x [B, H·W·C] times
    the convolution's full (Toeplitz) matrix [H·W·C, out_h·out_w·F], whose entry ((h, w, c), (p, q, f)) is
    kernel[dy, dx, c, f] where (h, w) is tap (dy, dx) of output (p, q) of the padded frame, else 0: one matmul, no
    windows gathered and no padding copied. The matrix is built from the kernel and a constant 0/1 tensor of the
    taps, so its gradient is the kernel's. Layers whose matrix has more than `TOEPLITZ_ENTRIES` entries (the first
    two of the default strides: their zeros would cost more arithmetic than the band's) stay banded."""
    batch, height, width, channels = x.shape
    k, features = kernel.shape[0], kernel.shape[-1]
    top, bottom, left, right = pads
    out_h, out_w = (height + top + bottom - k) // stride + 1, (width + left + right - k) // stride + 1
    if height * width * channels * out_h * out_w * features > TOEPLITZ_ENTRIES:
        return _banded_conv(x, kernel, stride, pads)
    y = x.reshape(batch, -1) @ toeplitz_matrix(kernel, height, width, stride, pads)
    return y.reshape(batch, out_h, out_w, features)


# how a conv is computed (`NetworkConfig.conv_impl`): the same function of the same parameters either way, so a
# checkpoint of one runs, resumes and compares under the other
CONVS: dict[str, Callable[..., jax.Array]] = {"patch": _patch_conv, "banded": _banded_conv,
                                               "toeplitz": _toeplitz_conv}
FUSED_IMPL = "pallas"  # NetworkConfig.conv_impl of the whole branch's convs in one kernel (bidal_jax.encoder_kernel)


class PatchConv(nn.Module):
    """A k×k convolution with stride s, written as matmuls instead of XLA's convolution op (the class keeps its
    name, which names the layers in the parameter tree: checkpoints hold PatchConv_0 ... PatchConv_3).

    Same result and parameter layout (kernel [k, k, C, F], bias [F]) as `nn.Conv`. `impl`
    (`NetworkConfig.conv_impl`, a key of `CONVS`) picks how it is computed: "patch" (`_patch_conv`: strided slices
    and one matmul, the fast form on a CPU, where XLA's convolution op is slow inside the training loop's
    `lax.scan`), "banded" (`_banded_conv`: whole input rows times band matrices of the kernel, the fast form on a
    GPU; the GPU presets'; docs/performance.md, "Image updates") or "toeplitz" (`_toeplitz_conv`: a small layer as one
    matmul of the whole frame by the conv's full matrix, the others banded). It computes in the dtype of `x`
    (float32 parameters cast to it): with bfloat16 input its matmuls and output are bfloat16
    (`NetworkConfig.vision_dtype`).
    """

    features: int
    kernel: int = 3
    stride: int = 2
    padding: str = "SAME"
    impl: str = "patch"  # NetworkConfig.conv_impl: a key of CONVS

    @nn.compact
    def weights(self, channels: int) -> tuple[jax.Array, jax.Array]:
        """The layer's float32 parameters for an input of `channels` channels: kernel [k, k, C, F], bias [F]."""
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (self.kernel, self.kernel, channels,
                                                                       self.features))
        return kernel, self.param("bias", nn.initializers.zeros, (self.features,))

    def __call__(self, x: jax.Array) -> jax.Array:
        chex.assert_rank(x, 4)
        _, height, width, channels = x.shape
        kernel, bias = (w.astype(x.dtype) for w in self.weights(channels))
        pads = same_pads(height, width, self.kernel, self.stride) if self.padding == "SAME" else (0, 0, 0, 0)
        return CONVS[self.impl](x, kernel, self.stride, pads) + bias


class VisionBranch(nn.Module):
    """Four 3×3 conv layers with ELU (paper Sec. III-B: "four convolution layers with Elu
    activation"), then a dense layer.

    The paper gives no strides (`NetworkConfig.conv_strides`). The default 3,2,2,1 (a first
    layer of non-overlapping patches, the first unpadded, the others 'same'-padded) maps 42×42 →
    14×14 → 7×7 → 4×4 → 4×4: a map of at least 3×3 keeps where things are, and a first layer of
    stride 3 keeps the later maps, and so the gradient step, small (docs/deviations.md).
    """

    channels: int
    features: int
    strides: tuple[int, ...] = (3, 2, 2, 1)
    impl: str = "patch"  # how the convs are computed (PatchConv.impl), or FUSED_IMPL (a fused kernel)
    dtype: Any = jnp.float32  # what the layers compute in (parameters stay float32); the features come out float32

    @nn.compact
    def __call__(self, image: jax.Array) -> jax.Array:
        chex.assert_rank(image, 4)  # [B, H, W, 1] uint8
        if self.impl == FUSED_IMPL:  # the first layers in one kernel, the others as toeplitz
            count = encoder_kernel.FUSED_LAYERS
            fused, rest, impl = self.strides[:count], self.strides[count:], "toeplitz"
            encoder_kernel.check_supported(self.strides, image.shape[1:], self.channels)
            inputs = [image.shape[-1]] + [self.channels] * (len(fused) - 1)
            convs = [PatchConv(self.channels, stride=stride).weights(c) for stride, c in zip(fused, inputs)]
            x = encoder_kernel.fused_convs(image, convs, fused, self.dtype)
        else:
            (first, *rest), impl = self.strides, self.impl
            x = image.astype(self.dtype) / 255.0
            x = nn.elu(PatchConv(self.channels, stride=first, padding="VALID", impl=impl)(x))
        for stride in rest:
            x = nn.elu(PatchConv(self.channels, stride=stride, impl=impl)(x))
        x = x.reshape(x.shape[0], -1)
        return nn.elu(nn.Dense(self.features, dtype=self.dtype)(x)).astype(jnp.float32)


PROPRIO_LAYER = "proprio"  # the encoder's proprio branch: its kernel's rows are the proprio features


class Encoder(nn.Module):
    """φ(s): the multimodal (or visual-only) encoder, paper Eq. 1."""

    config: Any  # NetworkConfig
    uses_proprio: bool

    @nn.compact
    def __call__(self, image: jax.Array, proprio: jax.Array) -> jax.Array:
        chex.assert_rank(proprio, 2)
        cfg = self.config
        parts = [VisionBranch(cfg.conv_channels, cfg.vision_features, parse_strides(cfg.conv_strides),
                              impl=cfg.conv_impl, dtype=jnp.dtype(cfg.vision_dtype))(image)]
        if self.uses_proprio:
            parts.append(nn.elu(nn.Dense(cfg.proprio_features, name=PROPRIO_LAYER)(proprio)))
        x = nn.Dense(cfg.latent_size)(jnp.concatenate(parts, axis=-1))
        return jnp.tanh(nn.LayerNorm()(x))


def _mlp(x: jax.Array, width: int, layers: int) -> jax.Array:
    for _ in range(layers):
        x = nn.relu(nn.Dense(width)(x))
    return x


ACTION_LAYER = "action"  # the actor's output layer: its bias has the action size


class Actor(nn.Module):
    """μ(ψ(s), η(g)) ∈ [-1, 1]^A with UVFA embeddings of state and goal."""

    config: Any  # NetworkConfig
    action_size: int

    @nn.compact
    def __call__(self, phi: jax.Array, goal: jax.Array) -> jax.Array:
        chex.assert_rank([phi, goal], 2)
        cfg = self.config
        psi = nn.elu(nn.Dense(cfg.embed_size, name="psi")(phi))
        eta = nn.elu(nn.Dense(cfg.embed_size, name="eta")(goal))
        x = _mlp(jnp.concatenate([psi, eta], axis=-1), cfg.hidden_size, cfg.hidden_layers)
        return jnp.tanh(nn.Dense(self.action_size, name=ACTION_LAYER)(x))


class Critic(nn.Module):
    """Q(ψ(s), a, η(g)) with UVFA embeddings of state and goal."""

    config: Any  # NetworkConfig

    @nn.compact
    def __call__(self, phi: jax.Array, action: jax.Array, goal: jax.Array) -> jax.Array:
        chex.assert_rank([phi, action, goal], 2)
        cfg = self.config
        psi = nn.elu(nn.Dense(cfg.embed_size, name="psi")(phi))
        eta = nn.elu(nn.Dense(cfg.embed_size, name="eta")(goal))
        x = _mlp(jnp.concatenate([psi, action, eta], axis=-1), cfg.hidden_size, cfg.hidden_layers)
        return nn.Dense(1)(x)[:, 0]


class ForwardModel(nn.Module):
    """f(φ(s), a) → φ̂(s'), two dense layers (paper Eq. 2)."""

    config: Any  # NetworkConfig

    @nn.compact
    def __call__(self, phi: jax.Array, action: jax.Array) -> jax.Array:
        chex.assert_rank([phi, action], 2)
        x = nn.elu(nn.Dense(self.config.model_hidden_size)(jnp.concatenate([phi, action], axis=-1)))
        return nn.Dense(phi.shape[-1])(x)


class InverseModel(nn.Module):
    """g(φ(s), φ(s')) → â ∈ [-1, 1]^A, two dense layers (paper Eq. 5)."""

    config: Any  # NetworkConfig
    action_size: int

    @nn.compact
    def __call__(self, phi: jax.Array, next_phi: jax.Array) -> jax.Array:
        chex.assert_rank([phi, next_phi], 2)
        x = nn.elu(nn.Dense(self.config.model_hidden_size)(jnp.concatenate([phi, next_phi], axis=-1)))
        return jnp.tanh(nn.Dense(self.action_size)(x))


@dataclasses.dataclass(frozen=True)
class Networks:
    """Pure apply functions of one agent's networks, and their joint initialiser.

    Every apply takes the parameter subtree of its network: `params["encoder"]`, ...
    `encode(params, image, proprio)` is the identity on proprio for the proprio baseline.
    """

    init: Callable[[jax.Array], dict]
    encode: Callable[..., jax.Array]
    actor: Callable[..., jax.Array]
    critic: Callable[..., jax.Array]
    forward: Callable[..., jax.Array] | None
    inverse: Callable[..., jax.Array] | None
    latent_size: int


def make_networks(
    config: Any, proprio_size: int, goal_size: int, action_size: int, image_shape, *, uses_image: bool,
    uses_proprio: bool, models: bool,
) -> Networks:
    """The actor and critic, an encoder for an agent that `uses_image` (reading proprio too if `uses_proprio`)
    and, with `models`, the forward and inverse models; `init(key)` returns a dict of param subtrees."""
    actor, critic = Actor(config, action_size), Critic(config)
    latent = config.latent_size if uses_image else proprio_size
    encoder = Encoder(config, uses_proprio) if uses_image else None
    fwd = ForwardModel(config) if models else None
    inv = InverseModel(config, action_size) if models else None

    def init(key: jax.Array) -> dict:
        keys = dict(zip(("encoder", "actor", "critic", "forward", "inverse"), jax.random.split(key, 5)))
        phi = jnp.zeros((1, latent))
        goal, action = jnp.zeros((1, goal_size)), jnp.zeros((1, action_size))
        params = {
            "actor": actor.init(keys["actor"], phi, goal),
            "critic": critic.init(keys["critic"], phi, action, goal),
        }
        if encoder is not None:
            image = jnp.zeros((1, *image_shape), jnp.uint8)
            params["encoder"] = encoder.init(keys["encoder"], image, jnp.zeros((1, proprio_size)))
        if models:
            params["forward"] = fwd.init(keys["forward"], phi, action)
            params["inverse"] = inv.init(keys["inverse"], phi, phi)
        return params

    def encode(params: dict, image: jax.Array, proprio: jax.Array) -> jax.Array:
        if encoder is None:
            return proprio
        return encoder.apply(params, image, proprio)

    return Networks(
        init=init,
        encode=encode,
        actor=actor.apply,
        critic=critic.apply,
        forward=fwd.apply if fwd else None,
        inverse=inv.apply if inv else None,
        latent_size=latent,
    )
