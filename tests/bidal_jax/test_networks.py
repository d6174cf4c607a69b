"""Networks (bidal_jax/networks.py): each agent gets the networks it needs, every conv implementation is a plain
convolution and they are one another's, and the conv strides set the vision branch's feature map."""

import jax
import numpy as np
import pytest

from bidal_jax.agents import ddpg
from bidal_jax.config import AGENTS, NetworkConfig
from bidal_jax.networks import CONVS, PatchConv, parse_strides

CONV_IMPLS = tuple(CONVS)  # the layer-wise implementations; the fused "pallas": test_encoder_kernel.py


def default_layers() -> list[tuple[int, int, str]]:
    """(input size, stride, padding) of each conv layer of the default strides on a 42×42 frame: the first
    unpadded, the others 'same'-padded."""
    first, *rest = parse_strides(NetworkConfig().conv_strides)
    layers, size = [(42, first, "VALID")], (42 - 3) // first + 1
    for stride in rest:
        layers.append((size, stride, "SAME"))
        size = -(-size // stride)
    return layers


DEFAULT_LAYERS = default_layers()


def plain_conv(params: dict, x: jax.Array, stride: int, padding: str) -> jax.Array:
    """XLA's convolution (`lax.conv_general_dilated`) of a `PatchConv`'s parameters, in full float32."""
    kernel, bias = params["params"]["kernel"], params["params"]["bias"]
    return jax.lax.conv_general_dilated(x, kernel, (stride, stride), padding, precision=jax.lax.Precision.HIGHEST,
                                        dimension_numbers=("NHWC", "HWIO", "NHWC")) + bias


def conv_case(size: int, stride: int, padding: str, impl: str) -> tuple[jax.Array, jax.Array]:
    """(the conv `impl` of a 16-channel float32 frame, XLA's convolution of it), the same random parameters."""
    x = jax.random.normal(jax.random.PRNGKey(0), (2, size, size, 16), np.float32)
    conv = PatchConv(16, stride=stride, padding=padding, impl=impl)
    params = conv.init(jax.random.PRNGKey(1), x)
    params = jax.tree.map(lambda p: p + jax.random.normal(jax.random.PRNGKey(2), p.shape), params)  # a bias too
    return conv.apply(params, x), plain_conv(params, x, stride, padding)


@pytest.mark.parametrize("agent", sorted(AGENTS))
def test_every_agent_builds_the_networks_it_needs(agent):
    spec = AGENTS[agent]
    params = spec.networks(NetworkConfig(conv_channels=4), 4, 2, 2, (42, 42, 1)).init(jax.random.PRNGKey(0))
    assert ("encoder" in params) == spec.uses_image
    models = spec.family in (ddpg.BIDAL, ddpg.BIDAL_NO_REWARD)
    assert ("forward" in params) == models and ("inverse" in params) == models


@pytest.mark.parametrize("impl", CONV_IMPLS)
@pytest.mark.parametrize("size, stride, padding",
                         [*DEFAULT_LAYERS, (10, 1, "SAME"), (11, 3, "VALID"), (9, 2, "VALID"), (10, 3, "SAME")])
def test_every_conv_impl_is_a_plain_convolution(size, stride, padding, impl):
    """--conv-impl patch and banded, float32, on the default strides' layers and others: XLA's convolution of the
    same kernel and bias, to float32 rounding."""
    ours, plain = conv_case(size, stride, padding, impl)
    assert ours.shape == plain.shape
    np.testing.assert_allclose(ours, plain, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("size, stride, padding", DEFAULT_LAYERS)
def test_the_conv_impls_agree_with_each_other(size, stride, padding):
    """patch and banded, float32, on the default strides' layers: the same output of the same parameters."""
    patch, *others = [conv_case(size, stride, padding, impl)[0] for impl in CONV_IMPLS]
    assert others
    for other in others:
        np.testing.assert_allclose(other, patch, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("impl", [impl for impl in CONV_IMPLS if impl != "patch"])
@pytest.mark.parametrize("strides", ["3,2,2,1", "3,2,2,2", "2,2,1,1"])
def test_every_conv_impl_is_the_same_encoder_with_the_same_parameters(strides, impl):
    """--conv-impl banded: the parameter tree (a checkpoint) is the same as patch's, and so are φ(s) and its
    gradients."""
    def networks(impl):
        config = NetworkConfig(conv_channels=4, latent_size=8, conv_strides=strides, conv_impl=impl)
        return AGENTS["multimodal_bidal"].networks(config, 4, 2, 2, (42, 42, 1))

    patch, native = networks("patch"), networks(impl)
    params = patch.init(jax.random.PRNGKey(0))["encoder"]
    assert jax.tree.structure(native.init(jax.random.PRNGKey(0))["encoder"]) == jax.tree.structure(params)
    image = jax.random.randint(jax.random.PRNGKey(1), (3, 42, 42, 1), 0, 256).astype(np.uint8)
    proprio = jax.random.normal(jax.random.PRNGKey(2), (3, 4))

    def loss(nets, p):
        return (nets.encode(p, image, proprio) ** 2).sum()

    np.testing.assert_allclose(native.encode(params, image, proprio), patch.encode(params, image, proprio), atol=1e-5)
    for a, b in zip(jax.tree.leaves(jax.grad(lambda p: loss(native, p))(params)),
                    jax.tree.leaves(jax.grad(lambda p: loss(patch, p))(params)), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-4)


@pytest.mark.parametrize("impl", [impl for impl in CONV_IMPLS if impl != "patch"])
def test_convs_under_the_seeds_vmap_are_the_seeds_own_encoders_and_gradients(impl):
    """--conv-impl banded: under the seeds' vmap (each seed its parameters and frames) φ(s) and its gradients are
    each seed's own, as with patch."""
    def networks(impl):
        config = NetworkConfig(conv_channels=4, latent_size=8, conv_impl=impl)
        return AGENTS["multimodal_bidal"].networks(config, 4, 2, 2, (42, 42, 1))

    patch, other = networks("patch"), networks(impl)
    params = jax.vmap(lambda key: patch.init(key)["encoder"])(jax.random.split(jax.random.PRNGKey(0), 3))
    images = jax.random.randint(jax.random.PRNGKey(1), (3, 5, 42, 42, 1), 0, 256).astype(np.uint8)
    proprio = jax.random.normal(jax.random.PRNGKey(2), (3, 5, 4))

    def grads(nets):
        return jax.vmap(jax.grad(lambda p, i, q: (nets.encode(p, i, q) ** 2).sum()))(params, images, proprio)

    np.testing.assert_allclose(jax.vmap(other.encode)(params, images, proprio),
                               jax.vmap(patch.encode)(params, images, proprio), atol=1e-5)
    for a, b in zip(jax.tree.leaves(grads(other)), jax.tree.leaves(grads(patch)), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-4)


@pytest.mark.parametrize("impl", CONV_IMPLS)
def test_a_bfloat16_vision_branch_keeps_float32_parameters_and_gradients(impl):
    """--vision-dtype bfloat16, each --conv-impl: the same parameter tree in float32 (a checkpoint of either loads in
    the other); φ(s) comes out float32, within bfloat16's rounding of the float32 patch branch's, and so do its
    gradients."""
    def networks(dtype, impl):
        config = NetworkConfig(conv_channels=4, latent_size=8, vision_dtype=dtype, conv_impl=impl)
        return AGENTS["multimodal_bidal"].networks(config, 4, 2, 2, (42, 42, 1))

    full, half = networks("float32", "patch"), networks("bfloat16", impl)
    params = full.init(jax.random.PRNGKey(0))["encoder"]
    assert jax.tree.structure(half.init(jax.random.PRNGKey(0))["encoder"]) == jax.tree.structure(params)
    assert {leaf.dtype for leaf in jax.tree.leaves(half.init(jax.random.PRNGKey(0)))} == {np.dtype(np.float32)}
    image = jax.random.randint(jax.random.PRNGKey(1), (3, 42, 42, 1), 0, 256).astype(np.uint8)
    proprio = jax.random.normal(jax.random.PRNGKey(2), (3, 4))
    phi = half.encode(params, image, proprio)
    assert phi.dtype == np.float32
    np.testing.assert_allclose(phi, full.encode(params, image, proprio), atol=0.05)
    assert not np.allclose(phi, full.encode(params, image, proprio), atol=1e-6)  # it did compute in bfloat16
    grads = jax.grad(lambda p: (half.encode(p, image, proprio) ** 2).sum())(params)
    assert {leaf.dtype for leaf in jax.tree.leaves(grads)} == {np.dtype(np.float32)}


@pytest.mark.parametrize(
    "strides, features", [("3,2,2,2", 2 * 2 * 4), ("2,2,1,1", 10 * 10 * 4), ("2,2,2,2", 3 * 3 * 4)]
)
def test_conv_strides_set_the_vision_branch_feature_map(strides, features):
    """--conv-strides: the first layer unpadded, the others 'same'-padded, so the dense layer that
    ends the vision branch sees H×W×C features (42 → 14 → 7 → 4 → 2 for 3,2,2,2)."""
    config = NetworkConfig(conv_channels=4, latent_size=8, conv_strides=strides)
    params = AGENTS["visual_bidal"].networks(config, 4, 2, 2, (42, 42, 1)).init(jax.random.PRNGKey(0))
    assert params["encoder"]["params"]["VisionBranch_0"]["Dense_0"]["kernel"].shape == (features, 64)
