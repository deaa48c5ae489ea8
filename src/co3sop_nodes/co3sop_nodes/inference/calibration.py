"""Int8 calibration: the range of each activation an int8 path quantizes, measured on scans (ROS-free).

An activation's range is the clipping point that minimises its mean squared quantization error over every scan
measured: below it, uint8 steps of range / 255 (a uniform rounding error of step^2 / 12 a value), above it the
distance to the clip; a signed activation (the head's input, quantized around a zero point of 128) by its
magnitude, in steps of range / 127.5. The head's activations are measured on each scan's own features: the fused
features it takes in the graph add the neighbours' to those. Exact zeros (half of a ReLU's outputs) quantize
exactly and count for nothing. The values are binned in a histogram that doubles its span when a value exceeds it,
so any number of scans takes the same memory. Calibrate on `train` or `validate`, never on `test`; the checkpoint
then carries the ranges (`checkpoint.save_calibrated`) and names the data in its history.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.model.co3sop import Co3SOP
from co3sop_nodes.model.path import InferencePath

BINS = 4096


class ActivationHistogram:
    """The nonzero values of one activation, binned over [0, span) (span doubling as needed)."""

    def __init__(self):
        self.counts = torch.zeros(BINS, dtype=torch.float64)
        self.span = 0.0

    def add(self, values: torch.Tensor) -> None:
        values = values.detach().flatten().float()
        values = values[values > 0]
        if values.numel() == 0:
            return
        top = float(values.max())
        if self.span == 0.0:
            self.span = top * (1 + 1e-6)
        while top >= self.span:  # merge pairs of bins: the same counts over twice the span
            self.counts = torch.cat([self.counts.view(-1, 2).sum(1), torch.zeros(BINS // 2, dtype=torch.float64)])
            self.span *= 2
        bins = (values * (BINS / self.span)).long().clamp_(max=BINS - 1)
        self.counts += torch.bincount(bins, minlength=BINS).double()

    def best_range(self, steps: float = 255.0) -> float:
        """The clip (a bin's upper edge) with the least total squared error when [0, clip] is quantized in `steps`
        steps; 0 where no nonzero value was seen."""
        if self.counts.sum() == 0:
            return 0.0
        width = self.span / BINS
        edges = torch.arange(1, BINS + 1, dtype=torch.float64) * width  # (BINS,) clip at each bin's upper edge
        centres = edges - width / 2
        n, nv, nvv = self.counts, self.counts * centres, self.counts * centres**2
        below = torch.cumsum(n, 0)  # values at or under each clip
        clipped = _above(nvv) - 2 * edges * _above(nv) + edges**2 * _above(n)  # sum of (v - clip)^2 above each clip
        error = below * (edges / steps) ** 2 / 12 + clipped
        return float(edges[int(torch.argmin(error))])


def _above(t: torch.Tensor) -> torch.Tensor:
    """Each bin's sum of t over the bins above it."""
    return t.flip(0).cumsum(0).flip(0) - t


@torch.no_grad()
def calibrate(model: Co3SOP, scans: Iterable[torch.Tensor]) -> dict[str, float]:
    """The range of each of `model.int8_activations()` over `scans`, each (1, 1, X, Y, Z) 0/1 occupancy on the
    model's grid, from the float32 forward (the head's on each scan's own features); the model is left on the path
    it was on."""
    names = model.int8_activations()
    if not names:
        raise Co3sopError(f"{model.cfg.name}: has no int8 layers to calibrate")
    previous = model.path
    model.use(InferencePath(str(previous.torch_device)))  # the float32 reference path
    histograms = [ActivationHistogram() for _ in names]
    try:
        for occupancy in scans:
            for histogram, values in zip(histograms, model.int8_values(occupancy)):
                histogram.add(values)
    finally:
        model.use(previous)
    ranges = {name: h.best_range(steps) for name, h, steps in zip(names, histograms, model.int8_steps())}
    empty = [name for name, r in ranges.items() if r <= 0]
    if empty:
        raise Co3sopError(f"calibration: no nonzero value of {', '.join(empty)} in the scans given")
    return ranges
