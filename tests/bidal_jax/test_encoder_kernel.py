"""The fused encoder kernel (bidal_jax/encoder_kernel.py, conv_impl "pallas"): the vision branch it computes, and
its parameter gradients, are the XLA path's ("toeplitz") of the same parameters, under the seeds' vmap; in float32
to float32 rounding, in bfloat16 to bfloat16's. On a CPU the kernel runs in Pallas's interpret mode; the last test
runs it compiled, at an update's size, on a GPU only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bidal_jax.networks import VisionBranch

STRIDES = (3, 2, 2, 1)


def branch(impl: str, dtype: str, strides: tuple[int, ...] = STRIDES) -> VisionBranch:
    return VisionBranch(16, 64, strides, impl=impl, dtype=jnp.dtype(dtype))


def seeds_case(seeds: int, frames: int, strides: tuple[int, ...] = STRIDES) -> tuple[dict, jax.Array]:
    """Each seed's random parameters (biases too) and random frames: ([seeds, ...] params, [seeds, frames, 42, 42, 1]
    uint8)."""
    images = jax.random.randint(jax.random.PRNGKey(1), (seeds, frames, 42, 42, 1), 0, 256).astype(np.uint8)
    params = jax.vmap(lambda key: branch("toeplitz", "float32", strides).init(key, images[0, :1]))(
        jax.random.split(jax.random.PRNGKey(0), seeds))
    noise = jax.random.split(jax.random.PRNGKey(2), len(jax.tree.leaves(params)))
    leaves = [leaf + 0.1 * jax.random.normal(key, leaf.shape) for leaf, key in zip(jax.tree.leaves(params), noise)]
    return jax.tree.unflatten(jax.tree.structure(params), leaves), images


def features_and_grads(impl: str, dtype: str, params: dict, images: jax.Array, strides: tuple[int, ...] = STRIDES):
    """The branch's features of each seed's frames and the gradients of a loss of them in each seed's parameters;
    float32 products in full float32 (a GPU's default is TF32, in XLA and in the kernel alike)."""
    net = branch(impl, dtype, strides)

    def loss(p, x):
        return (net.apply(p, x) ** 2).sum()

    with jax.default_matmul_precision("highest"):
        return jax.jit(jax.vmap(lambda p, x: (net.apply(p, x), jax.grad(loss)(p, x))))(params, images)


def assert_close(ours, theirs, rtol: float):
    """Each leaf within `rtol` of the largest magnitude of its reference leaf."""
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs), strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, atol=rtol * float(np.abs(b).max()), rtol=0)


@pytest.fixture(scope="module")
def small():
    """2 seeds × 20 frames (two blocks of the interpret mode's 16, the second padded), and the float32 XLA path's
    features and gradients."""
    params, images = seeds_case(2, 20)
    return params, images, features_and_grads("toeplitz", "float32", params, images)


def test_the_parameters_are_the_xla_paths():
    """A checkpoint of either loads in the other: the same tree, and the same initial values from the same key."""
    image = np.zeros((1, 42, 42, 1), np.uint8)
    fused = branch("pallas", "bfloat16").init(jax.random.PRNGKey(0), image)
    xla = branch("toeplitz", "bfloat16").init(jax.random.PRNGKey(0), image)
    assert jax.tree.structure(fused) == jax.tree.structure(xla)
    for a, b in zip(jax.tree.leaves(fused), jax.tree.leaves(xla), strict=True):
        np.testing.assert_array_equal(a, b)


def test_float32_features_and_gradients_are_the_xla_paths_under_the_seeds_vmap(small):
    params, images, (features, grads) = small
    ours, our_grads = features_and_grads("pallas", "float32", params, images)
    assert_close(ours, features, 1e-5)
    assert_close(our_grads, grads, 1e-5)
    other_seed = features_and_grads("pallas", "float32", jax.tree.map(lambda p: p[::-1], params), images)[0]
    assert not np.allclose(other_seed, ours, atol=1e-3)  # each seed's own parameters


def test_bfloat16_features_and_gradients_are_the_xla_paths_to_bfloat16_rounding(small):
    """bfloat16 inputs, float32 accumulation: within 3 % of the float32 XLA path's largest entry of each leaf (the
    bfloat16 XLA path's bias gradients, summed in bfloat16, are off by up to 20 %), and not the float32 result."""
    params, images, (features, grads) = small
    ours, our_grads = features_and_grads("pallas", "bfloat16", params, images)
    assert_close(ours, features, 3e-2)
    assert_close(our_grads, grads, 3e-2)
    assert not np.allclose(ours, features, atol=1e-6)  # it did compute in bfloat16


def test_other_strides_are_the_xla_paths_too():
    """Strides 3,2,1,2: a stride-1 third layer (a 7×7 map whose 784 features pad to 1,024 in the kernel; its positions
    are read by 4 to 9 of its taps) and a fourth layer of stride 2, float32."""
    strides = (3, 2, 1, 2)
    params, images = seeds_case(1, 5, strides)
    assert_close(features_and_grads("pallas", "float32", params, images, strides),
                 features_and_grads("toeplitz", "float32", params, images, strides), 1e-5)


@pytest.mark.parametrize("strides, channels", [((2, 2, 1, 1), 16), ((3, 2, 2, 1), 4), ((3, 2), 16)])
def test_an_unsupported_branch_is_refused_naming_what_is_supported(strides, channels):
    net = VisionBranch(channels, 64, strides, impl="pallas")
    with pytest.raises(ValueError, match="supports 3×3 convs, at least three, the first of stride 3.*use 'toeplitz'"):
        net.init(jax.random.PRNGKey(0), np.zeros((1, 42, 42, 1), np.uint8))


@pytest.mark.skipif(jax.default_backend() != "gpu", reason="the compiled kernel needs a GPU")
def test_the_compiled_kernel_at_an_updates_size_is_the_xla_paths():
    """2 seeds × 2,048 frames, bfloat16, compiled through Triton: within 3 % of the float32 XLA path's features and
    gradients."""
    params, images = seeds_case(2, 2048)
    features, grads = features_and_grads("toeplitz", "float32", params, images)
    ours, our_grads = features_and_grads("pallas", "bfloat16", params, images)
    assert_close(ours, features, 3e-2)
    assert_close(our_grads, grads, 3e-2)
