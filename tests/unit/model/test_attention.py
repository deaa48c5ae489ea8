"""Unit tests for the sampling and attention building blocks of the model.

deform_attn.sample_2d / sample_3d against explicit bilinear / trilinear loops
(align_corners=False: pixel / voxel centre i at (i + 0.5) / n, zeros outside);
DeformableAttention3d's per-query agent mask; VoxelFusion's masked path against
its dense path; the deformable convolution against its loop definition and a
plain convolution; the 3D sine positional encoding.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch
import torch.nn.functional as F

from co3sop_nodes.model.backbone import DeformConv2d, deform_conv2d, deform_conv2d_reference
from co3sop_nodes.model.config import AttentionConfig
from co3sop_nodes.model.deform_attn import DeformableAttention3d, sample_2d, sample_3d
from co3sop_nodes.model.fusion import VoxelFusion, channels_last_rows
from co3sop_nodes.model.positional import sine_encoding_3d

# ---------------------------------------------------------------- references


def _bilinear(img: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """img (C, H, W); (x, y) normalised in [0, 1] (pixel centre i at (i + 0.5) / n) -> (C,), zeros outside."""
    c, h, w = img.shape
    px, py = x * w - 0.5, y * h - 0.5
    x0, y0 = math.floor(px), math.floor(py)
    out = torch.zeros(c, dtype=torch.float64)
    for dy, dx in itertools.product((0, 1), (0, 1)):
        yy, xx = y0 + dy, x0 + dx
        wgt = (py - y0 if dy else 1 - (py - y0)) * (px - x0 if dx else 1 - (px - x0))
        if 0 <= yy < h and 0 <= xx < w:
            out += wgt * img[:, yy, xx].double()
    return out


def _trilinear(vol: torch.Tensor, x: float, y: float, z: float) -> torch.Tensor:
    """vol (C, X, Y, Z); (x, y, z) normalised in [0, 1] -> (C,), zeros outside."""
    c = vol.shape[0]
    pos = [v * n - 0.5 for v, n in zip((x, y, z), vol.shape[1:])]
    base = [math.floor(p) for p in pos]
    out = torch.zeros(c, dtype=torch.float64)
    for corner in itertools.product((0, 1), repeat=3):
        idx = [b + d for b, d in zip(base, corner)]
        wgt = 1.0
        for p, b, d in zip(pos, base, corner):
            wgt *= (p - b) if d else 1 - (p - b)
        if all(0 <= i < n for i, n in zip(idx, vol.shape[1:])):
            out += wgt * vol[:, idx[0], idx[1], idx[2]].double()
    return out


# ---------------------------------------------------------------- sample_2d / sample_3d


def test_sample_2d_matches_bilinear_loops():
    torch.manual_seed(0)
    b, q, h, p, ch = 2, 3, 2, 2, 3
    shapes = [(4, 5), (2, 3)]  # (Hl, Wl) per level
    values = [torch.randn(b * h, ch, hl, wl) for hl, wl in shapes]
    loc = torch.rand(b, q, h, len(shapes), p, 2) * 1.6 - 0.3  # some samples outside [0, 1]
    loc[0, 0, 0, 0, 0] = torch.tensor([1.2, 0.5])  # wholly outside: reads zero
    wts = torch.rand(b, q, h, len(shapes), p)
    out = sample_2d(values, loc, wts)
    assert out.shape == (b, q, h * ch)
    expected = torch.zeros(b, q, h * ch, dtype=torch.float64)
    for bi, qi, hi, lv, pi in itertools.product(range(b), range(q), range(h), range(len(shapes)), range(p)):
        x, y = loc[bi, qi, hi, lv, pi].tolist()
        s = _bilinear(values[lv][bi * h + hi], x, y)
        expected[bi, qi, hi * ch : (hi + 1) * ch] += wts[bi, qi, hi, lv, pi].double() * s
    torch.testing.assert_close(out.double(), expected, atol=1e-5, rtol=1e-5)


def test_sample_2d_pixel_centre_convention():
    """A location at pixel (r, c)'s centre ((c + 0.5) / W, (r + 0.5) / H) reads exactly that pixel; x is the width axis."""
    img = torch.arange(12, dtype=torch.float32).view(1, 1, 3, 4)  # H=3, W=4
    loc = torch.tensor([[(c + 0.5) / 4, (r + 0.5) / 3] for r in range(3) for c in range(4)]).view(1, 12, 1, 1, 1, 2)
    out = sample_2d([img], loc, torch.ones(1, 12, 1, 1, 1))
    torch.testing.assert_close(out.view(12), torch.arange(12, dtype=torch.float32), atol=1e-6, rtol=0)


