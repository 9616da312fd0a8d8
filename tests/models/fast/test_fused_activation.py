"""Convolutions with their activation fused (oneDNN post-ops on CPU) against float64."""
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models import pillars
from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fftradnet import fftradnet_tiny
from radarpc.models.fast.fused_activation import ConvActivation, fuse_activations_for_inference
from radarpc.models.fast.winograd import WinogradConv2d, winograd_for_inference

U32 = 2.0 ** -24
# an elementwise activation evaluated in float32 to within this many units of roundoff of its value
# at the computed input, plus as many of the input (oneDNN's erf is a polynomial approximation)
ACTIVATION_ULPS = 16

CONVS = [
    lambda: nn.Conv2d(6, 5, 3, padding=1),
    lambda: nn.Conv2d(6, 5, 3, stride=2, padding=1),
    lambda: nn.Conv2d(6, 5, (1, 3), padding=(0, 2), dilation=(1, 2)),
    lambda: nn.ConvTranspose2d(6, 5, 2, stride=2),
    lambda: nn.ConvTranspose2d(6, 5, 1),
    lambda: nn.ConvTranspose2d(6, 5, 3, stride=2, padding=1, output_padding=1),
]
ACTIVATIONS = [nn.GELU, lambda: nn.GELU(approximate="tanh"), nn.ReLU]


def bound(conv, x, act_ref):
    """|conv| applied to |x| (+ |b|) times gamma_n (n: terms per output + 2), carried through the
    activation (slope at most 1.13 for GELU, 1 for ReLU), plus the activation's own rounding."""
    with torch.no_grad():
        mag = type(conv)(**_kwargs(conv)).double()
        mag.weight.copy_(conv.weight.abs())
        mag.bias.copy_(conv.bias.abs())
        m = mag(x.double().abs())
    n = conv.weight[0].numel() + 2
    pre = n * U32 / (1 - n * U32) * m
    return 1.13 * pre + ACTIVATION_ULPS * U32 * (act_ref.abs() + m)


def _kwargs(conv):
    kw = dict(in_channels=conv.in_channels, out_channels=conv.out_channels, kernel_size=conv.kernel_size,
              stride=conv.stride, padding=conv.padding, dilation=conv.dilation)
    if isinstance(conv, nn.ConvTranspose2d):
        kw["output_padding"] = conv.output_padding
    return kw


@pytest.mark.parametrize("make_act", ACTIVATIONS)
@pytest.mark.parametrize("make_conv", CONVS)
def test_matches_float64_within_the_rounding_bound(make_conv, make_act):
    torch.manual_seed(0)
    conv, act = make_conv().eval(), make_act()
    layer = ConvActivation(conv, act)
    x = torch.randn(2, 6, 9, 10).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        y = layer(x)
    with torch.no_grad():
        ref = act.double()(conv.double()(x.double()))
    conv.float()
    assert y.shape == ref.shape and y.dtype == torch.float32
    assert ((y.double() - ref).abs() <= bound(conv, x, ref)).all()


def test_autograd_takes_the_unfused_path():
    conv = nn.Conv2d(3, 4, 3, padding=1)
    layer = ConvActivation(conv, nn.GELU())
    x = torch.randn(1, 3, 8, 8, requires_grad=True)
    y = layer(x)
    assert torch.equal(y, F.gelu(conv(x)))
    y.sum().backward()
    assert x.grad is not None and conv.weight.grad is not None


def test_pillar_model_conversion():
    model = randomise_batchnorm_(pillars.pillars_tiny(), torch.Generator().manual_seed(3)).eval()
    fused = fuse_for_inference(model)
    fast = fuse_activations_for_inference(fused)
    n_fused = sum(isinstance(m, ConvActivation) for m in fast.backbone.modules())
    n_gelu = sum(isinstance(m, nn.GELU) for m in fused.backbone.modules())
    left = [m for seq in fast.backbone.modules() if isinstance(seq, nn.Sequential) for m in seq if isinstance(m, nn.GELU)]
    assert n_fused == n_gelu > 0 and not left
    assert not any(isinstance(m, ConvActivation) for m in fused.modules())      # the original is unchanged
    canvas = torch.randn(1, fused.cfg.pfn_channels, *fused.cfg.grid)
    with torch.inference_mode():
        ref, out = fused.backbone(canvas), fast.backbone(canvas)
    # each fused layer within its bound above; a few in sequence stay well inside 1e-4
    assert float((out - ref).abs().max()) <= 1e-4 * float(ref.abs().max())


def test_bad_layers_are_named():
    with pytest.raises(ValueError, match="numeric zero padding"):
        ConvActivation(nn.Conv2d(3, 4, 3, padding="same"), nn.GELU())
    with pytest.raises(ValueError, match="numeric zero padding"):
        ConvActivation(nn.Conv2d(3, 4, 3, padding=1, padding_mode="circular"), nn.GELU())
    with pytest.raises(ValueError, match="must be nn.GELU or nn.ReLU"):
        ConvActivation(nn.Conv2d(3, 4, 3), nn.SiLU())


def test_fftradnet_conversion_with_winograd_layers():
    """Bottleneck, stem and decoder activations (attribute triples) fuse, into Winograd layers too."""
    model = fuse_for_inference(randomise_batchnorm_(fftradnet_tiny(), torch.Generator().manual_seed(4)).eval())
    wino = winograd_for_inference(model, min_channels=8, compiled=False)
    fast = fuse_activations_for_inference(wino)
    assert sum(isinstance(m, ConvActivation) for m in fast.modules()) >= 4
    assert any(isinstance(m, WinogradConv2d) and m.relu for m in fast.modules())
    assert not any(isinstance(m, WinogradConv2d) and m.relu for m in wino.modules())   # the original is unchanged
    x = torch.randn(1, 32, 128, 64, generator=torch.Generator().manual_seed(5))
    with torch.inference_mode():
        ref, out = model.forward_channels(x), fast.forward_channels(x)
    # as tests/models/test_winograd.py's tiny FFTRadNet: each layer within its bound, composed within 1e-3
    assert float((out.detection - ref.detection).abs().max()) <= 1e-3 * float(ref.detection.abs().max())
    assert float((out.freespace - ref.freespace).abs().max()) <= 1e-3 * float(ref.freespace.abs().max())


def test_autocast_takes_the_unfused_path():
    """Under autocast the layer runs as the unfused ones around it do (their dtype, not float32)."""
    conv = nn.Conv2d(3, 4, 3, padding=1).eval()
    layer = ConvActivation(conv, nn.GELU())
    x = torch.randn(1, 3, 8, 8)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        assert layer(x).dtype == F.gelu(conv(x)).dtype == torch.bfloat16


def test_only_known_modules_fuse_by_name():
    """conv/bn/act children of a module whose forward may apply them in another order are left alone."""
    class Other(nn.Module):
        def __init__(self):
            super().__init__()
            self.conv, self.bn, self.act = nn.Conv2d(3, 3, 3, padding=1), nn.Identity(), nn.ReLU()

        def forward(self, x):
            return self.conv(self.act(x))

    fast = fuse_activations_for_inference(Other())
    assert type(fast.conv) is nn.Conv2d and type(fast.act) is nn.ReLU
