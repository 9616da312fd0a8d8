"""The common range-azimuth heads: vehicle detection and freespace segmentation, as in FFTRadNet.

Every detector in radarpc (FFTRadNet on dense or sparse RD, the pillar models) ends in a
latent range-azimuth (RA) feature map ``(B, C, 128, A)`` and hands it to these two heads, so the
models differ only in how they reach that map (the seed's "common RA-aligned detection head").

Layout and conventions (those of valeoai/RADIal ``FFTRadNet/model/FFTRadNet.py``):

* RA map: rows are range cells of ``4 x 0.201171875 = 0.8047 m`` (row 0 nearest), columns are
  azimuth cells of ``0.8 deg``; 224 columns span -89.6..+89.6 deg.
* Detection output ``(B, 1 + n_reg, 128, 224)``: channel 0 is the vehicle **probability**
  (a sigmoid is applied, as the official head does, so the official focal loss and decoding see the
  same numbers); channels 1.. are the normalised range and azimuth offsets (see
  :mod:`radarpc.models.targets`). It is float32 under autocast too (float64 stays float64).
* Freespace output ``(B, 1, 256, 224)``: **logits** (the official code trains them with
  ``BCEWithLogitsLoss`` and thresholds ``sigmoid >= 0.5``); rows are range cells of
  ``2 x 0.201171875 = 0.4023 m`` (rows 0..123 are the scored 0-50 m).

Parameter names follow the official modules (``conv1``, ``bn1``, ..., ``clshead``, ``reghead``),
so an official state dict maps onto these heads by a key prefix only.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["DetectionHead", "FreespaceHead", "ConvBlock", "HeadOutput", "DETECTION_SHAPE", "FREESPACE_SHAPE"]

DETECTION_SHAPE = (128, 224)   # RA detection grid (range cells, azimuth cells)
FREESPACE_SHAPE = (256, 224)   # freespace grid (range cells, azimuth cells)


class HeadOutput(NamedTuple):
    """What every radarpc detector returns."""

    detection: torch.Tensor          # (B, 1 + n_reg, 128, 224): probability, then offsets
    freespace: torch.Tensor | None   # (B, 1, 256, 224) logits, None when the model has no freespace head


def conv3x3(c_in: int, c_out: int, stride: int | tuple[int, int] = 1, bias: bool = False) -> nn.Conv2d:
    """3 x 3 convolution, padding 1 ("same" at stride 1)."""
    return nn.Conv2d(c_in, c_out, kernel_size=3, stride=stride, padding=1, bias=bias)


class ConvBlock(nn.Module):
    """Two (conv3x3 + bias -> BN -> ReLU), no skip connection (the official ``BasicBlock``)."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv1 = conv3x3(c_in, c_out, bias=True)   # bias before BN: as the official weights have it
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = conv3x3(c_out, c_out, bias=True)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.act1, self.act2 = nn.ReLU(), nn.ReLU()     # modules, so an inference copy can fuse them

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.act1(self.bn1(self.conv1(x)))
        return self.act2(self.bn2(self.conv2(x)))


