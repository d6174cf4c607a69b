"""The vision branch's first three convs and ELUs as one fused Pallas kernel (`NetworkConfig.conv_impl` "pallas").

The same function of the same parameters as the other conv implementations (`bidal_jax.networks.CONVS`; paper
Sec. III-B: four 3×3 conv layers with ELU), computed for a block of `BLOCK` frames in one program whose activations
stay on chip: the first three layers, whose maps are large (14×14 and 7×7) and whose windows overlap, and where
XLA's layouts spend their time gathering and concatenating. The fourth conv (4×4×16 → 4×4×16, a 256 × 256 matrix)
and the dense layer stay XLA matmuls over all the frames (conv_impl "toeplitz"), which are large and well shaped.

Triton has no in-kernel gather and wants power-of-two tiles, so each fused layer is a matmul of a layout that XLA
prepares from the frame or the kernels, outside the kernel:

- layer 1 (stride = kernel, unpadded): the frames' space-to-depth patches [N / B, n1 + 1, B, 16] (uint8, the 9 pixels of
  each of the n1 patches, zero-padded to 16, then one zero patch) times the kernel [16, F];
- layer 2: one output position at a time, the sum over its 9 taps of layer 1's output at the tapped patch (found
  by a table of patch indices, the zero patch where the tap falls in the padding, its ELU masked to 0) times the
  tap's kernel [F, F]; layer 1 is recomputed for each tap (a 3×3 stride-2 conv reads a patch at most 4 times);
- layer 3: each output position of layer 2, as it is computed, times its rows of layer 3's whole-frame (Toeplitz)
  matrix (`bidal_jax.conv_matrices.toeplitz_matrix`), accumulated over the positions; the columns are padded to a
  power of two with zeros.

bf16 inputs (or the branch's dtype), float32 accumulation. `jax.custom_vjp`: the backward reads the forward's output
(ELU's derivative is a function of its output) and its cotangent. A first kernel recomputes layers 1 and 2 from the
frames, one layer-2 position at a time, and for each of its taps reads the layer-3 output that reads the position
through it (a table; a branch skips the taps no output reads), writing layer 2's output and gradient [N, n2·F]; a
second kernel accumulates the three layers' weight gradients one tap at a time (a few [F, F] accumulators live, not
19, which would not fit a thread's registers), recomputing layer 1; XLA sums the blocks' partial gradients. Frames
are data: no gradient reaches the image. On a GPU the kernels compile through Triton; elsewhere they run in Pallas's
interpret mode (slow: tests only).
"""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pltriton

from bidal_jax.conv_matrices import same_pads, toeplitz_matrix

# frames and warps per program on a GPU: at 64 frames and 8 warps none of the three kernels spills registers (at 4
# warps the forward's [64, 256] float32 accumulator does); `experiments.bench.encoder` times other tilings
BLOCK = 64
NUM_WARPS = 8
INTERPRET_BLOCK = 16  # frames per program in interpret mode (the smallest tile a Triton dot takes)
KERNEL = 3  # the convs' kernel size, the first layer's stride
TAPS = KERNEL * KERNEL
FUSED_LAYERS = 3  # the convs the kernel computes; the others are XLA's
PIXELS = 16  # a patch's 9 pixels, zero-padded to the smallest dot depth
SUPPORTED = ("3×3 convs, at least three, the first of stride 3 (unpadded), the others any; one input channel "
             "(gray); channels a power of two >= 16")


def _pow2(n: int) -> int:
    return 1 << (n - 1).bit_length()


def _elu(z: jax.Array) -> jax.Array:
    return jnp.where(z > 0, z, jnp.expm1(jnp.minimum(z, 0.0)))


def _elu_grad(z: jax.Array) -> jax.Array:
    return jnp.where(z > 0, 1.0, jnp.exp(jnp.minimum(z, 0.0)))


def _elu_grad_of_output(h: jax.Array) -> jax.Array:
    """ELU's derivative from its output h = ELU(z): 1 where z > 0, else exp(z) = h + 1."""
    return jnp.where(h > 0, 1.0, h + 1.0)


def _dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """a @ b, float32 accumulation."""
    return jnp.dot(a, b, preferred_element_type=jnp.float32)


def _dot_t(a: jax.Array, b: jax.Array) -> jax.Array:
    """a @ bᵀ, float32 accumulation."""
    return jax.lax.dot_general(a, b, (((1,), (1,)), ((), ())), preferred_element_type=jnp.float32)


def _t_dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """aᵀ @ b, float32 accumulation."""
    return jax.lax.dot_general(a, b, (((0,), (0,)), ((), ())), preferred_element_type=jnp.float32)


