"""fast_inference: every exact rewrite at once, on the tiny models."""
import pytest
import torch
import torch.nn as nn

from radarpc.models.fast.batchnorm import randomise_batchnorm_
from radarpc.models.fast.collapsed_head import CollapsedDetectionHead, collapse_mac_ratio
from radarpc.models.fast import fast_inference
from radarpc.models.fftradnet import fftradnet, fftradnet_s, fftradnet_tiny
from radarpc.models.fast.fourier_stem import FourierStem, stem_gmac
from radarpc.models.fast.fused_activation import ConvActivation
from radarpc.models.heads import DetectionHead
from radarpc.models.pillars import pillars_tiny


def test_fftradnet():
    model = randomise_batchnorm_(fftradnet_tiny(), torch.Generator().manual_seed(1)).eval()
    fast = fast_inference(model, winograd_min_channels=8, compiled=False)
    # the tiny model is small: the layers beat the Fourier stem, and collapsing its thin head would not
    # save multiply-adds, so both stay as they are
    assert not isinstance(fast.pre_encoder, FourierStem) and isinstance(fast.detection_head, DetectionHead)
    assert any(isinstance(m, ConvActivation) for m in fast.modules())
    x = torch.randn(1, 32, 128, 64, generator=torch.Generator().manual_seed(2))
    with torch.inference_mode():
        ref, out = model.forward_channels(x), fast.forward_channels(x)
        det_only = fast_inference(model, detections_only=True, compiled=False).forward_channels(x)
    # each rewrite is bounded by its own tests; composed, as the other tiny-model tests, within 1e-3
    assert float((out.detection - ref.detection).abs().max()) <= 1e-3 * float(ref.detection.abs().max())
    assert float((out.freespace - ref.freespace).abs().max()) <= 1e-3 * float(ref.freespace.abs().max())
    assert det_only.freespace is None
    assert float((det_only.detection - ref.detection).abs().max()) <= 1e-3 * float(ref.detection.abs().max())


def test_pillars():
    model = randomise_batchnorm_(pillars_tiny(), torch.Generator().manual_seed(3)).eval()
    fast = fast_inference(model, winograd_min_channels=8, compiled=False)
    assert any(isinstance(m, ConvActivation) for m in fast.backbone.modules())
    canvas = torch.randn(1, model.cfg.pfn_channels, *model.cfg.grid, generator=torch.Generator().manual_seed(4))
    with torch.inference_mode():
        ref = model.detection_head(model.backbone(canvas))
        out = fast.detection_head(fast.backbone(canvas))
    assert float((out - ref).abs().max()) <= 1e-3 * float(ref.abs().max())


def test_other_models_are_refused():
    with pytest.raises(TypeError, match="expected an FFTRadNet or a PointPillars model, got Conv2d"):
        fast_inference(nn.Conv2d(1, 1, 1))


def test_wide_heads_collapse_and_thin_ones_do_not():
    """The rule against hand-counted multiply-adds per output cell: the layers 256 x 144 x 9 +
    144 x 96 x 9 + 2 x 96 x 96 x 9 + 96 x 3 x 9 = 624,672; collapsed 256 x 3 x 11 x 11 = 92,928, and at
    azimuth stride 2 (the first layer at stride 2) 2 x 256 x 3 x 11 x 19 = 321,024 against the same."""
    assert collapse_mac_ratio(DetectionHead(256, 1, 2, (144, 96))) == pytest.approx(92928 / 624672)
    assert collapse_mac_ratio(DetectionHead(256, 2, 2, (144, 96))) == pytest.approx(321024 / 624672)
    model = randomise_batchnorm_(fftradnet_tiny(decoder_channels=(8, 256), detection_widths=(144, 96)),
                                 torch.Generator().manual_seed(1)).eval()
    assert isinstance(fast_inference(model, compiled=False).detection_head, CollapsedDetectionHead)


def test_full_size_fftradnet_takes_every_rewrite():
    """Built, not run: the full model's stem and head are converted, the -s model's stem is not."""
    assert stem_gmac(fftradnet()) == pytest.approx(512 * 256 * (192 * 32 * 12 + 192 * 192 * 9) / 1e9)
    assert stem_gmac(fftradnet_s()) == pytest.approx(128 * 64 * (64 * 32 * 12 + 64 * 64 * 9) / 1e9)
    fast = fast_inference(fftradnet().eval(), detections_only=True, compiled=False)
    assert isinstance(fast.pre_encoder, FourierStem) and isinstance(fast.detection_head, CollapsedDetectionHead)
    assert not isinstance(fast_inference(fftradnet_s().eval(), compiled=False).pre_encoder, FourierStem)
