"""The int8 path: the SSCNet-style encoder's 3D layers after its first and the head's layers up to 1/2 in int8
once calibrated, within 8-bit's rounding of float32; calibration ranges that minimise the quantization error,
shipped in checkpoints; a model without them, or a device other than the CPU, never silently on an int8 path it
cannot take."""

import numpy as np
import pytest
import torch
from model_checks import int8_pair_sums_saturate, lidar_model, scans

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.inference.calibration import ActivationHistogram, calibrate
from co3sop_nodes.inference.checkpoint import export_model, load_model, save_calibrated
from co3sop_nodes.kernels import quantized_add
from co3sop_nodes.model import path as path_module
from co3sop_nodes.model import quantized
from co3sop_nodes.model.co3sop import build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.path import InferencePath, inference_path


def test_the_histograms_range_minimises_the_squared_quantization_error():
    gen = torch.Generator().manual_seed(0)
    values = torch.cat([torch.rand(1_000_000, generator=gen) * 2, torch.full((2,), 50.0)])

    def error(c):
        q = torch.clamp(torch.round(values / (c / 255)), 0, 255) * (c / 255)
        return float(((q - values) ** 2).sum())

    histogram, with_zeros = ActivationHistogram(), ActivationHistogram()
    for part in values.split(30_000):  # the span grows as larger values come
        histogram.add(part)
        with_zeros.add(torch.cat([part, torch.zeros(50_000)]))  # exact zeros quantize exactly: no weight
    clip = histogram.best_range()
    best = min(np.linspace(0.5, 50, 500), key=error)
    assert 2 < clip < 49 and 2 < best < 49  # the two outliers are clipped, and the values below given finer steps
    assert error(clip) <= 1.02 * error(best)
    assert with_zeros.best_range() == clip
    assert ActivationHistogram().best_range() == 0.0


def test_the_int8_layers_run_here():
    """The pinned PyTorch has oneDNN's quantized convolution and the machine a C compiler: the int8 path is the one
    these tests take, never skipped."""
    assert quantized.available(32)


def test_the_int8_products_saturate_in_pairs_exactly_where_the_cpu_has_no_int8_dot_product_unit():
    """With VNNI or AMX oneDNN sums every product in 32 bits; without (AVX2), pairs in 16 bits first, saturating,
    which the int8 path accepts there (model/quantized.py says what it costs): `cpu_int8_unit` names which."""
    assert int8_pair_sums_saturate() == (path_module.cpu_int8_unit() not in ("AMX", "AVX-512 VNNI"))


def test_the_residual_sum_is_requantized_as_pytorch_rounds():
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randint(0, 256, (1, 32, 6, 64, 64), dtype=torch.uint8, generator=gen) for _ in range(2))
    a, b = (t.contiguous(memory_format=torch.channels_last_3d) for t in (a, b))
    offset = torch.randn(32, 6, generator=gen) * 3  # (C, Z) in steps
    got = quantized_add.quantized_add(a, 0.05, b, 0.03, 0.07, offset, threads=3)
    want = torch.clamp(
        torch.round((a.float() * 0.05 + b.float() * 0.03) / 0.07 + offset[None, :, :, None, None]), 0, 255
    )
    assert got.is_contiguous(memory_format=torch.channels_last_3d)
    assert (got.float() - want).abs().max() <= 1 and (got.float() == want).float().mean() > 0.999
    with pytest.raises(ValueError, match="channels-last volumes of one shape"):
        quantized_add.quantized_add(a, 1.0, b[:, :16], 1.0, 1.0, offset, threads=1)
    with pytest.raises(ValueError, match=r"a \(32, 6\) offset"):
        quantized_add.quantized_add(a, 1.0, b, 1.0, 1.0, offset[:, :5], threads=1)


