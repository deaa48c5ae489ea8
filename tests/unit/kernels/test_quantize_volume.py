"""The compiled quantization of a channels-last volume gives PyTorch's uint8 values, in the z-outer layout."""

import pytest
import torch

from co3sop_nodes import kernels
from co3sop_nodes.kernels import quantize_volume


def _volume(channels: int) -> torch.Tensor:
    """(2, C, 8, 6, 5) float32, channels-last in memory: values across the range, past both ends, and halfway cases."""
    gen = torch.Generator().manual_seed(channels)
    x = torch.randn(2, 8, 6, 5, channels, generator=gen) * 3
    x.view(-1)[:64] = (torch.arange(64) - 32) / 16 + 1 / 32  # x * 16 + 128 = n + 0.5: ties, to even
    return x.permute(0, 4, 1, 2, 3)


@pytest.mark.parametrize("channels", [32, 16, 24])
@pytest.mark.parametrize("threads", [1, 2])
def test_equals_pytorchs_quantization(channels, threads):
    x = _volume(channels)
    assert quantize_volume.fits(x)
    got = quantize_volume.quantized_z_outer(x, 1 / 0.0625, 128, threads)
    want = (x.permute(0, 4, 2, 3, 1) * (1 / 0.0625)).add_(128).round_().clamp_(0, 255).to(torch.uint8)
    assert got.is_contiguous() and got.shape == want.shape and torch.equal(got, want)
    assert (want == 0).any() and (want == 255).any() and ((want > 0) & (want < 255)).any()


def test_what_the_kernel_does_not_take(monkeypatch):
    x = _volume(32)
    assert not quantize_volume.fits(x.contiguous())  # channels-first in memory
    assert not quantize_volume.fits(x.double())
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert not quantize_volume.fits(x) and not quantize_volume.available(32)
