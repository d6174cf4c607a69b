"""The vision branch's four convs and ELUs as one fused Pallas kernel (`NetworkConfig.conv_impl` "pallas").

The same function of the same parameters as the other conv implementations (`bidal_jax.networks.CONVS`; paper
Sec. III-B: four 3×3 conv layers with ELU), computed for a block of `BLOCK` frames in one program whose activations
stay on chip. Triton has no in-kernel gather and wants power-of-two tiles, so each layer is a matmul of a layout
that XLA prepares from the frame or the kernels, outside the kernel:

- layer 1 (stride = kernel, unpadded): the frame's space-to-depth patches [N, n1 + 1, 16] (uint8, the 9 pixels of
  each of the n1 patches, zero-padded to 16, and one zero patch after them) times the kernel [16, F];
- layer 2: one output position at a time, the sum over its 9 taps of layer 1's output at the tapped patch (read by
  a table of patch indices, the zero patch where the tap falls in the padding, its ELU masked to 0) times the tap's
  kernel [F, F]; layer 1 is recomputed for each tap (a 3×3 stride-2 conv reads each patch at most 4 times);
- layers 3 and 4: each output position of layer 2 as it is computed, times its rows of layer 3's whole-frame
  (Toeplitz) matrix (`bidal_jax.conv_matrices.toeplitz_matrix`), accumulated over the positions; layer 4 is one matmul
  of the whole frame by its Toeplitz matrix. Their columns are padded to a power of two with zeros.

Inputs are bf16 (or the branch's dtype), products accumulate in float32. The dense layer that ends the branch stays
an XLA matmul. `jax.custom_vjp`: the forward kernel keeps layer 3's pre-activations (float32) as its residual, and
the backward kernel recomputes layers 1 and 2 from the frames, producing per-block partial gradients of the packed
weights (the tap kernels, the Toeplitz matrices, the biases) that XLA sums; the Toeplitz matrices' gradients reach
the [3, 3, C, F] kernels through the matrix builder's own (linear) VJP, as in the XLA path. Frames are data: no
gradient reaches the image. On a GPU the kernels compile through Triton; elsewhere they run in Pallas's interpret
mode (slow: tests only).
"""

from __future__ import annotations

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from bidal_jax.conv_matrices import same_pads, toeplitz_matrix

BLOCK = 64  # frames per program on a GPU
INTERPRET_BLOCK = 16  # frames per program in interpret mode (the smallest tile a Triton dot takes)
NUM_WARPS = 4
KERNEL = 3  # the convs' kernel size, the first layer's stride
PIXELS = 16  # a patch's 9 pixels, zero-padded to the smallest dot depth
SUPPORTED = ("strides: the first 3 (= the 3×3 kernel, unpadded), the others any; input: one channel (gray); "
             "conv channels: a power of two >= 16")


def _pow2(n: int) -> int:
    return 1 << (n - 1).bit_length()


def _elu(z: jax.Array) -> jax.Array:
    return jnp.where(z > 0, z, jnp.expm1(jnp.minimum(z, 0.0)))


def _elu_grad(z: jax.Array) -> jax.Array:
    return jnp.where(z > 0, 1.0, jnp.exp(jnp.minimum(z, 0.0)))


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
    if (len(strides) != 4 or strides[0] != KERNEL or image_shape[-1] != 1 or channels < 16
            or channels != _pow2(channels) or image_shape[0] < KERNEL or image_shape[1] < KERNEL):
        raise ValueError(f"conv_impl 'pallas' does not compute strides {','.join(map(str, strides))} on a "
                         f"{'×'.join(map(str, image_shape))} frame with {channels} channels; it supports {SUPPORTED}; "
                         "use 'toeplitz' there")


