"""The LiDAR vehicle half's output layers compiled: from the int8 layers' last volume, the features and confidence
the PyTorch layers compute under bfloat16 autocast, bit for bit, or in float32, within its rounding, with the
background offset or without; a vehicle half on an int8 path takes it, and gives what its PyTorch tail gives. Where
the CPU has no AVX-512 (for bfloat16: no bfloat16 products) the kernel is not available and the half keeps its
PyTorch tail."""

import pytest
import torch
from model_checks import lidar_model, scans

from co3sop_nodes.inference.calibration import calibrate
from co3sop_nodes.kernels import cpu_flags
from co3sop_nodes.kernels import lidar_output as output_kernel
from co3sop_nodes.kernels.transpose import channels_first_float32
from co3sop_nodes.model import co3sop
from co3sop_nodes.model.path import InferencePath, cpu_bfloat16_unit
from co3sop_nodes.model.quantized import Int8Volume

# float32: the kernel's features are the PyTorch layer's multiply-adds in the same order; the confidence layer's sum
# runs in another order and the sigmoid is the kernel's own, each within a few float32 roundings
FLOAT32_TOLERANCE = {"rtol": 1e-6, "atol": 1e-6}


def _pytorch_tail(volume: Int8Volume, offset, out, confidence, floats: str = "bfloat16"):
    """What the kernel replaces: the dequantized volume in the path's floats, the two 1x1 layers and the sigmoid
    (under autocast for bfloat16), widened to channels-first float32."""
    dtype = torch.bfloat16 if floats == "bfloat16" else torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=floats == "bfloat16"):
        features = out(volume.dequantize(dtype, offset))
        conf = torch.sigmoid(confidence(features))
    return channels_first_float32(features), channels_first_float32(conf)


def _layers(gen):
    out, confidence = torch.nn.Conv3d(32, 32, 1), torch.nn.Conv3d(32, 1, 1)
    for layer in (out, confidence):
        layer.weight.data.normal_(0, 0.3, generator=gen)
        layer.bias.data.normal_(0, 0.5, generator=gen)
    return out, confidence


def test_the_kernel_runs_where_the_cpu_computes_its_floats():
    avx512 = "avx512f" in cpu_flags()
    assert output_kernel.available(32) == (avx512 and cpu_bfloat16_unit() is not None)
    assert output_kernel.available(32, "float32") == avx512
    assert not output_kernel.available(48) and not output_kernel.available(48, "float32")  # 16-lane vector pairs
    assert not output_kernel.available(32, "float16")


@pytest.mark.parametrize(
    "floats",
    [
        pytest.param(f, marks=pytest.mark.skipif(not output_kernel.available(32, f), reason=f"no {f} kernel here"))
        for f in output_kernel.FLOATS
    ],
)  # where it runs: the test above
@pytest.mark.parametrize("with_offset", [False, True])
@torch.inference_mode()
def test_the_output_layers_are_the_pytorch_layers(floats, with_offset):
    """bfloat16: bit for bit; float32: within FLOAT32_TOLERANCE."""
    gen = torch.Generator().manual_seed(2)
    out, confidence = _layers(gen)
    # (1, C, Z, X, Y) views of z-outer volumes, as the int8 layers leave them; a height and a width the kernel's
    # blocks of columns do not divide
    for dims in [(6, 64, 64), (5, 9, 7)]:
        values = torch.randint(0, 256, (1, 32, *dims), dtype=torch.uint8, generator=gen)
        volume = Int8Volume(values.contiguous(memory_format=torch.channels_last_3d), 0.021)
        offset = torch.randn(32, dims[0], generator=gen) * 0.3 if with_offset else None
        want = _pytorch_tail(volume, offset, out, confidence, floats)
        assert float(want[1].min()) < 0.01 and float(want[1].max()) > 0.99  # the sigmoid's middle and its tails
        for threads in (1, 2):
            got = output_kernel.lidar_output(volume.values, volume.scale, offset, out, confidence, threads, floats)
            for g, w in zip(got, want):
                assert g.dtype == torch.float32 and g.is_contiguous()
                if floats == "bfloat16":
                    assert torch.equal(g, w)
                else:
                    torch.testing.assert_close(g, w, **FLOAT32_TOLERANCE)


