"""One call for a model's fastest exact CPU inference copy.

Every step is an exact rewrite in real arithmetic (float32 results differ by rounding only; each
module's tests bound it): BatchNorm folded into the convolutions, channels-last weights; FFTRadNet's
pre-encoder, stem and first ReLU per Doppler frequency where those layers take at least 4 GMAC a
frame (:mod:`radarpc.models.fast.fourier_stem`: full RADIal cubes, not ``radial-s``); the detection
head's linear layers as one correlation where that at least halves the head's multiply-adds
(:mod:`radarpc.models.fast.collapsed_head`: the full-size heads, not the thin ``-s`` ones); wide 3 x 3
layers as Winograd F(4x4, 3x3) (:mod:`radarpc.models.fast.winograd`); and activations fused into the
convolutions before them (:mod:`radarpc.models.fast.fused_activation`). What each gives is measured in
``docs/results/detection.md``.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from radarpc.models.fftradnet import FFTRadNet
from radarpc.models.fast.batchnorm import fuse_for_inference
from radarpc.models.fast.collapsed_head import collapse_mac_ratio, collapsed_head_for_inference
from radarpc.models.fast.fourier_stem import fourier_stem_for_inference, stem_gmac
from radarpc.models.fast.fused_activation import fuse_activations_for_inference
from radarpc.models.fast.winograd import winograd_for_inference

__all__ = ["fast_inference"]


def fast_inference(model: nn.Module, *, detections_only: bool = False, winograd_min_channels: int = 96,
                   compiled: bool = True) -> nn.Module:
    """A copy of ``model`` for inference on CPUs; ``model`` is unchanged.

    Device-agnostic by construction (the oneDNN fusions fall back to plain operators elsewhere), but
    measured on CPUs only; on GPUs cuDNN already picks fast convolution algorithms itself. Needs
    torch >= 2.4 (the Winograd layer is a ``torch.library.custom_op``).

    Parameters
    ----------
    model : FFTRadNet or PointPillars
    detections_only : bool
        Drop the freespace head (the copy's forward then returns no freespace map).
    winograd_min_channels : int
        As :func:`radarpc.models.fast.winograd.winograd_for_inference`'s ``min_channels``.
    compiled : bool
        Inductor-compile the Winograd transforms and the other steps' small kernels (fast; the first
        call of each shape compiles, with a C++ compiler on CPUs), or run them eagerly.

    Returns
    -------
    nn.Module
        In eval mode; inference only (the rewritten layers refuse autograd).
    """
    m = fuse_for_inference(model).to(memory_format=torch.channels_last)
    if detections_only:
        m.freespace_head = None
    if isinstance(m, FFTRadNet) and stem_gmac(m) >= 4:   # small maps: the layers are faster
        m = fourier_stem_for_inference(m, compiled=compiled)
    if collapse_mac_ratio(m.detection_head) <= 0.5:      # thin heads (the -s models) run faster as they are
        m = collapsed_head_for_inference(m, compiled=compiled)
    m = winograd_for_inference(m, min_channels=winograd_min_channels, compiled=compiled)
    return fuse_activations_for_inference(m)
