"""Co3SOP-Base, split into the half a vehicle runs and the half the ego runs, and `build_model(cfg)`.

Vehicle half: cameras (ResNet + FPN + image-to-voxel deformable attention) or
LiDAR (LMSCNet / SSCNet encoder) -> voxel features (B, C, X/4, Y/4, Z/4) and a
confidence volume (1x1x1 conv + sigmoid), in the sender's LiDAR frame.
Ego half: each collaborator's features and confidence warped into the ego
frame, hybrid mask (warp mask x confidence mask), masked deformable fusion,
then the prediction head (logits at 1/4, 1/2 and full resolution; or
OccFormer's encoder and mask decoder, `occformer.py`).
The node graph calls exactly these two halves; training calls both.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.kernels import lidar_output as output_kernel
from co3sop_nodes.kernels.transpose import channels_first_float32
from co3sop_nodes.kernels.warp import compiled_available, warp_compiled, warp_with_mask
from co3sop_nodes.model.backbone import ResNet
from co3sop_nodes.model.config import ModelConfig, WireConfig
from co3sop_nodes.model.fpn import FPN
from co3sop_nodes.model.fusion import VoxelFusion, hybrid_mask
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.lidar import LMSCNetEncoder, SSCNetEncoder
from co3sop_nodes.model.lifting import LiftingLayer, project, voxel_centres
from co3sop_nodes.model.occformer import OccFormerHead
from co3sop_nodes.model.path import InferencePath, inference_path
from co3sop_nodes.model.wire import WireDecoder, WireEncoder

# ImageNet-style normalisation of uint8 RGB inputs
_MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1) * 255
_STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1) * 255


@dataclass
class VehicleOutput:
    features: torch.Tensor  # (B, C, X, Y, Z) feature grid, sender's LiDAR frame
    confidence: torch.Tensor  # (B, 1, X, Y, Z) in [0, 1]
    code: torch.Tensor | None = None  # (B, K, X, Y, Z) integers: the wire code of a model that has one

    def to(self, device: torch.device) -> VehicleOutput:
        code = None if self.code is None else self.code.to(device)
        return VehicleOutput(self.features.to(device), self.confidence.to(device), code)


class VehicleHalf(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        fg = cfg.feature_grid
        c = cfg.embed_dims
        if cfg.modality == "camera":
            self.backbone = ResNet(cfg.backbone)
            self.fpn = FPN(cfg.backbone.channels[1:], cfg.fpn_channels, cfg.fpn_levels)
            self.to_dims = nn.Conv2d(cfg.fpn_channels, c, 1) if cfg.fpn_channels != c else nn.Identity()
            self.queries = nn.Parameter(torch.randn(fg.num_voxels, c) * 0.02)  # learnable voxel queries
            att = cfg.image_attention
            self.lifting = nn.ModuleList(
                LiftingLayer(c, att.heads, cfg.fpn_levels, att.points) for _ in range(att.layers)
            )
            self.register_buffer("centres", voxel_centres(fg), persistent=False)
            self._projected = None  # (key, projections): `_learned_projections`
        elif cfg.modality == "lidar":
            lc = cfg.lidar
            self.encoder = (
                LMSCNetEncoder(cfg.grid.dims[2], c, lc.channels)
                if lc.kind == "lmscnet"
                else SSCNetEncoder(c, lc.channels)
            )
        else:
            raise ValueError(f"unknown modality {cfg.modality!r}")
        self.confidence = nn.Conv3d(c, 1, 1)
        self.wire = WireEncoder(c, cfg.wire) if cfg.wire else None
        self.path = InferencePath()  # set by Co3SOP.use

    def forward(self, images=None, lidar2img=None, occupancy=None) -> VehicleOutput:
        """Camera: images (B, N, 3, H, W) uint8 or float 0..255, lidar2img (B, N, 4, 4).
        LiDAR: occupancy (B, 1, X, Y, Z) 0/1. Features and confidence in float32 whatever the path's precision (the
        wire's codecs take float32), and the wire code where the model has one (in float32: its rounding is the
        message)."""
        compiled = self._int8_output(occupancy)
        if compiled is not None:
            features, confidence = compiled
        else:
            with self.path.autocast():
                out = self._forward(images, lidar2img, occupancy)
            # one copy each (widened and made contiguous together) where the path computed another layout or precision
            features, confidence = (
                channels_first_float32(t, torch.get_num_threads()) for t in (out.features, out.confidence)
            )
        return VehicleOutput(features, confidence, self.encode(features, confidence))

    def _int8_output(self, occupancy) -> tuple[torch.Tensor, torch.Tensor] | None:
        """An SSCNet-style LiDAR half's scan on an int8 path: its int8 layers, then both 1x1 output layers and the
        confidence's sigmoid from their last volume in one compiled pass, what the PyTorch layers compute in the
        path's floats (bfloat16: bit for bit, under autocast; float32: within its rounding; kernels/lidar_output.py,
        tested) -> features, confidence in float32, channels-first. None on any other path, or where the kernel does
        not run."""
        encoder = getattr(self, "encoder", None)
        floats = self.path.floats
        if not (self.path.int8 and floats in output_kernel.FLOATS and isinstance(encoder, SSCNetEncoder)):
            return None  # (before the kernel's availability, which compiles it: only a path that runs it does)
        if occupancy is None or occupancy.shape[0] != 1:
            return None
        c = encoder.out.out_channels
        fits = encoder.out.in_channels == c and occupancy.shape[-1] // 4 <= output_kernel.MAX_HEIGHT
        if not (fits and output_kernel.available(c, floats)):
            return None
        last = encoder.int8_volume(occupancy)
        if last is None:
            return None
        threads = torch.get_num_threads()
        return output_kernel.lidar_output(
            last.values, last.scale, encoder.output_offset, encoder.out, self.confidence, threads, floats
        )

    def encode(self, features: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor | None:
        """The wire code (B, K, X, Y, Z) of features (B, C, X, Y, Z) and confidence (B, 1, X, Y, Z), or None."""
        return None if self.wire is None else self.wire(features, confidence)

    def _learned_projections(self, b: int):
        """The first lifting layer's offsets and logits of the learned queries, for a batch of b: the same in every
        frame, so inference computes them once per weights (their tensors' versions) and path; None while training
        (they take their gradients through the layer)."""
        if torch.is_grad_enabled():
            return None
        attention = self.lifting[0].attention
        weights = (self.queries, *attention.offsets.parameters(), *attention.weights.parameters())
        key = (self.path, *((t.data_ptr(), t._version) for t in weights))
        if self._projected is None or self._projected[0] != key:
            self._projected = key, attention.projections(self.queries[None])
        return tuple(t.expand(b, *t.shape[1:]) for t in self._projected[1])

    def _forward(self, images, lidar2img, occupancy) -> VehicleOutput:
        fg = self.cfg.feature_grid
        if self.cfg.modality == "camera":
            b, n = images.shape[:2]
            x = (images.flatten(0, 1).float() - _MEAN.to(images.device)) / _STD.to(images.device)  # (B*N, 3, H, W)
            feats = [self.to_dims(f) for f in self.fpn(self.backbone(x)[1:])]  # levels x (B*N, C, Hl, Wl)
            uv, visible = project(self.centres, lidar2img, self.cfg.image_size)  # (B, N, Q, 2), (B, N, Q)
            q = self.queries[None].expand(b, -1, -1)
            for i, layer in enumerate(self.lifting):
                q = layer(q, uv, visible, feats, self._learned_projections(b) if i == 0 else None)
            volume = q.transpose(1, 2).reshape(b, -1, *fg.dims)  # (B, C, X, Y, Z)
        else:
            volume = self.encoder(occupancy)
        return VehicleOutput(volume, torch.sigmoid(self.confidence(volume)))


class EgoHalf(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        fg = cfg.feature_grid
        self.fusion = (
            VoxelFusion(cfg.embed_dims, cfg.fusion_attention, cfg.max_collaborators, fg.dims) if cfg.fusion else None
        )
        if cfg.head == "conv":
            self.head = OccupancyHead(cfg.embed_dims, cfg.head_channels, cfg.num_classes)
        elif cfg.head == "occformer":
            self.head = OccFormerHead(cfg)
        else:
            raise ValueError(f"unknown head {cfg.head!r}")
        self.wire = WireDecoder(cfg.embed_dims, cfg.wire) if cfg.wire else None
        self.path = InferencePath()  # set by Co3SOP.use

    def receive(self, code: torch.Tensor, received: torch.Tensor) -> VehicleOutput:
        """A neighbour's wire code (B, K, X, Y, Z) at the voxels received (B, X, Y, Z) bool -> its output as fusion
        takes it (features and confidence 0 where not received)."""
        if self.wire is None:
            raise Co3sopError(f"{self.cfg.name}: has no wire code to decode")
        features, confidence = self.wire(code, received)
        return VehicleOutput(features, confidence)

    def align(self, ego: VehicleOutput, others: list[VehicleOutput], neighbour_from_ego: torch.Tensor):
        """Warped features (B, A, C, X, Y, Z), confidences (B, A, X, Y, Z) and hybrid masks (B, A, X, Y, Z); the
        features in bfloat16 where the compiled warp serves a bfloat16 path, else float32."""
        fg = self.cfg.feature_grid
        if self.path.kernels(ego.features) and len(ego.features) == 1 and compiled_available():
            # inference on the CPU: the compiled warp, channels-last (the attention reads the features so) and on a
            # bfloat16 path in bfloat16 (as the attention reads them), each neighbour written in place into the stack
            threads, a = torch.get_num_threads(), len(others)
            dtype = torch.bfloat16 if self.path.float_dtype == torch.bfloat16 else torch.float32
            feats = torch.empty(1, a, *fg.dims, self.cfg.embed_dims, dtype=dtype)  # (1, A, X, Y, Z, C)
            confs = torch.empty(1, a, *fg.dims)
            filled = torch.stack(
                [
                    warp_compiled(
                        other.features,
                        other.confidence,
                        neighbour_from_ego[:, i],
                        fg,
                        threads,
                        (feats[0, i], confs[0, i]),
                    )[2]
                    for i, other in enumerate(others)
                ]
            )[None]
            feats = feats.permute(0, 1, 5, 2, 3, 4)  # (1, A, C, X, Y, Z), channels-last in memory
            return feats, confs, hybrid_mask(ego.confidence, confs, filled)
        feats, confs, masks = [], [], []
        for a, other in enumerate(others):
            both = torch.cat([other.features, other.confidence], 1)
            warped, filled = warp_with_mask(both, neighbour_from_ego[:, a], fg)
            feats.append(warped[:, :-1])
            confs.append(warped[:, -1])
            masks.append(filled[:, 0])
        feats, confs, filled = torch.stack(feats, 1), torch.stack(confs, 1), torch.stack(masks, 1)
        return feats, confs, hybrid_mask(ego.confidence, confs, filled)

    def fuse(self, ego: VehicleOutput, others=(), neighbour_from_ego: torch.Tensor | None = None, dense: bool = False):
        """The ego's features after fusion (B, C, X, Y, Z); `others` nearest first, neighbour_from_ego (B, A, 4, 4)."""
        others = list(others)[: self.cfg.max_collaborators]
        if self.fusion is None or not others:
            return ego.features
        feats, _, mask = self.align(ego, others, neighbour_from_ego)
        with self.path.autocast():
            fused = self.fusion(ego.features, feats, mask, dense=dense)
        return fused if torch.is_grad_enabled() else fused.float()

    def forward(
        self,
        ego: VehicleOutput,
        others=(),
        neighbour_from_ego: torch.Tensor | None = None,
        sample_index: torch.Tensor | None = None,
    ) -> list[torch.Tensor]:
        """Logits at 1/4, 1/2 and 1 (B, K, X, Y, Z); with sample_index (B, N), full resolution only there (B, K, N).
        OccFormer's head: its decoder's predictions (`OccFormerHead.predict`), which its loss takes."""
        fused = self.fuse(ego, others, neighbour_from_ego)
        if isinstance(self.head, OccFormerHead):
            return self.head.predict(fused)
        return self.head(fused) if sample_index is None else self.head.forward_at(fused, sample_index)


class Co3SOP(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.vehicle = VehicleHalf(cfg)
        self.ego = EgoHalf(cfg)
        self.path = InferencePath()

    def use(self, path: InferencePath) -> Co3SOP:
        """Run inference on `path` from now on: the weights moved to its device, every module that chooses
        between a compiled kernel and its reference, or autocasts, told so. In reduced precision the
        convolutions' weights go channels-last (oneDNN's and cuDNN's fast layouts). On an int8 path the int8
        layers are made from the weights as they are now; a model with none (no calibration, or a machine without
        the int8 kernels) takes the path of the rest's precision (`InferencePath.floats`) instead."""
        self.to(path.torch_device)
        layout = {4: torch.channels_last, 5: torch.channels_last_3d} if path.reduced else {}
        for module in self.modules():
            if "path" in vars(module):
                module.path = path
            if isinstance(module, (nn.Conv2d, nn.Conv3d, nn.ConvTranspose3d)):
                fmt = layout.get(module.weight.dim(), torch.contiguous_format)
                module.weight.data = module.weight.data.contiguous(memory_format=fmt)
        if path.int8:
            made = [
                module.quantize(self.cfg.grid.dims[2]) if isinstance(module, SSCNetEncoder) else module.quantize()
                for module in self.int8_modules.values()
            ]
            if not any(made):
                return self.use(replace(path, precision=path.floats))
        return self

    @property
    def int8_modules(self) -> dict[str, nn.Module]:
        """The modules an int8 path can compute in int8, by name: an SSCNet-style LiDAR vehicle half's encoder and
        the convolutional head (each once calibrated)."""
        modules = {"vehicle.encoder": getattr(self.vehicle, "encoder", None), "ego.head": self.ego.head}
        return {name: m for name, m in modules.items() if isinstance(m, (SSCNetEncoder, OccupancyHead))}

    def int8_missing(self) -> str:
        """Why an int8 path computes nothing of this model in int8 (after `use` of one left it on another path)."""
        modules = self.int8_modules
        if not modules:
            return f"{self.cfg.name} has neither an SSCNet-style LiDAR vehicle half nor a convolutional head"
        if not any(m.calibrated for m in modules.values()):
            return f"{self.cfg.name} has no int8 calibration: make one with `calibrate`"
        return "this machine has no oneDNN quantized convolution or no C compiler for the int8 kernels"

    def int8_activations(self) -> list[str]:
        """The names of the activations an int8 path quantizes, which a calibration gives ranges of (none for a
        model without int8 layers)."""
        return [f"{prefix}.{name}" for prefix, m in self.int8_modules.items() for name in m.ACTIVATIONS]

    def int8_steps(self) -> list[float]:
        """Each of `int8_activations`' quantization steps over its range (255 after a ReLU)."""
        return [step for m in self.int8_modules.values() for step in m.STEPS]

    @torch.no_grad()
    def int8_values(self, occupancy: torch.Tensor) -> list[torch.Tensor]:
        """The float32 forward's values of each of `int8_activations` for a scan (1, 1, X, Y, Z): the vehicle half's,
        then the head's on that scan's own features (what a calibration measures)."""
        modules = self.int8_modules
        values = []
        if "vehicle.encoder" in modules:
            values += modules["vehicle.encoder"].activations(occupancy)
        if "ego.head" in modules:
            values += modules["ego.head"].activations(self.vehicle(occupancy=occupancy).features)
        return values

    def calibrate(self, ranges: dict[str, float], weights: dict[str, torch.Tensor] | None = None) -> Co3SOP:
        """Take an int8 calibration: the range of each activation of one or more of `int8_modules` by name
        (positive; a module takes all of its own or none), and the int8 layers' own folded weights where it has
        them (`int8_tuned_weights`' names; else the float layers', folded); their int8 layers are made at the next
        `use` of an int8 path."""
        names = self.int8_activations()
        if not names:
            raise Co3sopError(f"{self.cfg.name}: has no int8 layers to calibrate")
        unknown = sorted(set(ranges) - set(names))
        if unknown or not ranges or not all(float(r) > 0 for r in ranges.values()):
            raise Co3sopError(
                f"{self.cfg.name}: an int8 calibration gives a positive range of each of {', '.join(names)}"
                + (f" (not {', '.join(unknown)})" if unknown else "")
            )
        for prefix, module in self.int8_modules.items():
            own = [f"{prefix}.{n}" for n in module.ACTIVATIONS]
            given = [n for n in own if n in ranges]
            if given and len(given) < len(own):
                missing = ", ".join(n for n in own if n not in ranges)
                raise Co3sopError(f"{self.cfg.name}: an int8 calibration of {prefix} lacks {missing}")
            if given:
                module.int8_ranges.copy_(torch.tensor([float(ranges[n]) for n in own]))
        weights = weights or {}
        tuned = {prefix for name in weights for prefix in self.int8_modules if name.startswith(f"{prefix}.")}
        expected = [
            f"{prefix}.{n}.{part}" for prefix in tuned for n in self.int8_modules[prefix].INT8_LAYERS
            for part in ("weight", "bias")
        ]  # fmt: skip
        if sorted(weights) != sorted(expected) or not all(self.int8_modules[p].calibrated for p in tuned):
            layers = ", ".join(f"{p}.<{'|'.join(m.INT8_LAYERS)}>.<weight|bias>" for p, m in self.int8_modules.items())
            raise Co3sopError(
                f"{self.cfg.name}: int8 weights are each of a calibrated module's int8 layers ({layers}); "
                f"got {', '.join(sorted(weights))}"
            )
        for prefix, module in self.int8_modules.items():
            own = None
            if prefix in tuned:
                own = {n: (weights[f"{prefix}.{n}.weight"], weights[f"{prefix}.{n}.bias"]) for n in module.INT8_LAYERS}
            try:
                module.set_int8_weights(own)
            except ValueError as exc:
                raise Co3sopError(f"{self.cfg.name}: {prefix}: {exc}") from None
        return self

    def int8_tuned(self, prefix: str) -> bool:
        """Whether the int8 module `prefix` (of `int8_modules`) carries int8 weights fine-tuned for int8
        (`calibrate --fine-tune`), the case `auto` takes int8 for (`inference_path`'s `tuned_int8`)."""
        module = self.int8_modules.get(prefix)
        return module is not None and module.int8_weights is not None

    def vehicle_path(self, device: str, precision: str, compiled: bool = True, what: str = "") -> InferencePath:
        """`inference_path` for this model's vehicle half alone, as a vehicle node runs it (auto: int8 where its int8
        layers are fine-tuned for it)."""
        return inference_path(device, precision, compiled, what, tuned_int8=self.int8_tuned("vehicle.encoder"))

    def ego_path(self, device: str, precision: str, compiled: bool = True, what: str = "") -> InferencePath:
        """`inference_path` for this model's ego half, as an ego node runs it (auto: int8 where its head's int8
        layers are fine-tuned for it)."""
        return inference_path(device, precision, compiled, what, tuned_int8=self.int8_tuned("ego.head"))

    def int8_tuned_weights(self) -> dict[str, torch.Tensor]:
        """The int8 layers' own folded weights and biases by name (`<module>.<layer>.weight` / `.bias`, e.g.
        `vehicle.encoder.down.1.weight`), as a checkpoint's int8 entry carries them; none of a module whose int8
        layers are the float layers'."""
        return {
            f"{prefix}.{n}.{part}": t
            for prefix, module in self.int8_modules.items()
            if module.int8_weights is not None
            for n, pair in module.int8_weights.items()
            for part, t in zip(("weight", "bias"), pair)
        }

    def forward(
        self,
        agents: list[dict],
        neighbour_from_ego: torch.Tensor | None = None,
        sample_index: torch.Tensor | None = None,
    ) -> list[torch.Tensor]:
        """agents[0] is the ego, the rest its collaborators nearest first; each a dict of VehicleHalf inputs."""
        outs = [self.vehicle(**inputs) for inputs in agents]
        return self.ego(outs[0], outs[1:], neighbour_from_ego, sample_index)


def build_model(cfg: ModelConfig) -> Co3SOP:
    return Co3SOP(cfg)


def with_wire(model: Co3SOP, wire: WireConfig) -> Co3SOP:
    """`model` with a new wire code `wire` (its encoder and decoder freshly initialised, every other weight kept),
    named `<name>-wire`: what the wire stage starts from."""
    out = build_model(replace(model.cfg, wire=wire, name=f"{model.cfg.name}-wire"))
    missing, unexpected = out.load_state_dict(model.state_dict(), strict=False)
    assert not unexpected and all(k.split(".")[1] == "wire" for k in missing), (missing, unexpected)
    return out
