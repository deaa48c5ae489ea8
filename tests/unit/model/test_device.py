"""--device names checked against what torch can use (co3sop_nodes.model.path.resolve_device)."""

from __future__ import annotations

import pytest
import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.model.path import resolve_device


def test_auto_and_cpu():
    assert resolve_device("cpu", "--device") == torch.device("cpu")
    assert resolve_device("auto", "--device") == torch.device("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("name, message", [("gpu", "not a device"), ("meta", "only cpu and cuda"), ("cuda:99", "cuda")])
def test_bad_names_are_explained(name, message):
    with pytest.raises(Co3sopError, match=message):
        resolve_device(name, "--device")


def test_cuda_only_where_torch_sees_a_gpu():
    if torch.cuda.is_available():
        assert resolve_device("cuda", "--device").type == "cuda"
    else:
        with pytest.raises(Co3sopError, match="sees no CUDA GPU"):
            resolve_device("cuda", "--device")
