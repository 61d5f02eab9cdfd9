"""Backbones and the white-box policy contract: shapes, parameter counts, gradients."""

import numpy as np
import pytest
import torch

from sim.policies.backbones import BACKBONES, build_backbone
from sim.policies.interface import PolicyError, require_white_box
from sim.policies.policy import PolicyArch, VisuomotorPolicy


# ------------------------------------------------------------------ parameter counts from the architectures
def conv(k, cin, cout, bias=False):
    kh, kw = (k, k) if isinstance(k, int) else k
    return kh * kw * cin * cout + (cout if bias else 0)


def bn(c):
    return 2 * c  # weight and bias; running stats are buffers


def resnet_trunk(layers):
    n = conv(7, 3, 64) + bn(64)
    cin = 64
    for i, (blocks, cout) in enumerate(zip(layers, (64, 128, 256, 512))):
        for b in range(blocks):
            c_in = cin if b == 0 else cout
            n += conv(3, c_in, cout) + bn(cout) + conv(3, cout, cout) + bn(cout)
            if b == 0 and (i > 0 or c_in != cout):
                n += conv(1, c_in, cout) + bn(cout)
        cin = cout
    return n


def vgg16_bn_features():
    n, cin = 0, 3
    for cout in (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512):
        n += conv(3, cin, cout, bias=True) + bn(cout)
        cin = cout
    return n


def inception_v3_trunk():
    def bc(cin, cout, k):
        return conv(k, cin, cout) + bn(cout)

    def A(cin, pf):
        return (
            bc(cin, 64, 1)
            + bc(cin, 48, 1)
            + bc(48, 64, 5)
            + bc(cin, 64, 1)
            + bc(64, 96, 3)
            + bc(96, 96, 3)
            + bc(cin, pf, 1)
        )

    def B(cin):
        return bc(cin, 384, 3) + bc(cin, 64, 1) + bc(64, 96, 3) + bc(96, 96, 3)

    def C(cin, c7):
        return (
            bc(cin, 192, 1)
            + bc(cin, c7, 1)
            + bc(c7, c7, (1, 7))
            + bc(c7, 192, (7, 1))
            + bc(cin, c7, 1)
            + 3 * bc(c7, c7, (7, 1))
            + bc(c7, 192, (1, 7))
            + bc(cin, 192, 1)
        )

    def D(cin):
        return (
            bc(cin, 192, 1)
            + bc(192, 320, 3)
            + bc(cin, 192, 1)
            + bc(192, 192, (1, 7))
            + bc(192, 192, (7, 1))
            + bc(192, 192, 3)
        )

    def E(cin):
        return (
            bc(cin, 320, 1)
            + bc(cin, 384, 1)
            + 2 * bc(384, 384, (1, 3))
            + bc(cin, 448, 1)
            + bc(448, 384, 3)
            + 2 * bc(384, 384, (1, 3))
            + bc(cin, 192, 1)
        )

    stem = bc(3, 32, 3) + bc(32, 32, 3) + bc(32, 64, 3) + bc(64, 80, 1) + bc(80, 192, 3)
    return (
        stem
        + A(192, 32)
        + A(256, 64)
        + A(288, 64)
        + B(288)
        + C(768, 128)
        + 2 * C(768, 160)
        + C(768, 192)
        + D(768)
        + E(1280)
        + E(2048)
    )


EXPECTED_PARAMS = {
    "resnet18": resnet_trunk((2, 2, 2, 2)),
    "resnet34": resnet_trunk((3, 4, 6, 3)),
    "vgg16": vgg16_bn_features(),
    "inception_v3": inception_v3_trunk(),
}


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def test_architecture_formulas_agree_with_the_published_trunk_sizes():
    # Sanity of the formulas themselves: the well-known trunk sizes (classifier excluded).
    assert EXPECTED_PARAMS["resnet18"] == 11_176_512
    assert EXPECTED_PARAMS["resnet34"] == 21_284_672
    assert EXPECTED_PARAMS["vgg16"] == 14_723_136
    assert abs(EXPECTED_PARAMS["inception_v3"] - 21.8e6) < 0.05e6


@pytest.mark.parametrize("name", sorted(EXPECTED_PARAMS))
@pytest.mark.parametrize("small_stem", [True, False])
def test_trunk_parameter_count_matches_the_standard_architecture(name, small_stem):
    assert n_params(build_backbone(name, small_stem)) == EXPECTED_PARAMS[name]


