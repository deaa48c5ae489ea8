"""The compiled transposition is a copy of the transposed matrix, bit for bit, whatever its shape and split; from
bfloat16, the copy widened to float32."""

import pytest
import torch

from co3sop_nodes import kernels
from co3sop_nodes.kernels.transpose import channels_first_float32, transposed


@pytest.mark.parametrize("shape", [(32, 24576), (48, 4104), (13, 1001), (8, 8), (7, 5), (1, 9)])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("enabled", [True, False], ids=["compiled", "pytorch"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_equals_the_transposed_copy(shape, threads, enabled, dtype, monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", enabled)
    x = torch.randn(*shape, generator=torch.Generator().manual_seed(shape[1])).to(dtype)
    got = transposed(x, threads, dtype=torch.float32)
    assert got.is_contiguous() and got.dtype == torch.float32 and torch.equal(got, x.t().float())


def test_rows_of_a_wider_matrix_and_an_out_tensor():
    """A matrix whose rows are a longer array's (row stride above its width), written into a given tensor."""
    wide = torch.randn(16, 300)
    x, out = wide[:, 10:270], torch.full((260, 16), float("nan"))
    assert transposed(x, 2, out) is out and torch.equal(out, x.t())
    with pytest.raises(ValueError, match="out"):
        transposed(x, 1, torch.empty(16, 260))


def test_what_takes_a_gradient_keeps_it():
    x = torch.randn(16, 40, requires_grad=True)
    transposed(x).sum().backward()
    assert torch.equal(x.grad, torch.ones(16, 40))


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("layout", ["channels-last", "contiguous", "z-outer"])
def test_a_volume_in_any_layout_becomes_contiguous_float32(dtype, layout):
    """A reduced path's output (channels-last, or any other layout: PyTorch's copy) as the vehicle hands it on."""
    x = torch.randn(2, 12, 5, 6, 7).to(dtype)
    stored = {
        "channels-last": x.contiguous(memory_format=torch.channels_last_3d),
        "contiguous": x.contiguous(),
        "z-outer": x.permute(0, 4, 1, 2, 3).contiguous().permute(0, 2, 3, 4, 1),
    }[layout]
    got = channels_first_float32(stored)
    assert got.is_contiguous() and got.dtype == torch.float32 and torch.equal(got, x.float())
    if dtype == torch.float32 and layout == "contiguous":
        assert got is stored
