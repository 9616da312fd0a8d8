"""The detection head collapsed into one correlation, against the head's layers in float64."""
import copy

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.fast import collapsed_head
from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.fast.collapsed_head import CollapsedDetectionHead, collapsed_head_for_inference, compose_convs
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fftradnet import fftradnet_tiny
from radarpc.models.heads import DetectionHead
from radarpc.models.pillars import pillars_tiny
from testkit import warns_reduced_fp32_matmul

U32 = 2.0 ** -24


def folded_head(c, stride, widths, seed):
    head = randomise_batchnorm_(DetectionHead(c, stride, 2, widths), torch.Generator().manual_seed(seed)).eval()
    holder = nn.Module()
    holder.detection_head = head
    return head, collapsed_head_for_inference(holder, compiled=False).detection_head


def logits64(head: DetectionHead, x: torch.Tensor, magnitude: bool = False) -> torch.Tensor:
    """The head before its sigmoid, in float64; with ``magnitude``, every weight and bias (BN folded)
    and the input by their absolute values: the sum of the magnitudes of all the terms."""
    h = copy.deepcopy(head).double().eval()
    x = x.double()
    layers = []
    for i in range(1, 5):
        conv, bn = copy.deepcopy(getattr(h, f"conv{i}")), getattr(h, f"bn{i}")
        s = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        w = conv.weight * s[:, None, None, None]
        b = bn.bias - bn.running_mean * s + (0 if conv.bias is None else conv.bias * s)
        layers.append((w, b, conv.stride))
    final = (torch.cat([h.clshead.weight, h.reghead.weight]), torch.cat([h.clshead.bias, h.reghead.bias]), (1, 1))
    if magnitude:
        x = x.abs()
    with torch.no_grad():
        for w, b, stride in [*layers, final]:
            x = F.conv2d(x, w.abs() if magnitude else w, b.abs() if magnitude else b, stride=stride, padding=1)
    return x


