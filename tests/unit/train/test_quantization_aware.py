"""Quantization-aware fine-tuning of the int8 layers of the SSCNet-style encoder and of the head: each emulation is
the int8 path's arithmetic, fine-tuning brings the shipped model's int8 features (the head's: labels) closer to
float32's and leaves float32 as it was, an interrupted run resumes to the same weights, and the weights travel in the
checkpoint (malformed ones refused by name)."""

import copy

import numpy as np
import pytest
import torch
from model_checks import lidar_model, scans

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.inference.calibration import calibrate
from co3sop_nodes.inference.checkpoint import export_model, load_model, save_calibrated, shipped_checkpoint
from co3sop_nodes.model import path as path_module
from co3sop_nodes.model.path import InferencePath
from co3sop_nodes.train import quantization_aware
from co3sop_nodes.train.dataset import AgentRecord, Sample
from co3sop_nodes.train.quantization_aware import fine_tune_int8, head_example

ENCODER, HEAD = "vehicle.encoder", "ego.head"


def calibrated_model():
    model = lidar_model()
    return model.calibrate(calibrate(model, scans(6, seed=1)))


def exact(model, module: str, values: list[list[torch.Tensor]]):
    """The model with `module`'s activations calibrated to twice their largest magnitude in `values` (each input's
    float32 ACTIVATIONS): every uint8 activation then at most 128, as is the head's signed input for inputs that are
    not positive (its zero point 128), so no pair of products exceeds 16 bits and the int8 path sums them exactly on
    every CPU, VNNI or not (model_checks.int8_pair_sums_saturate): what the emulation computes."""
    names = model.int8_modules[module].ACTIVATIONS
    largest = [max(float(v[i].abs().max()) for v in values) for i in range(len(names))]
    return model.calibrate({f"{module}.{n}": 2 * m for n, m in zip(names, largest)})


def int8_features(model, held_out: list[torch.Tensor]) -> list[torch.Tensor]:
    model.use(InferencePath(precision="int8"))
    assert model.path.int8
    with torch.inference_mode():
        out = [model.vehicle(occupancy=s).features for s in held_out]
    model.use(InferencePath())
    return out


def error(got: list[torch.Tensor], want: list[torch.Tensor]) -> float:
    return float(sum((g - w).abs().mean() for g, w in zip(got, want)) / sum(w.abs().mean() for w in want))


@torch.no_grad()
def test_the_emulation_is_the_int8_paths_arithmetic(monkeypatch):
    """The emulated forward, on the layers the int8 path computes with, gives the int8 path's features up to its
    accumulation's last roundings: far closer to them than either is to float32 (the output layer in float32 on
    both: the path's bfloat16 would round it)."""
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    model, held_out = lidar_model(), scans(3, seed=2)
    encoder = model.vehicle.encoder
    exact(model, ENCODER, [encoder.activations(s) for s in held_out])
    want = [encoder(s.float()) for s in held_out]
    layers = [(w, b) for _, w, b in encoder.int8_layers()]
    encoder.set_int8_weights(dict(zip(encoder.INT8_LAYERS, layers)))  # the float layers' own: no corrections
    real = int8_features(model, held_out)
    emulated = [encoder.int8_emulated(s, layers) for s in held_out]
    assert error(real, want) > 0.002  # the rounding is there to emulate
    assert error(emulated, real) < 0.05 * error(real, want)  # 0 % measured (AVX2)


def test_fine_tuning_brings_the_shipped_int8_layers_closer_to_float32():
    """On the shipped LiDAR model, 30 steps bring its int8 features closer to float32's on scans not trained on than
    its layers as calibrated, with or without their background corrections; float32 computes as it did."""
    torch.set_num_threads(2)
    model, _ = load_model(shipped_checkpoint())
    encoder, gen = model.vehicle.encoder, torch.Generator().manual_seed(0)
    dims = model.cfg.grid.dims
    train, held_out = [
        [(torch.rand(1, 1, *dims, generator=gen) < 0.03).to(torch.uint8) for _ in range(n)] for n in (8, 2)
    ]
    with torch.no_grad():
        want = [model.vehicle(occupancy=s).features for s in held_out]
    calibrated = error(int8_features(model, held_out), want)  # with the corrections
    encoder.set_int8_weights({n: (w, b) for n, (_, w, b) in zip(encoder.INT8_LAYERS, encoder.int8_layers())})
    uncorrected = error(int8_features(model, held_out), want)
    encoder.set_int8_weights(None)
    fine_tune_int8(model, ENCODER, lambda i: train[i], len(train), 30, 3e-5)
    tuned = error(int8_features(model, held_out), want)
    assert tuned < 0.9 * min(calibrated, uncorrected), (calibrated, uncorrected, tuned)  # 0.81x measured
    with torch.no_grad():
        assert all(torch.equal(model.vehicle(occupancy=s).features, w) for s, w in zip(held_out, want))


