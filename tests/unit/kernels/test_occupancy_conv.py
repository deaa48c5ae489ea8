"""The LiDAR vehicle half's first layer by the compiled kernel: the float32 convolution's values (float32 sums in
another order) in float32, their bfloat16 rounding in bfloat16, and the encoder taking it on reduced paths only."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from co3sop_nodes import kernels
from co3sop_nodes.kernels import occupancy_conv as occupancy_kernel
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.conv_norm import is_z_outer
from co3sop_nodes.model.path import InferencePath


def scan(shape: tuple[int, ...], seed: int, occupied: float = 0.05) -> torch.Tensor:
    return (torch.from_numpy(np.random.default_rng(seed).random(shape)) < occupied).to(torch.uint8)


@pytest.mark.parametrize("dims, threads", [((16, 12, 8), 1), ((17, 9, 5), 1), ((33, 20, 7), 3)])
def test_the_kernel_gives_the_convolutions_values(dims, threads):
    occupancy = scan((2, 1, *dims), seed=sum(dims))
    torch.manual_seed(0)
    weight, bias = torch.randn(16, 1, 3, 3, 3), torch.randn(16)
    want = F.relu(F.conv3d(occupancy.float(), weight, bias, stride=2, padding=1))  # (2, 16, X/2, Y/2, Z/2)
    got = occupancy_kernel.occupancy_conv_relu(occupancy, weight, bias, torch.float32, threads)
    assert got.shape == want.shape and got.is_contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)  # float32 sums of up to 27 taps, another order
    rounded = occupancy_kernel.occupancy_conv_relu(occupancy.bool(), weight, bias, torch.bfloat16, threads)
    assert rounded.dtype == torch.bfloat16
    torch.testing.assert_close(rounded.float(), got.bfloat16().float(), rtol=0, atol=0)  # nearest even, as torch
    for dtype, same in ((torch.float32, got), (torch.bfloat16, rounded)):  # z-outer: the next layer's layout
        z = occupancy_kernel.occupancy_conv_relu(occupancy, weight, bias, dtype, threads, z_outer=True)
        assert is_z_outer(z) and torch.equal(z, same)
    scale = float(want.max()) / 300  # some values clipped at 255
    quantized = occupancy_kernel.occupancy_conv_relu(occupancy, weight, bias, torch.uint8, threads, True, scale)
    assert quantized.dtype == torch.uint8 and is_z_outer(quantized)
    expected = torch.clamp(torch.round(got / scale), 0, 255)  # rounded half to even, as the kernel
    assert (quantized.float() - expected).abs().max() <= 1  # got's float32 rounding, at a half step
    assert (quantized.float() == expected).float().mean() > 0.999


def test_the_encoder_takes_the_kernel_on_reduced_cpu_paths_only():
    model = build_model(preset("tiny-lidar", custom_grid=((-12.8, -12.8, -3.0), 0.4, (64, 64, 16)))).eval()
    encoder = model.vehicle.encoder
    occupancy = scan((1, 1, 64, 64, 16), seed=1)
    with torch.inference_mode():
        want = encoder(occupancy)  # float32: oneDNN's convolution
        assert not encoder._first_compiled(occupancy)
        for precision in ("bfloat16", "float16"):
            model.use(InferencePath(precision=precision))
            assert encoder._first_compiled(occupancy)
            with encoder.path.autocast():
                got = encoder(occupancy).float()
                first, layer = encoder._first(occupancy).float(), encoder.down[0](occupancy.float()).float()
            torch.testing.assert_close(first, layer, rtol=0.02, atol=0.02)  # bfloat16 / float16 rounding
            assert (got - want).abs().max() <= 0.05 * want.abs().max()  # the whole encoder, against float32
        model.use(InferencePath(precision="bfloat16"))
        original = kernels.ENABLED
        try:
            kernels.ENABLED = False
            assert not encoder._first_compiled(occupancy)  # no compiler, or CO3SOP_NATIVE=0: the layers
        finally:
            kernels.ENABLED = original
