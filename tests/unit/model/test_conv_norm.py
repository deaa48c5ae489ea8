"""Batch norm folded into its convolution on reduced-precision paths; float32 and training untouched."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from co3sop_nodes.model import conv_norm
from co3sop_nodes.model import path as path_module
from co3sop_nodes.model.conv_norm import ConvNorm, folded, is_z_outer, z_outer
from co3sop_nodes.model.path import InferencePath


def layers() -> list[nn.Module]:
    torch.manual_seed(0)
    conv, norm = nn.Conv3d(4, 8, 3, padding=1, bias=True), nn.BatchNorm3d(8)
    with torch.no_grad():  # statistics and affine parameters far from the identity
        norm.running_mean.normal_(0, 1)
        norm.running_var.uniform_(0.5, 2.0)
        norm.weight.normal_(1, 0.5)
        norm.bias.normal_(0, 0.5)
    return [conv, norm, nn.ReLU(inplace=True)]


@torch.no_grad()
def test_float32_and_training_run_the_layers_as_they_are():
    plain = nn.Sequential(*layers()).eval()
    folded = ConvNorm(*layers()).eval()
    assert folded.state_dict().keys() == plain.state_dict().keys()
    x = torch.randn(2, 4, 6, 5, 4)
    assert torch.equal(folded(x), plain(x))  # float32: bit for bit
    folded.train(), plain.train()
    assert torch.equal(folded(x), plain(x))


@torch.no_grad()
def test_on_a_reduced_path_the_norm_is_folded_into_the_convolution():
    folded = ConvNorm(*layers()).eval()
    x = torch.randn(2, 4, 6, 5, 4)
    want = nn.Sequential(*folded)(x)  # float32 reference
    calls = []
    folded[1].register_forward_hook(lambda *_: calls.append(1))
    folded.path = InferencePath(precision="bfloat16")
    with folded.path.autocast():
        got = folded(x)
    assert got.dtype == torch.bfloat16 and not calls  # the norm never ran: it is in the convolution
    assert torch.allclose(got.float(), want, atol=0.05 * want.abs().max())  # bfloat16 rounding of weights and inputs
    folded.path = InferencePath()
    assert torch.equal(folded(x), want)  # back to float32: nothing was stored


@torch.no_grad()
def test_a_z_outer_volume_stays_z_outer_through_a_folded_convolution():
    """The same convolution on the (B, C, Z, X, Y) views, whatever its per-axis stride, padding and dilation."""
    torch.manual_seed(1)
    conv, norm = nn.Conv3d(4, 6, (3, 3, 3), (2, 1, 1), (1, 0, 2), (1, 1, 2)), nn.BatchNorm3d(6).eval()
    x = torch.randn(2, 4, 9, 7, 6)
    want = folded(conv, norm, x)  # (B, C, X', Y', Z')
    got = folded(conv, norm, z_outer(x))
    assert is_z_outer(z_outer(x)) and not is_z_outer(x) and is_z_outer(got)
    assert got.shape == want.shape
    assert torch.allclose(got, want, atol=1e-5)  # float32: another summation order


@pytest.mark.skipif(not path_module.onednn(torch.bfloat16), reason="oneDNN has no bfloat16 convolution here")
@pytest.mark.parametrize("layout", ["z-outer", "channels-last", "2d"])
@torch.no_grad()
def test_the_relu_fused_into_the_convolution_gives_the_same_values(layout, monkeypatch):
    """On the CPU the folded convolution and its ReLU run as one oneDNN primitive: bit for bit the convolution
    then the ReLU, in any layout, with per-axis strides and dilations."""
    torch.manual_seed(2)
    if layout == "2d":
        conv, norm, x = nn.Conv2d(8, 16, 3, (2, 1), (1, 2), (1, 2)), nn.BatchNorm2d(16), torch.randn(2, 8, 12, 10)
    else:
        conv, norm = nn.Conv3d(8, 16, 3, (2, 1, 1), (1, 0, 2), (1, 1, 2)), nn.BatchNorm3d(16)
        x = torch.randn(2, 8, 9, 7, 6)
        x = z_outer(x) if layout == "z-outer" else x.contiguous(memory_format=torch.channels_last_3d)
    with torch.no_grad():
        norm.running_mean.normal_(0, 1)
    block = ConvNorm(conv, norm.eval(), nn.ReLU(inplace=True)).eval()
    block.path = InferencePath(precision="bfloat16")
    calls = []
    fused = torch.ops.mkldnn._convolution_pointwise
    monkeypatch.setattr(torch.ops.mkldnn, "_convolution_pointwise", lambda *a: calls.append(1) or fused(*a))
    with block.path.autocast():
        got = block(x)
        monkeypatch.setattr(conv_norm, "onednn", lambda dtype: False)
        want = block(x)
    assert calls == [1] and got.dtype == want.dtype == torch.bfloat16
    assert torch.equal(got, want) and (want > 0).any() and (want == 0).any()
    assert got.stride() == want.stride()  # the same layout out
