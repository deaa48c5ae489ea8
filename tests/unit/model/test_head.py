"""The head's exact inference paths (OccupancyHead.labels: compiled kernel and PyTorch loop) against their reference,
the dense pass + labels_from_logits."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from model_checks import assert_labels_equal, reference

from co3sop_nodes import kernels
from co3sop_nodes.kernels import octant as octant_kernel
from co3sop_nodes.model.config import preset
from co3sop_nodes.model.head import OccupancyHead
from co3sop_nodes.model.path import InferencePath, onednn


def quarter(dims: tuple[int, int, int]) -> tuple[int, int, int]:
    """A quarter of a feature grid (half of x and y): enough voxels for per-voxel tolerances, in a quarter of the
    time where bfloat16 is emulated."""
    return dims[0] // 2, dims[1] // 2, dims[2]


def random_head(channels: tuple[int, int, int], dims: int, seed: int) -> OccupancyHead:
    """A head with random weights large enough that many classes win somewhere, batch norm calibrated on noise."""
    torch.manual_seed(seed)
    head = OccupancyHead(dims, channels, 24)
    with torch.no_grad():
        for p in head.parameters():
            p.normal_(0, 0.3)
        head.train()(torch.randn(2, dims, 8, 8, 4))
    return head.eval()


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize(
    "name, range_name",
    [
        ("tiny", "25.6m"),
        ("tiny", "51.2m"),
        ("tiny", "76.8m"),
        ("tiny-lidar", "51.2m"),
        ("small", "51.2m"),
        ("paper", "76.8m"),
    ],
)
def test_fast_labels_equal_the_dense_reference_at_every_range(name, range_name, compiled):
    cfg = preset(name, range=range_name)
    head = random_head(cfg.head_channels, cfg.embed_dims, 1)
    x = torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims)  # (B, C, X/4, Y/4, Z/4)
    want_labels, want_conf = reference(head, x)
    labels, conf = head.labels(x, compiled=compiled)
    assert labels.shape == conf.shape == (1, *cfg.grid.dims) and labels.dtype == conf.dtype == torch.uint8
    assert len(np.unique(want_labels)) >= 5  # a real test: many classes win somewhere
    assert_labels_equal(labels.numpy(), want_labels, head, x)
    assert np.abs(conf.numpy().astype(int) - want_conf).max() <= 1  # one step of 1/255 (float summation order)


def test_a_label_that_is_not_a_float32_tie_fails_the_comparison():
    head = random_head((8, 8, 4), 8, 4)
    x = torch.randn(1, 8, 4, 4, 2)
    want = reference(head, x)[0]
    assert_labels_equal(want.copy(), want, head, x)
    wrong = want.copy()
    wrong[0, 1, 2, 3] = (wrong[0, 1, 2, 3] + 1) % 24
    with pytest.raises(AssertionError, match="beyond a float32 tie"):
        assert_labels_equal(wrong, want, head, x)


@pytest.mark.parametrize(
    "chunk, compiled, threads", [(1, False, 1), (7, False, 1), (100_000, False, 1), (0, True, 1), (0, True, 3)]
)
def test_chunking_threads_and_batches_do_not_change_the_result(chunk, compiled, threads):
    head = random_head((8, 8, 4), 8, 2)
    x = torch.randn(2, 8, 4, 6, 2)
    want_labels, want_conf = reference(head, x)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        labels, conf = head.labels(x, chunk=chunk, compiled=compiled)
    finally:
        torch.set_num_threads(before)
    assert_labels_equal(labels.numpy(), want_labels, head, x)
    assert np.abs(conf.numpy().astype(int) - want_conf).max() <= 1


def test_the_kernel_splits_parents_in_shares_of_any_size():
    """Two parents share a vector: 5 threads split 1536 parents a batch in shares of 307 and 308, odd ones too."""
    head = random_head((8, 8, 4), 8, 5)
    x = torch.randn(2, 8, 8, 6, 4)
    want_labels, want_conf = reference(head, x)
    labels, conf = zip(
        *(octant_kernel.octant_labels(p, head.up2, head.point2, head.classify[2], 5) for p in head.parents(x))
    )
    assert_labels_equal(torch.stack(labels).numpy(), want_labels, head, x)
    assert np.abs(torch.stack(conf).numpy().astype(int) - want_conf).max() <= 1


def octant_labels(
    head: OccupancyHead, parents: torch.Tensor, precision: str, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    out = octant_kernel.octant_labels(parents, head.up2, head.point2, head.classify[2], 1, precision, scale)
    return tuple(t[None].numpy() for t in out)


@pytest.mark.parametrize("name", ["tiny-lidar", "small"])
def test_the_reduced_precision_kernel_stays_within_its_tolerance(name):
    """Fused multiply-adds and the shorter exp: labels equal but for float32 ties, confidence within one step; read
    as bfloat16 without bfloat16 products, the same parents give the same result bit for bit."""
    cfg = preset(name)
    head = random_head(cfg.head_channels, cfg.embed_dims, 6)
    x = torch.randn(1, cfg.embed_dims, *quarter(cfg.feature_grid.dims))
    want_labels, want_conf = reference(head, x)
    got_labels, got_conf = octant_labels(head, head.parents(x)[0], "float16")  # the reduced kernel on float32 parents
    assert len(np.unique(want_labels)) >= 5
    assert_labels_equal(got_labels, want_labels, head, x)
    assert np.abs(got_conf.astype(int) - want_conf).max() <= 1
    if not octant_kernel.dot_bf16("bfloat16", cfg.head_channels[2]):
        rounded = head.parents(x)[0].bfloat16()
        for got, want in zip(octant_labels(head, rounded, "bfloat16"), octant_labels(head, rounded.float(), "float16")):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("name", ["tiny-lidar", "small"])
@torch.no_grad()
def test_uint8_parents_are_read_as_their_scaled_values(name):
    """An int8 head's parents (uint8, one scale, folded into the transposed convolution's weights): where the CPU
    has bfloat16 dot products, the bfloat16 layers' result on the integers with the scaled weights (tolerance as
    for bfloat16 parents); elsewhere the reduced kernel's on the same values in float32 (labels equal but where
    the fold's rounding breaks a near-tie, confidence within one step). Other dtypes are refused."""
    cfg = preset(name)
    head = random_head(cfg.head_channels, cfg.embed_dims, 6)
    parents = head.parents(torch.randn(1, cfg.embed_dims, *quarter(cfg.feature_grid.dims)))[0]
    scale = float(parents.max()) / 255
    q = torch.round(parents / scale).clamp(0, 255).to(torch.uint8)
    got_labels, got_conf = octant_labels(head, q, "int8", scale)
    if octant_kernel.dot_bf16("int8", cfg.head_channels[2]):
        want_labels, want_conf, gap = bfloat16_layers(head, q, scale)
        differ = got_labels != want_labels
        assert differ.mean() <= 1e-5 and (gap[differ] <= 0.01).all()
        assert (np.abs(got_conf.astype(int) - want_conf) > 1).mean() <= 1e-5
    else:
        want_labels, want_conf = octant_labels(head, q.float() * scale, "float16")
        assert (got_labels == want_labels).mean() > 0.999
        assert np.abs(got_conf.astype(int) - want_conf)[got_labels == want_labels].max() <= 1
    assert len(np.unique(want_labels)) >= 5
    with pytest.raises(ValueError, match="int8 takes uint8 parents, not torch.float32"):
        octant_labels(head, parents, "int8", scale)


