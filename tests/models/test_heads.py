"""The common heads: the detection head's starting point and float32 probability, the freespace head's two
resizing orders."""
import math

import pytest
import torch

from radarpc.models.heads import DetectionHead, FreespaceHead
from radarpc.models.losses import focal_loss


@pytest.mark.parametrize("prior", [0.01, 0.2])
def test_detection_head_starts_at_the_prior_probability(prior):
    head = DetectionHead(in_channels=4, widths=(4, 4), prior_probability=prior).eval()
    assert head.clshead.bias.item() == pytest.approx(math.log(prior / (1 - prior)), rel=1e-6)
    # a zero map passes the bias-free convs and eval-mode BN (running mean 0) as zeros, so every
    # cell's probability is sigmoid(bias) = prior
    with torch.no_grad():
        out = head(torch.zeros(1, 4, 128, 224))
    assert out.shape == (1, 3, 128, 224)
    torch.testing.assert_close(out[:, 0], torch.full((1, 128, 224), prior), rtol=1e-6, atol=0.0)


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_a_confident_false_alarm_keeps_its_gradient_under_bf16_autocast(compiled):
    # logit 8 on a negative cell: p = sigmoid(8) = 1 - 3.4e-4. A bf16 probability (8 mantissa bits)
    # rounds that to 1.0, so the loss's 1 - p is 0 and dL/dp = 1 / 1e-6 (focal_loss's floor). Eager
    # autograd then multiplies by the sigmoid's gradient p (1 - p) of the rounded p, 0: the cell
    # stops learning. Compiled, the cell got 336 (1e6 times the float32 p (1 - p)) instead of 1.
    # The head computes the probability in float32, where dL/dz = p (1 - p) / (1 - p + 1e-6)
    # holds in both.
    h, w = 2, 3                                 # a few cells: the bias gradient sums only 6 terms
    head = DetectionHead(in_channels=4, widths=(4, 4))
    with torch.no_grad():
        head.clshead.weight.zero_()
        head.clshead.bias.fill_(8.0)            # every logit exactly 8, in bf16 too
    net = torch.compile(head) if compiled else head
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(torch.randn(1, 4, h, w))
    assert out.dtype == torch.float32
    focal_loss(out[:, 0], torch.zeros(1, h, w), gamma=0.0).backward()
    p = 1 / (1 + math.exp(-8.0))
    expected = h * w * p * (1 - p) / (1 - p + 1e-6)
    # the bf16 convolution rounds each cell's gradient, the 6-term sum and its result to 8 bits
    # (at most 2^-9 relative each: < 1.6 % together, whatever the summation's precision); the
    # bf16 probability gave 0 eager and 336 per cell compiled
    assert head.clshead.bias.grad.item() == pytest.approx(expected, rel=2e-2)


@pytest.mark.parametrize("prior", [0.0, 1.0, -0.5])
def test_detection_head_rejects_a_prior_outside_0_1(prior):
    with pytest.raises(ValueError, match="prior_probability"):
        DetectionHead(in_channels=4, widths=(4, 4), prior_probability=prior)


def test_freespace_head_can_resize_its_logits_instead_of_its_input():
    # upsample_logits: the blocks run on the 128-row input and the 1-channel logits y are resized to
    # 256 rows bilinearly with align_corners=False, which puts output row k at input row k / 2 - 1/4:
    # out[2i] = 3/4 y[i] + 1/4 y[i-1], out[2i+1] = 3/4 y[i] + 1/4 y[i+1] (edge rows clamped); the 224
    # azimuth columns are kept as they are
    torch.manual_seed(0)
    head = FreespaceHead(in_channels=4, widths=(4, 4), upsample_logits=True).eval()
    official = FreespaceHead(in_channels=4, widths=(4, 4))
    # the same parameters, so weights move between the two
    assert {k: v.shape for k, v in head.state_dict().items()} == {k: v.shape for k, v in official.state_dict().items()}
    x = torch.randn(2, 4, 128, 224)
    with torch.no_grad():
        y = head.out(head.block2(head.block1(x)))[:, 0]                           # (2, 128, 224)
        out = head(x)
    assert out.shape == (2, 1, 256, 224)
    before = torch.cat([y[:, :1], y[:, :-1]], 1)
    after = torch.cat([y[:, 1:], y[:, -1:]], 1)
    want = torch.stack([0.75 * y + 0.25 * before, 0.75 * y + 0.25 * after], 2).reshape(2, 256, 224)
    # either side rounds a few times on values of size <= 2 max|y| (|y[i+1] - y[i]|, should the
    # kernel compute a + w (b - a)): within 8 ulps of max|y| in all
    tol = 8 * torch.finfo(torch.float32).eps * float(y.abs().max())
    torch.testing.assert_close(out[:, 0], want, rtol=0.0, atol=tol)