@pytest.mark.skipif(not output_kernel.available(32, "float32"), reason="needs AVX-512")
@torch.inference_mode()
def test_the_float32_sigmoid_holds_in_its_tails():
    """Confidence logits far out on both sides (e^-x past float32's range, or subnormal): 1 and 0 within rounding."""
    out, confidence = torch.nn.Conv3d(32, 32, 1), torch.nn.Conv3d(32, 1, 1)
    torch.nn.init.eye_(out.weight.data.view(32, 32))
    out.bias.data.zero_()
    confidence.weight.data.fill_(1.0)
    logits = torch.tensor([-200.0, -100.0, -87.0, -30.0, -1.0, 0.0, 1.0, 30.0, 87.0, 100.0, 200.0])
    values = torch.zeros(1, 32, 1, 1, 1, dtype=torch.uint8).contiguous(memory_format=torch.channels_last_3d)
    got = []
    for logit in logits:  # the volume's values are 0: the features are 0 and the logit the confidence's bias
        confidence.bias.data.fill_(float(logit))
        got.append(output_kernel.lidar_output(values, 1.0, None, out, confidence, 1, "float32")[1].flatten()[0])
    torch.testing.assert_close(torch.stack(got), torch.sigmoid(logits), rtol=1e-6, atol=1e-30)


@pytest.mark.skipif(not output_kernel.available(32), reason="needs AVX-512 BF16")
def test_it_refuses_what_it_cannot_read():
    out, confidence = torch.nn.Conv3d(32, 32, 1), torch.nn.Conv3d(32, 1, 1)
    flat = torch.zeros(1, 32, 6, 8, 8, dtype=torch.uint8)  # contiguous, not channels-last
    with pytest.raises(ValueError, match="one channels-last uint8 volume"):
        output_kernel.lidar_output(flat, 1.0, None, out, confidence, 1)
    tall = torch.zeros(1, 32, output_kernel.MAX_HEIGHT + 1, 2, 2, dtype=torch.uint8)
    with pytest.raises(ValueError, match="voxels high at most"):
        output_kernel.lidar_output(tall.contiguous(memory_format=torch.channels_last_3d), 1.0, None, out, confidence, 1)


@torch.inference_mode()
def test_an_int8_vehicle_half_gives_what_its_pytorch_tail_gives(monkeypatch):
    """Calibrated (no fine-tuned int8 weights: the background offset is added) on an int8 path: the kernel where it
    is available, the same features and confidence as with the PyTorch tail."""
    model = lidar_model()
    model.calibrate(calibrate(model, scans(4, seed=1))).use(InferencePath(precision="int8"))
    assert model.vehicle.encoder.output_offset is not None
    calls, original = [], output_kernel.lidar_output
    monkeypatch.setattr(output_kernel, "lidar_output", lambda *a: calls.append(1) or original(*a))
    held_out = scans(2, seed=2)
    got = [model.vehicle(occupancy=s) for s in held_out]
    floats = model.path.floats
    assert len(calls) == (len(held_out) if output_kernel.available(32, floats) else 0)
    monkeypatch.setattr(co3sop.VehicleHalf, "_int8_output", lambda self, occupancy: None)
    for g, s in zip(got, held_out):
        want = model.vehicle(occupancy=s)
        if floats == "bfloat16":
            assert torch.equal(g.features, want.features) and torch.equal(g.confidence, want.confidence)
        else:
            torch.testing.assert_close(g.features, want.features, **FLOAT32_TOLERANCE)
            torch.testing.assert_close(g.confidence, want.confidence, **FLOAT32_TOLERANCE)
