"""Unit tests of the learned wire code (model/wire.py), its place in the model, its trip through the codec
and the wire stage's forward (ROS-free, CPU, small grids)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from co3sop_nodes.common.errors import Co3sopError, CodecError
from co3sop_nodes.inference.checkpoint import export_model, load_model
from co3sop_nodes.inference.outputs import code_id, decoded_output, encode_output, through_codec
from co3sop_nodes.model.co3sop import build_model, with_wire
from co3sop_nodes.model.config import WireConfig, preset
from co3sop_nodes.model.wire import WireDecoder, WireEncoder
from co3sop_nodes.train.trainer import WIRE_VOXELS, through_wire
from co3sop_nodes.v2x.codec import FeatureCodecConfig, decode_features

SMALL = ((-12.8, -12.8, -2.0), 0.4, (64, 64, 16))  # 16 x 16 x 4 features


def lidar_model(wire=WireConfig(4, 7)):
    torch.manual_seed(0)
    return build_model(preset("tiny-lidar", custom_grid=SMALL, wire=wire)).eval()


def vehicle_out(model, seed=0):
    g = torch.Generator().manual_seed(seed)
    occupancy = (torch.rand(1, 1, *model.cfg.grid.dims, generator=g) < 0.1).float()
    with torch.no_grad():
        return model.vehicle(occupancy=occupancy)


def test_the_code_is_integers_within_its_levels_and_passes_gradients_straight_through():
    enc = WireEncoder(8, WireConfig(3, 2))
    features, conf = torch.randn(1, 8, 4, 4, 2) * 5, torch.rand(1, 1, 4, 4, 2)
    with torch.no_grad():
        code = enc(features, conf)
    assert code.shape == (1, 3, 4, 4, 2) and torch.equal(code, code.round()) and code.abs().max() <= 2
    trained = enc(features, conf)
    torch.testing.assert_close(trained, code)  # the same integers, within float rounding
    trained.sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.parameters())


def test_the_decoder_fills_only_the_received_voxels():
    dec = WireDecoder(8, WireConfig(3, 7))
    code = torch.randint(-7, 8, (1, 3, 4, 4, 2)).float()
    received = torch.zeros(1, 4, 4, 2, dtype=torch.bool)
    received[0, 1, 2, 0] = received[0, 3, 3, 1] = True
    features, conf = dec(code, received)
    assert features.shape == (1, 8, 4, 4, 2) and conf.shape == (1, 1, 4, 4, 2)
    assert torch.all(features[:, :, ~received[0]] == 0) and torch.all(conf[0, 0][~received[0]] == 0)
    assert torch.all(conf[0, 0][received[0]] > 0)
    # each voxel decodes from its own integers alone
    alone = dec(code[..., 1:2, 2:3, 0:1], torch.ones(1, 1, 1, 1, dtype=torch.bool))[0]
    torch.testing.assert_close(alone[0, :, 0, 0, 0], features[0, :, 1, 2, 0])


def test_a_code_is_named_by_its_weights_and_keeps_its_name_through_a_checkpoint(tmp_path):
    model = lidar_model()
    name = code_id(model)
    assert len(name) == 16 and code_id(lidar_model()) == name  # the same weights, the same name
    export_model(tmp_path / "m.pt", model, {}, half=False)
    assert code_id(load_model(tmp_path / "m.pt")[0]) == name
    with torch.no_grad():
        model.vehicle.wire.project[0].weight[0, 0] += 1
    assert code_id(model) != name
    assert code_id(lidar_model(None)) == ""


def test_with_wire_keeps_every_other_weight():
    plain = lidar_model(None)
    wired = with_wire(plain, WireConfig(2, 3))
    assert wired.cfg.wire == WireConfig(2, 3) and wired.vehicle.wire is not None and wired.ego.wire is not None
    assert wired.cfg.name == f"{plain.cfg.name}-wire"
    theirs = plain.state_dict()
    for key, value in wired.state_dict().items():
        if ".wire." not in key:
            assert torch.equal(value, theirs[key]), key


def test_config_refuses_a_code_it_cannot_send_or_use():
    with pytest.raises(Co3sopError, match="levels"):
        WireConfig(4, 8)  # beyond int4
    with pytest.raises(Co3sopError, match="rank"):
        WireConfig(0, 7)
    with pytest.raises(Co3sopError, match="collaborative"):
        preset("tiny-lidar", fusion=False, wire=WireConfig())


def test_through_the_codec_the_ego_decodes_the_senders_integers():
    model = lidar_model()
    out = vehicle_out(model)
    cfg = FeatureCodecConfig("int4", "topk", topk=200, learned=True)
    received, size = through_codec(model, out, cfg)
    enc = encode_output(out, model.cfg.feature_grid, cfg, None, code_id(model))
    dec = decode_features(enc)
    assert size == enc.budget_bytes and dec.mask.sum() == 200
    mask = torch.from_numpy(dec.mask)[None]
    with torch.no_grad():
        features, conf = model.ego.wire(out.code * mask[:, None], mask)
    torch.testing.assert_close(received.features, features)
    torch.testing.assert_close(received.confidence, conf)
    # the most confident voxels were chosen
    chosen = out.confidence[0, 0][mask[0]]
    assert chosen.min() >= out.confidence.flatten().sort().values[-200]


def test_an_ego_refuses_a_code_it_was_not_trained_with():
    model, other = lidar_model(), lidar_model()
    with torch.no_grad():
        other.vehicle.wire.project[2].bias += 0.5
    cfg = FeatureCodecConfig("int4", "topk", topk=50, learned=True)
    dec = decode_features(encode_output(vehicle_out(other), other.cfg.feature_grid, cfg, None, code_id(other)))
    with pytest.raises(CodecError, match="learned_code"):
        decoded_output(dec, model)
    with pytest.raises(CodecError, match="none"):
        decoded_output(dec, lidar_model(None))
    with pytest.raises(CodecError, match="learned wire code"):  # a model without a code cannot send one
        encode_output(vehicle_out(lidar_model(None)), model.cfg.feature_grid, cfg, None, "x")


def test_the_wire_stage_sends_the_requested_voxels_within_its_budget():
    model = lidar_model()
    out = vehicle_out(model)
    request = torch.zeros(model.cfg.feature_grid.dims)
    request[:8] = 1.0  # the ego asks for a slab of 8 x 16 x 4 = 512 voxels
    received, losses = through_wire(model, out, request, np.random.default_rng(0))
    sent = received.confidence[0, 0] > 0
    assert sent.sum() == min(512, WIRE_VOXELS[1]) and not sent[8:].any()
    assert set(losses) == {"wire_features", "wire_confidence", "wire_rate"}
    sum(losses.values()).backward()
    assert model.vehicle.wire.project[0].weight.grad is not None and model.ego.wire.expand[0].weight.grad is not None
    none, nothing = through_wire(model, out, torch.zeros_like(request), np.random.default_rng(0))
    assert nothing == {} and not none.confidence.any()
