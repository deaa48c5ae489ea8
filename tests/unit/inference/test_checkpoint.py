"""Checkpoints round-trip: the loaded model computes what the saved one did."""

import dataclasses
from pathlib import Path

import pytest
import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.inference.checkpoint import export_model, load_graph_model, load_model, save_training_state
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import AttentionConfig, BackboneConfig, preset

SMALL = dict(
    custom_grid=((-6.4, -6.4, -2.0), 0.4, (32, 32, 8)),
    image_size=(32, 24),
    backbone=BackboneConfig((1, 1, 1, 1), (8, 8, 16, 16), stem=8),
    fpn_channels=8,
    embed_dims=8,
    image_attention=AttentionConfig(1, 2, 2),
    fusion_attention=AttentionConfig(1, 2, 2),
    head_channels=(8, 8, 4),
)


def _inputs(cfg):
    w, h = cfg.image_size
    gen = torch.Generator().manual_seed(1)
    return [
        {
            "images": torch.randint(0, 255, (1, 4, 3, h, w), dtype=torch.uint8, generator=gen),
            "lidar2img": torch.eye(4).repeat(1, 4, 1, 1),
        }
    ]


@pytest.mark.parametrize("half", [False, True])
def test_export_and_load(tmp_path, half):
    torch.manual_seed(0)
    model = build_model(preset("tiny", **SMALL)).eval()
    export_model(tmp_path / "m.pt", model, {"history": [{"command": "train ..."}]}, half=half)
    loaded, data = load_model(tmp_path / "m.pt")
    assert loaded.cfg == model.cfg and data["meta"]["history"][0]["command"] == "train ..."
    with torch.no_grad():
        a, b = model(_inputs(model.cfg)), loaded(_inputs(model.cfg))
    for x, y in zip(a, b):
        if half:  # float16 weights: close, not equal
            torch.testing.assert_close(x, y, atol=5e-2, rtol=5e-2)
        else:
            torch.testing.assert_close(x, y, atol=0, rtol=0)


def test_the_graph_refuses_an_early_fusion_model_that_offline_evaluation_loads(tmp_path):
    """Its vehicles share voxel features; an early-fusion model needs the collaborators' scans before it."""
    for name in ("tiny-sscnet-early", "tiny-lidar"):
        export_model(tmp_path / f"{name}.pt", build_model(preset(name, **SMALL)), {})
    assert load_model(tmp_path / "tiny-sscnet-early.pt")[0].cfg.early_fusion
    with pytest.raises(Co3sopError, match="tiny-sscnet-early.pt: tiny-sscnet-early is an early-fusion reference"):
        load_graph_model(tmp_path / "tiny-sscnet-early.pt")
    assert load_graph_model(tmp_path / "tiny-lidar.pt")[0].cfg.name == "tiny-lidar"


def test_training_state_round_trip(tmp_path):
    model = build_model(preset("tiny", **SMALL))
    opt = torch.optim.AdamW(model.parameters())
    save_training_state(tmp_path / "state.pt", model, opt, 7, "ego", {"seed": 3})
    loaded, data = load_model(tmp_path / "state.pt")
    assert data["step"] == 7 and data["stage"] == "ego" and data["seed"] == 3
    for k, v in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v, atol=0, rtol=0)
    assert not list(tmp_path.glob(".*tmp"))  # written atomically


