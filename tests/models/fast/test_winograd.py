"""Winograd F(4x4, 3x3) convolution against a float64 direct convolution, within a rounding bound."""
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.fast import winograd
from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fftradnet import fftradnet_tiny
from radarpc.models.fast.winograd import (AT, BT, G, WinogradConv2d, supports_winograd, winograd_conv3x3,
                                     winograd_for_inference, winograd_weight)
from testkit import warns_reduced_fp32_matmul

U32 = 2.0 ** -24          # float32 unit roundoff


def magnitude(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor | None) -> torch.Tensor:
    """``|A^T| [sum_c (|G| |g| |G|^T) (.) (|B^T| |d| |B|)] |A| + |b|`` in float64, tile by tile (unfold):
    the sum of the magnitudes of every term the float32 algorithm adds, (B, K, H, W)."""
    bt, g, at = (torch.tensor(m, dtype=torch.float64).abs() for m in (BT, G, AT))
    n, c, h, wd = x.shape
    nr, nc = -(-h // 4), -(-wd // 4)
    xp = F.pad(x.double().abs(), (1, 4 * nc + 1 - wd, 1, 4 * nr + 1 - h))
    d = xp.unfold(2, 6, 4).unfold(3, 6, 4)                                   # (B, C, nr, nc, 6, 6)
    v = torch.einsum("ia,ncrsab,jb->ncrsij", bt, d, bt)
    u = torch.einsum("ia,kcab,jb->kcij", g, w.double().abs(), g)
    m = torch.einsum("ncrsij,kcij->nkrsij", v, u)
    y = torch.einsum("pi,nkrsij,qj->nkrpsq", at, m, at).reshape(n, -1, 4 * nr, 4 * nc)[:, :, :h, :wd]
    return y if b is None else y + b.double().abs()[:, None, None]


def rounding_bound(x, w, b) -> torch.Tensor:
    """Worst-case float32 error (Higham's gamma_n times the magnitude of the terms). The longest
    chain of roundings of one output: B^T d B (two stages of at most 4 terms and a constant
    multiply each: 8), U rounded from float64 (1), the product (1), the sum over C input channels
    (C - 1), A^T M A (two stages of at most 5 terms: 10), the bias (1): n = C + 20; C + 24 kept."""
    n = x.shape[1] + 24
    return n * U32 / (1 - n * U32) * magnitude(x, w, b)


CASES = [  # (B, C, K, H, W, tile_rows): sizes not multiples of 4, a 1 x 1 map, several blocks, one block
    (2, 5, 7, 9, 11, 1),
    (1, 3, 4, 1, 1, 4),
    (3, 16, 2, 17, 6, 2),
    (1, 24, 24, 12, 8, 100),
]


@pytest.mark.parametrize("case", CASES)
def test_matches_direct_convolution_within_the_rounding_bound(case):
    n, c, k, h, w, tile_rows = case
    g = torch.Generator().manual_seed(sum(case))
    x, weight, bias = torch.randn(n, c, h, w, generator=g), torch.randn(k, c, 3, 3, generator=g), torch.randn(k, generator=g)
    y = winograd_conv3x3(x, winograd_weight(weight), bias, tile_rows=tile_rows, compiled=False)
    ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1)
    bound = rounding_bound(x, weight, bias)
    assert y.shape == (n, k, h, w) and y.dtype == torch.float32
    assert y.is_contiguous(memory_format=torch.channels_last)
    assert ((y.double() - ref).abs() <= bound).all()
    # the bound stays 100x below the outputs (the transforms' coefficients, up to 5 and 8, make the
    # terms' magnitudes several hundred times the outputs), so a wrong tile, sign or offset breaks it
    assert float(bound.max()) < 1e-2 * float(ref.abs().max())


def test_a_wrong_transform_breaks_the_bound(monkeypatch):
    """The check above can fail: the same algorithm with one coefficient of B^T changed misses it."""
    g = torch.Generator().manual_seed(1)
    x, weight = torch.randn(1, 4, 8, 8, generator=g), torch.randn(3, 4, 3, 3, generator=g)
    bad = tuple(tuple(5 if (i, j) == (0, 0) else v for j, v in enumerate(row)) for i, row in enumerate(BT))
    monkeypatch.setattr(winograd, "BT", bad)
    y = winograd_conv3x3(x, winograd_weight(weight), compiled=False)
    ref = F.conv2d(x.double(), weight.double(), padding=1)
    assert not ((y.double() - ref).abs() <= rounding_bound(x, weight, None)).all()