# Feature-map sizes from the strides: /16 with the small stem for ResNet/VGG, (S/2 padded stem,
# /2 pool, two unpadded stride-2 reductions) for Inception; small CNN /8.
@pytest.mark.parametrize(
    "name,size,expected",
    [
        ("resnet18", 64, (512, 4, 4)),
        ("resnet34", 64, (512, 4, 4)),
        ("vgg16", 64, (512, 4, 4)),
        ("inception_v3", 64, (2048, 3, 3)),
        ("small_cnn", 64, (128, 8, 8)),
        ("resnet18", 128, (512, 8, 8)),
        ("inception_v3", 128, (2048, 7, 7)),
    ],
)
def test_backbone_feature_map_shape(name, size, expected):
    m = build_backbone(name).eval()
    with torch.no_grad():
        out = m(torch.rand(2, 3, size, size))
    assert tuple(out.shape) == (2, *expected)
    assert m.out_channels == expected[0]


def test_standard_inception_stem_still_handles_its_native_resolution():
    m = build_backbone("inception_v3", small_stem=False).eval()
    with torch.no_grad():
        assert tuple(m(torch.rand(1, 3, 299, 299)).shape) == (1, 2048, 8, 8)


def test_unknown_backbone_name_lists_the_choices():
    with pytest.raises(ValueError, match="resnet18"):
        build_backbone("resnet50")


# ------------------------------------------------------------------ policy contract
@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_policy_maps_images_to_bounded_six_dof_actions(name):
    torch.manual_seed(0)
    p = VisuomotorPolicy(arch=name, image_size=64).eval()
    x = torch.rand(3, 3, 64, 64)
    with torch.no_grad():
        A = p.features(x)
        a = p.head(A)
    assert A.shape[:2] == (3, p.backbone.out_channels) and tuple(A.shape[1:]) == p.feature_shape
    assert a.shape == (3, 6) and bool((a.abs() <= 1).all())
    assert torch.equal(a, p(x))


def test_act_accepts_env_uint8_images_and_matches_forward_on_floats():
    torch.manual_seed(0)
    p = VisuomotorPolicy(arch="small_cnn", image_size=64)
    imgs = np.random.default_rng(0).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8)
    x = torch.from_numpy(imgs).permute(0, 3, 1, 2).float() / 255
    p.eval()
    with torch.no_grad():
        ref = p(x).numpy()
    p.train()
    out = p.act(imgs)
    assert p.training  # act restores the mode it found
    assert out.dtype == np.float32 and np.allclose(out, ref, atol=1e-6)
    assert np.allclose(p.act(x.numpy()), ref, atol=1e-6)


def test_wrong_image_size_names_the_expected_size():
    p = VisuomotorPolicy(arch="small_cnn", image_size=64)
    with pytest.raises(PolicyError, match="64x64"):
        p.act(np.zeros((1, 32, 32, 3), np.uint8))
    with pytest.raises(PolicyError, match="64, 64"):
        p.features(torch.zeros(1, 3, 48, 48))


def test_normalization_lives_inside_features():
    p = VisuomotorPolicy(arch="small_cnn", image_size=64, mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25)).eval()
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        assert torch.allclose(p.features(x), p.backbone((x - 0.5) / 0.25))


def test_unknown_policy_config_key_is_an_error():
    with pytest.raises(ValueError, match="dropout"):
        PolicyArch(arch="resnet18", dropout=0.1)


@pytest.mark.parametrize("name", ["small_cnn", "resnet18"])
def test_gradcam_is_differentiable_twice_wrt_the_input_image(name):
    # Grad-CAM on the exposed feature map, then its gradient w.r.t. the image (create_graph=True).
    torch.manual_seed(0)
    p = VisuomotorPolicy(arch=name, image_size=64)
    p.train()
    with torch.no_grad():
        p(torch.rand(8, 3, 64, 64))  # non-trivial BN running statistics
    p.eval()
    x = torch.rand(2, 3, 64, 64, requires_grad=True)
    A = p.features(x)
    a = p.head(A)
    (g,) = torch.autograd.grad(a.norm(dim=1).sum(), A, create_graph=True)
    cam = (g.mean((2, 3), keepdim=True) * A).sum(1)
    (gx,) = torch.autograd.grad(cam.pow(2).sum(), x)
    assert gx.shape == x.shape and torch.isfinite(gx).all() and gx.abs().sum() > 0


def test_policy_follows_the_device_it_is_moved_to():
    p = VisuomotorPolicy(arch="small_cnn", image_size=64).to(torch.device("cpu"))
    assert p.device == torch.device("cpu")
    assert p.act(np.zeros((1, 64, 64, 3), np.uint8)).shape == (1, 6)


def test_torch_policy_passes_the_white_box_check():
    require_white_box(VisuomotorPolicy(arch="small_cnn", image_size=64))
