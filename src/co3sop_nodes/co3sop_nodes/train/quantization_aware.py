"""Quantization-aware fine-tuning of an SSCNet-style encoder's int8 layers, distilled from its float layers (ROS-free).

Rounded to a calibration's 8-bit steps after the fact, the encoder's four int8 layers give features whose errors are
spread over every activation like noise (no single layer or range dominates), which moves labels where float32's
sit near a tie. Fine-tuning those layers' folded weights and biases through the int8 arithmetic (weights and
activations rounded as the int8 path rounds them, the gradient straight through the rounding,
`SSCNetEncoder.int8_emulated`) toward the float encoder's own features makes the int8 features closer to them: the
loss is each channel's squared error over its variance on the first scans, plus, for a convolutional head, the
divergence of the head's coarsest class scores (its 1/4 stage, float32, frozen) on the int8 features from those on
the float ones, which weighs each feature error by how much it moves a class (vehicle halves in int8, the ego in
bfloat16, on `validate`: labels equal to float32's on 99.63 % of voxels after fine-tuning, 99.45 % before; results.md
gives `test`). The float weights stay as they were, so float32 and bfloat16 compute as before; only an int8 path takes
the fine-tuned ones. No labels are used: the float
model is the teacher. Fine-tune on `train`, never on `test`.

The state (weights, optimiser, step) is written every `SAVE_EVERY` steps, so an interrupted run resumes where it
stopped and ends with the weights an uninterrupted one ends with.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.model.co3sop import Co3SOP
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.lidar import SSCNetEncoder

SAVE_EVERY = 100
# scans whose float features give each channel's variance, the loss's normalisation
VARIANCE_SCANS = 32


def fine_tune_int8(
    model: Co3SOP,
    scan: Callable[[int], torch.Tensor],
    scans: int,
    steps: int,
    lr: float = 1e-4,
    seed: int = 0,
    state: Path | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> dict[str, torch.Tensor]:
    """Fine-tune a calibrated SSCNet-style encoder's int8 layers for `steps` steps of one scan each (`scan(i)`, i in
    range(scans): (1, 1, X, Y, Z) occupancy), Adam at `lr`, the scans in an order drawn from `seed`; resumed from
    and saved to `state` where given (removed at the end). Sets the model's int8 weights and returns them
    (`Co3SOP.int8_tuned_weights`). `on_step(step, loss)` after each step."""
    encoder = model.int8_modules.get("vehicle.encoder")
    if not isinstance(encoder, SSCNetEncoder) or not encoder.calibrated:
        raise Co3sopError(f"{model.cfg.name}: int8 fine-tuning needs a calibrated SSCNet-style LiDAR vehicle half")
    if scans < 1 or steps < 1:
        raise Co3sopError(f"int8 fine-tuning needs scans and steps (got {scans} scans, {steps} steps)")
    model.eval()
    frozen = [p for p in model.parameters() if p.requires_grad]
    for p in frozen:  # the float model is the teacher: no gradient of its own
        p.requires_grad_(False)
    try:
        return _fine_tune(model, encoder, scan, scans, steps, lr, seed, state, on_step)
    finally:
        for p in frozen:
            p.requires_grad_(True)


def _fine_tune(model, encoder, scan, scans, steps, lr, seed, state, on_step) -> dict[str, torch.Tensor]:
    head = model.ego.head if isinstance(model.ego.head, OccupancyHead) else None
    params = [torch.nn.Parameter(t.clone()) for pair in _layers(encoder) for t in pair]
    optimizer = torch.optim.Adam(params, lr=lr)
    order = _order(scans, steps, seed)
    variance, start = None, 0
    if state is not None and state.is_file():
        saved = torch.load(state, map_location="cpu", weights_only=True)
        if saved["setup"] != _setup(scans, steps, lr, seed):
            raise Co3sopError(f"{state}: a fine-tuning state of other settings ({saved['setup']}); remove it")
        with torch.no_grad():
            for p, t in zip(params, saved["params"]):
                p.copy_(t)
        optimizer.load_state_dict(saved["optimizer"])
        variance, start = saved["variance"], saved["step"]
    if variance is None:
        with torch.no_grad():
            feats = [encoder(scan(int(i))) for i in order[:VARIANCE_SCANS]]
            variance = torch.cat(feats).transpose(0, 1).flatten(1).var(dim=1).clamp_min(1e-12)  # (C,)
    for step in range(start, steps):
        occupancy = scan(int(order[step]))
        with torch.no_grad():
            want = encoder(occupancy.float())  # (1, C, X/4, Y/4, Z/4) float32
        got = encoder.int8_emulated(occupancy, list(zip(params[0::2], params[1::2])))
        loss = ((got - want) ** 2).mean(dim=(0, 2, 3, 4)).div(variance).mean()
        if head is not None:
            with torch.no_grad():
                teacher = _coarse_scores(head, want)
            loss = loss + F.kl_div(_coarse_scores(head, got), teacher, log_target=True, reduction="none").sum(1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if on_step is not None:
            on_step(step, loss.item())
        if state is not None and ((step + 1) % SAVE_EVERY == 0 or step + 1 == steps):
            _save(state, params, optimizer, variance, step + 1, _setup(scans, steps, lr, seed))
    tuned = {n: (w.detach(), b.detach()) for n, w, b in zip(encoder.INT8_LAYERS, params[0::2], params[1::2])}
    encoder.set_int8_weights(tuned)
    if state is not None:
        state.unlink(missing_ok=True)
    return model.int8_tuned_weights()


def _coarse_scores(head: OccupancyHead, features: torch.Tensor) -> torch.Tensor:
    """(1, K, X/4, Y/4, Z/4) the head's log class probabilities at its coarsest stage."""
    return F.log_softmax(head.classify[0](head.stage0(features)), dim=1)


def _layers(encoder: SSCNetEncoder) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Where fine-tuning starts: the int8 layers' weights as the int8 path has them now."""
    return [(w.detach().float(), b.detach().float()) for _, w, b in encoder.int8_layers()]


def _order(scans: int, steps: int, seed: int) -> np.ndarray:
    """Each step's scan: one permutation of the scans per pass, pass e drawn from (seed, e)."""
    passes = -(-steps // scans)
    return np.concatenate([np.random.default_rng([seed, e]).permutation(scans) for e in range(passes)])[:steps]


def _setup(scans: int, steps: int, lr: float, seed: int) -> dict:
    return {"scans": scans, "steps": steps, "lr": lr, "seed": seed}


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
