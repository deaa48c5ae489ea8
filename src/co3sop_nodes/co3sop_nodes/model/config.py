"""Model configurations: frozen dataclasses and named presets.

Voxel axis order everywhere in the model: (B, C, X, Y, Z) in the agent's LiDAR
frame, REP-103 axes (x forward, y left, z up), matching GridSpec arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.grid import BENCHMARK_RANGES, GridSpec


@dataclass(frozen=True)
class BackboneConfig:
    depth: tuple[int, ...] = (1, 1, 1, 1)  # residual blocks per stage (ResNet-18: 2,2,2,2; ResNet-101: 3,4,23,3)
    channels: tuple[int, ...] = (16, 32, 64, 128)  # output channels per stage (ResNet-101 bottleneck: 256..2048)
    bottleneck: bool = False  # ResNet-50/101 style blocks
    deform_stages: tuple[bool, ...] = (False, False, False, False)  # DCN in a stage's 3x3 convs (paper: last three)
    stem: int = 16  # stem channels


@dataclass(frozen=True)
class AttentionConfig:
    layers: int = 1
    heads: int = 4
    points: int = 4


@dataclass(frozen=True)
class LidarConfig:
    kind: str = "lmscnet"  # "lmscnet" (2D UNet over height slices) | "sscnet" (3D dilated convs)
    channels: int = 32


@dataclass(frozen=True)
class OccFormerConfig:
    """OccFormer's ego-side network (head "occformer"): dual-path transformer encoder, top-down neck, mask decoder."""

    stages: tuple[int, ...] = (32, 64)  # encoder stage channels: the first at the feature grid, each next at 1/2
    blocks: int = 2  # dual-path blocks per stage
    window: int = 7  # side of the attention windows on each horizontal slice and on the BEV plane (voxels)
    queries: int = 32  # mask queries (not tied to classes)
    dims: int = 64  # decoder width and mask-feature channels
    layers: int = 3  # decoder layers, attending to the encoder levels coarse to fine in turn
    heads: int = 4  # decoder attention heads
    points: int = 8192  # class-guided points per sample for the matching and the mask losses


@dataclass(frozen=True)
class WireConfig:
    """The code learned for the V2X wire (model/wire.py): K integers in [-L, L] per voxel sent."""

    rank: int = 4  # K
    levels: int = 7  # L: 2L + 1 values, int4 on the wire up to 7

    def __post_init__(self):
        if not 1 <= self.rank <= 64 or not 1 <= self.levels <= 7:
            raise Co3sopError(f"wire code: rank {self.rank} must be in 1..64 and levels {self.levels} in 1..7 (int4)")


