"""Checkpoints: training state (resumable) and exported models (weights + config + provenance)."""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
from pathlib import Path

import torch

from co3sop_nodes.common.errors import Co3sopError, exception_line
from co3sop_nodes.model.co3sop import Co3SOP, build_model
from co3sop_nodes.model.config import ModelConfig, config_from_dict

# the model every node, launch file, `demo` and `evaluate` use unless told otherwise: the best collaborative
# model shipped (how it was trained: checkpoints/tiny-lidar.md); `tiny` and `small` are the camera models
DEFAULT_MODEL = "tiny-lidar"
# the history step of an int8 calibration (`save_calibrated`)
CALIBRATION_STAGE = "int8 calibration"


def shipped_checkpoint(name: str = f"{DEFAULT_MODEL}.pt") -> Path:
    """The checkpoint installed with co3sop_nodes (found on AMENT_PREFIX_PATH, as ROS tools find packages)."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        candidate = Path(prefix, "share", "co3sop_nodes", "checkpoints", name)
        if candidate.is_file():
            return candidate
    raise Co3sopError(
        f"no installed checkpoint {name!r}: build the workspace (ros2_ws/bootstrap.sh) and source ros2_ws/env.sh"
    )


def shipped_names() -> list[str]:
    """The shipped checkpoints by name (tiny-lidar, tiny, small), as installed."""
    folder = shipped_checkpoint().parent
    return sorted(p.stem for p in folder.glob("*.pt"))


def resolve_checkpoint(value: str | Path | None, what: str = "checkpoint") -> Path:
    """A checkpoint given as a path (a .pt file) or as the name of a shipped one (tiny-lidar, tiny, small); empty:
    the shipped default. `what` names the option or parameter in errors."""
    if not value:
        return shipped_checkpoint()
    path = Path(value)
    if path.suffix == ".pt" or path.exists() or len(path.parts) > 1:
        if not path.is_file():
            raise Co3sopError(f"{what} {value}: no such checkpoint file")
        return path
    known = shipped_names()
    if str(value) not in known:
        raise Co3sopError(f"{what} {value!r}: neither a checkpoint file nor a shipped model ({', '.join(known)})")
    return shipped_checkpoint(f"{value}.pt")


def _atomic_save(obj, path: Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)  # a crash never leaves a half-written checkpoint under the real name


def save_training_state(path: Path, model: Co3SOP, optimizer, step: int, stage: str, extra: dict) -> None:
    _atomic_save(
        {
            "config": dataclasses.asdict(model.cfg),
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "step": step,
            "stage": stage,
            **extra,
        },
        path,
    )


def export_model(path: Path, model: Co3SOP, meta: dict, half: bool = True) -> None:
    """Weights (float16 by default: half the size, cast back on load) + config + how they were made."""
    state = {k: (v.half() if half and v.is_floating_point() else v) for k, v in model.state_dict().items()}
    _atomic_save({"config": dataclasses.asdict(model.cfg), "model": state, "meta": meta}, path)


def read_checkpoint(path: Path) -> dict:
    """The dict a checkpoint holds, loaded without running code: tensors, numbers, strings and containers
    only (`weights_only`), so a crafted pickle is refused instead of executed."""
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise Co3sopError(f"{path}: no such checkpoint") from None
    except IsADirectoryError:
        raise Co3sopError(f"{path}: a directory, not a checkpoint") from None
    except pickle.UnpicklingError as exc:
        if "Unsupported global" in str(exc):  # a pickled object (class, function) rather than weights
            raise Co3sopError(
                f"{path}: refused: holds Python objects other than weights (loading it could run code); "
                "not a Co3SOP checkpoint"
            ) from None
        raise Co3sopError(f"{path}: not a readable checkpoint (damaged, or not a PyTorch file)") from None
    except Exception as exc:
        raise Co3sopError(f"{path}: not a readable checkpoint ({exception_line(exc)})") from None
    if (
        not isinstance(data, dict)
        or not isinstance(data.get("config"), dict)
        or not isinstance(data.get("model"), dict)
    ):
        raise Co3sopError(f"{path}: not a Co3SOP checkpoint (no config/model)")
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in data["model"].items()):
        raise Co3sopError(f"{path}: not a Co3SOP checkpoint (its model entry is not a dict of named tensors)")
    return data


def load_model(path: Path) -> tuple[Co3SOP, dict]:
    """A model in eval mode from a training state or an exported checkpoint, and the checkpoint's dict."""
    data = read_checkpoint(path)
    try:
        cfg: ModelConfig = config_from_dict(data["config"])
    except Co3sopError as exc:
        raise Co3sopError(f"{path}: {exc}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise Co3sopError(f"{path}: its config is not one this version knows ({exc})") from None
    model = build_model(cfg)
    state = {k: v.float() if v.is_floating_point() else v for k, v in data["model"].items()}
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:  # missing, unexpected or mis-shaped weights
        raise Co3sopError(f"{path}: its weights do not fit its config ({exception_line(exc)})") from None
    if "int8" in data:
        ranges = _int8_ranges(path, data["int8"])
        weights = data["int8"].get("weights", {})
        if not isinstance(weights, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) and v.is_floating_point() for k, v in weights.items()
        ):
            raise Co3sopError(f"{path}: its int8 weights are not a dict of named float tensors")
        if not all(bool(torch.isfinite(v).all()) for v in weights.values()):
            raise Co3sopError(f"{path}: its int8 weights hold a value that is not a finite number")
        try:
            model.calibrate(ranges, {k: v.float() for k, v in weights.items()})
        except Co3sopError as exc:
            raise Co3sopError(f"{path}: its int8 calibration does not fit its model ({exc})") from None
    return model.eval(), data


