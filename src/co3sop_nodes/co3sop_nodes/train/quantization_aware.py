"""Quantization-aware fine-tuning of a model's int8 layers, distilled from its float layers (ROS-free): an
SSCNet-style encoder's, then a convolutional head's.

Rounded to a calibration's 8-bit steps after the fact, the encoder's four int8 layers give features whose errors are
spread over every activation like noise (no single layer or range dominates), which moves labels where float32's
sit near a tie. Fine-tuning those layers' folded weights and biases through the int8 arithmetic (weights and
activations rounded as the int8 path rounds them, the gradient straight through the rounding, `int8_emulated`)
toward the float encoder's own features makes the int8 features closer to them: the loss is each channel's squared
error over its variance on the first scans, plus the divergence of the head's coarsest class scores (its 1/4 stage,
float32, frozen) on the int8 features from those on the float ones, which weighs each feature error by how much it
moves a class (vehicle halves in int8, the ego in bfloat16, on `validate`: labels equal to float32's on 99.63 % of
voxels after fine-tuning, 99.45 % before).

Most of the labels an int8 ego then still moves are moved by the int8 vehicles' features, not by its own int8
layers (on `validate`, the float head on those features moves several times the labels the int8 head moves on float
features). So the head's four int8 layers learn on the features an
int8 ego takes (`head_example`: int8 vehicles, the ego's fusion), toward the float32 model's full-resolution class
scores on the float32 features: the loss is their divergence per voxel, over the octants of a share of the voxels
at 1/2 drawn each step (`PARENT_SHARE`). They then undo part of the vehicles' error too (results.md gives `test`).

The float weights stay as they were, so float32 and bfloat16 compute as before; only an int8 path takes the
fine-tuned ones. No labels are used: the float model is the teacher. Fine-tune on `train`, never on `test`.

The state (weights, optimiser, step) is written every `SAVE_EVERY` steps, so an interrupted run resumes where it
stopped and ends with the weights an uninterrupted one ends with; a finished run's state is kept (the command that
ran it removes it once its checkpoint is written), so resuming after the end takes no step.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.inference.inputs import to_batch
from co3sop_nodes.model.co3sop import Co3SOP
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.lidar import SSCNetEncoder
from co3sop_nodes.train.dataset import Sample

SAVE_EVERY = 100
# scans whose float features give each channel's variance, the loss's normalisation
VARIANCE_SCANS = 32
# the share of the voxels at 1/2 whose octants a head's step weighs (drawn anew each step): the full resolution is
# most of the step's cost, and every voxel is drawn in turn
PARENT_SHARE = 1 / 8


def fine_tune_int8(
    model: Co3SOP,
    prefix: str,
    example: Callable[[int], Any],
    examples: int,
    steps: int,
    lr: float = 1e-4,
    seed: int = 0,
    state: Path | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> dict[str, torch.Tensor]:
    """Fine-tune the int8 layers of the calibrated module `prefix` of `model.int8_modules` for `steps` steps of one
    example each (`example(i)`, i in range(examples)), Adam at `lr`, the examples in an order drawn from `seed`;
    resumed from and saved to `state` where given (kept when done: a run resumed after its end takes no step). An
    example of "vehicle.encoder" is a scan (1, 1, X, Y, Z) occupancy; of "ego.head" the features the int8 head
    takes and those the float head takes (`head_example`). Sets the module's int8 weights and returns them
    (`Co3SOP.int8_tuned_weights`' of the module). `on_step(step, loss)` after each step."""
    module = model.int8_modules.get(prefix)
    if module is None or not module.calibrated:
        raise Co3sopError(
            f"{model.cfg.name}: int8 fine-tuning of {prefix} needs it calibrated (int8 modules: "
            f"{', '.join(model.int8_modules) or 'none'})"
        )
    if examples < 1 or steps < 1:
        raise Co3sopError(f"int8 fine-tuning needs examples and steps (got {examples} examples, {steps} steps)")
    model.eval()
    frozen = [p for p in model.parameters() if p.requires_grad]
    for p in frozen:  # the float model is the teacher: no gradient of its own
        p.requires_grad_(False)
    try:
        _fine_tune(model, prefix, module, example, examples, steps, lr, seed, state, on_step)
    finally:
        for p in frozen:
            p.requires_grad_(True)
    return {name: t for name, t in model.int8_tuned_weights().items() if name.startswith(f"{prefix}.")}


def _fine_tune(model, prefix, module, example, examples, steps, lr, seed, state, on_step) -> None:
    # from the float layers, folded, whatever int8 weights the module has: a run's result is its settings' alone
    params = [torch.nn.Parameter(t.detach().float().clone()) for _, w, b in module.folded_int8_layers() for t in (w, b)]
    optimizer = torch.optim.Adam(params, lr=lr)
    order = _order(examples, steps, seed)
    setup = {"module": prefix, "examples": examples, "steps": steps, "lr": lr, "seed": seed}
    variance, start = None, 0
    if state is not None and state.is_file():
        saved = torch.load(state, map_location="cpu", weights_only=True)
        if saved["setup"] != setup:
            raise Co3sopError(f"{state}: a fine-tuning state of other settings ({saved['setup']}); remove it")
        with torch.no_grad():
            for p, t in zip(params, saved["params"]):
                p.copy_(t)
        optimizer.load_state_dict(saved["optimizer"])
        variance, start = saved["variance"], saved["step"]
    if variance is None and isinstance(module, SSCNetEncoder):
        with torch.no_grad():
            feats = [module(example(int(i))) for i in order[:VARIANCE_SCANS]]
            variance = torch.cat(feats).transpose(0, 1).flatten(1).var(dim=1).clamp_min(1e-12)  # (C,)
    head = model.ego.head if isinstance(model.ego.head, OccupancyHead) else None
    for step in range(start, steps):
        layers = list(zip(params[0::2], params[1::2]))
        if isinstance(module, SSCNetEncoder):
            loss = _encoder_loss(module, head, example(int(order[step])), layers, variance)
        else:
            got, want = example(int(order[step]))
            voxels = want[0, 0].numel() * 8  # at 1/2
            loss = _head_loss(module, got, want, layers, _parents(step, seed, voxels))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if on_step is not None:
            on_step(step, loss.item())
        if state is not None and ((step + 1) % SAVE_EVERY == 0 or step + 1 == steps):
            _save(state, params, optimizer, variance, step + 1, setup)
    module.set_int8_weights(
        {n: (w.detach(), b.detach()) for n, w, b in zip(module.INT8_LAYERS, params[0::2], params[1::2])}
    )


def _encoder_loss(encoder: SSCNetEncoder, head: OccupancyHead | None, occupancy, layers, variance) -> torch.Tensor:
    """Each channel's squared feature error over its variance, plus the divergence of the head's coarsest class
    scores on the int8 features from those on the float ones."""
    with torch.no_grad():
        want = encoder(occupancy.float())  # (1, C, X/4, Y/4, Z/4) float32
    got = encoder.int8_emulated(occupancy, layers)
    loss = ((got - want) ** 2).mean(dim=(0, 2, 3, 4)).div(variance).mean()
    if head is None:
        return loss
    with torch.no_grad():
        teacher = _coarse_scores(head, want)
    return loss + F.kl_div(_coarse_scores(head, got), teacher, log_target=True, reduction="none").sum(1).mean()


def _head_loss(head: OccupancyHead, got: torch.Tensor, want: torch.Tensor, layers, parents) -> torch.Tensor:
    """The divergence of the full-resolution class scores of the int8 layers on `got` (the features the int8 head
    takes) from the float head's on `want`, per voxel, over the octants of the voxels `parents` (1, N) at 1/2."""
    with torch.no_grad():
        teacher = F.log_softmax(head.octant_logits(head.coarse(want)[1], parents), dim=2)  # (1, 8, K, N)
    student = F.log_softmax(head.octant_logits(head.int8_emulated(got, layers), parents), dim=2)
    return F.kl_div(student, teacher, log_target=True, reduction="none").sum(2).mean()


def _parents(step: int, seed: int, voxels: int) -> torch.Tensor:
    """(1, N) the voxels at 1/2 whose octants step `step`'s head loss weighs: a share PARENT_SHARE drawn from
    (seed, step), so that a resumed run draws the same."""
    generator = torch.Generator().manual_seed(int(np.random.default_rng([seed, step]).integers(2**62)))
    return torch.randperm(voxels, generator=generator)[: max(1, int(voxels * PARENT_SHARE))][None]


@torch.no_grad()
def head_example(model: Co3SOP, deployed: Co3SOP, sample: Sample) -> tuple[torch.Tensor, torch.Tensor]:
    """A sample's fused features (1, C, X/4, Y/4, Z/4) as an int8 ego takes them (`deployed`: a copy of the model on
    its int8 path, whose vehicles and fusion run as in the graph) and as the float32 model's head does."""

    def fused(m: Co3SOP) -> torch.Tensor:
        outs = [m.vehicle(**to_batch(a.inputs)) for a in (sample.ego, *sample.others)]
        rel = torch.from_numpy(sample.neighbour_from_ego).float()[None] if sample.others else None
        return m.ego.fuse(outs[0], outs[1:], rel).float()

    return fused(deployed), fused(model)


def _coarse_scores(head: OccupancyHead, features: torch.Tensor) -> torch.Tensor:
    """(1, K, X/4, Y/4, Z/4) the head's log class probabilities at its coarsest stage."""
    return F.log_softmax(head.classify[0](head.stage0(features)), dim=1)


def _order(scans: int, steps: int, seed: int) -> np.ndarray:
    """Each step's scan: one permutation of the scans per pass, pass e drawn from (seed, e)."""
    passes = -(-steps // scans)
    return np.concatenate([np.random.default_rng([seed, e]).permutation(scans) for e in range(passes)])[:steps]


def _save(path: Path, params, optimizer, variance, step: int, setup: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(
        {
            "params": [p.detach() for p in params],
            "optimizer": optimizer.state_dict(),
            "variance": variance,
            "step": step,
            "setup": setup,
        },
        tmp,
    )
    tmp.replace(path)
