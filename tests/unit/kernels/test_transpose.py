"""The compiled transposition is a copy of the transposed matrix, bit for bit, whatever its shape and split."""

import pytest
import torch

from co3sop_nodes import kernels
from co3sop_nodes.kernels.transpose import transposed


@pytest.mark.parametrize("shape", [(32, 24576), (48, 4104), (13, 1001), (8, 8), (7, 5), (1, 9)])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("enabled", [True, False], ids=["compiled", "pytorch"])
def test_equals_the_transposed_copy(shape, threads, enabled, monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", enabled)
    x = torch.randn(*shape, generator=torch.Generator().manual_seed(shape[1]))
    got = transposed(x, threads)
    assert got.is_contiguous() and torch.equal(got, x.t())


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
