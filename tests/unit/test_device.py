"""Unit tests for co3sop_nodes.cli.device: --device names checked against what torch can use."""

from __future__ import annotations

import pytest
import torch

from co3sop_nodes.cli.device import select_device
from co3sop_nodes.common.errors import Co3sopError


def test_auto_and_cpu():
    assert select_device("cpu") == torch.device("cpu")
    assert select_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("name, message", [("gpu", "not a device"), ("meta", "only cpu and cuda"), ("cuda:99", "cuda")])
def test_bad_names_are_explained(name, message):
    with pytest.raises(Co3sopError, match=message):
        select_device(name)


def test_cuda_only_where_torch_sees_a_gpu():
    if torch.cuda.is_available():
        assert select_device("cuda").type == "cuda"
    else:
        with pytest.raises(Co3sopError, match="sees no CUDA GPU"):
            select_device("cuda")
