"""Training of Co3SOP-Base and the baselines: the ego, fusion and joint stages, data-parallel steps under
torchrun, a resumable state and the exported model (the `train` command, co3sop_nodes.cli.train, explains each)."""

from __future__ import annotations

import contextlib
import csv
import math
import os
import random
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from co3sop_nodes.common.bounded_cache import BoundedCache
from co3sop_nodes.common.errors import Co3sopError, DatasetError
from co3sop_nodes.common.progress import progress
from co3sop_nodes.inference.checkpoint import export_model, load_model, read_checkpoint, save_training_state
from co3sop_nodes.inference.inputs import to_batch
from co3sop_nodes.model.co3sop import VehicleOutput, build_model, with_wire
from co3sop_nodes.model.config import WireConfig, preset
from co3sop_nodes.model.losses import confidence_loss, downsample_labels, occupancy_loss
from co3sop_nodes.model.mask_loss import mask_classification_loss
from co3sop_nodes.model.occformer import class_scores, log_scores
from co3sop_nodes.train import distributed
from co3sop_nodes.train.dataset import OccupancyDataset, Sample, early_fused
from co3sop_nodes.train.loader import StepSamples, step_loader
from co3sop_nodes.train.log import keep_log_until, log_header, plot_losses
from co3sop_nodes.v2x.request_map import request_for_neighbour, request_of


def learning_rate(lr: float, schedule: str, step: int, steps: int) -> float:
    """The rate of step `step` (0-based) of `steps`: constant, or cosine-decayed from lr to 0 (a function of
    the step alone, so a resumed run follows the same curve)."""
    if schedule == "constant":
        return lr
    return 0.5 * lr * (1 + math.cos(math.pi * step / steps))


