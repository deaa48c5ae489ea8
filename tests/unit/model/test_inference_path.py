"""co3sop_nodes.model.path: the inference path chosen from the machine, held by each model, float32 unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.inference.checkpoint import load_model, shipped_checkpoint
from co3sop_nodes.inference.pace import shaped_inputs
from co3sop_nodes.inference.predict import predict_frame
from co3sop_nodes.model import path as path_module
from co3sop_nodes.model.co3sop import VehicleOutput, build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.path import InferencePath, inference_path


def test_auto_takes_bfloat16_only_where_the_cpu_computes_it(monkeypatch):
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: None)
    assert inference_path("cpu", "auto") == InferencePath("cpu", "float32")
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: "AMX")
    assert inference_path("cpu", "auto") == InferencePath("cpu", "bfloat16")
    assert inference_path("cpu", "float32", compiled=False) == InferencePath("cpu", "float32", False)


def test_auto_takes_int8_only_for_a_vehicle_half_tuned_for_it_on_a_cpu_with_an_int8_unit(monkeypatch):
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: "AVX-512 BF16")
    monkeypatch.setattr(path_module, "cpu_int8_unit", lambda: "AVX-512 VNNI")
    assert inference_path("cpu", "auto", tuned_int8=True) == InferencePath("cpu", "int8")
    assert inference_path("cpu", "auto") == InferencePath("cpu", "bfloat16")  # an ego's, or a half not tuned
    assert inference_path("cpu", "bfloat16", tuned_int8=True) == InferencePath("cpu", "bfloat16")  # asked for
    monkeypatch.setattr(path_module, "cpu_int8_unit", lambda: None)
    assert inference_path("cpu", "auto", tuned_int8=True) == InferencePath("cpu", "bfloat16")


@pytest.mark.parametrize(
    ("flags", "unit", "words"),
    [
        (
            "avx2 avx512f avx512bw amx_tile amx_int8 amx_bf16 avx512_bf16 avx512_vnni",
            "AMX",
            "int8: AMX; bfloat16: AMX",
        ),
        ("avx2 avx512f avx512bw avx512_vnni avx512_bf16", "AVX-512 VNNI", "int8: AVX-512 VNNI; bfloat16: AVX-512 BF16"),
        ("avx2 fma", "AVX2", "int8: AVX2, no VNNI; bfloat16: none"),  # 16-bit pair sums, 1.35-1.4x float32 still
        ("sse4_2", None, "int8: none; bfloat16: none"),
    ],
)
def test_the_reduced_precision_units_are_read_from_the_cpu_flags(monkeypatch, flags, unit, words):
    """The int8 unit `auto` decides by, and the words a result measured on the CPU names its units in."""
    monkeypatch.setattr(path_module.kernels, "cpu_flags", lambda: tuple(flags.split()))
    units = (path_module.cpu_int8_unit, path_module.cpu_bfloat16_unit)
    for cached in units:
        cached.cache_clear()
    try:
        assert path_module.cpu_int8_unit() == unit
        assert path_module.cpu_units() == words
    finally:
        for cached in units:
            cached.cache_clear()


def test_a_shipped_module_is_tuned_for_int8_where_its_checkpoint_carries_its_int8_weights():
    for name in ("tiny-lidar.pt", "tiny-lidar-76.8m.pt", "tiny.pt"):
        model, data = load_model(shipped_checkpoint(name))
        weights = data.get("int8", {}).get("weights", {})
        for prefix in ("vehicle.encoder", "ego.head"):
            assert model.int8_tuned(prefix) == any(n.startswith(f"{prefix}.") for n in weights), (name, prefix)
    assert load_model(shipped_checkpoint("tiny-lidar.pt"))[0].int8_tuned("vehicle.encoder")  # the demo's vehicles
    assert load_model(shipped_checkpoint("tiny-lidar.pt"))[0].int8_tuned("ego.head")  # and its ego


def test_each_half_takes_int8_by_auto_where_its_own_int8_layers_are_tuned(monkeypatch):
    monkeypatch.setattr(path_module, "cpu_bfloat16_unit", lambda: "AVX-512 BF16")
    monkeypatch.setattr(path_module, "cpu_int8_unit", lambda: "AVX-512 VNNI")
    model = load_model(shipped_checkpoint("tiny-lidar.pt"))[0]
    assert model.vehicle_path("cpu", "auto").int8 and model.ego_path("cpu", "auto").int8
    weights = {n: t for n, t in model.int8_tuned_weights().items() if n.startswith("vehicle.")}
    ranges = {
        n: float(r)
        for n, r in zip(model.int8_activations(), torch.cat([m.int8_ranges for m in model.int8_modules.values()]))
    }
    model.calibrate(ranges, weights)  # the vehicle half's int8 weights alone
    assert model.vehicle_path("cpu", "auto").int8 and model.ego_path("cpu", "auto").precision == "bfloat16"
    assert model.ego_path("cpu", "int8").int8  # asked for


@pytest.mark.parametrize(
    ("device", "precision", "message"),
    [
        ("gpu", "auto", "parameter device 'gpu': not a device"),
        ("meta", "auto", "only cpu and cuda"),
        ("cpu", "half", "parameter precision 'half': one of auto, float32"),
    ],
)
def test_a_bad_device_or_precision_is_refused_by_name(device, precision, message):
    with pytest.raises(Co3sopError, match=message):
        inference_path(device, precision, what="parameter ")


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is there")
def test_cuda_without_a_gpu_is_refused():
    with pytest.raises(Co3sopError, match="--device cuda: this torch build .* sees no CUDA GPU"):
        inference_path("cuda", what="--")


def test_each_model_holds_its_own_path():
    a, b = (build_model(preset("tiny-lidar")).eval() for _ in range(2))
    a.use(InferencePath("cpu", "bfloat16"))
    b.use(InferencePath("cpu", "float32", compiled=False))
    for model, want in ((a, InferencePath("cpu", "bfloat16")), (b, InferencePath("cpu", "float32", False))):
        held = {m.path for m in model.modules() if "path" in vars(m)}
        assert held == {want}
    conv = a.vehicle.encoder.modules()
    assert any(
        isinstance(m, torch.nn.Conv3d) and m.weight.is_contiguous(memory_format=torch.channels_last_3d) for m in conv
    )


@torch.no_grad()
def test_float32_is_bit_identical_after_a_round_trip_through_bfloat16():
    torch.manual_seed(0)
    model = build_model(preset("tiny-lidar")).eval()
    inputs = shaped_inputs(model)

    def frame():
        ego = model.vehicle(**inputs)
        others = {1: (VehicleOutput(ego.features.roll(3, 2), ego.confidence.roll(3, 2)), np.diag([1.0, 1, 1, 1]))}
        pred = predict_frame(model, ego, np.eye(4), others)
        return ego.features.clone(), pred.labels, pred.confidence

    before = frame()
    model.use(InferencePath("cpu", "bfloat16"))
    model.use(InferencePath("cpu", "float32"))
    after = frame()
    assert all(
        torch.equal(x, y) if isinstance(x, torch.Tensor) else np.array_equal(x, y) for x, y in zip(before, after)
    )
    assert all(p.is_contiguous() for p in model.parameters())


@torch.no_grad()
def test_float32_products_of_a_reduced_path_equal_f_linear_to_float_rounding(monkeypatch):
    """A reduced CPU path's float32 products (the fusion's projections) run by oneDNN where this build has it;
    float32 and training keep F.linear, bit for bit."""
    torch.manual_seed(0)
    x, weight, bias = torch.randn(2, 1000, 32), torch.randn(96, 32), torch.randn(96)
    want = torch.nn.functional.linear(x, weight, bias)
    assert path_module.onednn(torch.float32)  # the pinned PyTorch has it: the fast path is the one tested here
    got = InferencePath(precision="bfloat16").linear(x, weight, bias)
    assert got.shape == want.shape and got.dtype == torch.float32
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    assert torch.equal(InferencePath().linear(x, weight, bias), want)
    with torch.enable_grad():  # training: PyTorch's product and its gradient
        assert torch.equal(InferencePath(precision="bfloat16").linear(x, weight, bias), want)
    monkeypatch.setattr(path_module, "onednn", lambda dtype: False)  # a build without it: F.linear
    assert torch.equal(InferencePath(precision="bfloat16").linear(x, weight, bias), want)


@pytest.mark.skipif(not path_module.onednn(torch.bfloat16), reason="oneDNN has no bfloat16 product here")
@torch.no_grad()
def test_a_bfloat16_product_and_its_relu_equal_autocast_bit_for_bit(monkeypatch):
    """The head's half-resolution product: oneDNN with the ReLU fused gives autocast's values, bit for bit."""
    torch.manual_seed(1)
    x, weight, bias = torch.randn(4096, 32).bfloat16(), torch.randn(128, 32), torch.randn(128)
    path = InferencePath(precision="bfloat16")
    with path.autocast():
        got = path.linear(x, weight, bias, relu=True)
        monkeypatch.setattr(path_module, "onednn", lambda dtype: False)  # PyTorch's layers under autocast
        want = path.linear(x, weight, bias, relu=True)
    assert got.dtype == want.dtype == torch.bfloat16 and torch.equal(got, want)
    assert (want == 0).any() and (want > 0).any()


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
@torch.no_grad()
def test_the_fusions_padded_queries_change_no_value(precision):
    """On the compiled path the fusion's queries are padded to a multiple of query_rows, so that oneDNN reuses its
    primitives from frame to frame: every query's result is computed on its own, so the fused volume is the same,
    bit for bit, as without padding."""
    torch.manual_seed(0)
    model = build_model(preset("tiny-lidar")).eval()
    ego = model.vehicle(**shaped_inputs(model))
    others = [VehicleOutput(ego.features.roll(3 * i, 2), ego.confidence.roll(3 * i, 2)) for i in (1, 2)]
    poses = torch.eye(4).repeat(1, 2, 1, 1)
    poses[0, :, 0, 3] = torch.tensor([4.0, -4.0])  # metres: the neighbours' volumes shifted against the ego's
    fused = {}
    for rows in (1, 512, 20_000):
        model.use(InferencePath("cpu", precision, query_rows=rows))
        fused[rows] = model.ego.fuse(ego, others, poses)
    queries = int(model.ego.align(ego, others, poses)[2].any(1).sum())
    assert queries % 512 and queries < 20_000  # both paddings pad
    assert torch.equal(fused[1], fused[512]) and torch.equal(fused[1], fused[20_000])
    with pytest.raises(Co3sopError, match="query_rows 0: at least 1"):
        InferencePath(query_rows=0)
