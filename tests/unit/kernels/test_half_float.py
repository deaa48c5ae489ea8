"""The compiled float16 conversions give NumPy's bits, every special value included, and NumPy's where disabled; the
byte-shuffled ones NumPy's bits as planes of low and high bytes."""

import numpy as np
import pytest

from co3sop_nodes import kernels
from co3sop_nodes.kernels import half_float


def _values() -> np.ndarray:
    """float32 values across every float16 regime: subnormal, normal, halfway cases, overflow, NaN and infinities."""
    rng = np.random.default_rng(0)
    x = (rng.standard_normal(100_003) * 10.0 ** rng.integers(-9, 6, 100_003)).astype(np.float32)
    specials = [0.0, -0.0, 6e-8, 2.9802322e-08, 65504.0, 65519.99, 65520.0, 1e9, np.inf, -np.inf, np.nan]
    return np.concatenate([np.asarray(specials, np.float32), x, np.float32(1.0) + np.arange(64, dtype=np.float32)])


@pytest.mark.parametrize("enabled", [True, False], ids=["compiled", "numpy"])
def test_conversions_give_numpys_bits(enabled, monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", enabled)
    assert half_float.available() == enabled  # CI machines have a C compiler with _Float16 (GCC 12 on)
    x = _values()
    with np.errstate(over="ignore"):
        want = x.astype(np.float16)
    got = half_float.to_float16(x[::1])
    assert got.dtype == np.float16 and np.array_equal(got.view(np.uint16), want.view(np.uint16))
    back = half_float.from_float16(want)
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), want.astype(np.float32).view(np.uint32))


def test_strided_input_is_converted_in_order():
    x = _values()[:2000].reshape(40, 50)[:, ::3]  # (40, 17), not contiguous
    with np.errstate(over="ignore"):
        want = x.astype(np.float16)
    got = half_float.to_float16(x)
    assert got.shape == x.shape and np.array_equal(got.view(np.uint16), want.view(np.uint16))


@pytest.mark.parametrize("enabled", [True, False], ids=["compiled", "numpy"])
@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, None], ids=lambda n: f"n{n}")  # the vector loop's edges, and all
def test_byte_shuffled_conversions_are_planes_of_numpys_bits(enabled, n, monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", enabled)
    x = _values()[:n]
    with np.errstate(over="ignore"):
        bits = x.astype(np.float16).view(np.uint16)
    planes = half_float.to_float16_planes(x)
    assert planes.dtype == np.uint8 and planes.shape == (2 * x.size,)
    assert np.array_equal(planes[: x.size], bits & 0xFF) and np.array_equal(planes[x.size :], bits >> 8)
    back = half_float.from_float16_planes(planes)
    want = bits.view(np.float16).astype(np.float32)
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), want.view(np.uint32))
    with pytest.raises(ValueError, match="not two planes"):
        half_float.from_float16_planes(planes[:1] if x.size else np.zeros(3, np.uint8))
