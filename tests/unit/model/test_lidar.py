"""The SSCNet-style LiDAR encoder on reduced paths: its dilated layers on z-outer volumes, the float32 layers' values
within bfloat16's rounding; float32 untouched."""

import pytest
import torch

from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.conv_norm import is_z_outer
from co3sop_nodes.model.path import InferencePath


@pytest.mark.parametrize("nz", [24, 12, 20])  # 51.2 m's 6 voxels at 1/4, 25.6 m's 3, one not a multiple of 4
@torch.inference_mode()
def test_on_a_reduced_path_the_dilated_layers_run_on_z_outer_volumes(nz):
    torch.manual_seed(0)
    model = build_model(preset("tiny-lidar", custom_grid=((-12.8, -12.8, -3.0), 0.4, (64, 64, nz)))).eval()
    enc = model.vehicle.encoder
    for layer in (*enc.down, *enc.dilated):  # norms that are not the identity
        layer[1].running_mean.normal_()
        layer[1].running_var.uniform_(0.5, 2.0)
    seen = []
    for layer in enc.dilated:
        layer.register_forward_pre_hook(lambda _, args: seen.append(is_z_outer(args[0])))
    occupancy = (torch.rand(2, 1, 64, 64, nz, generator=torch.Generator().manual_seed(nz)) < 0.1).to(torch.uint8)

    want = enc(occupancy)  # float32 reference
    assert seen == [False] * 3
    model.use(InferencePath(precision="bfloat16"))
    with enc.path.autocast():
        got = enc(occupancy)
    assert seen[3:] == [True] * 3
    assert got.shape == want.shape
    assert torch.allclose(got.float(), want, atol=0.05 * want.abs().max())  # bfloat16 rounding through 6 layers
    model.use(InferencePath())
    assert torch.equal(enc(occupancy), want)  # float32: the layers as they are, bit for bit
