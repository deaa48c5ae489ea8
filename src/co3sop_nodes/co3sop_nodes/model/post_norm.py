"""The parts a post-norm transformer layer (BEVFormer's, SurroundOcc's) puts around its attention: the residual sum
with its layer norm, and the feed-forward network.

Both are the PyTorch layers they subclass (same parameters, same checkpoints); on a path with compiled kernels
(inference on the CPU) the sum and the norm are one compiled pass and the feed-forward's products oneDNN's with the
ReLU fused (`InferencePath.linear`), in the path's precision as autocast would compute them.
"""

from __future__ import annotations

import torch
from torch import nn

from co3sop_nodes.kernels import layer_norm as layer_norm_kernel
from co3sop_nodes.model.path import InferencePath


class AddNorm(nn.LayerNorm):
    """LayerNorm(x + y): the residual sum of a layer's input x and a sublayer's output y, normalised."""

    def __init__(self, dims: int):
        super().__init__(dims)
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """x, y (..., C) -> (..., C), float32 (autocast's layer norm is float32 as well)."""
        if self.path.kernels(x) and layer_norm_kernel.fits(x, y):
            return layer_norm_kernel.add_layer_norm(x, y, self.weight, self.bias, self.eps, torch.get_num_threads())
        return super().forward(x + y)


class FeedForward(nn.Sequential):
    """Linear, ReLU, Linear: C -> hidden -> C."""

    def __init__(self, dims: int, hidden: int):
        super().__init__(nn.Linear(dims, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, dims))
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., C) -> (..., C)."""
        first, _, second = self
        if not self.path.kernels(x):
            return super().forward(x)
        if self.path.reduced:  # as autocast would cast x for the product
            x = x.to(self.path.float_dtype)
        hidden = self.path.linear(x, first.weight, first.bias, relu=True)
        return self.path.linear(hidden, second.weight, second.bias)