def _at_least_float32(x: torch.Tensor) -> torch.Tensor:
    """``x`` in float32 if it is a narrower float (bf16, fp16 under autocast), else unchanged."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


class DetectionHead(nn.Module):
    """RA feature map -> vehicle probability and range/azimuth offsets on the 128 x 224 grid.

    Four conv3x3 + BN layers (``w1, w2, w2, w2`` channels, official 144, 96, 96, 96; no
    activation between them, exactly as the official head), then a 1-channel sigmoid
    classification conv and an ``n_reg``-channel regression conv.

    The classification bias starts at ``-log((1 - pi) / pi)`` (RetinaNet's prior, ``pi =
    prior_probability``) rather than near 0: with p ~ 0.5 on all 28,672 cells the summed focal
    loss of the first steps is almost all background, and the first steps only push p down. The
    official model does not do this; loading its weights overwrites the bias, so outputs for
    given weights are unchanged.

    Parameters
    ----------
    in_channels : int
        Channels ``C`` of the input map (FFTRadNet: 256).
    angle_stride : {1, 2, 4}
        Input azimuth columns per output column: inputs of 224, 448 or 896 columns (the official
        ``input_angle_size``); the stride is applied by the first (2, 4: and second) conv.
    n_reg : int
        Regression channels (RADIal: 2, range and azimuth offsets).
    widths : tuple of int
        Channels of the first conv and of the three after it (official: 144, 96); the ``-s``
        models thin them so they train on a CPU.
    prior_probability : float
        Initial vehicle probability of every cell, in (0, 1).

    Shapes
    ------
    ``(B, C, 128, 224 * angle_stride)`` -> ``(B, 1 + n_reg, 128, 224)``.
    """

    def __init__(self, in_channels: int = 256, angle_stride: int = 1, n_reg: int = 2,
                 widths: tuple[int, int] = (144, 96), prior_probability: float = 0.01):
        super().__init__()
        if not 0 < prior_probability < 1:
            raise ValueError(f"prior_probability must be in (0, 1), got {prior_probability}")
        if angle_stride not in (1, 2, 4):
            raise ValueError(f"angle_stride must be 1, 2 or 4 (224, 448 or 896 input columns), got {angle_stride}")
        s1, s2 = {1: (1, 1), 2: (2, 1), 4: (2, 2)}[angle_stride]
        w1, w2 = widths
        self.conv1 = conv3x3(in_channels, w1, stride=(1, s1))
        self.bn1 = nn.BatchNorm2d(w1)
        self.conv2 = conv3x3(w1, w2, stride=(1, s2))
        self.bn2 = nn.BatchNorm2d(w2)
        self.conv3 = conv3x3(w2, w2)
        self.bn3 = nn.BatchNorm2d(w2)
        self.conv4 = conv3x3(w2, w2)
        self.bn4 = nn.BatchNorm2d(w2)
        self.clshead = conv3x3(w2, 1, bias=True)
        self.reghead = conv3x3(w2, n_reg, bias=True)
        nn.init.constant_(self.clshead.bias, -math.log((1 - prior_probability) / prior_probability))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.bn1(self.conv1(x))                                   # (B, w1, 128, 224 * s2)
        x = self.bn2(self.conv2(x))                                   # (B, w2, 128, 224)
        x = self.bn3(self.conv3(x))
        x = self.bn4(self.conv4(x))
        # float32 under autocast: a bf16 probability rounds p > 1 - 2^-9 to 1, where the sigmoid's
        # gradient p (1 - p) vanishes; compiled bf16 training also took wrong gradients through it
        logit, offsets = _at_least_float32(self.clshead(x)), _at_least_float32(self.reghead(x))
        return torch.cat([torch.sigmoid(logit), offsets], dim=1)     # (B, 1 + n_reg, 128, 224)


class FreespaceHead(nn.Module):
    """RA feature map -> freespace logits on the 256 x 224 grid.

    Nearest-neighbour resize of the input to ``out_size`` (``F.interpolate``'s default mode, as
    the official model), two :class:`ConvBlock` (``widths``, official 128, 64 channels) and a
    1 x 1 conv. With ``upsample_logits`` the blocks run on the input grid instead and the 1-channel
    logits are resized bilinearly: the same parameters at half the cost for a 128-row input (the
    blocks are most of a pillar model's time), for models trained from scratch.

    Parameters
    ----------
    in_channels : int
        Channels ``C`` of the input map (FFTRadNet: 256).
    out_size : tuple of int
        Output grid (range cells, azimuth cells).
    widths : tuple of int
        Channels of the two blocks (official: 128, 64).
    upsample_logits : bool
        Convolve on the input grid and resize the logits (bilinear, ``align_corners=False``)
        rather than resize the features first (the official head, which its weights need).

    Shapes
    ------
    ``(B, C, H, W)`` (any ``H, W``; 128 x 224 in every radarpc model) -> ``(B, 1, *out_size)``.
    """

    def __init__(self, in_channels: int = 256, out_size: tuple[int, int] = FREESPACE_SHAPE,
                 widths: tuple[int, int] = (128, 64), upsample_logits: bool = False):
        super().__init__()
        self.out_size = tuple(int(s) for s in out_size)
        self.upsample_logits = bool(upsample_logits)
        self.block1 = ConvBlock(in_channels, widths[0])
        self.block2 = ConvBlock(widths[0], widths[1])
        self.out = nn.Conv2d(widths[1], 1, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.upsample_logits:
            logits = self.out(self.block2(self.block1(x)))            # (B, 1, H, W)
            return F.interpolate(logits, self.out_size, mode="bilinear", align_corners=False)  # (B, 1, 256, 224)
        x = F.interpolate(x, self.out_size)                           # (B, C, 256, 224), nearest
        return self.out(self.block2(self.block1(x)))                  # (B, 1, 256, 224)
