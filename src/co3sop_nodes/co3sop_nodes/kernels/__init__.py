"""Small C kernels shipped as source, compiled on first use for the machine at hand, loaded with ctypes.

Why not a Python extension built by colcon: the kernels are specialised per
shape (compile-time constants let the compiler keep everything in registers)
and per CPU (`-march=native`), which a package built once cannot be. The
compiler is the system's C compiler (`$CC`, else `cc`), which every ROS 2
install has. The library is cached under `$CO3SOP_CACHE` (default
`~/.cache/co3sop/native`), keyed by source (and the headers beside it), defines, flags and CPU; written
atomically, so concurrent nodes never load a half-written file. Without a
compiler, `load` returns None and callers take their PyTorch or NumPy path
(tested equal); `CO3SOP_NATIVE=0` makes them take it anyway.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import cache
from pathlib import Path

import numpy as np

FLAGS = ("-O3", "-march=native", "-fPIC", "-shared", "-std=c11")
# False: every caller takes its PyTorch path (CO3SOP_NATIVE=0 in the environment; benchmarks toggle it to time both)
ENABLED = os.environ.get("CO3SOP_NATIVE", "1") != "0"
log = logging.getLogger(__name__)


def cache_dir() -> Path:
    return Path(os.environ.get("CO3SOP_CACHE") or Path.home() / ".cache" / "co3sop") / "native"


@cache
def cpu_flags() -> tuple[str, ...]:
    """The CPU's feature flags as /proc/cpuinfo lists them (none where there is no such file)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return ()
    return tuple(next((line for line in text.splitlines() if line.startswith("flags")), "").split(":")[-1].split())


def _cpu() -> str:
    """What `-march=native` depends on: the machine and its CPU's feature flags."""
    return f"{platform.machine()} {' '.join(cpu_flags())}"


@cache
def load(name: str, contract: bool = False, **defines: int) -> ctypes.CDLL | None:
    """The compiled `native/<name>.c` with `-D NAME=value` for each define; None (logged once) without a C compiler.
    Multiplies and adds stay separate operations, rounded as PyTorch's reference rounds them, unless `contract`
    (for a reduced-precision path, whose tolerance covers the fused multiply-adds' other rounding)."""
    source = Path(__file__).with_name(f"{name}.c").read_bytes()
    headers = {h.name: h.read_bytes() for h in sorted(Path(__file__).parent.glob("*.h"))}  # what sources include
    compiler = os.environ.get("CC", "cc")
    contraction = "-ffp-contract=fast" if contract else "-ffp-contract=off"
    args = [*FLAGS, contraction, *(f"-D{k}={int(v)}" for k, v in sorted(defines.items()))]
    parts = [source, *headers.values(), compiler.encode(), " ".join(args).encode(), _cpu().encode()]
    key = hashlib.sha256(b"\0".join(parts)).hexdigest()[:20]
    path = cache_dir() / f"{name}-{key}.so"
    if not path.exists():
        if shutil.which(compiler) is None:
            log.warning("no C compiler (%s): %s runs on its PyTorch path", compiler, name)
            return None
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
            src, out = Path(tmp) / f"{name}.c", Path(tmp) / path.name
            src.write_bytes(source)
            for header, text in headers.items():
                (Path(tmp) / header).write_bytes(text)
            done = subprocess.run([compiler, *args, str(src), "-o", str(out)], capture_output=True, text=True)
            if done.returncode != 0:
                log.warning(
                    "%s failed to compile %s (%s): it runs on its PyTorch path",
                    compiler,
                    name,
                    done.stderr.strip()[-500:],
                )
                return None
            os.replace(out, path)  # atomic: a concurrent loader sees the old state or the whole file
    return ctypes.CDLL(str(path))


def array(t, dtype=np.float32) -> np.ndarray:
    """A tensor as a C-contiguous numpy array of `dtype` for a kernel (a view where it already is one; bfloat16
    and float16, which numpy lacks or the kernels do not read, widened to float32 first)."""
    t = t.detach().cpu()
    if str(t.dtype) in (
        "torch.bfloat16",
        "torch.float16",
    ):  # without importing torch: the simulator's kernels need none
        t = t.float()
    return np.ascontiguousarray(t.numpy(), dtype)


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="co3sop-native")


def parallel(fn, args: tuple, n: int, threads: int, grain: int = 1024) -> None:
    """fn(*args, start, end) over [0, n), split in `threads` parts run at once (ctypes releases the GIL) when there
    are `grain` items or more (fewer are not worth a thread: the default suits items of a few operations); the caller
    keeps every array the args point to referenced until this returns."""
    if threads <= 1 or n < grain:
        fn(*args, 0, n)
        return
    bounds = np.linspace(0, n, threads + 1).astype(np.int64)
    list(_pool(threads).map(lambda i: fn(*args, int(bounds[i]), int(bounds[i + 1])), range(threads)))


def interleaved(fn, args: tuple, threads: int) -> None:
    """fn(*args, part, threads) for every part in [0, threads) at once: the kernel takes every threads-th block of
    its work from `part` on (even shares where cost varies along the data, as a camera's sky rows and street rows)."""
    if threads <= 1:
        fn(*args, 0, 1)
        return
    list(_pool(threads).map(lambda part: fn(*args, part, threads), range(threads)))


def together(fn, threads: int) -> list:
    """fn() on `threads` threads at once (workers sharing a queue inside the kernel); their results."""
    if threads <= 1:
        return [fn()]
    return list(_pool(threads).map(lambda _: fn(), range(threads)))


def mapped(fragment: str) -> list[str]:
    """Paths of the shared libraries this process has loaded whose path contains `fragment` (from /proc/self/maps;
    none where there is no such file): a library another package loaded, to call it with ctypes."""
    try:
        maps = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return []
    return list(dict.fromkeys(line.split(None, 5)[5] for line in maps if line.count(" ") >= 5 and fragment in line))


@cache
def _blas_threads_setter():
    """OpenBLAS's openblas_set_num_threads_local (0.3.27 on: the calling thread's BLAS threads, returns the previous
    count) from the OpenBLAS numpy loaded; None with another BLAS."""
    for path in mapped("openblas"):
        fn = getattr(ctypes.CDLL(path), "openblas_set_num_threads_local", None)
        if fn is not None:
            fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
            return fn
    return None


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """NumPy's matrix products on the calling thread alone, inside the block. After a multithreaded product
    OpenBLAS's threads busy-wait for more work for about 0.1 s, taking the cores from the kernels' threads that
    follow (a camera's rays on 2 cores ran no faster than on one); the sensors' small products gain nothing from
    them. Same results: a product's elements do not depend on how its rows are split among threads (tested)."""
    setter = _blas_threads_setter()
    previous = setter(1) if setter is not None else None
    try:
        yield
    finally:
        if setter is not None:
            setter(previous)
