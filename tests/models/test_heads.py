"""The common detection head's starting point."""
import math

import pytest
import torch

from radarpc.models.heads import DetectionHead


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


@pytest.mark.parametrize("prior", [0.0, 1.0, -0.5])
def test_detection_head_rejects_a_prior_outside_0_1(prior):
    with pytest.raises(ValueError, match="prior_probability"):
        DetectionHead(in_channels=4, widths=(4, 4), prior_probability=prior)
