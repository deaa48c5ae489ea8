"""How a loaded model runs inference: on which device, in which precision, and whether its compiled CPU
kernels replace their PyTorch reference paths (ROS-free).

Chosen once, by `inference_path`, from what the machine has; held by the model (`Co3SOP.use`), never by
a process-wide flag, so two models in one process (a benchmark's reference and fast path) run their own.

Reduced precision is autocast: convolutions and matrix products in bfloat16 or float16, reductions and
the compiled kernels (which read float32) in float32. On the CPU it pays only where the hardware computes
bfloat16 (AMX tiles or AVX-512 BF16; oneDNN then wants channels-last 3D volumes); elsewhere it is
emulated and slower than float32, so `auto` keeps float32 there. On CUDA, `auto` takes bfloat16 where
the GPU has it, else float16.

`int8` (the CPU only) computes a model's calibrated layers in int8 (`model/quantized.py`: the LiDAR vehicle
half's 3D convolutions after its first and the head's layers up to 1/2, with activation ranges measured by
`calibrate` and shipped in the checkpoint) and the rest as `auto` would on this CPU (bfloat16 where the CPU
computes it, else float32). A model without a calibration runs that rest only (`Co3SOP.use`). `auto` takes int8,
on a CPU with an int8 unit, only for a half whose int8 layers carry weights fine-tuned for int8 (`calibrate
--fine-tune`; `Co3SOP.vehicle_path` and `ego_path` say which): a LiDAR vehicle half's (the shipped `tiny-lidar`'s
keep the mIoU within 0.2 points of float32's, its interval too, on `validate` and `test`: results.md, "Inference
precision"), or an ego's head's.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from functools import cache

import torch
import torch.nn.functional as F

from co3sop_nodes import kernels
from co3sop_nodes.common.errors import Co3sopError

PRECISIONS = ("auto", "float32", "bfloat16", "float16", "int8")
DEVICES = ("auto", "cpu", "cuda")
_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


@dataclass(frozen=True)
class InferencePath:
    device: str = "cpu"  # a torch device: cpu, cuda, cuda:N
    precision: str = "float32"  # float32, bfloat16, float16 or int8 (calibrated layers; the rest in `floats`)
    compiled: bool = True  # the compiled CPU kernels where they compile (tested equal to the reference paths)
    # with the compiled kernels, the fusion's queries padded to a multiple of this many: oneDNN builds its
    # primitives per row count, and a frame's count of queries is new nearly every frame (1: no padding)
    query_rows: int = 512

    def __post_init__(self):
        if self.precision not in PRECISIONS[1:]:
            raise Co3sopError(f"precision {self.precision!r}: one of {', '.join(PRECISIONS[1:])}")
        if self.int8 and self.torch_device.type != "cpu":
            raise Co3sopError(f"precision int8 on {self.device}: int8 layers run on the CPU only")
        if self.query_rows < 1:
            raise Co3sopError(f"query_rows {self.query_rows}: at least 1")

    @property
    def torch_device(self) -> torch.device:
        return torch.device(self.device)

    @property
    def reduced(self) -> bool:
        return self.precision != "float32"

    @property
    def int8(self) -> bool:
        return self.precision == "int8"

    @property
    def floats(self) -> str:
        """The precision of what is not int8: the precision itself, or for int8 bfloat16 where the CPU computes it
        (else float32)."""
        if self.int8:
            return "bfloat16" if cpu_bfloat16_unit() else "float32"
        return self.precision

    @property
    def float_dtype(self) -> torch.dtype:
        """`floats` as a torch dtype: what autocast computes products in on this path."""
        return _DTYPES[self.floats]

    def autocast(self):
        """The context a forward pass runs in: nothing in float32, autocast to `floats` otherwise."""
        if self.floats == "float32":
            return nullcontext()
        return torch.autocast(self.torch_device.type, dtype=self.float_dtype)

    def linear(
        self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None, relu: bool = False
    ) -> torch.Tensor:
        """F.linear of x (..., Cin), then with `relu` its ReLU, as inference on this path computes it: on a
        reduced-precision CPU path by oneDNN's primitive (`onednn`), the ReLU fused, weight and bias in x's
        precision (as autocast gives a reduced-precision x's product them). In float32 that is about 2x PyTorch's
        default product for the fusion's thin products (32 inputs) on an AMD CPU, equal to float rounding; in
        bfloat16 the same values as autocast's product, bit for bit (both tested). Float32 keeps F.linear."""
        if self.reduced and self.kernels(x) and onednn(x.dtype):
            rows = x.reshape(-1, x.shape[-1])
            bias = None if bias is None else bias.to(x.dtype)
            out = torch.ops.mkldnn._linear_pointwise(rows, weight.to(x.dtype), bias, "relu" if relu else "none", [], "")
            return out.view(*x.shape[:-1], weight.shape[0])
        if weight.dtype != x.dtype:  # a reduced x where oneDNN does not compute its precision: as autocast would
            weight, bias = weight.to(x.dtype), None if bias is None else bias.to(x.dtype)
        out = F.linear(x, weight, bias)
        return out.relu_() if relu else out

    def kernels(self, x: torch.Tensor) -> bool:
        """Whether inference on `x` takes a compiled CPU kernel (never while training: they have no gradient)."""
        return self.compiled and x.device.type == "cpu" and not torch.is_grad_enabled()

    def describe(self) -> str:
        precision = f"int8 + {self.floats}" if self.int8 else self.precision
        return f"{self.device}, {precision}" + ("" if self.compiled else ", reference paths")


@cache
def onednn(dtype: torch.dtype) -> bool:
    """Whether this PyTorch build has oneDNN's primitives with fused post-operations (torch.ops.mkldnn's
    _linear_pointwise and _convolution_pointwise, which PyTorch's own compiler uses for CPU inference) and they
    compute `dtype` on this CPU (a reduced precision where oneDNN has it; PyTorch's own layers take another path
    elsewhere)."""
    ops = ("_linear_pointwise", "_convolution_pointwise")
    if not (torch.backends.mkldnn.is_available() and all(hasattr(torch.ops.mkldnn, op) for op in ops)):
        return False
    if dtype == torch.bfloat16:
        return torch.ops.mkldnn._is_mkldnn_bf16_supported()
    if dtype == torch.float16:
        return torch.ops.mkldnn._is_mkldnn_fp16_supported()
    return dtype == torch.float32


@cache
def cpu_bfloat16_unit() -> str | None:
    """The CPU's bfloat16 hardware, from its feature flags: "AMX", "AVX-512 BF16", or None (emulated)."""
    flags = set(kernels.cpu_flags())
    if "amx_bf16" in flags and "amx_tile" in flags:
        return "AMX"
    return "AVX-512 BF16" if "avx512_bf16" in flags else None


@cache
def cpu_int8_unit() -> str | None:
    """The CPU's int8 dot-product hardware oneDNN's int8 primitives use, from its feature flags: "AMX",
    "AVX-512 VNNI", "AVX2" (no VNNI: pairs of uint8 x int8 products summed in 16 bits, saturating, then in 32;
    1.35-1.4x float32's speed on the shipped models, `model/quantized.py` says what the saturation costs), or None
    (int8 gains nothing there)."""
    flags = set(kernels.cpu_flags())
    if "amx_int8" in flags and "amx_tile" in flags:
        return "AMX"
    if "avx512_vnni" in flags:
        return "AVX-512 VNNI"
    return "AVX2" if "avx2" in flags else None


def cpu_units() -> str:
    """This CPU's reduced-precision hardware in words, as a result measured on it names it: its int8 and bfloat16
    units (`cpu_int8_unit`, `cpu_bfloat16_unit`)."""
    int8 = cpu_int8_unit()
    int8 = "none" if int8 is None else int8 + (", no VNNI" if int8 == "AVX2" else "")
    return f"int8: {int8}; bfloat16: {cpu_bfloat16_unit() or 'none'}"


def resolve_device(name: str, what: str = "device") -> torch.device:
    """The torch device `name` names (auto: the first CUDA GPU if torch sees one, else cpu), checked against
    what this torch build can use; `what` names the option or parameter in errors."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise Co3sopError(f"{what} {name!r}: not a device (auto, cpu, cuda, cuda:N)") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise Co3sopError(f"{what} {name!r}: only cpu and cuda are supported")
    count = torch.cuda.device_count()  # 0 on a CPU-only build or without a driver
    if count == 0:
        raise Co3sopError(f"{what} {name}: this torch build ({torch.__version__}) sees no CUDA GPU")
    if device.index is not None and device.index >= count:
        raise Co3sopError(f"{what} {name}: torch sees {count} CUDA GPU(s) (cuda:0..cuda:{count - 1})")
    return device


def inference_path(
    device: str = "auto", precision: str = "auto", compiled: bool = True, what: str = "", tuned_int8: bool = False
) -> InferencePath:
    """The path for `device` (auto | cpu | cuda | cuda:N) and `precision` (auto | float32 | bfloat16 |
    float16 | int8) on this machine, `auto` resolved to what it has; a device it lacks is refused, and int8 off the
    CPU. `what`: how the caller spells its options in errors ("--" for a command line, "parameter " for a
    node). `tuned_int8`: the path runs a half whose int8 layers are fine-tuned for int8 (`Co3SOP.int8_tuned`),
    which `auto` then takes on a CPU with an int8 unit."""
    dev = resolve_device(device, f"{what}device")
    if precision not in PRECISIONS:
        raise Co3sopError(f"{what}precision {precision!r}: one of {', '.join(PRECISIONS)}")
    if precision == "auto":
        if dev.type == "cuda":
            precision = "bfloat16" if torch.cuda.is_bf16_supported() else "float16"
        elif tuned_int8 and cpu_int8_unit():  # a build without int8 layers runs them in `floats` (Co3SOP.use)
            precision = "int8"
        else:
            precision = "bfloat16" if cpu_bfloat16_unit() else "float32"
    if precision == "int8" and dev.type != "cpu":
        raise Co3sopError(f"{what}precision int8 with {what}device {dev}: int8 layers run on the CPU only")
    return InferencePath(str(dev), precision, compiled)