def test_sample_3d_matches_trilinear_loops():
    torch.manual_seed(1)
    b, q, h, a, p, ch = 2, 3, 2, 2, 2, 2
    dims = (4, 3, 2)
    values = torch.randn(b * h, a, ch, *dims)
    loc = torch.rand(b, q, h, a, p, 3) * 1.6 - 0.3
    loc[1, 2, 1, 1, 1] = torch.tensor([0.5, -0.4, 0.5])  # wholly outside: reads zero
    wts = torch.rand(b, q, h, a, p)
    out = sample_3d(values, loc, wts)
    assert out.shape == (b, q, h * ch)
    expected = torch.zeros(b, q, h * ch, dtype=torch.float64)
    for bi, qi, hi, ai, pi in itertools.product(range(b), range(q), range(h), range(a), range(p)):
        x, y, z = loc[bi, qi, hi, ai, pi].tolist()
        s = _trilinear(values[bi * h + hi, ai], x, y, z)
        expected[bi, qi, hi * ch : (hi + 1) * ch] += wts[bi, qi, hi, ai, pi].double() * s
    torch.testing.assert_close(out.double(), expected, atol=1e-5, rtol=1e-5)


def test_sample_3d_voxel_centre_convention():
    """Location ((i+.5)/X, (j+.5)/Y, (k+.5)/Z) reads voxel (i, j, k) of a (X, Y, Z) volume, axis order kept."""
    dims = (4, 3, 2)
    vol = torch.arange(24, dtype=torch.float32).view(1, 1, 1, *dims)
    idx = list(itertools.product(*(range(n) for n in dims)))
    loc = torch.tensor([[(i + 0.5) / n for i, n in zip(ijk, dims)] for ijk in idx]).view(1, len(idx), 1, 1, 1, 3)
    out = sample_3d(vol, loc, torch.ones(1, len(idx), 1, 1, 1))
    torch.testing.assert_close(out.view(-1), torch.arange(24, dtype=torch.float32), atol=1e-6, rtol=0)


# ---------------------------------------------------------------- DeformableAttention3d


def _randomised_attention(seed: int, dims=8, heads=2, points=2, slots=3, extent=(4, 3, 2)) -> DeformableAttention3d:
    torch.manual_seed(seed)
    att = DeformableAttention3d(dims, heads, points, slots, extent)
    with torch.no_grad():
        for p in att.parameters():
            p.add_(torch.randn_like(p) * 0.3)  # break the structured init: offsets depend on the query
    return att.eval()


def test_attention_masked_agent_values_do_not_matter():
    att = _randomised_attention(0)
    b, q, a, c = 2, 5, 3, 8
    query, ref = torch.randn(b, q, c), torch.rand(b, q, 3)
    values = torch.randn(b, a, c, 4, 3, 2)
    mask = torch.rand(b, q, a) > 0.4
    mask[:, :, 0] = True  # everyone may read agent 0
    mask[0, 0] = torch.tensor([True, False, False])
    mask[0, 1] = torch.tensor([True, True, False])
    out = att(query, ref, values, mask)
    for agent in (1, 2):
        changed = values.clone()
        changed[:, agent] = torch.randn_like(changed[:, agent]) * 5
        out2 = att(query, ref, changed, mask)
        blind = ~mask[:, :, agent]
        torch.testing.assert_close(out2[blind], out[blind], atol=1e-6, rtol=0)
        assert blind.any() and (~blind).any()
        # the agent does matter to queries allowed to read it
        assert not torch.allclose(out2[~blind], out[~blind], atol=1e-4)


def test_attention_single_allowed_agent_equals_attending_to_it_alone():
    """Softmax over the remaining agents x points: a query allowed only agent 0 equals a one-agent call."""
    att = _randomised_attention(1)
    b, q, c = 1, 4, 8
    query, ref = torch.randn(b, q, c), torch.rand(b, q, 3)
    values = torch.randn(b, 3, c, 4, 3, 2)
    only0 = torch.zeros(b, q, 3, dtype=torch.bool)
    only0[..., 0] = True
    full = att(query, ref, values, only0)
    alone = att(query, ref, values[:, :1], torch.ones(b, q, 1, dtype=torch.bool))
    torch.testing.assert_close(full, alone, atol=1e-6, rtol=1e-5)


def test_attention_all_agents_masked_outputs_bias():
    att = _randomised_attention(2)
    b, q, c = 2, 4, 8
    query, ref = torch.randn(b, q, c), torch.rand(b, q, 3)
    values = torch.randn(b, 2, c, 4, 3, 2)
    mask = torch.ones(b, q, 2, dtype=torch.bool)
    mask[0, 1] = False
    mask[1, 3] = False
    out = att(query, ref, values, mask)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out[0, 1], att.output.bias, atol=1e-6, rtol=0)
    torch.testing.assert_close(out[1, 3], att.output.bias, atol=1e-6, rtol=0)
    assert not torch.allclose(out[0, 0], att.output.bias, atol=1e-3)