def _int8_ranges(path: Path, entry) -> dict[str, float]:
    """A checkpoint's int8 calibration entry ({"ranges": {activation: range}, ...}) as finite floats."""
    ranges = entry.get("ranges") if isinstance(entry, dict) else None
    try:
        ranges = {str(k): float(v) for k, v in ranges.items()}
    except (AttributeError, TypeError, ValueError):
        raise Co3sopError(f"{path}: its int8 calibration holds no ranges by activation name") from None
    if not all(math.isfinite(v) for v in ranges.values()):
        raise Co3sopError(f"{path}: its int8 calibration holds a range that is not a finite number")
    return ranges


def save_calibrated(
    source: Path, out: Path, ranges: dict[str, float], made: dict, weights: dict[str, torch.Tensor] | None = None
) -> None:
    """`source`'s checkpoint with the int8 calibration `ranges` and the int8 layers' own `weights` where given
    (`Co3SOP.int8_tuned_weights`; replacing any it had), `made` (the command, data and splits) added to its
    history, written atomically to `out` (which may be `source`). The int8 entry is replaced whole, so an earlier
    calibration's step leaves the history: it made nothing the file still holds."""
    data = read_checkpoint(source)
    data["int8"] = {"ranges": dict(ranges), **made}
    if weights:
        data["int8"]["weights"] = {k: v.detach().float().contiguous() for k, v in weights.items()}
    meta = data.setdefault("meta", {})
    kept = [step for step in meta.get("history", []) if step.get("stage") != CALIBRATION_STAGE]
    meta["history"] = [*kept, {"stage": CALIBRATION_STAGE, **made}]
    _atomic_save(data, out)


def load_graph_model(path: Path) -> tuple[Co3SOP, dict]:
    """load_model for the node graph, whose vehicles share voxel features: an early-fusion model (the
    collaborators' scans merged before it, an offline reference) has no place there and is refused."""
    model, data = load_model(path)
    if model.cfg.early_fusion:
        raise Co3sopError(
            f"{path}: {model.cfg.name} is an early-fusion reference (collaborators' LiDAR scans merged before the "
            "model); the node graph shares voxel features: score it with `evaluate`, run the graph with a "
            "Co3SOP-Base checkpoint"
        )
    return model, data
