"""The LiDAR vehicle half's output layers compiled: from the int8 layers' last volume, the features and confidence
the PyTorch layers compute under bfloat16 autocast, bit for bit, with the background offset or without; a vehicle
half on an int8 path whose floats are bfloat16 takes it, and gives what its PyTorch tail gives. Where the CPU has
no bfloat16 products the kernel is not available and the half keeps its PyTorch tail."""

import pytest
import torch
from model_checks import lidar_model, scans

from co3sop_nodes.inference.calibration import calibrate
from co3sop_nodes.kernels import lidar_output as output_kernel
from co3sop_nodes.kernels.transpose import channels_first_float32
from co3sop_nodes.model import co3sop
from co3sop_nodes.model.path import InferencePath, cpu_bfloat16_unit
from co3sop_nodes.model.quantized import Int8Volume


def _pytorch_tail(volume: Int8Volume, offset, out, confidence):
    """What the kernel replaces: the dequantized volume in bfloat16, the two 1x1 layers and the sigmoid under
    autocast, widened to channels-first float32."""
    with torch.autocast("cpu", dtype=torch.bfloat16):
        features = out(volume.dequantize(torch.bfloat16, offset))
        conf = torch.sigmoid(confidence(features))
    return channels_first_float32(features), channels_first_float32(conf)


def test_the_kernel_runs_where_the_cpu_computes_bfloat16_products():
    assert output_kernel.available(32) == (cpu_bfloat16_unit() is not None)
    assert not output_kernel.available(48)  # channels in pairs of 16-lane vectors


@pytest.mark.skipif(not output_kernel.available(32), reason="needs AVX-512 BF16 (the test above checks that)")
@pytest.mark.parametrize("with_offset", [False, True])
@torch.inference_mode()
def test_the_output_layers_are_the_pytorch_layers_bit_for_bit(with_offset):
    gen = torch.Generator().manual_seed(1)
    out, confidence = torch.nn.Conv3d(32, 32, 1), torch.nn.Conv3d(32, 1, 1)
    for layer in (out, confidence):
        layer.weight.data.normal_(0, 0.3, generator=gen)
        layer.bias.data.normal_(0, 0.5, generator=gen)
    # (1, C, Z, X, Y) views of z-outer volumes, as the int8 layers leave them; a height and a width the kernel's
    # blocks of columns do not divide
    for dims in [(6, 64, 64), (5, 9, 7)]:
        values = torch.randint(0, 256, (1, 32, *dims), dtype=torch.uint8, generator=gen)
        volume = Int8Volume(values.contiguous(memory_format=torch.channels_last_3d), 0.021)
        offset = torch.randn(32, dims[0], generator=gen) * 0.3 if with_offset else None
        want = _pytorch_tail(volume, offset, out, confidence)
        for threads in (1, 2):
            got = output_kernel.lidar_output(volume.values, volume.scale, offset, out, confidence, threads)
            for g, w in zip(got, want):
                assert g.dtype == torch.float32 and g.is_contiguous() and torch.equal(g, w)


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
    assert len(calls) == (len(held_out) if model.path.floats == "bfloat16" else 0)
    monkeypatch.setattr(co3sop.VehicleHalf, "_int8_output", lambda self, occupancy: None)
    for g, s in zip(got, held_out):
        want = model.vehicle(occupancy=s)
        assert torch.equal(g.features, want.features) and torch.equal(g.confidence, want.confidence)
