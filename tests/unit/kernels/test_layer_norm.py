"""The compiled residual sum and layer norm equals PyTorch's layer norm of the sum, in each precision it reads."""

import pytest
import torch
import torch.nn.functional as F

from co3sop_nodes import kernels
from co3sop_nodes.kernels import layer_norm


@pytest.mark.parametrize("channels", [32, 48, 64])
@pytest.mark.parametrize(
    "x_dtype, y_dtype",
    [
        (torch.float32, torch.float32),
        (torch.float32, torch.bfloat16),
        (torch.bfloat16, torch.float32),
        (torch.bfloat16, torch.bfloat16),
    ],
)
@pytest.mark.parametrize("threads", [1, 2])
def test_equals_the_layer_norm_of_the_sum(channels, x_dtype, y_dtype, threads):
    gen = torch.Generator().manual_seed(channels)
    rows = 4099  # blocks of 8 rows and a tail of 3; two threads' shares
    x = (torch.randn(1, rows, channels, generator=gen) * 3 + 1).to(x_dtype)
    y = torch.randn(1, rows, channels, generator=gen).to(y_dtype)
    weight, bias = torch.randn(channels, generator=gen), torch.randn(channels, generator=gen)
    assert layer_norm.fits(x, y)
    got = layer_norm.add_layer_norm(x, y, weight, bias, 1e-5, threads)
    want = F.layer_norm(x.float() + y.float(), (channels,), weight, bias, 1e-5)
    assert got.dtype == torch.float32 and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_rows_of_one_value_normalise_to_the_bias():
    """A row whose values are all equal has no variance: its output is the bias, as PyTorch's (eps keeps it finite)."""
    x, y = torch.full((9, 32), 2.5), torch.zeros(9, 32)
    weight, bias = torch.randn(32), torch.randn(32)
    got = layer_norm.add_layer_norm(x, y, weight, bias, 1e-5, 1)
    torch.testing.assert_close(got, bias.expand(9, 32), rtol=0, atol=1e-6)


def test_what_the_kernel_does_not_take(monkeypatch):
    x = torch.randn(10, 32)
    assert layer_norm.fits(x, x.bfloat16()) and layer_norm.available(32)
    assert not layer_norm.fits(torch.randn(10, 12), torch.randn(10, 12))  # rows of whole vectors of 8 only
    assert not layer_norm.available(12)
    assert not layer_norm.fits(x, torch.randn(10, 1))  # a broadcast, not a residual sum
    assert not layer_norm.fits(x, x.half())
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert not layer_norm.fits(x, x) and not layer_norm.available(32)