def test_attention_all_masked_backward_is_finite():
    att = _randomised_attention(3).train()
    query = torch.randn(1, 3, 8, requires_grad=True)
    values = torch.randn(1, 2, 8, 4, 3, 2, requires_grad=True)
    mask = torch.zeros(1, 3, 2, dtype=torch.bool)
    mask[0, 0, 1] = True
    att(query, torch.rand(1, 3, 3), values, mask).sum().backward()
    for t in [query.grad, values.grad] + [p.grad for p in att.parameters()]:
        assert t is not None and torch.isfinite(t).all()


# ---------------------------------------------------------------- VoxelFusion


def _fusion(seed: int, dims_xyz=(4, 3, 2)) -> VoxelFusion:
    torch.manual_seed(seed)
    fusion = VoxelFusion(8, AttentionConfig(layers=2, heads=2, points=2), slots=3, dims_xyz=dims_xyz)
    with torch.no_grad():
        for layer in fusion.layers:
            layer.attention.offsets.weight.normal_(0, 0.3)
    return fusion.eval()


@pytest.mark.parametrize("b", [1, 2])
@pytest.mark.parametrize("seed", range(3))
def test_fusion_masked_path_equals_dense(b, seed):
    fusion = _fusion(seed)
    a, dims = 2, (4, 3, 2)
    ego = torch.randn(b, 8, *dims)
    values = torch.randn(b, a, 8, *dims)
    mask = torch.rand(b, a, *dims) < 0.3
    if b == 2 and seed == 0:
        mask[1] = False  # a batch element with nothing to fuse
    with torch.no_grad():
        sparse = fusion(ego, values, mask, dense=False)
        dense = fusion(ego, values, mask, dense=True)
    assert sparse.shape == ego.shape
    torch.testing.assert_close(sparse, dense, atol=1e-5, rtol=1e-5)
    selected = mask.any(1, keepdim=True).expand_as(ego)
    assert torch.equal(sparse[~selected], ego[~selected])  # unselected voxels keep the ego's own feature
    assert selected.any()
    assert not torch.allclose(sparse[selected], ego[selected], atol=1e-3)  # selected ones are fused


@pytest.mark.parametrize("b", [1, 2])
def test_fusion_selected_voxel_equals_layers_on_that_voxel_alone(b):
    """Each selected voxel is the layer stack applied to that one query, with its own position, reference,
    batch element's collaborator volumes and mask."""
    fusion = _fusion(5)
    dims = (4, 3, 2)
    ego, values = torch.randn(b, 8, *dims), torch.randn(b, 2, 8, *dims)
    mask = torch.rand(b, 2, *dims) < 0.4
    checked = 0
    with torch.no_grad():
        out = fusion(ego, values, mask)
        for n in range(b):
            flat_mask = mask[n].flatten(1).T  # (V, A)
            for v in flat_mask.any(-1).nonzero()[:, 0].tolist():
                i, j, k = v // 6, (v // 2) % 3, v % 2
                q = ego[n, :, i, j, k][None, None]
                ref = torch.tensor([[(i + 0.5) / 4, (j + 0.5) / 3, (k + 0.5) / 2]])[None]
                for layer in fusion.layers:
                    q = layer(q, fusion.pos[v][None, None], ref, values[n : n + 1], flat_mask[v][None, None])
                torch.testing.assert_close(out[n, :, i, j, k], q[0, 0], atol=1e-5, rtol=1e-5)
                checked += 1
    assert checked > 3 * b


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("b", [1, 2])
def test_channels_last_rows_copy_each_voxels_channels_together(b, dtype):
    volume = torch.randn(b, 8, 4, 3, 2).to(dtype)
    rows = channels_last_rows(volume)
    assert rows.is_contiguous() and rows.dtype == dtype
    assert torch.equal(rows, volume.flatten(2).transpose(1, 2))
    volume = volume.contiguous(memory_format=torch.channels_last_3d)  # whatever the source's layout
    assert torch.equal(channels_last_rows(volume), rows)


def test_fusion_reference_points_are_voxel_centres():
    fusion = _fusion(0)
    ref = fusion.reference.view(4, 3, 2, 3)
    assert ref[1, 2, 0].tolist() == pytest.approx([1.5 / 4, 2.5 / 3, 0.5 / 2])
    assert fusion.pos.shape == (24, 8)