def test_compiled_transforms_agree_with_the_bound():
    # one block holding all three tile rows (one input graph, padded above and cut below, and one
    # output graph: each graph costs tens of seconds of Inductor code generation on a cold cache),
    # on a crop of a channels-last tensor, which is read without a copy. The middle and last block
    # positions (pad_top 0) compile separately and are tested eagerly only (test_any_memory_layout)
    g = torch.Generator().manual_seed(2)
    full = torch.randn(2, 3, 10, 9, generator=g).contiguous(memory_format=torch.channels_last)
    x = full[:, :, :, 1:8]
    assert x.stride(1) == 1 and not x.is_contiguous(memory_format=torch.channels_last)
    weight, bias = torch.randn(4, 3, 3, 3, generator=g), torch.randn(4, generator=g)
    with torch.inference_mode():
        y = winograd_conv3x3(x, winograd_weight(weight), bias, tile_rows=4, compiled=True)
    ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1)
    assert ((y.double() - ref).abs() <= rounding_bound(x, weight, bias)).all()


@pytest.mark.parametrize("layout", ["channels_last_crop", "rows_crop", "channels_first"])
def test_any_memory_layout(layout):
    g = torch.Generator().manual_seed(6)
    full = torch.randn(3, 5, 14, 11, generator=g)
    x = {"channels_last_crop": full.contiguous(memory_format=torch.channels_last)[:, :, 2:13, 1:10],
         "rows_crop": full[:, :, 3:, :], "channels_first": full}[layout]
    weight, bias = torch.randn(2, 5, 3, 3, generator=g), torch.randn(2, generator=g)
    y = winograd_conv3x3(x, winograd_weight(weight), bias, tile_rows=1, compiled=False)
    ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1)
    assert ((y.double() - ref).abs() <= rounding_bound(x, weight, bias)).all()


def test_float64_input_stays_float64():
    g = torch.Generator().manual_seed(3)
    x, weight = torch.randn(1, 3, 5, 5, generator=g, dtype=torch.float64), torch.randn(2, 3, 3, 3, generator=g, dtype=torch.float64)
    y = winograd_conv3x3(x, winograd_weight(weight), compiled=False)
    ref = F.conv2d(x, weight, padding=1)
    assert y.dtype == torch.float64
    # both round now: Winograd's n = C + 24, the direct sum's 9 C + 1, and U's float64 einsum
    # (1/6, 1/12, 1/24 inexact; 8 more); the Winograd magnitude is at least the direct one (every
    # direct term appears in it with coefficients summing to 1)
    n, u64 = (3 + 24) + (9 * 3 + 1) + 8, 2.0 ** -53
    assert ((y - ref).abs() <= n * u64 / (1 - n * u64) * magnitude(x, weight, None)).all()


def test_module_and_model_conversion():
    model = nn.Sequential(nn.Conv2d(8, 8, 3, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, stride=2, padding=1),
                          nn.Sequential(nn.Conv2d(8, 8, 3, padding=1, bias=False)), nn.Conv2d(8, 4, 3, padding=1),
                          nn.Conv2d(4, 8, 1))
    converted = winograd_for_inference(model, min_channels=8, compiled=False)
    assert [type(m).__name__ for m in converted] == ["WinogradConv2d", "ReLU", "Conv2d", "Sequential", "Conv2d", "Conv2d"]
    assert isinstance(converted[3][0], WinogradConv2d) and converted[3][0].bias is None
    assert type(model[0]) is nn.Conv2d                                           # the original is untouched
    assert not supports_winograd(model[2]) and not supports_winograd(model[5])
    x = torch.randn(2, 8, 9, 13, generator=torch.Generator().manual_seed(4))
    weight, bias = model[0].weight.detach(), model[0].bias.detach()
    with torch.inference_mode():
        y = converted[0](x)
    ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1)
    assert ((y.double() - ref).abs() <= rounding_bound(x, weight, bias)).all()