@dataclass(frozen=True)
class ModelConfig:
    name: str
    modality: str = "camera"  # vehicle half: "camera" (Co3SOP-Base, SurroundOcc-style) | "lidar" (LMSCNet / SSCNet)
    range: str = "51.2m"  # benchmark grid the model predicts
    num_classes: int = 24
    image_size: tuple[int, int] = (160, 120)  # camera input (width, height) after resizing
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    fpn_channels: int = 32
    fpn_levels: int = 4
    embed_dims: int = 32  # C of the voxel features sent over V2X
    downsample: int = 4  # the feature volume is 1/4 of the label grid per axis
    image_attention: AttentionConfig = field(default_factory=AttentionConfig)
    fusion: bool = True  # collaborate (Co3SOP-Base); False: single agent (SurroundOcc / LMSCNet / SSCNet)
    # LiDAR single agent only: the collaborators' scans join the ego's before the model (early fusion, OPV2V's
    # raw-data sharing), the reference of what the neighbours' sensing itself adds; offline only (the graph shares features)
    early_fusion: bool = False
    fusion_attention: AttentionConfig = field(default_factory=AttentionConfig)
    max_collaborators: int = 6
    head_channels: tuple[int, int, int] = (32, 16, 8)  # per output scale: 1/4, 1/2, 1
    head: str = "conv"  # "conv": Co3SOP-Base's 3D conv head | "occformer": OccFormer's encoder + mask decoder
    occformer: OccFormerConfig = field(default_factory=OccFormerConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    # (origin, voxel size, dims) of a grid other than the benchmark range's (custom extents, small tests)
    custom_grid: tuple | None = None
    # a code learned for the wire (collaborative models; trained in the `wire` stage), None: features as they are
    wire: WireConfig | None = None

    def __post_init__(self):
        if self.early_fusion and (self.modality != "lidar" or self.fusion):
            raise Co3sopError(
                f"{self.name}: early_fusion merges LiDAR scans before a single-agent model (modality lidar, fusion off)"
            )
        if self.wire is not None and not self.fusion:
            raise Co3sopError(f"{self.name}: a wire code needs a collaborative model (fusion on)")

    @property
    def grid(self) -> GridSpec:
        return GridSpec(*self.custom_grid) if self.custom_grid else BENCHMARK_RANGES[self.range]

    @property
    def feature_grid(self) -> GridSpec:
        """The grid of the voxel features: same extent, `downsample` times coarser."""
        g = self.grid
        return GridSpec(g.origin, g.voxel_size * self.downsample, tuple(n // self.downsample for n in g.dims))


def _tiny(**kw) -> ModelConfig:
    return ModelConfig(name="tiny", **kw)


PRESETS: dict[str, ModelConfig] = {
    # CPU-sized Co3SOP-Base: its two stages train on small generated splits on 2 cores (step times: BENCHMARKS.md).
    "tiny": _tiny(),
    # The paper's sizes (ResNet101-DCN, FPN 4 levels, 3 image / 3 fusion layers, 4 heads, 4 points), for a GPU.
    "paper": ModelConfig(
        name="paper",
        image_size=(800, 600),
        backbone=BackboneConfig(
            depth=(3, 4, 23, 3),
            channels=(256, 512, 1024, 2048),
            bottleneck=True,
            deform_stages=(False, True, True, True),
            stem=64,
        ),
        fpn_channels=256,
        embed_dims=128,
        image_attention=AttentionConfig(layers=3, heads=8, points=4),
        fusion_attention=AttentionConfig(layers=3, heads=4, points=4),
        head_channels=(128, 64, 32),
    ),
}
# GPU-trained Co3SOP-Base between the two: the dataset's full 320x240 images, a ResNet-18-like backbone at 3/8 of
# its width, two image and two fusion attention layers, 48 feature channels; float16 checkpoint under 5 MB.
PRESETS["small"] = ModelConfig(
    name="small",
    image_size=(320, 240),
    backbone=BackboneConfig(depth=(1, 2, 2, 1), channels=(24, 48, 96, 176), stem=24),
    fpn_channels=48,
    embed_dims=48,
    image_attention=AttentionConfig(layers=2, heads=4, points=4),
    fusion_attention=AttentionConfig(layers=2, heads=4, points=4),
    head_channels=(48, 32, 16),
)
# Baselines of the paper's Table 2, as presets of the same structure.
PRESETS["tiny-single"] = replace(PRESETS["tiny"], name="tiny-single", fusion=False)  # SurroundOcc-style
PRESETS["surroundocc"] = replace(PRESETS["paper"], name="surroundocc", fusion=False)
PRESETS["tiny-lmscnet"] = replace(PRESETS["tiny"], name="tiny-lmscnet", modality="lidar", fusion=False)
PRESETS["tiny-sscnet"] = replace(
    PRESETS["tiny"], name="tiny-sscnet", modality="lidar", fusion=False, lidar=LidarConfig("sscnet", 32)
)
# Collaborative LiDAR Co3SOP-Base: the SSCNet-style LiDAR vehicle half with the same warp, hybrid mask,
# masked deformable fusion and head, trained in the paper's two stages.
PRESETS["tiny-lidar"] = replace(PRESETS["tiny-sscnet"], name="tiny-lidar", fusion=True)
# The same with three fusion layers, the depth of Co3SOP's released voxel fusion (a query that has read its
# neighbours once chooses where to read them again): tried on `validate` and not taken, its gain there is smaller
# (results.md, "Choices made on validate").
PRESETS["tiny-lidar-f3"] = replace(
    PRESETS["tiny-lidar"], name="tiny-lidar-f3", fusion_attention=AttentionConfig(layers=3)
)
# Early fusion with the same SSCNet-style network: what sharing the scans themselves adds, set against tiny-lidar's
# shared features (the same neighbours' information: each scan as the occupied voxels of its own grid).
PRESETS["tiny-sscnet-early"] = replace(PRESETS["tiny-sscnet"], name="tiny-sscnet-early", early_fusion=True)
PRESETS["lmscnet"] = replace(
    PRESETS["paper"], name="lmscnet", modality="lidar", fusion=False, lidar=LidarConfig("lmscnet", 128)
)
PRESETS["sscnet"] = replace(
    PRESETS["paper"], name="sscnet", modality="lidar", fusion=False, lidar=LidarConfig("sscnet", 128)
)
# OccFormer (camera, single agent): the same camera lifting, then its dual-path transformer encoder and mask
# decoder. The paper-size one follows OccFormer's SemanticKITTI configuration (4 stages of 2 blocks, 128..1024
# channels, window 7; 100 queries, 9 decoder layers of width 192, 6 heads; 50176 points).
PRESETS["tiny-occformer"] = replace(PRESETS["tiny"], name="tiny-occformer", fusion=False, head="occformer")
PRESETS["occformer"] = replace(
    PRESETS["paper"],
    name="occformer",
    fusion=False,
    head="occformer",
    occformer=OccFormerConfig(stages=(128, 256, 512, 1024), queries=100, dims=192, layers=9, heads=6, points=50176),
)


def config_from_dict(data: dict) -> ModelConfig:
    """Inverse of dataclasses.asdict(ModelConfig) (as stored in checkpoints)."""
    nested = {
        "backbone": BackboneConfig,
        "image_attention": AttentionConfig,
        "fusion_attention": AttentionConfig,
        "lidar": LidarConfig,
        "occformer": OccFormerConfig,
        "wire": WireConfig,
    }
    kwargs = {}
    for key, value in data.items():
        if key in nested and value is not None:
            value = nested[key](**{k: tuple(v) if isinstance(v, list) else v for k, v in value.items()})
        elif key == "custom_grid" and value is not None:
            origin, voxel, dims = value
            value = (tuple(origin), voxel, tuple(dims))
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[key] = value
    return ModelConfig(**kwargs)


def preset(name: str, **overrides) -> ModelConfig:
    if name not in PRESETS:
        raise Co3sopError(f"unknown model preset {name!r} (known: {', '.join(PRESETS)})")
    return replace(PRESETS[name], **overrides)