def test_an_interrupted_fine_tuning_resumes_to_the_same_weights(tmp_path, monkeypatch):
    train, steps, lr = scans(8, seed=3), 24, 1e-5
    weights = fine_tune_int8(calibrated_model(), ENCODER, lambda i: train[i], len(train), steps, lr)
    assert sorted(weights) == sorted(
        f"vehicle.encoder.{n}.{p}" for n in lidar_model().vehicle.encoder.INT8_LAYERS for p in ("weight", "bias")
    )
    # the same run interrupted after step 10 (its state written every 5 steps), then resumed
    monkeypatch.setattr(quantization_aware, "SAVE_EVERY", 5)
    state, again = tmp_path / "tuning.pt", calibrated_model()

    def stop(step, loss):
        if step == 10:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fine_tune_int8(again, ENCODER, lambda i: train[i], len(train), steps, lr, state=state, on_step=stop)
    assert state.is_file()
    with pytest.raises(Co3sopError, match="a fine-tuning state of other settings"):
        fine_tune_int8(calibrated_model(), ENCODER, lambda i: train[i], len(train), steps, lr / 2, state=state)
    resumed = fine_tune_int8(again, ENCODER, lambda i: train[i], len(train), steps, lr, state=state)
    for name, value in weights.items():
        torch.testing.assert_close(resumed[name], value, rtol=1e-5, atol=1e-6, msg=name)
    # a run resumed after its end takes no step and ends with the same weights
    done = fine_tune_int8(calibrated_model(), ENCODER, lambda i: None, len(train), steps, lr, state=state, on_step=stop)
    assert all(torch.equal(done[name], value) for name, value in resumed.items())


def test_fine_tuning_needs_a_calibrated_module():
    with pytest.raises(Co3sopError, match="int8 fine-tuning of vehicle.encoder needs it calibrated"):
        fine_tune_int8(lidar_model(), ENCODER, lambda i: scans(1, seed=0)[0], 1, 1)
    with pytest.raises(Co3sopError, match="int8 fine-tuning of vehicle.lifting needs it calibrated"):
        fine_tune_int8(calibrated_model(), "vehicle.lifting", lambda i: None, 1, 1)


def test_the_int8_weights_travel_in_the_checkpoint(tmp_path):
    model = lidar_model()
    ranges = calibrate(model, scans(6, seed=1))
    model.calibrate(ranges)
    train, held_out = scans(4, seed=3), scans(2, seed=2)
    weights = fine_tune_int8(model, ENCODER, lambda i: train[i], len(train), 4, 1e-3)
    source, out = tmp_path / "model.pt", tmp_path / "tuned.pt"
    export_model(source, model, {"history": []}, half=False)  # float32: the same float layers
    save_calibrated(source, out, ranges, {"command": "calibrate ..."}, weights)
    loaded, data = load_model(out)
    assert sorted(loaded.int8_tuned_weights()) == sorted(weights)
    for name, value in weights.items():
        assert torch.equal(loaded.int8_tuned_weights()[name], value)
    got = int8_features(loaded, held_out)
    assert all(torch.equal(g, w) for g, w in zip(got, int8_features(model, held_out)))
    plain = load_model(source)[0].calibrate(ranges)
    assert not plain.int8_tuned_weights()
    assert not all(torch.equal(g, w) for g, w in zip(got, int8_features(plain, held_out)))

    refused = {
        "not a dict of named float tensors": {"vehicle.encoder.down.1.weight": "w"},
        "not a finite number": {**weights, "vehicle.encoder.down.1.bias": torch.full((32,), float("nan"))},
        "vehicle.encoder: int8 weights of down.1": {**weights, "vehicle.encoder.down.1.bias": torch.zeros(3)},
        "int8 weights are each of a calibrated module's int8 layers": {"vehicle.encoder.down.1.weight": torch.zeros(1)},
        "int8 weights are each of a calibrated module's": {**weights, "ego.fusion.weight": torch.zeros(1)},
    }
    for message, bad in refused.items():
        data["int8"]["weights"] = bad
        torch.save(data, tmp_path / "bad.pt")
        with pytest.raises(Co3sopError, match=f"bad.pt: .*{message}"):
            load_model(tmp_path / "bad.pt")


def head_model(seed: int = 0):
    """A lidar_model whose head's norms are not the identity either."""
    model = lidar_model(seed)
    for layer in (*model.ego.head.stage0, model.ego.head.up1[3]):
        layer[1].running_mean.normal_(0, 0.1)
        layer[1].running_var.uniform_(0.5, 2.0)
    return model