def test_fftradnet_with_winograd_layers():
    """The tiny FFTRadNet (non-trivial BN statistics) with every eligible layer converted: detection
    and freespace maps within 1e-3 of the direct model's largest value (each converted layer stays
    within ~1e-5 of its direct result, see above; a few such layers in sequence, with ReLUs and
    sums, compose well inside 1e-3)."""
    torch.manual_seed(5)
    model = fuse_for_inference(randomise_batchnorm_(fftradnet_tiny(), torch.Generator().manual_seed(5)).eval())
    fast = winograd_for_inference(model, min_channels=8, compiled=False)
    assert sum(isinstance(m, WinogradConv2d) for m in fast.modules()) >= 4
    x = torch.randn(1, 32, 128, 64)
    with torch.inference_mode():
        ref, out = model.forward_channels(x), fast.forward_channels(x)
    assert out.detection.shape == ref.detection.shape and out.freespace.shape == ref.freespace.shape
    assert float((out.detection - ref.detection).abs().max()) <= 1e-3 * float(ref.detection.abs().max())
    assert float((out.freespace - ref.freespace).abs().max()) <= 1e-3 * float(ref.freespace.abs().max())


def test_bad_input_is_named():
    w = torch.randn(4, 3, 3, 3)
    u = winograd_weight(w)
    with pytest.raises(ValueError, match=r"\(K, C, 3, 3\) weight"):
        winograd_weight(torch.randn(4, 3, 5, 5))
    with pytest.raises(ValueError, match=r"u must be \(36, C=5, K\)"):
        winograd_conv3x3(torch.randn(1, 5, 8, 8), u)
    with pytest.raises(ValueError, match="float64 on cpu, x is torch.float32"):
        winograd_conv3x3(torch.randn(1, 3, 8, 8), u.double())
    with pytest.raises(ValueError, match="must be a .B, C, H, W. float32 or float64 tensor"):
        winograd_conv3x3(torch.ones(3, 8, 8), u)
    with pytest.raises(ValueError, match=r"bias must be \(4,\)"):
        winograd_conv3x3(torch.randn(1, 3, 8, 8), u, torch.zeros(3))
    with pytest.raises(ValueError, match="tile_rows must be >= 1"):
        winograd_conv3x3(torch.randn(1, 3, 8, 8), u, tile_rows=0)
    with pytest.raises(ValueError, match="stride 1, padding 1"):
        WinogradConv2d(nn.Conv2d(3, 4, 3, stride=2, padding=1))
    with pytest.raises(ValueError, match="WinogradConv2d: tile_rows must be >= 1"):
        WinogradConv2d(nn.Conv2d(3, 4, 3, padding=1), tile_rows=0)
    with pytest.raises(ValueError, match="float32 or float64"):
        winograd_conv3x3(torch.randn(1, 3, 8, 8).bfloat16(), u.bfloat16())
    with pytest.raises(ValueError, match=r"bias must be \(4,\) torch.float32 on cpu, got \(4,\) torch.float64"):
        winograd_conv3x3(torch.randn(1, 3, 8, 8), u, torch.zeros(4, dtype=torch.float64))


def test_autograd_is_refused():
    conv = nn.Conv2d(3, 4, 3, padding=1)
    layer = WinogradConv2d(conv, compiled=False)
    x = torch.randn(1, 3, 8, 8, requires_grad=True)
    with pytest.raises(RuntimeError, match="inference only"):
        layer(x)
    with torch.no_grad():
        assert layer(x).shape == (1, 4, 8, 8)


def test_reduced_float32_matmul_precision_is_warned():
    u = winograd_weight(torch.randn(4, 3, 3, 3))
    x = torch.randn(1, 3, 8, 8)
    with warns_reduced_fp32_matmul():
        winograd_conv3x3(x, u, compiled=False)


def test_relu_in_the_output_transform():
    """``relu=True`` is the ReLU of the same computation (ReLU is 1-Lipschitz: the bound holds)."""
    g = torch.Generator().manual_seed(3)
    x, weight, bias = torch.randn(2, 5, 9, 11, generator=g), torch.randn(7, 5, 3, 3, generator=g), torch.randn(7, generator=g)
    y = winograd_conv3x3(x, winograd_weight(weight), bias, tile_rows=1, compiled=False, relu=True)
    ref = F.conv2d(x.double(), weight.double(), bias.double(), padding=1).clamp_min(0)
    assert (y >= 0).all() and ((y.double() - ref).abs() <= rounding_bound(x, weight, bias)).all()
