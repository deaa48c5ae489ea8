"""The compiled deformable samplers against their definitions (deform_attn.sample_2d / sample_3d with grid_sample):
the 2D one alone and inside the vehicle half, the 3D one inside the fusion's attention."""

from __future__ import annotations

import math

import pytest
import torch
from model_checks import MICRO

from co3sop_nodes import kernels
from co3sop_nodes.inference import pace
from co3sop_nodes.kernels import deform as deform_kernel
from co3sop_nodes.kernels import octant as octant_kernel
from co3sop_nodes.kernels.warp import compiled_available, warp_compiled
from co3sop_nodes.model.co3sop import VehicleOutput, build_model
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.deform_attn import DeformableAttention3d, sample_2d
from co3sop_nodes.model.path import InferencePath


@pytest.mark.parametrize("channels_per_head, threads", [(8, 1), (16, 1), (8, 3), (12, 1), (4, 2)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("levels, points", [(3, 4), (4, 4), (2, 3)])
def test_the_compiled_sampler_equals_grid_sample(channels_per_head, threads, dtype, levels, points):
    """Offsets and logits as a float32 or a bfloat16 path's projections write them; the definition reads the same
    values widened to float32. Terms (levels x points) in whole vectors of 8 and not."""
    gen = torch.Generator().manual_seed(channels_per_head + threads)
    h, q, n = 4, 2000, 3
    shapes = [(30, 40), (15, 20), (7, 11), (4, 5)][:levels]  # (Hl, Wl)
    values = [
        torch.randn(n, rows, cols, h * channels_per_head, generator=gen) for rows, cols in shapes
    ]  # channels-last, per camera
    visible = torch.rand(n, q, generator=gen) < 0.4
    visible[:, :5] = False  # queries no camera sees: zeros
    uv = torch.rand(n, q, 2, generator=gen)
    # pixels: some points fall outside every map
    offsets = (torch.randn(q, h, levels, points, 2, generator=gen) * 8).to(dtype)
    first = visible.any(0).nonzero()[0, 0]
    offsets[first, 0, 0, 0] = float("nan")  # the kernel reads zeros there (grid_sample's value for NaN is unspecified)
    logits = (torch.randn(q, h, levels * points, generator=gen) * 3).to(dtype)
    assert deform_kernel.available(channels_per_head)
    got = deform_kernel.sample_cameras(values, uv, visible, offsets, logits, threads)
    offsets, logits = offsets.float(), logits.float()
    offsets[first, 0, 0, 0] = 1e6  # the definition on a point outside every map: zeros
    weights = torch.softmax(logits, -1).view(q, h, levels, points)
    scale = torch.tensor([[cols, rows] for rows, cols in shapes], dtype=torch.float32)  # (L, 2) W, H
    total = torch.zeros(q, h * channels_per_head)
    for k in range(n):  # the definition, camera by camera: (B*H, Ch, Hl, Wl) maps, B = 1
        maps = [v[k].permute(2, 0, 1).reshape(h, channels_per_head, *v.shape[1:3]) for v in values]
        mine = visible[k].nonzero()[:, 0]
        loc = uv[k, mine][:, None, None, None, :] + offsets[mine] / scale[None, None, :, None, :]
        total[mine] += sample_2d(maps, loc[None], weights[mine][None])[0]
    want = total / visible.sum(0).clamp(min=1)[:, None]
    # the kernel's softmax takes libm's exp, not PyTorch's, and divides each weight by the sum: the 3D sampler's 1e-4
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)
    assert not got[:5].any()


def test_no_kernel_for_head_widths_that_are_not_vectors():
    """A head's channels are read as 8-lane vectors, or 4-lane ones (`small`'s 12 channels a head)."""
    assert not deform_kernel.available(6) and not deform_kernel.available(10)
    assert deform_kernel.available(12) and deform_kernel.available(8)
    # the kernels' softmax takes at most MAX_TERMS terms a query and head
    assert deform_kernel.available(8, deform_kernel.MAX_TERMS) and not deform_kernel.available(
        8, deform_kernel.MAX_TERMS + 1
    )


@pytest.mark.parametrize("name", ["tiny", "small", "paper"])
def test_the_camera_vehicle_half_at_inference_equals_its_training_path(name, monkeypatch):
    torch.manual_seed(0)
    model = build_model(preset(name, **MICRO)).eval()
    inputs = pace.shaped_inputs(model)
    calls = []
    compiled = deform_kernel.sample_cameras
    monkeypatch.setattr(deform_kernel, "sample_cameras", lambda *a: calls.append(1) or compiled(*a))
    with torch.no_grad():  # inference: the compiled sampler
        fast = model.vehicle(**inputs)
    assert len(calls) == model.cfg.image_attention.layers  # every lifting layer
    with torch.enable_grad():  # the PyTorch definition (grid_sample), as in training
        ref = model.vehicle(**inputs)
    torch.testing.assert_close(fast.features, ref.features.detach(), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fast.confidence, ref.confidence.detach(), rtol=1e-4, atol=1e-4)


# heads sampled 4 at a time, and one at a time where 4 does not divide them
@pytest.mark.parametrize("dims, heads, agents", [(32, 4, 2), (64, 4, 3), (48, 4, 2), (48, 3, 2), (16, 2, 3)])
def test_the_compiled_3d_sampler_equals_the_attention_training_path(dims, heads, agents, monkeypatch):
    torch.manual_seed(dims + agents)
    att = DeformableAttention3d(dims, heads, 4, slots=6, extent_voxels=(16, 12, 6)).eval()
    with torch.no_grad():
        for param in att.parameters():
            param.normal_(0, 0.5)  # offsets of several voxels: many samples between and outside voxels
    q = 3000
    query, reference = torch.randn(1, q, dims), torch.rand(1, q, 3)
    values = torch.randn(1, agents, dims, 16, 12, 6)
    mask = torch.rand(1, q, agents) < 0.6  # some queries may attend to no agent: they read nothing
    calls = []
    compiled = deform_kernel.sample_3d
    monkeypatch.setattr(deform_kernel, "sample_3d", lambda *a: calls.append(1) or compiled(*a))
    with torch.no_grad():
        got = att(query, reference, values, mask)
    with torch.enable_grad():
        want = att(query, reference, values, mask).detach()
    assert calls == [1]
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("agents", [2, 3])
@pytest.mark.parametrize("ch", [8, 12])
def test_the_3d_sampler_reads_bfloat16_values_and_projections_as_their_float32_widening(agents, ch):
    """A bfloat16 path's volumes, offsets and logits, read as they are: the same sums as from the same values in
    float32, bit for bit (bfloat16 widens exactly; only the loads differ). Terms (agents x points) in whole vectors
    and not; a head's channels in vectors of 8 and of 4."""
    gen = torch.Generator().manual_seed(5)
    q, h, a, p = 1500, 4, agents, 4
    values = torch.randn(a, 16, 12, 6, h * ch, generator=gen).bfloat16()
    reference = torch.rand(q, 3, generator=gen)
    offsets = (torch.randn(q, h, a, p, 3, generator=gen) * 3).bfloat16()
    logits = (torch.randn(q, h, a, p, generator=gen) * 3).bfloat16()
    allowed = torch.rand(q, a, generator=gen) < 0.6
    calls = []
    compiled = deform_kernel._kernel
    with pytest.MonkeyPatch.context() as patch:  # the bfloat16 function is the one that ran
        patch.setattr(deform_kernel, "_kernel", lambda *a: calls.append(a[-1]) or compiled(*a))
        got = deform_kernel.sample_3d(values, reference, offsets, logits, allowed, 1)
    want = deform_kernel.sample_3d(values.float(), reference, offsets.float(), logits.float(), allowed, 1)
    assert calls == ["deform_sample_3d_bf16"]
    assert got.any() and torch.equal(got, want)


def warp_scene(seed: int, yaw: float, shift: tuple[float, float, float]):
    """tiny-lidar's model, random ego and 2 neighbours' outputs, the first neighbour turned by `yaw` and moved by
    `shift`, the second moved back by it: (model, ego, others, neighbour_from_ego (1, 2, 4, 4))."""
    torch.manual_seed(seed)
    cfg = preset("tiny-lidar")
    model = build_model(cfg).eval()
    grid = cfg.feature_grid
    ego = VehicleOutput(torch.randn(1, cfg.embed_dims, *grid.dims), torch.rand(1, 1, *grid.dims))
    others = [VehicleOutput(torch.randn(1, cfg.embed_dims, *grid.dims), torch.rand(1, 1, *grid.dims)) for _ in range(2)]
    rel = torch.eye(4).repeat(1, 2, 1, 1)  # (B, A, 4, 4) neighbour_from_ego
    c, s = math.cos(yaw), math.sin(yaw)
    rel[0, 0, :2, :2] = torch.tensor([[c, -s], [s, c]])
    rel[0, 0, :3, 3] = torch.tensor(shift)
    rel[0, 1, :3, 3] = -torch.tensor(shift)
    return model, ego, others, rel


@pytest.mark.parametrize("yaw, shift", [(0.3, (7.3, -4.1, 0.2)), (-2.0, (-20.5, 13.7, -0.4))])
def test_the_compiled_warp_equals_grid_sample(yaw, shift):
    model, ego, others, rel = warp_scene(1, yaw, shift)
    with torch.no_grad():
        fast = model.ego.align(ego, others, rel)
    with torch.enable_grad():
        ref = model.ego.align(ego, others, rel)
    assert fast[0].shape == ref[0].shape and fast[2].dtype == torch.bool
    # grid_sample samples at positions rounded through [-1, 1]: a few 1e-6 voxels off on a 64-voxel axis, times the
    # random features' differences between neighbouring voxels (up to about 6), as a CPU's own rounding gives them
    torch.testing.assert_close(fast[0], ref[0].detach(), rtol=1e-5, atol=5e-5)  # features
    torch.testing.assert_close(fast[1], ref[1].detach(), rtol=1e-5, atol=1e-5)  # confidences
    assert 0.1 < ref[2].float().mean() < 0.9 and torch.equal(fast[2], ref[2])  # hybrid masks


@torch.no_grad()
def test_a_bfloat16_path_warps_into_bfloat16_the_float32_warp_rounded():
    """The warp writes a bfloat16 path's features as the attention reads them: the float32 warp's values rounded to
    nearest even, bit for bit; confidences and masks as on the float32 path."""
    model, ego, others, rel = warp_scene(2, 0.9, (7.3, -4.1, 0.2))
    grid = model.cfg.feature_grid
    want = model.ego.align(ego, others, rel)
    model.use(InferencePath(precision="bfloat16"))
    got = model.ego.align(ego, others, rel)
    assert want[0].dtype == torch.float32 and got[0].dtype == torch.bfloat16 and got[0].shape == want[0].shape
    assert torch.equal(got[0], want[0].bfloat16()) and got[0].abs().sum() > 0
    assert torch.equal(got[1], want[1]) and torch.equal(got[2], want[2])
    with pytest.raises(ValueError, match="float32 or bfloat16 features, not torch.float16"):
        warp_compiled(
            others[0].features,
            others[0].confidence,
            rel[:, 0],
            grid,
            1,
            (torch.empty(*grid.dims, 32, dtype=torch.float16), torch.empty(*grid.dims)),
        )


def test_disabled_kernels_leave_the_pytorch_paths(monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert not deform_kernel.available(8) and not octant_kernel.available(16, 8, 24) and not compiled_available()