def sample_order(samples: int, seed: int, steps: int) -> np.ndarray:
    """The sample of every step: one permutation of the dataset per epoch, epoch e drawn from (seed, e).

    Step k's sample does not depend on `steps`, so a finished run resumed with more --steps continues
    the order a longer run would have followed (the first epoch is the single permutation runs of at most
    one epoch have always used).
    """
    epochs = -(-steps // samples)
    perms = [np.random.default_rng(seed if e == 0 else [seed, e]).permutation(samples) for e in range(epochs)]
    return np.concatenate(perms)[:steps]


def previous_history(out: Path, state: dict | None, init: Path | None) -> list[dict]:
    """The commands that made the starting weights: a resumed run's own, the interrupted or finished one
    included (kept in its state; for states written before they kept it: its finished model's), or the --init
    checkpoint's."""
    if state is not None:
        if "history" in state:
            return state["history"]
        finished = out / "model.pt"
        return read_checkpoint(finished).get("meta", {}).get("history", []) if finished.is_file() else []
    return read_checkpoint(init).get("meta", {}).get("history", []) if init else []


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def training_sample(cfg, stage: str) -> Callable[[OccupancyDataset, int], Sample]:
    """How sample i is read for a stage: the ego alone in the ego stage, and for an early-fusion model its
    collaborators' scans merged into its own (nothing is fused after the model)."""

    def prepare(dataset: OccupancyDataset, i: int) -> Sample:
        if cfg.early_fusion:
            return early_fused(dataset.sample(i), cfg.grid)
        return dataset.sample(i, 0 if stage == "ego" else None)

    return prepare


class _Forward(torch.nn.Module):
    """One sample's training forward (its vehicle halves, then the ego half) as one module call, so that
    DistributedDataParallel sees every parameter a step uses. In the fusion and wire stages the frozen vehicle
    half's outputs are float16 (as a float32 output rounds there), kept while they fit `cache_bytes`; in the wire
    stage each collaborator's output then crosses the learned wire code as a budget would send it
    (`through_wire`)."""

    def __init__(self, model, stage: str, device: torch.device, cache_bytes: int = 4 << 30):
        super().__init__()
        self.model, self.stage, self.device = model, stage, device
        self.cache = BoundedCache(cache_bytes, lambda out: out.features.nbytes + out.confidence.nbytes)

    def _vehicle(self, record_key, inputs) -> VehicleOutput:
        if self.stage not in FROZEN_VEHICLE:
            return self.model.vehicle(**to_batch(inputs, self.device))
        out = self.cache.get(record_key)
        if out is None:  # frozen: computed in eval mode, rounded to float16 whether kept or not
            with torch.no_grad():
                out = self.model.vehicle.eval()(**to_batch(inputs, self.device))
            out = VehicleOutput(out.features.half(), out.confidence.half())
            self.cache[record_key] = out
        return VehicleOutput(out.features.float(), out.confidence.float())

    def forward(
        self, sample: Sample, index: torch.Tensor, rng: np.random.Generator
    ) -> tuple[list[torch.Tensor], torch.Tensor, np.ndarray, dict[str, torch.Tensor]]:
        """Logits, the ego's confidence, its labels and the wire code's own losses (wire stage; else none)."""
        frame = sample.key[:3]
        ego = self._vehicle((frame, sample.ego.cav_id), sample.ego.inputs)
        others = [self._vehicle((frame, a.cav_id), a.inputs) for a in sample.others]
        wire: dict[str, torch.Tensor] = {}
        if self.stage == "wire" and others:
            request = request_of(ego.confidence)
            sent = []
            for record, out in zip(sample.others, others):
                wanted = request_for_neighbour(
                    request, sample.ego.world_from_lidar, record.world_from_lidar, self.model.cfg.feature_grid
                )
                received, losses = through_wire(self.model, out, torch.from_numpy(wanted).to(self.device), rng)
                sent.append(received)
                for k, v in losses.items():
                    wire[k] = wire.get(k, 0.0) + v / len(others)
            others = sent
        rel = torch.from_numpy(sample.neighbour_from_ego).float()[None].to(self.device) if others else None
        return self.model.ego(ego, others, rel, sample_index=index), ego.confidence, sample.ego.labels, wire


# stages that train with the vehicle half frozen (its outputs cached); the wire stage trains its wire encoder
FROZEN_VEHICLE = ("fusion", "wire")
# voxels a collaborator sends per message in the wire stage: log-uniform over this range, so that the fusion
# learns from messages of every budget it will meet (with the request-weighted choice the graph makes)
WIRE_VOXELS = (1024, 16384)
# the wire code's own losses beside the occupancy loss: its decoded features and confidence against the sender's
# (the confidence only reaches the hybrid mask, which passes no gradient), and its mean |integer| (smaller
# integers compress better)
WIRE_WEIGHTS = {"wire_features": 0.1, "wire_confidence": 1.0, "wire_rate": 0.01}


def through_wire(
    model, out: VehicleOutput, request: torch.Tensor, rng: np.random.Generator
) -> tuple[VehicleOutput, dict[str, torch.Tensor]]:
    """A collaborator's output (1, C, X, Y, Z) as the ego receives it through the model's wire code: the voxels
    its request (X, Y, Z) in [0, 1] weighs highest (confidence x request, nonzero only), as many as a drawn budget
    holds, coded and decoded with a gradient; and the code's losses."""
    score = (out.confidence[0, 0] * request).flatten()  # (V,)
    count = int(np.exp(rng.uniform(*np.log(WIRE_VOXELS))))
    keep = torch.topk(score, min(count, int((score > 0).sum()))).indices
    received = torch.zeros_like(score, dtype=torch.bool)
    received[keep] = True
    received = received.view(1, *out.confidence.shape[2:])  # (1, X, Y, Z)
    code = model.vehicle.encode(out.features, out.confidence)  # (1, K, X, Y, Z)
    decoded = model.ego.receive(code, received)
    if not len(keep):
        return decoded, {}
    sent = received[:, None]  # (1, 1, X, Y, Z)
    features, target = decoded.features.masked_select(sent), out.features.masked_select(sent)  # (C * N,)
    losses = {
        "wire_features": torch.mean((features - target) ** 2) / (target.var() + 1e-6),
        "wire_confidence": torch.mean((decoded.confidence - out.confidence).masked_select(sent) ** 2),
        "wire_rate": code.abs().masked_select(sent).mean(),
    }
    return decoded, {k: WIRE_WEIGHTS[k] * v for k, v in losses.items()}


class Trainer:
    """One optimisation step per global batch of samples (one sample by default), spread over the processes of a
    torchrun world."""

    def __init__(
        self,
        model,
        stage: str,
        sample_fraction: float,
        lr: float,
        device: torch.device = torch.device("cpu"),
        world: distributed.World = distributed.World(),
    ):
        self.model, self.stage, self.device, self.world = model, stage, device, world
        self.sample_fraction = sample_fraction
        if stage in FROZEN_VEHICLE:
            if model.ego.fusion is None:
                raise Co3sopError(f"--stage {stage} needs a model with fusion (e.g. preset tiny, not tiny-single)")
            if stage == "wire" and model.vehicle.wire is None:
                raise Co3sopError("--stage wire needs a model with a wire code (--wire-rank)")
            for p in model.vehicle.parameters():
                p.requires_grad_(False)
            for p in model.vehicle.wire.parameters() if stage == "wire" else ():
                p.requires_grad_(True)
        params = [p for p in model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
        self.forward = _Forward(model, stage, device)
        if (
            world.size > 1
        ):  # a parameter unused by one sample (the fusion, alone) is averaged as a zero gradient, as one process does
            self.forward = torch.nn.parallel.DistributedDataParallel(
                self.forward, device_ids=[device.index] if device.type == "cuda" else None, find_unused_parameters=True
            )

    def _loss(self, sample: Sample, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        cfg = self.model.cfg
        if cfg.head == "occformer":  # mask classification on class-guided points (model/mask_loss.py)
            preds, confidence, labels, _ = self.forward(sample, None, rng)
            labels = torch.from_numpy(labels)[None].to(self.device).long()  # (1, X, Y, Z): a byte a voxel on the bus
            parts = mask_classification_loss(preds, labels, cfg.occformer.points, rng)
            if self.stage not in FROZEN_VEHICLE:
                parts["confidence"] = confidence_loss(
                    confidence, log_scores(class_scores(*preds[-1])), downsample_labels(labels, 4, cfg.num_classes)
                )
            return sum(parts.values()), parts
        n = cfg.grid.num_voxels
        index = torch.from_numpy(np.sort(rng.choice(n, max(1, int(n * self.sample_fraction)), replace=False)))[None].to(
            self.device
        )
        logits, confidence, labels, wire = self.forward(sample, index, rng)
        labels = torch.from_numpy(labels)[None].to(self.device).long()  # (1, X, Y, Z): a byte a voxel on the bus
        k = self.model.cfg.num_classes
        targets = [
            downsample_labels(labels, 4, k),
            downsample_labels(labels, 2, k),
            torch.gather(labels.flatten(1), 1, index),
        ]
        parts = {**occupancy_loss(logits, targets), **wire}
        if self.stage not in FROZEN_VEHICLE:
            parts["confidence"] = confidence_loss(confidence, logits[0], targets[0])
        return sum(parts.values()), parts

    def step(self, samples: list[Sample], rngs: list[np.random.Generator]) -> dict[str, float]:
        """One optimisation step on this process's share of the global batch (samples[j] drawing its loss voxels
        with rngs[j]); the gradient is the mean over the global batch. Returns the batch's mean losses."""
        self.model.train()
        if self.stage in FROZEN_VEHICLE:
            self.model.vehicle.eval()
        self.optimizer.zero_grad(set_to_none=True)
        logged: dict[str, float] = {}
        for j, (sample, rng) in enumerate(zip(samples, rngs)):
            last = j == len(samples) - 1  # DDP averages over processes once, after a process's last sample
            sync = self.forward.no_sync() if self.world.size > 1 and not last else contextlib.nullcontext()
            with sync:
                loss, parts = self._loss(sample, rng)
                (loss / len(samples)).backward()
            for k, v in {"loss": loss, **parts}.items():
                logged[k] = logged.get(k, 0.0) + v.item() / len(samples)
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 5.0)
        self.optimizer.step()
        return distributed.mean_over_world(self.world, logged, self.device)


def train(opts, command: str) -> int:
    """Trains as `opts` (train's options) says, data-parallel under torchrun; `command` is recorded with the weights."""
    world = distributed.world_from_env()
    for option, value, ok, needs in (
        ("--steps", opts.steps, opts.steps >= 1, "at least 1"),
        ("--batch", opts.batch, opts.batch >= 1, "at least 1"),
        ("--save-every", opts.save_every, opts.save_every >= 1, "at least 1"),
        ("--lr", opts.lr, opts.lr > 0, "above 0"),
        ("--sample-fraction", opts.sample_fraction, 0 < opts.sample_fraction <= 1, "in (0, 1]"),
        ("--threads", opts.threads, opts.threads is None or opts.threads >= 1, "at least 1"),
        ("--workers", opts.workers, opts.workers >= 0, "0 or more"),
    ):
        if not ok:  # refused before the dataset is read, which takes minutes
            raise Co3sopError(f"{option} {value}: must be {needs}")
    if not opts.resume and (opts.out / "state.pt").exists():  # a new run there would overwrite its state and log
        raise Co3sopError(f"--out {opts.out}: holds a run (state.pt): --resume continues it, or choose another --out")
    torch.set_num_threads(opts.threads or (2 if world.size == 1 else max(1, (os.cpu_count() or 1) // world.local_size)))
    device = distributed.device_for(world, opts.device)
    seed_everything(opts.seed)
    if opts.stage in FROZEN_VEHICLE and not (opts.init or opts.resume):
        raise Co3sopError(f"--stage {opts.stage} starts from a trained vehicle half: give --init CHECKPOINT")
    distributed.start(world, device)
    try:
        code = _train(opts, command, world, device)
        distributed.finish(world)
        return code
    finally:
        distributed.stop(world)


def _train(opts, command: str, world: distributed.World, device: torch.device) -> int:
    say = print if world.main else (lambda *a, **k: None)

    start, state = 0, None
    if opts.resume:
        state = read_checkpoint(opts.out / "state.pt")
        model, _ = load_model(opts.out / "state.pt")
        start = state["step"]
    elif opts.init:
        model, _ = load_model(opts.init)
        if opts.stage == "wire" and model.vehicle.wire is None:
            model = with_wire(model, WireConfig(opts.wire_rank, opts.wire_levels))
    else:
        overrides = {"range": opts.range} if opts.range else {}
        model = build_model(preset(opts.preset, **overrides))
    model.to(device)  # before the optimizer exists: a resumed optimizer state follows its parameters' device
    cfg = model.cfg
    say(
        f"train: {cfg.name} ({cfg.modality}, {cfg.range}), stage {opts.stage}, "
        f"{sum(p.numel() for p in model.parameters()):,} parameters, "
        f"on {device}" + (f" x {world.size} processes (torchrun)" if world.size > 1 else ""),
        flush=True,
    )
    dataset = OccupancyDataset(opts.data, opts.splits, cfg, cache=opts.cache)
    batch = opts.batch * world.size  # the global batch: every process's share of each step together
    say(
        f"train: {len(dataset)} samples from {len(dataset.frames)} frames; global batch {batch} per step"
        + (f" ({opts.batch} in each of {world.size} processes)" if world.size > 1 else ""),
        flush=True,
    )
    trainer = Trainer(model, opts.stage, opts.sample_fraction, opts.lr, device, world)
    if state is not None:
        trainer.optimizer.load_state_dict(state["optimizer"])
    if world.main:
        opts.out.mkdir(parents=True, exist_ok=True)
    # how the weights were made: the commands before this one (the run's own when resumed, else the --init's), then this
    history = previous_history(opts.out, state, opts.init) + [
        {
            "command": command,
            "stage": opts.stage,
            "from_step": start,
            "steps": opts.steps,
            "seed": opts.seed,
            "data": str(opts.data),
            "splits": opts.splits,
            "batch": batch,
            "processes": world.size,
        }
    ]
    log_path = opts.out / "log.csv"
    if world.main:
        keep_log_until(log_path, start)
    fields = log_header(log_path) if world.main else None
    writer = None
    # one sample per step in one process: the voxels of the loss drawn from one stream (as every earlier run);
    # otherwise each sample's from its place in the order, whichever process takes it
    rng = np.random.default_rng(opts.seed + start)
    share = opts.batch  # this process's samples of each step
    order = sample_order(len(dataset), opts.seed, opts.steps * batch)
    steps = StepSamples(dataset, order, start, opts.steps, batch, world.rank, share, training_sample(cfg, opts.stage))
    bar = progress(opts.steps, f"train {opts.stage}", "step", disable=not world.main)
    bar.update(start)
    t0 = time.time()
    waited = 0.0  # seconds the step waited for its samples
    with open(log_path, "a", newline="") if world.main else contextlib.nullcontext() as log:
        loaded = iter(step_loader(steps, opts.workers, device))
        for step in range(start, opts.steps):
            lr = learning_rate(opts.lr, opts.schedule, step, opts.steps)
            for group in trainer.optimizer.param_groups:
                group["lr"] = lr
            t_wait = time.perf_counter()
            samples = next(loaded)
            waited += time.perf_counter() - t_wait
            if isinstance(samples, DatasetError):
                raise samples
            places = steps.places(step)
            rngs = [rng] if batch == 1 else [np.random.default_rng([opts.seed, p]) for p in places]
            parts = trainer.step(samples, rngs)
            if not world.main:
                continue
            row = {
                "step": step + 1,
                "stage": opts.stage,
                **parts,
                # a wire stage's step whose sample has no collaborator has no wire losses: its columns stay empty
                **{k: "" for k in (WIRE_WEIGHTS if opts.stage == "wire" else ()) if k not in parts},
                "lr": lr,
                "seconds": round(time.time() - t0, 2),
                "data_wait_seconds": round(waited, 2),
            }
            if writer is None:
                writer = csv.DictWriter(log, fieldnames=fields or list(row), extrasaction="ignore")
                if log.tell() == 0:
                    writer.writeheader()
            writer.writerow(row)
            bar.set_postfix(loss=f"{parts['loss']:.3f}")
            bar.update(1)
            if (step + 1) % opts.save_every == 0 or step + 1 == opts.steps:
                log.flush()
                save_training_state(
                    opts.out / "state.pt",
                    model,
                    trainer.optimizer,
                    step + 1,
                    opts.stage,
                    {"seed": opts.seed, "history": history},
                )
    bar.close()
    if world.main:
        export_model(opts.out / "model.pt", model, {"history": history})
        plot_losses(log_path, opts.out / "loss.png")
        elapsed = max(time.time() - t0, 1e-9)
        print(
            f"train: done; model {opts.out / 'model.pt'}, log {log_path}, plot {opts.out / 'loss.png'}; "
            f"{100 * waited / elapsed:.1f} % of the time waiting for data ({opts.workers} workers)"
        )
    return 0