def head_int8(model, features: list[torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The head's 1/2 features on the int8 path (dequantized, (1, C1, X/2, Y/2, Z/2)) and its labels."""
    model.use(InferencePath(precision="int8"))
    assert model.path.int8 and model.ego.head._int8 is not None
    out = []
    with torch.inference_mode():
        for x in features:
            values, scale = model.ego.head._parents_int8(x)
            out.append((values.permute(0, 4, 1, 2, 3).float() * scale, model.ego.head.labels(x)[0]))
    model.use(InferencePath())
    return out


@torch.no_grad()
def test_the_heads_emulation_is_the_int8_paths_arithmetic(monkeypatch):
    """The head's emulated layers up to 1/2 give the int8 path's 1/2 features up to its accumulation's last
    roundings, far closer to them than either is to float32's (on features made non-positive, which the head's
    signed input then holds without a pair of products exceeding 16 bits: `exact`)."""
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    model = head_model()
    head = model.ego.head
    features = [-model.vehicle(occupancy=s).features.abs() for s in scans(3, seed=2)]
    exact(model, HEAD, [head.activations(x) for x in features])
    want = [head.coarse(x)[1] for x in features]
    real = [f for f, _ in head_int8(model, features)]
    emulated = [head.int8_emulated(x, [(w, b) for _, w, b in head.int8_layers()]) for x in features]
    assert error(real, want) > 0.002  # the rounding is there to emulate
    assert error(emulated, real) < 0.05 * error(real, want)  # 0.4 % measured (AVX2)


def test_fine_tuning_brings_the_heads_int8_labels_closer_to_float32(monkeypatch):
    """On the shipped LiDAR model, fine-tuning its head's int8 layers on the features its int8 vehicle half makes,
    toward the float32 head's labels on the float32 features, brings the int8 head's labels on scans not trained on
    closer to float32's than the layers as calibrated; float32 labels as it did; the weights are the head's alone and
    the vehicle half's stay as they were."""
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    torch.set_num_threads(2)
    model, _ = load_model(shipped_checkpoint())
    deployed = load_model(shipped_checkpoint())[0].use(InferencePath(precision="int8"))
    encoder_weights = {n: t for n, t in model.int8_tuned_weights().items() if n.startswith(ENCODER)}
    head, gen = model.ego.head, torch.Generator().manual_seed(0)
    dims = model.cfg.grid.dims
    with torch.no_grad():
        train, held_out = [
            [
                tuple(m.vehicle(occupancy=s).features for m in (deployed, model))
                for s in [(torch.rand(1, 1, *dims, generator=gen) < 0.03).to(torch.uint8) for _ in range(n)]
            ]
            for n in (8, 2)
        ]
        want = [head.labels(w)[0] for _, w in held_out]

    def differing() -> int:
        got = head_int8(model, [g for g, _ in held_out])
        return sum(int((labels != w).sum()) for (_, labels), w in zip(got, want))

    before = differing()
    weights = fine_tune_int8(model, HEAD, lambda i: train[i], len(train), 16, 3e-5)
    assert sorted(weights) == sorted(f"{HEAD}.{n}.{p}" for n in head.INT8_LAYERS for p in ("weight", "bias"))
    after = differing()
    assert after < 0.9 * before, (before, after)
    assert model.int8_tuned(HEAD) and model.int8_tuned(ENCODER)
    assert all(torch.equal(model.int8_tuned_weights()[n], t) for n, t in encoder_weights.items())
    with torch.no_grad():
        assert all(torch.equal(head.labels(w)[0], labels) for (_, w), labels in zip(held_out, want))


@torch.no_grad()
def test_a_heads_example_is_the_int8_egos_fused_features_and_the_float_ones(monkeypatch):
    """head_example: the features an int8 ego fuses from int8 vehicles, and the float32 model's, for a sample with a
    neighbour; they differ by the int8 rounding only."""
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    model = calibrated_model()
    deployed = copy.deepcopy(model).use(InferencePath(precision="int8"))
    ego, other = scans(2, seed=4)
    pose = torch.eye(4).numpy()
    shifted = pose.copy()
    shifted[0, 3] = 2.0
    sample = Sample(
        ("validate", "s", 0, 1),
        AgentRecord(1, pose, {"occupancy": ego[0].numpy()}, None),
        [AgentRecord(2, shifted, {"occupancy": other[0].numpy()}, None)],
        (np.linalg.inv(shifted) @ pose)[None],
    )
    got, want = head_example(model, deployed, sample)
    outs = [model.vehicle(occupancy=s) for s in (ego, other)]
    exact = model.ego.fuse(outs[0], outs[1:], torch.from_numpy(sample.neighbour_from_ego).float()[None])
    assert torch.equal(want, exact) and not torch.equal(want, outs[0].features)  # the neighbour is fused
    assert got.shape == want.shape and 0 < error([got], [want]) < 0.05