def bfloat16_layers(
    head: OccupancyHead, parents: torch.Tensor, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The full-resolution stage as bfloat16 layers compute it, the definition of the kernel's bfloat16 products:
    weights and hidden activations rounded to bfloat16, products and sums exact (float64), the classifier in base 2
    as the reduced kernel scales it. parents (X1, Y1, Z1, C1), each `scale` times its value (folded into the
    transposed convolution's weights before they are rounded, as the kernel folds it) -> labels, round(255
    p(label)) and the gap between the two best logits, each (1, X, Y, Z)."""

    def rounded(t):
        return t.float().bfloat16().double()

    x1, y1, z1, c1 = parents.shape
    log2e = 1.44269504  # in float32, as the kernel scales
    p = parents.double().reshape(-1, c1)  # (P, C1)
    up = rounded(head.up2.weight.flatten(2) * scale)  # (C1, C2, 8): octant 4 dx + 2 dy + dz
    h = torch.relu(torch.einsum("pc,cjo->poj", p, up) + head.up2.bias.double())  # (P, 8, C2)
    g = torch.relu(rounded(h) @ rounded(head.point2.weight[:, :, 0, 0, 0].t()) + head.point2.bias.double())
    cls = head.classify[2]
    logits = rounded(g) @ rounded(cls.weight[:, :, 0, 0, 0].t() * log2e) + (cls.bias * log2e).double()  # (P, 8, K)
    top2 = logits.topk(2, -1).values
    confidence = torch.round(255 / torch.exp2(logits - top2[..., :1]).sum(-1))

    def fine(t):  # (P, 8) octants of parents -> (1, X, Y, Z)
        return t.view(x1, y1, z1, 2, 2, 2).permute(0, 3, 1, 4, 2, 5).reshape(1, 2 * x1, 2 * y1, 2 * z1).numpy()

    return fine(logits.argmax(-1)), fine(confidence), fine(top2[..., 0] - top2[..., 1])


@pytest.mark.skipif(not octant_kernel.dot_bf16("bfloat16", 8), reason="the CPU has no bfloat16 dot products")
@pytest.mark.parametrize("name", ["tiny-lidar", "small"])
@torch.no_grad()
def test_the_bfloat16_products_compute_as_bfloat16_layers(name):
    """Labels equal to the definition's but where an activation's bfloat16 rounding may go either way (its float32
    sum and the exact one on either side of a rounding boundary, about one voxel in 10^6 here) and the two best
    logits then tie; confidence within one step but in such voxels. Closer to the definition than float32 products
    (which differ on about 3 labels in 10^3): the kernel rounds as a bfloat16 layer does."""
    cfg = preset(name)
    head = random_head(cfg.head_channels, cfg.embed_dims, 6)
    parents = head.parents(torch.randn(1, cfg.embed_dims, *cfg.feature_grid.dims))[0].bfloat16()
    labels, conf = octant_labels(head, parents, "bfloat16")
    want_labels, want_conf, gap = bfloat16_layers(head, parents)
    assert len(np.unique(want_labels)) >= 5
    differ = labels != want_labels
    assert differ.mean() <= 1e-5 and (gap[differ] <= 0.01).all()
    steps = np.abs(conf.astype(int) - want_conf)
    assert (steps > 1).mean() <= 1e-5
    float32_products = octant_labels(head, parents.float(), "float16")[1]
    assert steps.mean() < np.abs(float32_products.astype(int) - want_conf).mean()


@torch.no_grad()
def test_the_reduced_path_folds_the_half_resolution_norm_to_the_same_features():
    cfg = preset("tiny-lidar")
    head = random_head(cfg.head_channels, cfg.embed_dims, 7)
    x = torch.randn(1, cfg.embed_dims, *quarter(cfg.feature_grid.dims))
    want = head.parents(x)  # float32: the layers as they are
    for module in head.modules():  # as Co3SOP.use sets it
        if "path" in vars(module):
            module.path = InferencePath(precision="bfloat16")
    with head.path.autocast():
        got = head.parents(x)
    assert got.dtype == torch.bfloat16 and got.shape == want.shape
    assert (got.float() - want).abs().max() <= 0.03 * want.abs().max()  # bfloat16 rounding through three layers
    if onednn(torch.bfloat16):  # oneDNN's convolutions keep their input's layout; PyTorch's emulation has its own
        assert got.permute(0, 3, 1, 2, 4).is_contiguous()  # z-outer in memory, as the convolutions left it: no copy


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_the_kernel_reads_parents_in_any_layout(precision):
    """Parents stored z-outer (the reduced path's layout) or transposed give what their contiguous copy gives."""
    head = random_head((8, 8, 4), 8, 8)
    parents = head.parents(torch.randn(1, 8, 4, 6, 3))[0].detach().to(getattr(torch, precision))  # (X1, Y1, Z1, C1)
    want = octant_kernel.octant_labels(parents.contiguous(), head.up2, head.point2, head.classify[2], 2, precision)
    for layout in ((2, 0, 1, 3), (1, 0, 2, 3), (3, 0, 1, 2)):  # z outermost, y before x, channels outermost (copied)
        order = [layout.index(i) for i in range(4)]
        stored = parents.permute(*layout).contiguous().permute(*order)
        assert torch.equal(stored, parents)
        got = octant_kernel.octant_labels(stored, head.up2, head.point2, head.classify[2], 2, precision)
        for g, w in zip(got, want):
            assert torch.equal(g, w)


def test_the_compiled_kernel_is_the_default_on_the_cpu_and_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("CO3SOP_CACHE", str(tmp_path))
    kernels.load.cache_clear()
    octant_kernel._kernel.cache_clear()
    try:
        assert octant_kernel.available(16, 8, 24)  # CI machines have a C compiler, as every ROS 2 install
        assert len(list((tmp_path / "native").glob("octant_labels-*.so"))) == 1
        assert octant_kernel.available(16, 8, 24, "bfloat16")  # compiled apart: other flags, another library
        assert len(list((tmp_path / "native").glob("octant_labels-*.so"))) == 2
    finally:
        kernels.load.cache_clear()
        octant_kernel._kernel.cache_clear()


def test_without_a_compiler_the_head_takes_its_pytorch_path(tmp_path, monkeypatch):
    monkeypatch.setenv("CO3SOP_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    kernels.load.cache_clear()
    octant_kernel._kernel.cache_clear()
    try:
        head = random_head((8, 8, 4), 8, 3)
        x = torch.randn(1, 8, 4, 4, 2)
        assert not octant_kernel.available(8, 4, 24)
        labels, _ = head.labels(x)
        assert_labels_equal(labels.numpy(), reference(head, x)[0], head, x)
    finally:
        kernels.load.cache_clear()
        octant_kernel._kernel.cache_clear()


def test_a_head_with_an_odd_channel_count_at_half_resolution_takes_the_pytorch_loop():
    """The kernel reads parents' channels in pairs: with an odd C1 it is not offered, and labels stay exact."""
    head = random_head((8, 7, 4), 8, 9)
    x = torch.randn(1, 8, 4, 4, 2)
    assert not octant_kernel.available(7, 4, 24) and octant_kernel.available(8, 4, 24)
    labels, conf = head.labels(x)
    want_labels, want_conf = reference(head, x)
    assert_labels_equal(labels.numpy(), want_labels, head, x)
    assert np.abs(conf.numpy().astype(int) - want_conf).max() <= 1


@torch.no_grad()
def test_the_octants_logits_of_chosen_voxels_are_the_full_resolution_logits_there():
    """octant_logits (what the head's int8 fine-tuning weighs) gives, for voxels at 1/2, the dense pass's logits of
    their 8 fine voxels, octants in the transposed convolution's kernel order."""
    torch.manual_seed(0)
    head = OccupancyHead(32, (32, 16, 8), 24).eval()
    f1 = torch.randn(1, 16, 6, 5, 4)
    dense = head.full(f1)  # (1, K, 12, 10, 8)
    parents = torch.tensor([[0, 7, 33, 119]])
    got = head.octant_logits(f1, parents)  # (1, 8, K, 4)
    x1, y1, z1 = f1.shape[2:]
    for n, flat in enumerate(parents[0].tolist()):
        i, j, k = flat // (y1 * z1), (flat // z1) % y1, flat % z1
        for o in range(8):
            dx, dy, dz = o // 4, (o // 2) % 2, o % 2
            torch.testing.assert_close(got[0, o, :, n], dense[0, :, 2 * i + dx, 2 * j + dy, 2 * k + dz])