def check_supported(strides: tuple[int, ...], image_shape: tuple[int, ...], channels: int) -> None:
    """ValueError (one line naming what is supported) unless the fused kernel computes this branch."""
    if (len(strides) < FUSED_LAYERS or strides[0] != KERNEL or image_shape[-1] != 1 or channels < 16
            or channels != _pow2(channels) or image_shape[0] < KERNEL or image_shape[1] < KERNEL):
        raise ValueError(f"conv_impl 'pallas' does not compute strides {','.join(map(str, strides))} on a "
                         f"{'×'.join(map(str, image_shape))} frame with {channels} channels; it supports {SUPPORTED}; "
                         "use 'toeplitz' there")


def _geometry(strides: tuple[int, ...], image_shape: tuple[int, ...]) -> dict:
    """The map sizes of the fused layers, and the tables that stand in for gathers, for each layer-2 position and
    tap t (row-major): `taps2`, the layer-1 patch it reads (n1, the zero patch, in the padding); `outs3`, the layer-3
    output that reads it through tap t (-1: none)."""
    side1 = image_shape[0] // KERNEL, image_shape[1] // KERNEL
    side2 = -(-side1[0] // strides[1]), -(-side1[1] // strides[1])
    side3 = -(-side2[0] // strides[2]), -(-side2[1] // strides[2])
    n1, n2 = side1[0] * side1[1], side2[0] * side2[1]
    p, q, dy, dx = np.meshgrid(np.arange(side2[0]), np.arange(side2[1]), np.arange(KERNEL), np.arange(KERNEL),
                               indexing="ij")
    top, _, left, _ = same_pads(*side1, KERNEL, strides[1])
    rows, cols = strides[1] * p + dy - top, strides[1] * q + dx - left
    inside = (rows >= 0) & (rows < side1[0]) & (cols >= 0) & (cols < side1[1])
    taps2 = np.where(inside, rows * side1[1] + cols, n1).reshape(n2, TAPS)
    top, _, left, _ = same_pads(*side2, KERNEL, strides[2])
    rows, cols = p + top - dy, q + left - dx  # stride × the layer-3 output that reads (p, q) through tap (dy, dx)
    inside = (rows % strides[2] == 0) & (cols % strides[2] == 0) & (rows >= 0) & (cols >= 0)
    rows, cols = rows // strides[2], cols // strides[2]
    inside &= (rows < side3[0]) & (cols < side3[1])
    outs3 = np.where(inside, rows * side3[1] + cols, -1).reshape(n2, TAPS)
    return {"strides": tuple(strides[:FUSED_LAYERS]), "side2": side2, "side3": side3, "n1": n1, "n2": n2,
            "taps2": taps2.reshape(-1).astype(np.int32), "outs3": outs3.reshape(-1).astype(np.int32)}


def space_to_depth(image: jax.Array, block: int) -> jax.Array:
    """The first layer's patches of uint8 frames [N, H, W, 1] (N a multiple of `block`), a block of frames at a
    time: [N / block, n1 + 1, block, 16], each patch's 3×3 pixels in the kernel's (dy, dx) order, zero-padded to 16,
    then a patch of zeros (the padding's); a patch of a block's frames is contiguous, so a tap reads it at once."""
    n, height, width, _ = image.shape
    rows, cols = height // KERNEL, width // KERNEL
    x = image[:, : rows * KERNEL, : cols * KERNEL, 0].reshape(n // block, block, rows, KERNEL, cols, KERNEL)
    x = x.transpose(0, 2, 4, 1, 3, 5).reshape(n // block, rows * cols, block, TAPS)
    return jnp.pad(x, ((0, 0), (0, 1), (0, 0), (0, PIXELS - TAPS)))


def pack_weights(convs: list[tuple[jax.Array, jax.Array]], geometry: dict) -> dict[str, jax.Array]:
    """The float32 operands of the kernels, from the three convs' (kernel [3, 3, C, F], bias [F]): layer 1's kernel
    [16, F] (rows past the 9 taps zero), layers 2 and 3's taps stacked [9·F, F], biases as rows [1, F], layer 3's
    repeated over its output positions and zero-padded to a power of two [1, P3]."""
    (k1, b1), (k2, b2), (k3, b3) = convs
    features = k1.shape[-1]
    n3 = geometry["side3"][0] * geometry["side3"][1] * features
    return {"w1": jnp.pad(k1.reshape(-1, features), ((0, PIXELS - TAPS), (0, 0))), "b1": b1[None],
            "w2": k2.reshape(-1, features), "b2": b2[None], "w3": k3.reshape(-1, features),
            "b3": jnp.pad(jnp.tile(b3, n3 // features), (0, _pow2(n3) - n3))[None]}


def _layer3_matrix(w3: jax.Array, geometry: dict) -> jax.Array:
    """Layer 3's Toeplitz matrix [n2·F, P3] of its stacked taps [9·F, F], columns zero-padded to P3."""
    features = w3.shape[-1]
    matrix = toeplitz_matrix(w3.reshape(KERNEL, KERNEL, features, features), *geometry["side2"],
                             geometry["strides"][2], same_pads(*geometry["side2"], KERNEL, geometry["strides"][2]))
    return jnp.pad(matrix, ((0, 0), (0, _pow2(matrix.shape[1]) - matrix.shape[1])))


def _tap(ref, t: int, dtype) -> jax.Array:
    """Tap t's kernel [F, F] of stacked taps [9·F, F]."""
    features = ref.shape[-1]
    return ref[t * features: (t + 1) * features, :].astype(dtype)


def _layer_1(s_ref, taps2_ref, w1, b1, pos, t: int, n1: int, dtype) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Layer 1 at the patch that tap t of layer-2 position `pos` reads: (its pixels [B, 16] in `dtype`, its
    pre-activation [B, F], 1 if the tap is inside the frame else 0)."""
    index = taps2_ref[pos * TAPS + t]
    patches = (s_ref[index, :, :].astype(jnp.float32) * (1.0 / 255.0)).astype(dtype)
    return patches, _dot(patches, w1) + b1, (index < n1).astype(jnp.float32)


def _layer_2(s_ref, taps2_ref, w1, b1, w2_ref, b2, pos, n1: int, dtype) -> jax.Array:
    """Layer 2's pre-activation [B, F] at output position `pos`."""
    z2 = 0.0
    for t in range(TAPS):
        _, z1, inside = _layer_1(s_ref, taps2_ref, w1, b1, pos, t, n1, dtype)
        z2 = z2 + _dot((_elu(z1) * inside).astype(dtype), _tap(w2_ref, t, dtype))
    return z2 + b2


def _forward_kernel(taps2_ref, s_ref, w1_ref, b1_ref, w2_ref, b2_ref, m3_ref, b3_ref, h3_ref, *, n1: int, n2: int,
                    dtype):
    features = w2_ref.shape[-1]
    w1, b1, b2 = w1_ref[...].astype(dtype), b1_ref[...], b2_ref[...]

    def position(pos, z3):
        z2 = _layer_2(s_ref, taps2_ref, w1, b1, w2_ref, b2, pos, n1, dtype)
        return z3 + _dot(_elu(z2).astype(dtype), m3_ref[pl.ds(pos * features, features), :])

    z3 = jax.lax.fori_loop(0, n2, position, jnp.zeros(h3_ref.shape, jnp.float32))
    h3_ref[...] = _elu(z3 + b3_ref[...]).astype(h3_ref.dtype)


def _dz3(g_ref, h3_ref, out, features: int, dtype) -> jax.Array:
    """Layer 3's pre-activation gradient [B, F] at its output position `out`, from its output and cotangent."""
    cols = pl.ds(out * features, features)
    return (g_ref[:, cols].astype(jnp.float32) * _elu_grad_of_output(h3_ref[:, cols].astype(jnp.float32))).astype(dtype)


def _layer2_grad_kernel(taps2_ref, outs3_ref, s_ref, h3_ref, g_ref, w1_ref, b1_ref, w2_ref, b2_ref, w3_ref,
                        h2_ref, dz2_ref, db2_ref, db3_ref, *, n1: int, n2: int, dtype):
    """Layer 2's output and pre-activation gradient at each of its positions ([B, n2·F] each, in `dtype`), and
    the block's bias gradients of layers 2 and 3."""
    features = w2_ref.shape[-1]
    w1, b1, b2 = w1_ref[...].astype(dtype), b1_ref[...], b2_ref[...]
    db3_ref[...] = jnp.sum(g_ref[...].astype(jnp.float32) * _elu_grad_of_output(h3_ref[...].astype(jnp.float32)),
                           axis=0, keepdims=True)

    def position(pos, db2):
        z2 = _layer_2(s_ref, taps2_ref, w1, b1, w2_ref, b2, pos, n1, dtype)
        dh2 = jnp.zeros_like(z2)
        for t in range(TAPS):  # the layer-3 output that reads this position through tap t, if one does
            out = outs3_ref[pos * TAPS + t]
            dh2 = jax.lax.cond(out >= 0, lambda dh2, out=out, t=t: dh2 + _dot_t(
                _dz3(g_ref, h3_ref, out, features, dtype), _tap(w3_ref, t, dtype)), lambda dh2: dh2, dh2)
        dz2 = dh2 * _elu_grad(z2)
        cols = pl.ds(pos * features, features)
        h2_ref[:, cols] = _elu(z2).astype(h2_ref.dtype)
        dz2_ref[:, cols] = dz2.astype(dz2_ref.dtype)
        return db2 + dz2  # summed over the frames once, at the end

    db2 = jax.lax.fori_loop(0, n2, position, jnp.zeros(g_ref.shape[:1] + (features,), jnp.float32))
    db2_ref[...] = jnp.sum(db2, axis=0, keepdims=True)


def _weight_grad_kernel(taps2_ref, outs3_ref, s_ref, h2_ref, dz2_ref, h3_ref, g_ref, w1_ref, b1_ref, w2_ref,
                        dw1_ref, db1_ref, dw2_ref, dw3_ref, *, n1: int, n2: int, dtype):
    """The block's weight gradients of layers 1 to 3 and bias gradient of layer 1, one tap at a time (few
    accumulators live), over layer 2's positions; layer 1 recomputed."""
    features = w2_ref.shape[-1]
    w1, b1 = w1_ref[...].astype(dtype), b1_ref[...]
    square = jnp.zeros((features, features), jnp.float32)
    dw1, db1 = jnp.zeros((PIXELS, features), jnp.float32), jnp.zeros(g_ref.shape[:1] + (features,), jnp.float32)
    for t in range(TAPS):
        w2 = _tap(w2_ref, t, dtype)

        def position(pos, grads, t=t, w2=w2):
            dw1, db1, dw2, dw3 = grads
            patches, z1, inside = _layer_1(s_ref, taps2_ref, w1, b1, pos, t, n1, dtype)
            cols = pl.ds(pos * features, features)
            dz2, h2 = dz2_ref[:, cols], h2_ref[:, cols]
            dw2 = dw2 + _t_dot((_elu(z1) * inside).astype(dtype), dz2)
            dz1 = _dot_t(dz2, w2) * _elu_grad(z1) * inside
            out = outs3_ref[pos * TAPS + t]
            dw3 = jax.lax.cond(out >= 0, lambda dw3: dw3 + _t_dot(h2, _dz3(g_ref, h3_ref, out, features, dtype)),
                               lambda dw3: dw3, dw3)
            return dw1 + _t_dot(patches, dz1.astype(dtype)), db1 + dz1, dw2, dw3

        dw1, db1, dw2, dw3 = jax.lax.fori_loop(0, n2, position, (dw1, db1, square, square))
        dw2_ref[t * features: (t + 1) * features, :] = dw2
        dw3_ref[t * features: (t + 1) * features, :] = dw3
    dw1_ref[...], db1_ref[...] = dw1, jnp.sum(db1, axis=0, keepdims=True)


def _whole(*arrays) -> list[pl.BlockSpec]:
    """Each array whole to every program."""
    return [pl.BlockSpec(a.shape, functools.partial(lambda ndim, i: (0,) * ndim, a.ndim)) for a in arrays]


def _frames(block: int, shape: tuple[int, ...]) -> pl.BlockSpec:
    """Program i's `block` frames of an array [N, ...]."""
    return pl.BlockSpec((block, *shape[1:]), lambda i: (i,) + (0,) * (len(shape) - 1))


def _patches(shape: tuple[int, ...]) -> pl.BlockSpec:
    """Program i's block of patches [N / block, n1 + 1, block, 16] (`space_to_depth`)."""
    return pl.BlockSpec((None, *shape[1:]), lambda i: (i, 0, 0, 0))


def _partials(shape: tuple[int, ...]) -> pl.BlockSpec:
    """Program i's own slice of per-block partial sums [blocks, ...]."""
    return pl.BlockSpec((None, *shape), lambda i: (i,) + (0,) * len(shape))


def _options() -> dict:
    """Compiled through Triton on a GPU, interpreted elsewhere."""
    if jax.default_backend() != "gpu":
        return {"interpret": True}
    return {"compiler_params": pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1)}


WEIGHTS = ("w1", "b1", "w2", "b2", "w3", "b3")


def _forward(patches, weights, geometry, dtype, block: int) -> jax.Array:
    n, taps2 = patches.shape[0] * block, jnp.asarray(geometry["taps2"])
    operands = [weights["w1"], weights["b1"], weights["w2"], weights["b2"],
                _layer3_matrix(weights["w3"], geometry).astype(dtype), weights["b3"]]
    width = weights["b3"].shape[1]
    kernel = functools.partial(_forward_kernel, n1=geometry["n1"], n2=geometry["n2"], dtype=dtype)
    return pl.pallas_call(kernel, out_shape=jax.ShapeDtypeStruct((n, width), dtype), grid=(n // block,),
                          in_specs=[*_whole(taps2), _patches(patches.shape), *_whole(*operands)],
                          out_specs=_frames(block, (n, width)), **_options())(taps2, patches, *operands)


def _backward(patches, h3, g, weights, geometry, dtype, block: int) -> dict[str, jax.Array]:
    """The weights' gradients: per block by two kernels (layer 2's output and gradient, then the weight gradients
    one tap at a time), summed over the blocks."""
    tables = [jnp.asarray(geometry[name]) for name in ("taps2", "outs3")]
    blocks, features = patches.shape[0], weights["w2"].shape[-1]
    n = blocks * block
    width = geometry["n2"] * features
    sizes = {"n1": geometry["n1"], "n2": geometry["n2"], "dtype": dtype}
    layer2 = [weights[name] for name in ("w1", "b1", "w2", "b2", "w3")]
    h2, dz2, db2, db3 = pl.pallas_call(
        functools.partial(_layer2_grad_kernel, **sizes),
        out_shape=[jax.ShapeDtypeStruct((n, width), dtype)] * 2 + [
            jax.ShapeDtypeStruct((blocks, *weights[name].shape), jnp.float32) for name in ("b2", "b3")],
        grid=(blocks,),
        in_specs=[*_whole(*tables), _patches(patches.shape), *(_frames(block, a.shape) for a in (h3, g)),
                  *_whole(*layer2)],
        out_specs=[_frames(block, (n, width))] * 2 + [_partials(weights[name].shape) for name in ("b2", "b3")],
        **_options())(*tables, patches, h3, g, *layer2)
    layer1 = [weights[name] for name in ("w1", "b1", "w2")]
    dw1, db1, dw2, dw3 = pl.pallas_call(
        functools.partial(_weight_grad_kernel, **sizes),
        out_shape=[jax.ShapeDtypeStruct((blocks, *weights[name].shape), jnp.float32)
                   for name in ("w1", "b1", "w2", "w3")],
        grid=(blocks,),
        in_specs=[*_whole(*tables), _patches(patches.shape), *(_frames(block, a.shape) for a in (h2, dz2, h3, g)),
                  *_whole(*layer1)],
        out_specs=[_partials(weights[name].shape) for name in ("w1", "b1", "w2", "w3")],
        **_options())(*tables, patches, h2, dz2, h3, g, *layer1)
    grads = {"w1": dw1, "b1": db1, "w2": dw2, "b2": db2, "w3": dw3, "b3": db3}
    return {name: grads[name].sum(axis=0) for name in WEIGHTS}


def fused_convs(image: jax.Array, convs: list[tuple[jax.Array, jax.Array]], strides: tuple[int, ...],
                dtype) -> jax.Array:
    """The first three convs with ELU of uint8 frames [N, H, W, 1] by the float32 (kernel, bias) of each:
    [N, h, w, F] in `dtype`, as the XLA path's; differentiable in the parameters (not in the frames)."""
    chex.assert_rank(image, 4)
    chex.assert_equal(len(convs), FUSED_LAYERS)
    features = convs[0][0].shape[-1]
    check_supported(strides, image.shape[1:], features)
    geometry = _geometry(strides, image.shape[1:])
    dtype = jnp.dtype(dtype)
    block = BLOCK if jax.default_backend() == "gpu" else INTERPRET_BLOCK
    n = image.shape[0]
    patches = space_to_depth(jnp.pad(image, ((0, -n % block), (0, 0), (0, 0), (0, 0))), block)

    @jax.custom_vjp
    def layers(patches, weights):
        return _forward(patches, weights, geometry, dtype, block)

    def forward(patches, weights):
        h3 = _forward(patches, weights, geometry, dtype, block)
        return h3, (patches, h3, weights)

    def backward(residuals, g):
        patches, h3, weights = residuals
        return None, _backward(patches, h3, g, weights, geometry, dtype, block)

    layers.defvjp(forward, backward)
    side3 = geometry["side3"]
    h3 = layers(patches, pack_weights(convs, geometry))[:n, : side3[0] * side3[1] * features]
    return h3.reshape(n, *side3, features)
