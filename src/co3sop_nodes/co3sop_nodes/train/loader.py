"""The samples of each training step, read ahead by DataLoader worker processes while the model trains.

Step k's samples are fixed by the run's order (train.trainer.sample_order) and the process's share of the
global batch, so a run reads exactly what it would read in one process, whatever the workers, the torchrun
world or the resumed step: item k of `StepSamples` is this process's samples of step `start + k`, delivered in
step order. A sample that cannot be read comes back as its DatasetError (raised in the training process,
naming the file), not as a worker's traceback.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.train.dataset import OccupancyDataset, Sample


class StepSamples(torch.utils.data.Dataset):
    def __init__(
        self,
        dataset: OccupancyDataset,
        order: np.ndarray,
        start: int,
        steps: int,
        batch: int,
        rank: int,
        share: int,
        prepare: Callable[[OccupancyDataset, int], Sample],
    ):
        self.dataset, self.order, self.start, self.steps = dataset, order, start, steps
        self.batch, self.rank, self.share, self.prepare = batch, rank, share, prepare

    def places(self, step: int) -> range:
        """Positions in the run's order of this process's samples of `step`."""
        first = step * self.batch + self.rank * self.share
        return range(first, first + self.share)

    def __len__(self) -> int:
        return self.steps - self.start

    def __getitem__(self, k: int) -> list[Sample] | DatasetError:
        try:
            return [self.prepare(self.dataset, int(self.order[p])) for p in self.places(self.start + k)]
        except DatasetError as exc:
            return exc


def step_loader(
    samples: StepSamples, workers: int, device: torch.device = torch.device("cpu")
) -> torch.utils.data.DataLoader:
    """Steps in order, read by `workers` processes ahead of the step that trains on `device` (0: in this process,
    in turn); for a CUDA step their arrays are handed over in page-locked memory (Sample.pin_memory)."""
    return torch.utils.data.DataLoader(
        samples,
        batch_size=None,
        shuffle=False,
        num_workers=workers,
        collate_fn=_unchanged,
        prefetch_factor=2 if workers else None,
        pin_memory=device.type == "cuda",
    )


def _unchanged(item):
    return item