def check(head, fast, x):
    """Every output within Higham's gamma_n of the magnitudes; ``n`` covers the longer of the two
    paths: the composed product (C + U V + 3 roundings: products and sums over channels and taps, the
    float64 kernel's rounding, the bias) and the layers on the strips (9 C_l + 2 per layer). The
    sigmoid is 1/4-Lipschitz."""
    with torch.inference_mode():
        y = fast(x)
    ref = logits64(head, x)
    mag = logits64(head, x, magnitude=True)
    n_u, n_v = fast.kernel_size
    n = max(x.shape[1] + n_u * n_v + 3,
            sum(9 * getattr(head, f"conv{i}").in_channels + 2 for i in range(1, 5)) + 9 * head.clshead.in_channels + 2)
    bound = n * U32 / (1 - n * U32) * mag
    bound[:, :1] /= 4
    ref = torch.cat([torch.sigmoid(ref[:, :1]), ref[:, 1:]], dim=1)
    assert y.shape == ref.shape
    return (y.double() - ref).abs(), bound


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_matches_the_layers_within_the_rounding_bound(stride):
    head, fast = folded_head(6, stride, (5, 7), seed=stride)
    assert fast.kernel_size == (11, 1 + 2 * (1 + [1, 2, 2][stride // 2] + 3 * stride))
    x = torch.randn(2, 6, 13, 12 * stride, generator=torch.Generator().manual_seed(0))
    err, bound = check(head, fast, x)
    assert (err <= bound).all()
    # the bound is far below the outputs' magnitudes, so a wrong tap, bias or border breaks it
    assert float(bound.max()) < 1e-3 * float(logits64(head, x, magnitude=True).max())


def test_compose_convs_is_the_layers_away_from_their_borders():
    convs = [nn.Conv2d(3, 4, 3, stride=(1, 2), padding=1), nn.Conv2d(4, 2, 3, padding=1)]
    kernel, bias, pad_rows, pad_cols, stride = compose_convs(convs)
    assert (pad_rows, pad_cols, stride) == (2, 3, 2) and kernel.shape == (2, 3, 5, 7)
    x = torch.randn(1, 3, 12, 24, dtype=torch.float64)
    with torch.no_grad():
        layered = convs[1].double()(convs[0].double()(x))
    composed = F.conv2d(x, kernel, bias, stride=(1, stride), padding=(pad_rows, pad_cols))
    # one row / column in from the edges the second layer's zero padding no longer matters
    assert torch.allclose(composed[..., 1:-1, 1:-1], layered[..., 1:-1, 1:-1], rtol=0, atol=1e-12)


def test_a_narrower_border_breaks_the_bound(monkeypatch):
    head, fast = folded_head(6, 1, (5, 7), seed=1)
    monkeypatch.setattr(collapsed_head, "BORDER", 3)
    x = torch.randn(1, 6, 13, 12, generator=torch.Generator().manual_seed(0))
    err, bound = check(head, fast, x)
    assert not (err <= bound).all()


def test_compiled_sum_agrees():
    head, _ = folded_head(6, 2, (5, 7), seed=7)
    holder = nn.Module()
    holder.detection_head = head
    fast = collapsed_head_for_inference(holder, compiled=True).detection_head
    err, bound = check(head, fast, torch.randn(1, 6, 13, 24, generator=torch.Generator().manual_seed(0)))
    assert (err <= bound).all()


@pytest.mark.parametrize("build", [fftradnet_tiny, pillars_tiny])
def test_models_convert(build):
    model = randomise_batchnorm_(build(), torch.Generator().manual_seed(5)).eval()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    fast = collapsed_head_for_inference(model, compiled=False)
    assert isinstance(fast.detection_head, CollapsedDetectionHead)
    assert isinstance(model.detection_head, DetectionHead)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
    head_in = torch.randn(2, model.detection_head.conv1.in_channels, 128,
                          224 * model.detection_head.conv1.stride[1] * model.detection_head.conv2.stride[1])
    with torch.inference_mode():
        ref, out = model.detection_head(head_in), fast.detection_head(head_in)
    assert float((out - ref).abs().max()) <= 1e-3 * float(ref.abs().max())   # the bound above, on a larger head


def test_bad_input_is_named():
    head, fast = folded_head(6, 2, (5, 7), seed=1)
    with pytest.raises(ValueError, match=r"x must be \(B, 6, H >= 9, W\) with W a multiple of 2 and >= 18, got \(1, 6, 13, 17\)"):
        fast(torch.randn(1, 6, 13, 17))
    with pytest.raises(ValueError, match="H >= 9"):
        fast(torch.randn(1, 6, 8, 24))
    with pytest.raises(RuntimeError, match="inference only"):
        fast(torch.randn(1, 6, 13, 24, requires_grad=True))
    with pytest.raises(ValueError, match="x is torch.float64 on cpu, the weights torch.float32"):
        fast(torch.randn(1, 6, 13, 24, dtype=torch.float64))
    with pytest.raises(ValueError, match="fold the head's BatchNorms"):
        CollapsedDetectionHead(DetectionHead(6, 1, 2, (5, 7)))
    with pytest.raises(TypeError, match="not a DetectionHead"):
        collapsed_head_for_inference(nn.Conv2d(1, 1, 1))
    head = fuse_for_inference(fftradnet_tiny()).detection_head
    head.conv1 = nn.Identity()
    with pytest.raises(ValueError, match="plain nn.Conv2d"):
        CollapsedDetectionHead(head)


def test_built_on_the_weights_device_and_dtype():
    head = fuse_for_inference(fftradnet_tiny()).detection_head
    assert all(b.device.type == "meta" for b in CollapsedDetectionHead(head.to("meta")).buffers())
    head64 = fuse_for_inference(fftradnet_tiny()).detection_head.double()
    fast = CollapsedDetectionHead(head64, compiled=False)
    x = torch.randn(1, head64.conv1.in_channels, 12, 12, dtype=torch.float64)
    with torch.inference_mode():
        assert fast(x).dtype == torch.float64
        # float64 rounding (n 2^-53 with n ~ 10^3 terms) is ~1e-13 of the magnitudes: 1e-9 leaves room
        assert torch.allclose(fast(x), head64(x), rtol=0, atol=1e-9 * float(head64(x).abs().max()))


def test_reduced_float32_matmul_precision_is_warned():
    _, fast = folded_head(6, 1, (5, 7), seed=1)
    with warns_reduced_fp32_matmul(), torch.inference_mode():
        fast(torch.randn(1, 6, 13, 12))
