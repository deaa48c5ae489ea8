"""A post-norm layer's sum and norm and its feed-forward: their inference paths equal the layers they subclass."""

import pytest
import torch
from torch import nn

from co3sop_nodes.kernels import layer_norm as layer_norm_kernel
from co3sop_nodes.model.path import InferencePath
from co3sop_nodes.model.post_norm import AddNorm, FeedForward


def _randomised(module: nn.Module) -> nn.Module:
    torch.manual_seed(0)
    with torch.no_grad():
        for param in module.parameters():
            param.normal_(0, 0.5)
    return module.eval()


def test_add_norm_at_inference_is_the_compiled_pass_and_equals_the_layer_norm_of_the_sum(monkeypatch):
    norm = _randomised(AddNorm(32))
    x, y = torch.randn(1, 1001, 32) * 2, torch.randn(1, 1001, 32).bfloat16()
    calls = []
    compiled = layer_norm_kernel.add_layer_norm
    monkeypatch.setattr(layer_norm_kernel, "add_layer_norm", lambda *a: calls.append(1) or compiled(*a))
    with torch.no_grad():
        got = norm(x, y)
    want = nn.functional.layer_norm(x + y.float(), (32,), norm.weight, norm.bias, norm.eps).detach()
    assert calls == [1]
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    with torch.enable_grad():  # training: PyTorch's layers
        assert torch.equal(norm(x, y).detach(), want)
    assert calls == [1]


def test_the_layers_keep_their_checkpoints_parameter_names():
    assert set(AddNorm(32).state_dict()) == set(nn.LayerNorm(32).state_dict())
    old = nn.Sequential(nn.Linear(32, 64), nn.ReLU(inplace=True), nn.Linear(64, 32))
    assert set(FeedForward(32, 64).state_dict()) == set(old.state_dict())


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_the_feed_forward_at_inference_equals_the_sequential_under_autocast(precision):
    """Bit for bit: in bfloat16 oneDNN's product with the ReLU fused is autocast's product (InferencePath.linear;
    where oneDNN computes no bfloat16, autocast's product itself)."""
    ffn = _randomised(FeedForward(32, 64))
    x = torch.randn(1, 777, 32)
    path = InferencePath("cpu", precision)
    with torch.no_grad(), path.autocast():
        want = nn.Sequential.forward(ffn, x)
        ffn.path = path
        got = ffn(x)
    assert got.dtype == want.dtype and torch.equal(got, want)