def _geometry(strides: tuple[int, ...], image_shape: tuple[int, ...]) -> dict:
    """The map sizes of each layer and layer 2's tap table: for each of its output positions and taps (row-major),
    the index of layer 1's patch it reads, n1 (the zero patch) where the tap falls in the padding."""
    side1 = image_shape[0] // KERNEL, image_shape[1] // KERNEL
    pads2 = same_pads(*side1, KERNEL, strides[1])
    side2 = -(-side1[0] // strides[1]), -(-side1[1] // strides[1])
    pads3 = same_pads(*side2, KERNEL, strides[2])
    side3 = -(-side2[0] // strides[2]), -(-side2[1] // strides[2])
    pads4 = same_pads(*side3, KERNEL, strides[3])
    side4 = -(-side3[0] // strides[3]), -(-side3[1] // strides[3])
    n1 = side1[0] * side1[1]
    p, q, dy, dx = np.meshgrid(np.arange(side2[0]), np.arange(side2[1]), np.arange(KERNEL), np.arange(KERNEL),
                               indexing="ij")
    rows, cols = strides[1] * p + dy - pads2[0], strides[1] * q + dx - pads2[2]
    inside = (rows >= 0) & (rows < side1[0]) & (cols >= 0) & (cols < side1[1])
    taps = np.where(inside, rows * side1[1] + cols, n1).reshape(-1).astype(np.int32)
    return {"strides": tuple(strides), "side1": side1, "side2": side2, "side3": side3, "side4": side4,
            "pads3": pads3, "pads4": pads4, "n1": n1, "n2": side2[0] * side2[1], "taps": taps}


def space_to_depth(image: jax.Array) -> jax.Array:
    """The first layer's patches of uint8 frames [N, H, W, 1]: [N, n1 + 1, 16], each row a patch's 3×3 pixels in the
    kernel's (dy, dx) order, zero-padded to 16, and a last row of zeros (the padding's patch)."""
    n, height, width, _ = image.shape
    rows, cols = height // KERNEL, width // KERNEL
    x = image[:, : rows * KERNEL, : cols * KERNEL, 0].reshape(n, rows, KERNEL, cols, KERNEL)
    x = x.transpose(0, 1, 3, 2, 4).reshape(n, rows * cols, KERNEL * KERNEL)
    return jnp.pad(x, ((0, 0), (0, 1), (0, PIXELS - KERNEL * KERNEL)))


def pack_weights(convs: list[tuple[jax.Array, jax.Array]], geometry: dict) -> dict[str, jax.Array]:
    """The kernel's float32 operands from the four convs' (kernel [3, 3, C, F], bias [F]): the first layer's
    [16, F], the second's taps stacked [9·F, F], the third and fourth as Toeplitz matrices with columns (and the
    fourth's rows) zero-padded to a power of two, biases as rows [1, ·] (the padded ones zero)."""
    (k1, b1), (k2, b2), (k3, b3), (k4, b4) = convs
    features = k1.shape[-1]
    n3 = geometry["side3"][0] * geometry["side3"][1] * features
    n4 = geometry["side4"][0] * geometry["side4"][1] * features
    m3 = toeplitz_matrix(k3, *geometry["side2"], geometry["strides"][2], geometry["pads3"])
    m4 = toeplitz_matrix(k4, *geometry["side3"], geometry["strides"][3], geometry["pads4"])
    pad3, pad4 = _pow2(n3) - n3, _pow2(n4) - n4
    return {
        "w1": jnp.pad(k1.reshape(-1, features), ((0, PIXELS - KERNEL * KERNEL), (0, 0))), "b1": b1[None],
        "w2": k2.reshape(-1, features), "b2": b2[None],
        "m3": jnp.pad(m3, ((0, 0), (0, pad3))), "b3": jnp.pad(jnp.tile(b3, n3 // features), (0, pad3))[None],
        "m4": jnp.pad(m4, ((0, pad3), (0, pad4))), "b4": jnp.pad(jnp.tile(b4, n4 // features), (0, pad4))[None],
    }


WEIGHTS = ("w1", "b1", "w2", "b2", "m3", "b3", "m4", "b4")


def _loaded(weight_refs, dtype) -> tuple[dict[str, jax.Array], dict]:
    """The weights small enough to keep loaded (matrices in `dtype`, biases float32), and all the refs by name;
    layer 2's tap kernels and layer 3's matrix are read a tile at a time."""
    refs = dict(zip(WEIGHTS, weight_refs, strict=True))
    return {name: ref[...].astype(dtype if name[0] in "wm" else jnp.float32) for name, ref in refs.items()
            if name not in ("w2", "m3")}, refs


def _tap_kernel(refs: dict, t: int, dtype) -> jax.Array:
    features = refs["w2"].shape[-1]
    return refs["w2"][t * features: (t + 1) * features, :].astype(dtype)


def _layers_1_2(s_ref, taps_ref, w, refs, pos, n1: int, dtype) -> tuple[list, jax.Array]:
    """Layer 2's pre-activation [B, F] at output position `pos`, and for each tap its (patches, layer-1
    pre-activation, in-frame mask)."""
    taps, z2 = [], 0.0
    for t in range(KERNEL * KERNEL):
        index = taps_ref[pos * KERNEL * KERNEL + t]
        patches = (s_ref[:, index, :].astype(jnp.float32) * (1.0 / 255.0)).astype(dtype)
        z1 = _dot(patches, w["w1"]) + w["b1"]
        inside = (index < n1).astype(jnp.float32)
        z2 = z2 + _dot((_elu(z1) * inside).astype(dtype), _tap_kernel(refs, t, dtype))
        taps.append((patches, z1, inside))
    return taps, z2 + w["b2"]


def _forward_kernel(taps_ref, s_ref, *refs, n1: int, n2: int, dtype, residual: bool):
    weight_refs, (h4_ref, *z3_ref) = refs[: len(WEIGHTS)], refs[len(WEIGHTS):]
    w, refs = _loaded(weight_refs, dtype)
    m3_ref, features = refs["m3"], refs["w2"].shape[-1]

    def position(pos, z3):
        _, z2 = _layers_1_2(s_ref, taps_ref, w, refs, pos, n1, dtype)
        return z3 + _dot(_elu(z2).astype(dtype), m3_ref[pl.ds(pos * features, features), :].astype(dtype))

    z3 = jax.lax.fori_loop(0, n2, position, jnp.zeros(h4_ref.shape[:1] + m3_ref.shape[1:], jnp.float32)) + w["b3"]
    h4_ref[...] = _elu(_dot(_elu(z3).astype(dtype), w["m4"]) + w["b4"]).astype(h4_ref.dtype)
    if residual:
        z3_ref[0][...] = z3


def _backward_kernel(taps_ref, s_ref, z3_ref, g_ref, *refs, n1: int, n2: int, dtype):
    weight_refs, out = refs[: len(WEIGHTS)], dict(zip(["d" + name for name in WEIGHTS], refs[len(WEIGHTS):]))
    w, refs = _loaded(weight_refs, dtype)
    m3_ref, features = refs["m3"], refs["w2"].shape[-1]
    z3 = z3_ref[...]
    h3 = _elu(z3).astype(dtype)
    z4 = _dot(h3, w["m4"]) + w["b4"]
    dz4 = g_ref[...] * _elu_grad(z4)
    out["dm4"][...] = _t_dot(h3, dz4.astype(dtype))
    out["db4"][...] = jnp.sum(dz4, axis=0, keepdims=True)
    dz3 = _dot_t(dz4.astype(dtype), w["m4"]) * _elu_grad(z3)
    out["db3"][...] = jnp.sum(dz3, axis=0, keepdims=True)
    dz3 = dz3.astype(dtype)

    def position(pos, grads):
        dw1, db1, db2, *dw2 = grads
        taps, z2 = _layers_1_2(s_ref, taps_ref, w, refs, pos, n1, dtype)
        rows = pl.ds(pos * features, features)
        out["dm3"][rows, :] = _t_dot(_elu(z2).astype(dtype), dz3)
        dz2 = _dot_t(dz3, m3_ref[rows, :].astype(dtype)) * _elu_grad(z2)
        db2 = db2 + jnp.sum(dz2, axis=0, keepdims=True)
        dz2 = dz2.astype(dtype)
        for t, (patches, z1, inside) in enumerate(taps):
            dw2[t] = dw2[t] + _t_dot((_elu(z1) * inside).astype(dtype), dz2)
            dz1 = _dot_t(dz2, _tap_kernel(refs, t, dtype)) * _elu_grad(z1) * inside
            dw1 = dw1 + _t_dot(patches, dz1.astype(dtype))
            db1 = db1 + jnp.sum(dz1, axis=0, keepdims=True)
        return (dw1, db1, db2, *dw2)

    square, row = jnp.zeros((features, features), jnp.float32), jnp.zeros((1, features), jnp.float32)
    dw1, db1, db2, *dw2 = jax.lax.fori_loop(0, n2, position, (jnp.zeros((PIXELS, features), jnp.float32), row, row,
                                                               *[square] * (KERNEL * KERNEL)))
    out["dw1"][...], out["db1"][...], out["db2"][...] = dw1, db1, db2
    for t, grad in enumerate(dw2):
        out["dw2"][t * features: (t + 1) * features, :] = grad


def _specs(block: int, *arrays) -> list[pl.BlockSpec]:
    """Each array whole to every program."""
    return [pl.BlockSpec(a.shape, functools.partial(lambda ndim, i: (0,) * ndim, a.ndim)) for a in arrays]


def _frames(block: int, shape: tuple[int, ...]) -> pl.BlockSpec:
    """Program i's `block` frames of an array [N, ...]."""
    return pl.BlockSpec((block, *shape[1:]), lambda i: (i,) + (0,) * (len(shape) - 1))


def _partials(shape: tuple[int, ...]) -> pl.BlockSpec:
    """Program i's own slice of per-block partial sums [blocks, ...]."""
    return pl.BlockSpec((None, *shape), lambda i: (i,) + (0,) * len(shape))


def _options(block: int) -> dict:
    interpret = jax.default_backend() != "gpu"
    if interpret:
        return {"interpret": True}
    from jax.experimental.pallas import triton as pltriton
    return {"compiler_params": pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1)}


def _forward(patches, weights, geometry, dtype, block: int, residual: bool):
    taps = jnp.asarray(geometry["taps"])
    n = patches.shape[0]
    width3, width4 = weights["m3"].shape[1], weights["m4"].shape[1]
    out_shape = [jax.ShapeDtypeStruct((n, width4), dtype)]
    out_specs = [_frames(block, (n, width4))]
    if residual:
        out_shape.append(jax.ShapeDtypeStruct((n, width3), jnp.float32))
        out_specs.append(_frames(block, (n, width3)))
    kernel = functools.partial(_forward_kernel, n1=geometry["n1"], n2=geometry["n2"], dtype=dtype, residual=residual)
    ordered = [weights[name] for name in WEIGHTS]
    return pl.pallas_call(kernel, out_shape=out_shape, grid=(n // block,),
                          in_specs=[*_specs(block, taps), _frames(block, patches.shape), *_specs(block, *ordered)],
                          out_specs=out_specs, **_options(block))(taps, patches, *ordered)


def _backward(patches, z3, g, weights, geometry, dtype, block: int) -> dict[str, jax.Array]:
    taps = jnp.asarray(geometry["taps"])
    blocks = patches.shape[0] // block
    ordered = [weights[name] for name in WEIGHTS]
    kernel = functools.partial(_backward_kernel, n1=geometry["n1"], n2=geometry["n2"], dtype=dtype)
    partial_sums = pl.pallas_call(
        kernel, out_shape=[jax.ShapeDtypeStruct((blocks, *w.shape), jnp.float32) for w in ordered], grid=(blocks,),
        in_specs=[*_specs(block, taps), _frames(block, patches.shape), _frames(block, z3.shape),
                  _frames(block, g.shape), *_specs(block, *ordered)],
        out_specs=[_partials(w.shape) for w in ordered], **_options(block))(taps, patches, z3, g, *ordered)
    return {name: grad.sum(axis=0) for name, grad in zip(WEIGHTS, partial_sums, strict=True)}


def fused_convs(image: jax.Array, convs: list[tuple[jax.Array, jax.Array]], strides: tuple[int, ...],
                dtype) -> jax.Array:
    """The four convs with ELU of uint8 frames [N, H, W, 1] by the float32 (kernel, bias) of each layer:
    [N, out_h·out_w·F] in `dtype`, flattened in (h, w, c) order, the same as the XLA path's; differentiable in the
    parameters (not in the frames)."""
    chex.assert_rank(image, 4)
    check_supported(strides, image.shape[1:], convs[0][0].shape[-1])
    geometry = _geometry(strides, image.shape[1:])
    dtype = jnp.dtype(dtype)
    block = BLOCK if jax.default_backend() == "gpu" else INTERPRET_BLOCK
    n = image.shape[0]
    patches = space_to_depth(jnp.pad(image, ((0, -n % block), (0, 0), (0, 0), (0, 0))))
    features = convs[0][0].shape[-1]
    width = geometry["side4"][0] * geometry["side4"][1] * features

    @jax.custom_vjp
    def convs4(patches, weights):
        return _forward(patches, weights, geometry, dtype, block, residual=False)[0]

    def forward(patches, weights):
        h4, z3 = _forward(patches, weights, geometry, dtype, block, residual=True)
        return h4, (patches, z3, weights)

    def backward(residuals, g):
        patches, z3, weights = residuals
        return None, _backward(patches, z3, g.astype(jnp.float32), weights, geometry, dtype, block)

    convs4.defvjp(forward, backward)
    return convs4(patches, pack_weights(convs, geometry))[:n, :width]
