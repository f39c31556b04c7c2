"""``policy.unet_inference``: the matrix-product convolutions and the softplus Mish compute what
torch's layers compute (to float rounding), for the shapes the U-Net uses and others; unsupported
layers are refused or left alone; the copy never touches the original."""

import pytest
import torch
from plugin_helpers import HORIZON, tiny_config
from torch import nn

from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy
from lerobot_formation.policy.unet_inference import (
    Im2colConv1d,
    MatmulConvTranspose1d,
    SoftplusMish,
    inference_copy,
)

TOL = dict(rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("c_in", "c_out", "kernel", "stride", "padding", "length", "bias"),
    [
        (32, 32, 5, 1, 2, 16, True),  # the U-Net's residual convolutions
        (64, 64, 3, 2, 1, 8, True),  # its downsampling
        (2, 32, 1, 1, 0, 16, True),  # its residual projections
        (5, 7, 4, 3, 0, 11, False),  # neither padded nor biased, stride not dividing the length
        (3, 4, 5, 1, 4, 3, True),  # padding wider than the input
    ],
)
def test_im2col_conv1d_matches_conv1d(c_in, c_out, kernel, stride, padding, length, bias):
    torch.manual_seed(0)
    conv = nn.Conv1d(c_in, c_out, kernel, stride, padding, bias=bias)
    x = torch.randn(3, c_in, length)
    torch.testing.assert_close(Im2colConv1d(conv)(x), conv(x), **TOL)


@pytest.mark.parametrize(
    ("c_in", "c_out", "kernel", "stride", "padding", "length", "bias"),
    [
        (64, 64, 4, 2, 1, 4, True),  # the U-Net's upsampling
        (8, 5, 6, 3, 2, 7, True),
        (3, 4, 2, 2, 0, 5, False),
        (4, 6, 3, 1, 1, 9, True),  # stride 1
    ],
)
def test_matmul_conv_transpose1d_matches_conv_transpose1d(c_in, c_out, kernel, stride, padding, length, bias):
    torch.manual_seed(0)
    conv = nn.ConvTranspose1d(c_in, c_out, kernel, stride, padding, bias=bias)
    x = torch.randn(3, c_in, length)
    torch.testing.assert_close(MatmulConvTranspose1d(conv)(x), conv(x), **TOL)


def test_softplus_mish_matches_mish():
    x = torch.linspace(-30.0, 30.0, 2001)
    torch.testing.assert_close(SoftplusMish()(x), nn.Mish()(x), **TOL)


@pytest.mark.parametrize(
    "layer",
    [
        nn.Conv1d(4, 4, 3, groups=2),
        nn.Conv1d(4, 4, 3, dilation=2),
        nn.Conv1d(4, 4, 3, padding=1, padding_mode="reflect"),
        nn.Conv1d(4, 4, 3, padding="same"),
    ],
)
def test_unsupported_convolutions_are_refused_and_kept(layer):
    with pytest.raises(ValueError, match="Im2colConv1d needs"):
        Im2colConv1d(layer)
    assert type(inference_copy(nn.Sequential(layer), matmul_convolutions=True)[0]) is nn.Conv1d


def test_unsupported_transposed_convolution_is_refused_and_kept():
    layer = nn.ConvTranspose1d(4, 4, 3, stride=2)  # kernel not a multiple of the stride
    with pytest.raises(ValueError, match="a kernel that is a multiple of the stride"):
        MatmulConvTranspose1d(layer)
    assert type(inference_copy(nn.Sequential(layer), matmul_convolutions=True)[0]) is nn.ConvTranspose1d


def _unet():
    torch.manual_seed(0)
    return FormationDiffusionPolicy(tiny_config()).diffusion.unet.eval()


@pytest.mark.parametrize("matmul_convolutions", [True, False])
def test_inference_copy_of_the_unet_matches_it_and_leaves_it_alone(matmul_convolutions):
    unet = _unet()
    before = {n: type(m) for n, m in unet.named_modules()}
    state = {k: v.clone() for k, v in unet.state_dict().items()}
    fast = inference_copy(unet, matmul_convolutions)
    kinds = {type(m) for m in fast.modules()}
    assert SoftplusMish in kinds and nn.Mish not in kinds
    assert (Im2colConv1d in kinds) is matmul_convolutions and (nn.Conv1d in kinds) is not matmul_convolutions
    assert (MatmulConvTranspose1d in kinds) is matmul_convolutions
    # the FiLM encoders read the step embedding and the global conditioning
    cond_dim = unet.down_modules[0][0].cond_encoder[1].in_features - unet.config.diffusion_step_embed_dim
    for rows in (1, 10):
        sample = torch.randn(rows, HORIZON, 2)
        timestep = torch.randint(0, 100, (rows,))
        cond = torch.randn(rows, cond_dim)
        with torch.inference_mode():
            torch.testing.assert_close(fast(sample, timestep, cond), unet(sample, timestep, cond), **TOL)
    assert {n: type(m) for n, m in unet.named_modules()} == before
    for k, v in unet.state_dict().items():
        assert torch.equal(v, state[k])