# ---------------------------------------------------------------- deformable convolution


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("seed", range(2))
def test_deform_conv2d_matches_reference(stride, seed):
    torch.manual_seed(seed)
    b, cin, cout, h, w = 2, 3, 4, 5, 6
    x = torch.randn(b, cin, h, w)
    weight, bias = torch.randn(cout, cin, 3, 3), torch.randn(cout)
    ho, wo = (h - 1) // stride + 1, (w - 1) // stride + 1
    offset = torch.randn(b, 18, ho, wo) * 2.0
    offset[0, :2, 0, 0] = torch.tensor([-7.3, 0.4])  # far above the image
    offset[1, 16:18, -1, -1] = torch.tensor([0.2, 9.1])  # far right of the image
    offset[0, 8:10, 1, 1] = torch.tensor([-1.0, 2.0])  # integer offset
    mask = torch.rand(b, 9, ho, wo)
    fast = deform_conv2d(x, offset, mask, weight, bias, stride, 1)
    ref = deform_conv2d_reference(x, offset, mask, weight, bias, stride, 1)
    assert fast.shape == (b, cout, ho, wo)
    torch.testing.assert_close(fast, ref, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(
        deform_conv2d(x, offset, mask, weight, None, stride, 1),
        deform_conv2d_reference(x, offset, mask, weight, None, stride, 1),
        atol=1e-4,
        rtol=1e-4,
    )


@pytest.mark.parametrize("stride", [1, 2])
def test_deform_conv2d_zero_offsets_unit_mask_is_conv2d(stride):
    torch.manual_seed(4)
    x, weight, bias = torch.randn(1, 2, 5, 4), torch.randn(3, 2, 3, 3), torch.randn(3)
    expected = F.conv2d(x, weight, bias, stride, 1)
    ho, wo = expected.shape[-2:]
    zeros, ones = torch.zeros(1, 18, ho, wo), torch.ones(1, 9, ho, wo)
    torch.testing.assert_close(deform_conv2d(x, zeros, ones, weight, bias, stride, 1), expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(
        deform_conv2d_reference(x, zeros, ones, weight, bias, stride, 1), expected, atol=1e-5, rtol=1e-5
    )


def test_deform_conv2d_offset_order_is_dy_dx():
    """offset channels (2t, 2t+1) = (dy, dx) of tap t: a +1 dx everywhere equals convolving the image shifted left."""
    torch.manual_seed(6)
    x, weight = torch.randn(1, 1, 4, 5), torch.randn(1, 1, 3, 3)
    offset = torch.zeros(1, 18, 4, 5)
    offset[:, 1::2] = 1.0  # dx = +1 on every tap
    shifted = torch.cat([x[..., 1:], torch.zeros(1, 1, 4, 1)], dim=-1)  # shifted[.., c] = x[.., c + 1]
    out = deform_conv2d(x, offset, torch.ones(1, 9, 4, 5), weight, None, 1, 1)
    # column 0's left taps read x[.., 0] (not padding) once moved right by one: compare the others
    torch.testing.assert_close(out[..., 1:], F.conv2d(shifted, weight, None, 1, 1)[..., 1:], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("stride", [1, 2])
def test_deform_conv_module_at_init_is_plain_conv(stride):
    torch.manual_seed(7)
    layer = DeformConv2d(3, 4, stride)
    x = torch.randn(2, 3, 7, 6)
    torch.testing.assert_close(layer(x), F.conv2d(x, layer.weight, None, stride, 1), atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        layer.offset.bias[0] = 0.7  # a learned offset moves it off the plain convolution
    assert not torch.allclose(layer(x), F.conv2d(x, layer.weight, None, stride, 1), atol=1e-3)


# ---------------------------------------------------------------- positional encoding


def _grid_positions(dims=(4, 3, 2)) -> torch.Tensor:
    axes = [(torch.arange(n, dtype=torch.float32) + 0.5) / n for n in dims]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


@pytest.mark.parametrize("dims", [6, 12, 16, 30, 32, 33, 128])
def test_sine_encoding_shape_range_and_distinctness(dims):
    pos = _grid_positions()
    enc = sine_encoding_3d(pos, dims)
    assert enc.shape == (len(pos), dims)
    assert enc.abs().max() <= 1.0 + 1e-6
    dist = torch.cdist(enc, enc) + torch.eye(len(pos)) * 10
    assert dist.min() > 1e-3  # every voxel centre is encoded differently


def test_sine_encoding_known_values():
    """dims=6: one frequency per axis, (sin, cos) of 2 pi p for x, then y, then z."""
    enc = sine_encoding_3d(torch.tensor([[0.25, 0.5, 0.0]]), 6)[0]
    torch.testing.assert_close(enc, torch.tensor([1.0, 0.0, 0.0, -1.0, 0.0, 1.0]), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dims", [7, 8])
def test_sine_encoding_small_dims_keep_height(dims):
    pos = torch.tensor([[0.5, 0.5, 0.25], [0.5, 0.5, 0.75]])
    enc = sine_encoding_3d(pos, dims)
    assert not torch.allclose(enc[0], enc[1])
