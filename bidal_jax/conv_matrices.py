"""The full (Toeplitz) matrix of a k×k convolution and the padding of a 'SAME' one: the layouts that both the XLA
path (`bidal_jax.networks`) and the fused kernel (`bidal_jax.encoder_kernel`) multiply frames by."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def toeplitz_matrix(kernel: jax.Array, height: int, width: int, stride: int,
                    pads: tuple[int, int, int, int]) -> jax.Array:
    """The full matrix of the convolution (conv_impl "toeplitz"'s) of a height × width frame zero-padded by `pads`:
    [H·W·C, out_h·out_w·F], rows in the frame's (h, w, c) order and columns in the output's (p, q, f) order; a
    linear function of the kernel, so the kernel's gradient is the matrix's gradient pulled back through it."""
    k, _, channels, _ = kernel.shape
    top, bottom, left, right = pads
    out_h, out_w = (height + top + bottom - k) // stride + 1, (width + left + right - k) // stride + 1
    rows = np.arange(height)[:, None, None] == stride * np.arange(out_h)[None, :, None] + np.arange(k) - top
    cols = np.arange(width)[:, None, None] == stride * np.arange(out_w)[None, :, None] + np.arange(k) - left
    taps = rows[:, None, :, None, :, None] & cols[None, :, None, :, None, :]  # [H, W, out_h, out_w, k, k]
    matrix = jnp.einsum("hwpqyx,yxcf->hwcpqf", taps.astype(kernel.dtype), kernel)
    return matrix.reshape(height * width * channels, -1)


def same_pads(height: int, width: int, k: int, stride: int) -> tuple[int, int, int, int]:
    """The zero rows and columns (top, bottom, left, right) that 'SAME' padding adds around a height × width frame
    so that a k×k convolution of `stride` gives ⌈height/stride⌉ × ⌈width/stride⌉ outputs, the odd one at the end
    (as `nn.Conv` and `lax.conv_general_dilated` pad)."""
    pad_h = max((-(-height // stride) - 1) * stride + k - height, 0)
    pad_w = max((-(-width // stride) - 1) * stride + k - width, 0)
    return pad_h // 2, pad_h - pad_h // 2, pad_w // 2, pad_w - pad_w // 2