def test_bad_checkpoints_are_explained(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(Co3sopError, match="not a readable checkpoint"):
        load_model(tmp_path / "junk.pt")
    with pytest.raises(Co3sopError, match="no such checkpoint"):
        load_model(tmp_path / "missing.pt")
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(Co3sopError, match="not a Co3SOP checkpoint"):
        load_model(tmp_path / "other.pt")


SHIPPED = sorted(p.stem for p in (Path(__file__).parents[3] / "src/co3sop_nodes/checkpoints").glob("*.pt"))


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_checkpoint_is_installed_small_and_loads(name):
    from co3sop_nodes.inference.checkpoint import shipped_checkpoint

    path = shipped_checkpoint(f"{name}.pt")
    assert path.stat().st_size <= 5 * 2**20
    model, data = load_model(path)
    history = data["meta"]["history"]
    training = [h for h in history if h["stage"] != "int8 calibration"]
    stages = [h["stage"] for h in training]
    # the two stages in order (then a wire code's, where it has one), each possibly resumed or extended
    assert model.cfg.name == name and stages[0] == "ego" and "fusion" in stages
    assert stages == sorted(stages, key=["ego", "fusion", "wire"].index)
    assert ("wire" in stages) == (model.cfg.wire is not None)
    assert all("--seed" in h["command"] for h in training)
    # a model with int8 layers ships calibrated, after its training and never on the reported split
    calibrations = history[len(training) :]
    assert all(h["stage"] == "int8 calibration" and "test" not in h["splits"] for h in calibrations)
    assert bool(calibrations) == (model.cfg.modality == "lidar") == ("int8" in data)
    if calibrations:  # every int8 layer's range: the vehicle half's and the head's
        assert sorted(data["int8"]["ranges"]) == sorted(model.int8_activations())


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_checkpoints_card_lists_the_commands_that_made_it(name):
    from co3sop_nodes.inference.checkpoint import shipped_checkpoint

    card = (Path(__file__).parents[3] / f"src/co3sop_nodes/checkpoints/{name}.md").read_text()
    _, data = load_model(shipped_checkpoint(f"{name}.pt"))
    for step in data["meta"]["history"]:
        assert f"$L/{step['command']}" in card, step["command"]


class _Payload:
    """What a crafted checkpoint carries: unpickling it would create a marker file."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_crafted_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "ran"
    torch.save({"config": {}, "model": {}, "meta": _Payload(marker)}, tmp_path / "evil.pt")
    with pytest.raises(Co3sopError, match=r"evil\.pt: refused: holds Python objects"):
        load_model(tmp_path / "evil.pt")
    assert not marker.exists()


def test_checkpoints_without_weights_or_config_or_that_do_not_fit_are_explained(tmp_path):
    model = build_model(preset("tiny", **SMALL))
    export_model(tmp_path / "m.pt", model, {})
    data = torch.load(tmp_path / "m.pt", weights_only=True)
    cases = {
        "no-weights": ({"config": data["config"]}, r"no config/model"),
        "no-config": ({"model": data["model"]}, r"no config/model"),
        "weights-not-tensors": ({"config": data["config"], "model": {"a": 1}}, r"not a dict of named tensors"),
        "unknown-config": (
            {"config": {**data["config"], "wings": 2}, "model": data["model"]},
            r"config is not one this version knows",
        ),
        "other-model": (
            {"config": dataclasses.asdict(preset("tiny-lidar")), "model": data["model"]},
            r"weights do not fit its config",
        ),
    }
    for name, (content, message) in cases.items():
        torch.save(content, tmp_path / f"{name}.pt")
        with pytest.raises(Co3sopError, match=rf"{name}\.pt: .*{message}"):
            load_model(tmp_path / f"{name}.pt")
    with pytest.raises(Co3sopError, match="a directory"):
        load_model(tmp_path)


def test_a_checkpoint_is_named_by_path_or_by_shipped_name(tmp_path):
    from co3sop_nodes.inference.checkpoint import resolve_checkpoint, shipped_checkpoint

    assert resolve_checkpoint("tiny-lidar") == shipped_checkpoint("tiny-lidar.pt")
    assert resolve_checkpoint("") == resolve_checkpoint(None) == shipped_checkpoint()
    path = tmp_path / "mine.pt"
    path.write_bytes(b"")
    assert resolve_checkpoint(str(path)) == path
    with pytest.raises(
        Co3sopError, match="--model 'tiny_lidar': neither a checkpoint file nor a shipped model .*tiny-lidar"
    ):
        resolve_checkpoint("tiny_lidar", "--model")
    with pytest.raises(Co3sopError, match="no such checkpoint file"):
        resolve_checkpoint(str(tmp_path / "none.pt"))
