"""The LiDAR vehicle half's dilated layers as 2D convolutions over z's phases: the 3D layer's values (float32 sums in
another order), taken on reduced CPU paths over thin volumes only."""

import pytest
import torch

from co3sop_nodes.model import lidar
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.lidar import SSCNetEncoder, phase_conv_relu, thin
from co3sop_nodes.model.path import InferencePath


def encoder() -> SSCNetEncoder:
    torch.manual_seed(0)
    enc = SSCNetEncoder(32, 32).eval()
    with torch.no_grad():
        for p in enc.parameters():
            p.normal_(0, 0.3)
        for layer in enc.dilated:  # a norm that is not the identity
            layer[1].running_mean.normal_()
            layer[1].running_var.uniform_(0.5, 2.0)
    return enc


@pytest.mark.parametrize("nz", [6, 4, 5, 3])  # 51.2 m and 76.8 m at 1/4; z padded to a multiple of the dilation
@torch.no_grad()
def test_the_phases_give_the_dilated_layers_values(nz):
    enc = encoder()
    x = torch.randn(2, 32, 11, 9, nz).relu()
    for layer in enc.dilated:  # dilations 2, 2, 3
        assert thin(layer, x)
        want, got = layer(x), phase_conv_relu(layer, x)
        assert got.shape == want.shape and got.is_contiguous(memory_format=torch.channels_last_3d)
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


def test_a_volume_with_more_than_three_steps_per_phase_is_not_thin():
    layer = encoder().dilated[0]  # dilation 2
    assert not thin(layer, torch.zeros(1, 32, 4, 4, 12))  # 25.6 m: 12 voxels at 1/4, 6 steps of 2
    assert thin(layer, torch.zeros(1, 32, 4, 4, 6))


@pytest.mark.parametrize("precision, calls", [("float32", 0), ("bfloat16", 3)])
def test_the_encoder_takes_the_phases_on_reduced_paths_only(precision, calls, monkeypatch):
    model = build_model(preset("tiny-lidar", custom_grid=((-12.8, -12.8, -3.0), 0.4, (64, 64, 24)))).eval()
    model.use(InferencePath(precision=precision))
    taken = []
    monkeypatch.setattr(lidar, "phase_conv_relu", lambda *a: taken.append(1) or phase_conv_relu(*a))
    occupancy = (torch.rand(1, 1, 64, 64, 24, generator=torch.Generator().manual_seed(3)) < 0.05).to(torch.uint8)
    with torch.inference_mode():
        model.vehicle(occupancy=occupancy)
    assert len(taken) == calls
    model.vehicle(occupancy=occupancy)  # with gradients, as in training: the 3D layers
    assert len(taken) == calls