def test_the_residual_sum_rounds_as_its_definition_does_bit_for_bit():
    """In float32: a ka + b kb fused into one rounding (as the compiler contracts the plain loop, which the AVX-512
    version keeps), then the offset added, clamped (NaN: 0) and rounded to nearest even. The fused product-sum is
    exact in float64 for these magnitudes, so rounding it once to float32 is the fused multiply-add. On these values
    either other order (b kb fused first, or the offset inside) differs in one to three sums."""
    gen = torch.Generator().manual_seed(3)
    a, b = (torch.randint(0, 256, (1, 32, 6, 64, 64), dtype=torch.uint8, generator=gen) for _ in range(2))
    a, b = (t.contiguous(memory_format=torch.channels_last_3d) for t in (a, b))
    offset = torch.randn(32, 6, generator=gen) * 3
    offset[5, 2] = float("nan")
    ka, kb = 0.61803, 1.2345  # in steps of the sum
    got = quantized_add.quantized_add(a, ka * 0.07, b, kb * 0.07, 0.07, offset, threads=2)
    ka, kb = np.float32(ka * 0.07 / 0.07), np.float32(kb * 0.07 / 0.07)  # the kernel's factors, as it takes them
    an, bn = a.permute(0, 2, 3, 4, 1).numpy(), b.permute(0, 2, 3, 4, 1).numpy()  # (1, Z, X, Y, C) as stored
    fused = (an.astype(np.float64) * np.float64(ka) + (bn.astype(np.float32) * kb).astype(np.float64)).astype(
        np.float32
    )
    total = fused + offset.t().numpy()[None, :, None, None, :]
    want = np.rint(np.clip(np.nan_to_num(total, nan=0.0), 0, 255)).astype(np.uint8)
    assert np.array_equal(got.permute(0, 2, 3, 4, 1).numpy(), want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_a_quantized_volume_dequantizes_to_its_values_times_its_scale_plus_the_offset(dtype):
    torch.manual_seed(0)
    values = torch.randint(0, 256, (1, 6, 8, 8, 32), dtype=torch.uint8).permute(0, 4, 1, 2, 3)  # (B, C, Z, X, Y) view
    offset = torch.randn(32, 6)
    volume = quantized.Int8Volume(values, 0.0371)
    want = values.permute(0, 1, 3, 4, 2).to(dtype) * volume.scale  # (B, C, X, Y, Z), as rounded in `dtype`
    for got, add in (
        (volume.dequantize(dtype), 0),
        (volume.dequantize(dtype, offset), offset.to(dtype)[:, None, None]),
    ):
        assert got.dtype == dtype and got.shape == (1, 32, 8, 8, 6)
        assert got.is_contiguous(memory_format=torch.channels_last_3d)  # as the 1x1 output layer reads it
        assert torch.equal(got, want + add)


@torch.inference_mode()
def test_a_calibrated_encoder_computes_in_int8_near_float32(monkeypatch):
    model = lidar_model()
    calibration, held_out = scans(6, seed=1), scans(3, seed=2)
    want = [model.vehicle(occupancy=s).features for s in held_out]  # float32 reference
    model.use(InferencePath(precision="int8"))
    assert model.path.precision != "int8"  # not calibrated: the rest's precision, said by describe()
    ranges = calibrate(model, calibration)
    assert sorted(ranges) == sorted(model.int8_activations()) and all(r > 0 for r in ranges.values())
    model.calibrate(ranges).use(InferencePath(precision="int8"))
    assert model.path.int8 and model.path.describe().startswith("cpu, int8 + ")
    calls, original = [], quantized.Int8ConvReLU.__call__
    monkeypatch.setattr(quantized.Int8ConvReLU, "__call__", lambda self, x: calls.append(1) or original(self, x))
    got = [model.vehicle(occupancy=s).features for s in held_out]
    assert len(calls) == 4 * len(held_out)  # down.1 and the three dilated layers, each scan
    for g, w in zip(got, want):
        assert g.dtype == torch.float32 and g.shape == w.shape and g.is_contiguous()
        relative = float((g - w).abs().mean() / w.abs().mean())
        assert relative < 0.12  # 8-bit steps through four layers (5-7 % measured on bag scans)
    model.use(InferencePath())
    assert all(torch.equal(model.vehicle(occupancy=s).features, w) for s, w in zip(held_out, want))  # float32


def test_the_calibration_travels_in_the_checkpoint(tmp_path):
    model = lidar_model()
    source, out = tmp_path / "model.pt", tmp_path / "calibrated.pt"
    export_model(source, model, {"history": [{"stage": "ego"}]})
    ranges = calibrate(model, scans(3, seed=1))
    save_calibrated(source, out, ranges, {"command": "calibrate ...", "splits": ["validate"]})
    loaded, data = load_model(out)
    assert loaded.vehicle.encoder.calibrated and not load_model(source)[0].vehicle.encoder.calibrated
    assert [h["stage"] for h in data["meta"]["history"]] == ["ego", "int8 calibration"]
    ranges_in = torch.cat([loaded.vehicle.encoder.int8_ranges, loaded.ego.head.int8_ranges])  # int8_activations'
    torch.testing.assert_close(ranges_in, torch.tensor(list(ranges.values())))
    assert loaded.use(InferencePath(precision="int8")).path.int8
    # calibrated again: the new step replaces the one whose ranges it replaced, training's steps stay
    save_calibrated(out, out, ranges, {"command": "calibrate again", "splits": ["validate"]})
    history = load_model(out)[1]["meta"]["history"]
    assert [(h["stage"], h.get("command")) for h in history] == [("ego", None), ("int8 calibration", "calibrate again")]

    data["int8"] = {"ranges": {**ranges, "vehicle.encoder.sum.2": float("nan")}}
    torch.save(data, tmp_path / "nan.pt")
    with pytest.raises(Co3sopError, match="nan.pt: its int8 calibration holds a range that is not a finite number"):
        load_model(tmp_path / "nan.pt")
    data["int8"] = {"ranges": {"vehicle.encoder.down.0": 1.0}}
    torch.save(data, tmp_path / "short.pt")
    with pytest.raises(Co3sopError, match="short.pt: its int8 calibration does not fit its model"):
        load_model(tmp_path / "short.pt")
    data["int8"] = "ranges"
    torch.save(data, tmp_path / "odd.pt")
    with pytest.raises(Co3sopError, match="odd.pt: its int8 calibration holds no ranges"):
        load_model(tmp_path / "odd.pt")


def test_an_uncalibrated_camera_model_takes_the_rest_of_the_path():
    model = build_model(preset("tiny")).eval()
    assert model.int8_activations() == [f"ego.head.{n}" for n in OccupancyHead.ACTIVATIONS]  # its head's only
    assert model.use(InferencePath(precision="int8")).path.precision == InferencePath(precision="int8").floats
    assert "no int8 calibration" in model.int8_missing()
    with pytest.raises(Co3sopError, match="gives a positive range"):
        model.calibrate({})
    with pytest.raises(Co3sopError, match=r"\(not vehicle.encoder.down.0\)"):
        model.calibrate({"vehicle.encoder.down.0": 1.0})
    with pytest.raises(Co3sopError, match="an int8 calibration of ego.head lacks ego.head.up1, ego.head.up1.3"):
        model.calibrate({f"ego.head.{n}": 1.0 for n in OccupancyHead.ACTIVATIONS[:3]})


def features(count: int, seed: int, dims=(16, 16, 6)) -> list[torch.Tensor]:
    """Fused features as the head takes them: signed, mostly one profile along z (the empty grid), with objects."""
    gen = torch.Generator().manual_seed(seed)
    background = torch.randn(1, 32, 1, 1, dims[2], generator=gen)
    out = []
    for _ in range(count):
        objects = (torch.rand(1, 1, *dims, generator=gen) < 0.15) * torch.randn(1, 32, *dims, generator=gen) * 2
        out.append(background + objects + 0.1 * torch.randn(1, 32, *dims, generator=gen))
    return out


@torch.inference_mode()
def test_a_calibrated_head_computes_its_labels_in_int8_near_float32(monkeypatch):
    model = lidar_model()
    head = model.ego.head
    for layer in (*head.stage0, head.up1[3]):  # norms that are not the identity
        layer[1].running_mean.normal_(0, 0.1)
        layer[1].running_var.uniform_(0.5, 2.0)
    calibration, held_out = features(6, seed=1), features(3, seed=2)
    want = [head.labels(x) for x in held_out]  # the float32 path
    histograms = [ActivationHistogram() for _ in head.ACTIVATIONS]
    for x in calibration:
        for histogram, values in zip(histograms, head.activations(x)):
            histogram.add(values)
    ranges = {f"ego.head.{n}": h.best_range(steps) for n, h, steps in zip(head.ACTIVATIONS, histograms, head.STEPS)}
    model.calibrate(ranges).use(InferencePath(precision="int8"))
    assert model.path.int8 and head._int8 is not None and not model.vehicle.encoder.calibrated  # the head's alone
    calls, original = [], quantized.Int8ConvReLU.__call__
    monkeypatch.setattr(quantized.Int8ConvReLU, "__call__", lambda self, x: calls.append(1) or original(self, x))
    got = [head.labels(x) for x in held_out]
    assert len(calls) == 3 * len(held_out)  # stage0's two 3x3x3 layers and the block at 1/2
    for (labels, confidence), (want_labels, want_confidence) in zip(got, want):
        assert labels.shape == want_labels.shape and labels.dtype == confidence.dtype == torch.uint8
        # 8-bit steps through four layers of random weights (99.8-99.9 % on the shipped weights' bag frames)
        assert float((labels == want_labels).float().mean()) > 0.97
        same = labels == want_labels
        assert float((confidence[same].float() - want_confidence[same].float()).abs().mean()) < 6
    model.use(InferencePath())
    assert all(torch.equal(head.labels(x)[0], w[0]) for x, w in zip(held_out, want))  # float32 as it was


def test_int8_runs_on_the_cpu_only(monkeypatch):
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    assert InferencePath(precision="int8").floats == "float32"
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: "AMX")
    assert InferencePath(precision="int8").floats == "bfloat16"
    with pytest.raises(Co3sopError, match="precision int8 on cuda: int8 layers run on the CPU only"):
        InferencePath("cuda", "int8")
    if torch.cuda.is_available():
        with pytest.raises(Co3sopError, match="--precision int8 with --device cuda"):
            inference_path("cuda", "int8", what="--")
