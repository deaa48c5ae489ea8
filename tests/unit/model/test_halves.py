"""Unit tests for co3sop_nodes.model.co3sop and config: the vehicle half, the ego half and Co3SOP.

Two configurations, both small in channels:
- `BIG`: the real "76.8m" benchmark range (label grid 256 x 256 x 16, feature
  grid 64 x 64 x 4), for the output shapes of both modalities (eval mode);
- `SmallGridConfig`: the same model on a 32 x 32 x 16 label grid (a subclass
  overriding `grid`; nothing is patched), for the equivalence, training and
  collaborator tests, which compare several passes.
Untrained batch-norm statistics can switch the head's full-resolution ReLUs
off entirely; eval-mode comparisons first calibrate them (`_calibrated`) so
that every output scale responds to its input.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec
from co3sop_nodes.model.backbone import DeformConv2d
from co3sop_nodes.model.co3sop import Co3SOP, EgoHalf, VehicleHalf, VehicleOutput, build_model
from co3sop_nodes.model.config import AttentionConfig, BackboneConfig, LidarConfig, ModelConfig, preset
from co3sop_nodes.model.lifting import project
from co3sop_nodes.model.losses import confidence_loss, downsample_labels, occupancy_loss

W, H = 32, 24
BIG = ModelConfig(
    name="test",
    range="76.8m",
    image_size=(W, H),
    backbone=BackboneConfig(channels=(8, 8, 16, 16), stem=8),
    fpn_channels=8,
    embed_dims=8,
    head_channels=(8, 8, 4),
)
SMALL_GRID = GridSpec((-4.8, -4.8, -2.0), 0.3, (32, 32, 16))


class SmallGridConfig(ModelConfig):
    """The model on a small label grid: only `grid` differs (feature grid 8 x 8 x 4)."""

    @property
    def grid(self) -> GridSpec:
        return SMALL_GRID


SMALL = SmallGridConfig(**{f: getattr(BIG, f) for f in BIG.__dataclass_fields__})


def _lidar2img(yaw: float) -> torch.Tensor:
    """A pinhole camera at the LiDAR origin looking along the LiDAR's direction `yaw` (90 degree field of view)."""
    k = torch.tensor([[W / 2, 0, W / 2, 0], [0, W / 2, H / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float32)
    cam_from_lidar_axes = torch.tensor([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=torch.float32)
    c, s = math.cos(yaw), math.sin(yaw)
    unrotate = torch.tensor([[c, s, 0, 0], [-s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float32)
    return k @ cam_from_lidar_axes @ unrotate


RIG = torch.stack([_lidar2img(0.0), _lidar2img(math.pi)])  # front and back cameras


def _camera_inputs(b: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    return dict(
        images=torch.randint(0, 256, (b, 2, 3, H, W), generator=g, dtype=torch.uint8),
        lidar2img=RIG.expand(b, 2, 4, 4).clone(),
    )


def _transforms(b: int, a: int, seed: int, voxel: float) -> torch.Tensor:
    """(B, A, 4, 4) neighbour_from_ego: small yaws and shifts of a few feature voxels."""
    g = torch.Generator().manual_seed(seed)
    t = torch.eye(4).repeat(b, a, 1, 1)
    for i in range(b):
        for j in range(a):
            yaw = (torch.rand((), generator=g).item() - 0.5) * 0.6
            c, s = math.cos(yaw), math.sin(yaw)
            t[i, j, :2, :2] = torch.tensor([[c, -s], [s, c]])
            t[i, j, :2, 3] = (torch.rand(2, generator=g) - 0.5) * 4 * voxel
    return t


def _model(cfg: ModelConfig, seed: int = 0) -> Co3SOP:
    torch.manual_seed(seed)
    return build_model(cfg)


def _calibrated(model: Co3SOP, agents: list[dict], t: torch.Tensor) -> Co3SOP:
    """Batch-norm running statistics set from one training-mode pass over these inputs, then eval mode.

    Freshly initialised running statistics (mean 0, variance 1) leave the head's
    activations so small at init that its full-resolution ReLUs can all be off;
    calibrated statistics make every output scale depend on its input.
    """
    for m in model.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None  # cumulative average of this pass's batches, not a blend with the init values
    model.train()
    with torch.no_grad():
        outs = [model.vehicle(**a) for a in agents]
        model.ego(outs[0], [_confident(o) for o in outs[1:]], t)
    return model.eval()


def _confident(out: VehicleOutput) -> VehicleOutput:
    """A collaborator sure of every voxel: its confidence beats the ego's wherever its warp covers."""
    return VehicleOutput(out.features, torch.ones_like(out.confidence))


# ---------------------------------------------------------------- config


def test_presets_and_feature_grid():
    assert BIG.grid == BENCHMARK_RANGES["76.8m"]
    assert BIG.feature_grid.dims == (64, 64, 4)
    assert BIG.feature_grid.voxel_size == pytest.approx(1.2)
    assert BIG.feature_grid.origin == BIG.grid.origin
    assert SMALL.feature_grid.dims == (8, 8, 4) and SMALL.embed_dims == 8 and SMALL.image_size == (W, H)
    tiny = preset("tiny")
    assert tiny.fusion and tiny.modality == "camera" and tiny.feature_grid.dims == (64, 64, 6)
    assert preset("tiny-single").fusion is False
    assert preset("tiny-sscnet").lidar.kind == "sscnet" and preset("tiny-lmscnet").modality == "lidar"
    lidar = preset("tiny-lidar")  # collaborative LiDAR Co3SOP-Base: tiny-sscnet's vehicle half, tiny's fusion and head
    assert lidar.fusion and lidar.modality == "lidar" and lidar.lidar == preset("tiny-sscnet").lidar
    assert replace(lidar, name="tiny", modality="camera", lidar=tiny.lidar) == tiny
    assert preset("tiny", max_collaborators=2).max_collaborators == 2
    early = preset("tiny-sscnet-early")  # tiny-sscnet itself, fed the merged scans
    assert early.early_fusion and replace(early, name="tiny-sscnet", early_fusion=False) == preset("tiny-sscnet")
    for bad in ({"fusion": True}, {"modality": "camera"}):  # early fusion merges scans before a single-agent model
        with pytest.raises(Co3sopError, match="early_fusion"):
            preset("tiny-sscnet-early", **bad)
    with pytest.raises(Co3sopError):
        preset("no-such-model")


def test_camera_rig_projection():
    """The test rig itself: a point 10 m ahead is the front camera's image centre and invisible to the back one."""
    pts = torch.tensor([[10.0, 0.0, 0.0], [-10.0, 0.0, 0.0], [10.0, 5.0, 2.5]])
    uv, visible = project(pts, RIG[None], (W, H))
    torch.testing.assert_close(uv[0, 0, 0], torch.tensor([0.5, 0.5]))
    torch.testing.assert_close(uv[0, 1, 1], torch.tensor([0.5, 0.5]))
    assert visible[0].tolist() == [[True, False, True], [False, True, False]]
    # left (+y) and up (+z) are the image's left (u < 0.5) and top (v < 0.5)
    assert uv[0, 0, 2, 0] < 0.5 and uv[0, 0, 2, 1] < 0.5
    # behind the front camera, on the line through its image corner (0, 0): u d = v d = 0 but d < 0, so not seen
    uv, visible = project(torch.tensor([[-10.0, -10.0, -7.5]]), RIG[None, :1], (W, H))
    assert not visible.any()


def test_projection_is_float32_under_autocast():
    """Geometry in float32 whatever the precision around it: bfloat16 would move a point by up to a pixel."""
    pts = torch.rand(2000, 3, generator=torch.Generator().manual_seed(3)) * 40 - 20
    want = project(pts, RIG[None], (W, H))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        uv, visible = project(pts, RIG[None], (W, H))
    assert uv.dtype == torch.float32 and torch.equal(uv, want[0]) and torch.equal(visible, want[1])
    assert want[1].any() and not want[1].all()


def test_the_learned_queries_projections_are_computed_once_per_weights(monkeypatch):
    """The first lifting layer's offsets and logits of the learned queries are the same every frame: inference
    computes them once, again when a weight changes in place (an optimiser's step, a checkpoint loaded), and
    training through the layer. Either way the features are those computed afresh, bit for bit."""
    model = _model(SMALL, 4).eval()
    attention = model.vehicle.lifting[0].attention
    calls = []
    projections = attention.projections
    monkeypatch.setattr(attention, "projections", lambda q: calls.append(1) or projections(q))
    g = torch.Generator().manual_seed(4)
    inputs = {"images": torch.randint(0, 256, (1, 2, 3, H, W), generator=g, dtype=torch.uint8), "lidar2img": RIG[None]}

    def afresh():
        model.vehicle._projected = None
        return model.vehicle(**inputs).features

    with torch.no_grad():
        first, second = model.vehicle(**inputs).features, model.vehicle(**inputs).features
        assert len(calls) == 1 and torch.equal(first, second) and torch.equal(first, afresh())
        attention.offsets.bias.add_(0.7)
        changed = model.vehicle(**inputs).features
        assert len(calls) == 3 and not torch.equal(changed, first) and torch.equal(changed, afresh())
    with torch.enable_grad():
        model.vehicle(**inputs)
        model.vehicle(**inputs)
    assert len(calls) == 6


# ---------------------------------------------------------------- shapes


def test_output_shapes_at_benchmark_range():
    model = _model(BIG).eval()
    b = 1
    agents = [_camera_inputs(b, s) for s in range(3)]
    with torch.no_grad():
        outs = [model.vehicle(**a) for a in agents]
        logits = model.ego(outs[0], outs[1:], _transforms(b, 2, 0, BIG.feature_grid.voxel_size))
    for out in outs:
        assert out.features.shape == (b, 8, 64, 64, 4)
        assert out.confidence.shape == (b, 1, 64, 64, 4)
        assert ((out.confidence >= 0) & (out.confidence <= 1)).all()
    assert [tuple(lg.shape) for lg in logits] == [(b, 24, 64, 64, 4), (b, 24, 128, 128, 8), (b, 24, 256, 256, 16)]
    assert all(torch.isfinite(lg).all() for lg in logits)
    # the cameras see part of the grid: lifted features vary over the voxels
    assert outs[0].features.std(dim=(2, 3, 4)).min() > 0


def test_lifted_features_depend_on_images_only_where_a_camera_sees_the_voxel():
    """Front camera only (90 x 74 degree view along +x): a feature voxel's centre p is seen iff x > 0, |y| <= x and
    |z| <= 0.75 x. Changing the image changes exactly those voxels' features, at their (x, y, z) place in the volume."""
    model = _model(SMALL, 9).eval()
    fg = SMALL.feature_grid
    axes = [fg.origin[a] + (torch.arange(n, dtype=torch.float64) + 0.5) * fg.voxel_size for a, n in enumerate(fg.dims)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")  # (X, Y, Z) each
    margin = 0.05
    seen = (x > margin) & (y.abs() < x - margin) & (z.abs() < 0.75 * x - margin)
    unseen = (x < -margin) | (y.abs() > x + margin) | (z.abs() > 0.75 * x + margin)
    assert seen.any() and unseen.any()
    g = torch.Generator().manual_seed(9)
    lidar2img = RIG[None, :1]
    images = [torch.randint(0, 256, (1, 1, 3, H, W), generator=g, dtype=torch.uint8) for _ in range(2)]
    with torch.no_grad():
        a, b_ = (model.vehicle(images=im, lidar2img=lidar2img).features[0] for im in images)  # (C, X, Y, Z)
    diff = (a - b_).abs().amax(0)
    assert torch.all(diff[unseen] == 0)
    assert torch.all(diff[seen] > 1e-6)


def test_align_warps_each_collaborator_with_its_own_transform():
    """align: collaborator a's features and confidence warped by neighbour_from_ego[:, a]; hybrid mask = warp mask and
    a confidence above the ego's."""
    model = _model(SMALL, 10).eval()
    fg = SMALL.feature_grid
    g = torch.Generator().manual_seed(10)
    shape = (2, 8, *fg.dims)
    ego = VehicleOutput(torch.randn(shape, generator=g), torch.rand(2, 1, *fg.dims, generator=g))
    others = [VehicleOutput(torch.randn(shape, generator=g), torch.rand(2, 1, *fg.dims, generator=g)) for _ in range(2)]
    t = torch.eye(4).repeat(2, 2, 1, 1)
    t[:, 0, 0, 3] = fg.voxel_size  # collaborator 0: one voxel along x
    t[:, 1, 1, 3] = -2 * fg.voxel_size  # collaborator 1: two voxels along -y
    t[1, 1, 2, 3] = fg.voxel_size  # ... and for batch element 1, one up
    feats, confs, mask = model.ego.align(ego, others, t)
    assert feats.shape == (2, 2, 8, *fg.dims) and confs.shape == mask.shape == (2, 2, *fg.dims)
    shifts = {(0, 0): (1, 0, 0), (1, 0): (1, 0, 0), (0, 1): (0, -2, 0), (1, 1): (0, -2, 1)}
    nx, ny, nz = fg.dims
    for (n, a), (dx, dy, dz) in shifts.items():
        exp_f, exp_c = torch.zeros(8, *fg.dims), torch.zeros(fg.dims)
        covered = torch.zeros(fg.dims, dtype=torch.bool)
        xs, ys, zs = (
            slice(max(0, -dx), nx - max(0, dx)),
            slice(max(0, -dy), ny - max(0, dy)),
            slice(max(0, -dz), nz - max(0, dz)),
        )
        src = (
            slice(xs.start + dx, xs.stop + dx),
            slice(ys.start + dy, ys.stop + dy),
            slice(zs.start + dz, zs.stop + dz),
        )
        exp_f[:, xs, ys, zs] = others[a].features[n][(slice(None),) + src]
        exp_c[xs, ys, zs] = others[a].confidence[n, 0][src]
        covered[xs, ys, zs] = True
        torch.testing.assert_close(feats[n, a], exp_f, atol=1e-5, rtol=0)
        torch.testing.assert_close(confs[n, a], exp_c, atol=1e-5, rtol=0)
        assert torch.equal(mask[n, a], covered & (exp_c > ego.confidence[n, 0]))
        assert mask[n, a].any() and not mask[n, a].all()


# ---------------------------------------------------------------- halves vs whole


def test_halves_called_separately_equal_forward():
    model = _model(SMALL, 1)
    agents = [_camera_inputs(1, 10 + s) for s in range(3)]
    t = _transforms(1, 2, 1, SMALL.feature_grid.voxel_size)
    _calibrated(model, agents, t)
    with torch.no_grad():
        whole = model(agents, t)
        outs = [model.vehicle(**a) for a in agents]
        halves = model.ego(outs[0], outs[1:], t)
        fused = model.ego.fuse(outs[0], outs[1:], t)
        dense = model.ego.head(model.ego.fuse(outs[0], outs[1:], t, dense=True))
        alone = model.ego(outs[0])
        _, _, mask = model.ego.align(outs[0], outs[1:], t)
    assert mask.any() and not mask.all()  # fusion does run, on part of the grid
    selected = mask.any(1, keepdim=True).expand_as(fused)
    assert torch.equal(fused[~selected], outs[0].features[~selected])
    assert (fused[selected] - outs[0].features[selected]).abs().max() > 1e-2
    for w_, h_, d_, a_ in zip(whole, halves, dense, alone):
        torch.testing.assert_close(w_, h_, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(d_, h_, atol=1e-4, rtol=1e-4)
        assert (w_ - a_).abs().max() > 1e-4  # the collaborators changed the prediction at every scale


def test_batch_elements_are_independent():
    model = _model(SMALL, 2)
    b = 2
    agents = [_camera_inputs(b, 20 + s) for s in range(3)]
    t = _transforms(b, 2, 2, SMALL.feature_grid.voxel_size)
    _calibrated(model, agents, t)
    with torch.no_grad():
        both = model(agents, t)
        second = model([{k: v[1:] for k, v in a.items()} for a in agents], t[1:])
    for lg_both, lg_one in zip(both, second):
        torch.testing.assert_close(lg_both[1:], lg_one, atol=1e-5, rtol=1e-5)
        assert (lg_both[0] - lg_both[1]).abs().max() > 1e-4


@pytest.mark.parametrize("train", [False, True], ids=["eval", "train"])
def test_sampled_full_resolution_logits_equal_dense(train):
    """sample_index: full-resolution logits at chosen voxels only, equal to the dense pass there."""
    model = _model(SMALL, 8)
    b = 2
    agents = [_camera_inputs(b, 80 + s) for s in range(2)]
    t = _transforms(b, 1, 8, SMALL.feature_grid.voxel_size)
    _calibrated(model, agents, t).train(train)
    g = torch.Generator().manual_seed(8)
    n_full = SMALL.grid.num_voxels
    index = torch.randint(0, n_full, (b, 50), generator=g)
    index[0, :3] = torch.tensor([0, n_full - 1, 16 * 32 + 5])  # corners and a voxel in the middle of a row
    with torch.no_grad():
        dense = model(agents, t)
        sampled = model(agents, t, index)
    assert sampled[2].shape == (b, SMALL.num_classes, 50)
    torch.testing.assert_close(sampled[0], dense[0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(sampled[1], dense[1], atol=1e-5, rtol=1e-5)
    flat = dense[2].flatten(2)  # (B, K, X*Y*Z), C order over (x, y, z)
    expected = torch.gather(flat, 2, index[:, None].expand(-1, SMALL.num_classes, -1))
    torch.testing.assert_close(sampled[2], expected, atol=1e-5, rtol=1e-5)
    assert (expected - expected[..., :1]).abs().max() > 1e-3  # the sampled voxels' logits do differ


# ---------------------------------------------------------------- training


# The paper's sizes (ResNet-101 with DCN, 256-channel FPN, 3 + 3 attention layers) on the small grid and images.
PAPER_SMALL = preset(
    "paper", image_size=(W, H), custom_grid=(SMALL_GRID.origin, SMALL_GRID.voxel_size, SMALL_GRID.dims)
)


def test_paper_preset_has_the_papers_sizes():
    cfg = preset("paper")
    assert cfg.backbone.depth == (3, 4, 23, 3) and cfg.backbone.bottleneck  # ResNet-101
    assert cfg.backbone.channels == (256, 512, 1024, 2048) and cfg.backbone.deform_stages == (False, True, True, True)
    assert cfg.fpn_levels == 4 and cfg.fpn_channels == 256
    assert (cfg.fusion_attention.layers, cfg.fusion_attention.heads, cfg.fusion_attention.points) == (3, 4, 4)
    assert cfg.image_attention.layers == 3 and cfg.max_collaborators == 6 and cfg.fusion
    model = _model(PAPER_SMALL)
    backbone = model.vehicle.backbone
    assert [len(stage) for stage in backbone.stages] == [3, 4, 23, 3]
    # a 3x3 DCN in every block of the last three stages
    assert sum(isinstance(m, DeformConv2d) for m in backbone.modules()) == 4 + 23 + 3
    # torchvision's ResNet-101 without its classifier holds 42,500,160 parameters; each DCNv2 adds a 3x3 conv to
    # 27 offset/mask channels from the block's C mid channels
    offsets = sum(n * (27 * 9 * c + 27) for c, n in ((128, 4), (256, 23), (512, 3)))
    assert sum(p.numel() for p in backbone.parameters()) == 42_500_160 + offsets


SMALL_DCN = replace(
    SMALL,
    backbone=replace(SMALL.backbone, deform_stages=(False, True, True, True)),
    fusion_attention=AttentionConfig(layers=2, heads=2, points=2),
)


@pytest.mark.parametrize("cfg", [SMALL_DCN, PAPER_SMALL], ids=["small", "paper"])
def test_every_parameter_gets_a_gradient_with_two_collaborators(cfg):
    model = _model(cfg, 3).train()
    agents = [_camera_inputs(1, 30 + s) for s in range(3)]
    t = _transforms(1, 2, 3, cfg.feature_grid.voxel_size)
    outs = [model.vehicle(**a) for a in agents]
    others = [_confident(o) for o in outs[1:]]
    _, _, mask = model.ego.align(outs[0], others, t)
    assert mask.any()
    logits = model.ego(outs[0], others, t)
    g = torch.Generator().manual_seed(3)
    labels = torch.randint(0, cfg.num_classes, (1, *cfg.grid.dims), generator=g)
    labels[:, :4] = 255
    targets = [downsample_labels(labels, f, cfg.num_classes) for f in (4, 2, 1)]
    loss = sum(occupancy_loss(logits, targets).values()) + confidence_loss(outs[0].confidence, logits[0], targets[0])
    loss.backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert missing == []
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())
    assert any(isinstance(m, DeformConv2d) for m in model.modules())


# ---------------------------------------------------------------- collaborators


def test_zero_collaborators_equals_fusion_off():
    fused_model = _model(SMALL, 4)
    agents = [_camera_inputs(1, 40 + s) for s in range(2)]
    t = _transforms(1, 1, 4, SMALL.feature_grid.voxel_size)
    _calibrated(fused_model, agents, t)
    single = EgoHalf(replace(SMALL, fusion=False)).eval()
    assert single.fusion is None
    single.head.load_state_dict(fused_model.ego.head.state_dict())
    with torch.no_grad():
        outs = [fused_model.vehicle(**a) for a in agents]
        none = fused_model.ego(outs[0], [], None)
        via_whole = fused_model(agents[:1])
        off = single(outs[0])
        off_ignores_others = single(outs[0], [_confident(outs[1])], t)
        with_one = fused_model.ego(outs[0], [_confident(outs[1])], t)
    for a, b_, c, d, e in zip(none, via_whole, off, off_ignores_others, with_one):
        torch.testing.assert_close(a, c, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(b_, c, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(d, c, atol=1e-6, rtol=1e-6)
        assert (e - c).abs().max() > 1e-4


@pytest.mark.parametrize("kind", ["lmscnet", "sscnet"])
def test_lidar_modality_feature_shape(kind):
    cfg = replace(BIG, modality="lidar", lidar=LidarConfig(kind, 8))
    torch.manual_seed(5)
    vehicle = VehicleHalf(cfg).eval()
    occupancy = (torch.rand(1, 1, *cfg.grid.dims) < 0.05).float()
    with torch.no_grad():
        out = vehicle(occupancy=occupancy)
    camera_shape = (1, BIG.embed_dims, *BIG.feature_grid.dims)
    assert out.features.shape == camera_shape == (1, 8, 64, 64, 4)
    assert out.confidence.shape == (1, 1, 64, 64, 4)
    assert out.features.std() > 0


@pytest.mark.parametrize("kind", ["lmscnet", "sscnet"])
def test_lidar_modality_end_to_end_with_fusion(kind):
    cfg = replace(SMALL, modality="lidar", lidar=LidarConfig(kind, 8))
    model = _model(cfg, 6).eval()
    g = torch.Generator().manual_seed(6)
    agents = [dict(occupancy=(torch.rand(1, 1, *cfg.grid.dims, generator=g) < 0.1).float()) for _ in range(3)]
    t = _transforms(1, 2, 6, cfg.feature_grid.voxel_size)
    with torch.no_grad():
        logits = model(agents, t)
        outs = [model.vehicle(**a) for a in agents]
    assert outs[0].features.shape == (1, 8, 8, 8, 4)
    assert [tuple(lg.shape) for lg in logits] == [(1, 24, 8, 8, 4), (1, 24, 16, 16, 8), (1, 24, 32, 32, 16)]
    with torch.no_grad():  # scans arrive as uint8 0/1 (model.inputs.lidar_occupancy): the same as float input
        as_bytes = model.vehicle(occupancy=agents[0]["occupancy"].to(torch.uint8))
    torch.testing.assert_close(as_bytes.features, outs[0].features, atol=0, rtol=0)


def test_max_collaborators_caps_the_number_used():
    capped = _model(replace(SMALL, max_collaborators=1), 7)
    agents = [_camera_inputs(1, 70 + s) for s in range(3)]
    t = _transforms(1, 2, 7, SMALL.feature_grid.voxel_size)
    _calibrated(capped, agents, t)
    with torch.no_grad():
        outs = [capped.vehicle(**a) for a in agents]
        first, second = _confident(outs[1]), _confident(outs[2])
        other_second = VehicleOutput(second.features + 3 * torch.randn_like(second.features), second.confidence)
        other_first = VehicleOutput(first.features + 3 * torch.randn_like(first.features), first.confidence)
        base = capped.ego(outs[0], [first, second], t)
        only_first = capped.ego(outs[0], [first], t[:, :1])
        second_changed = capped.ego(outs[0], [first, other_second], t)
        first_changed = capped.ego(outs[0], [other_first, second], t)
        whole3 = capped(agents, t)
        whole2 = capped(agents[:2], t[:, :1])
    for a, b_, c, d in zip(base, only_first, second_changed, first_changed):
        torch.testing.assert_close(a, b_, atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(a, c, atol=1e-6, rtol=1e-6)
        assert (a - d).abs().max() > 1e-4
    for a, b_ in zip(whole3, whole2):
        torch.testing.assert_close(a, b_, atol=1e-6, rtol=1e-6)
    # control: allowed two collaborators, the second one does count
    two = _calibrated(_model(SMALL, 7), agents, t)
    with torch.no_grad():
        base2 = two.ego(outs[0], [first, second], t)
        second_changed2 = two.ego(outs[0], [first, other_second], t)
    for a, c in zip(base2, second_changed2):
        assert (a - c).abs().max() > 1e-4


@pytest.mark.parametrize("fault", ["nan-intrinsics", "inf-mount", "singular-mount", "zero-intrinsics", "empty-image"])
def test_sensor_inputs_refuse_degenerate_cameras(fault):
    """What a vehicle receives may be anything: a camera that cannot project is an input error, never NaN features."""
    from co3sop_nodes.inference.inputs import sensor_inputs

    cfg = preset("tiny")
    rgb, k, mount = np.zeros((48, 64, 3), np.uint8), np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]), np.eye(4)
    if fault == "nan-intrinsics":
        k[0, 0] = np.nan
    elif fault == "inf-mount":
        mount[0, 3] = np.inf
    elif fault == "singular-mount":
        mount[:3, :3] = 0.0
    elif fault == "zero-intrinsics":
        k[:] = 0.0
    else:
        rgb = np.zeros((0, 64, 3), np.uint8)
    sensor_inputs(
        cfg,
        np.eye(4),
        [("camera0", np.zeros((48, 64, 3), np.uint8), np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]), np.eye(4))],
    )
    with pytest.raises(Co3sopError, match="camera0|mount|projections"):
        sensor_inputs(cfg, np.eye(4), [("camera0", rgb, k, mount)])
