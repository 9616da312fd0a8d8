"""RADIal's training losses: focal loss on the probability map, smooth L1 on the offsets, BCE on
freespace, with RADIal's weights.

Facts from RADIal ``FFTRadNet/loss/loss.py`` and ``1-Train.py`` (not code) that fix the scale of
each term, so that the weights ``(1, 100, 100)`` mean what they mean there:

* classification: focal loss ``-(1 - p_t)^gamma log(p_t + 1e-6)``, ``gamma = 2``, with
  ``p_t = p`` on positive cells and ``1 - p`` elsewhere, **summed** over every cell of the batch;
* regression: smooth L1 (``beta = 1``) between ``M * prediction`` and the target offsets (which
  are 0 off the patches), summed over cells and both channels, divided by the number of positive
  cells ``sum(M)`` of the batch (``M`` = the target probability channel);
* freespace: ``BCEWithLogits`` averaged over every pixel of the batch, times the batch size.

RADIal's configuration asks for ``"smoothL1Loss"`` but its loss compares against
``"SmoothL1Loss"``, so the official runs fell through to plain L1; ``regression="l1"`` reproduces
that, ``"smooth_l1"`` (the default) is what the configuration and the seed say.

Every term is computed in float32 whatever the autocast dtype (sums over ``B x 128 x 224`` cells).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

__all__ = ["LossConfig", "LossTerms", "focal_loss", "regression_loss", "freespace_loss", "detection_loss"]

_REGRESSION = ("smooth_l1", "l1")


@dataclass(frozen=True)
class LossConfig:
    """Loss settings (RADIal's by default).

    Attributes
    ----------
    focal_gamma : focusing exponent of the focal loss. ``0`` is cross-entropy (up to the
        ``1e-6``), RADIal's other classification loss. At ``2`` the loss is smallest, for a cell
        that is positive 2.4 % of the time, at score 0.2 (at ``0``, at 0.024), so RADIal's fixed
        threshold 0.2 can admit many weak detections (``docs/notebook/scripts/operating_points.py``;
        measured in ``docs/results/detection.md``).
    regression : ``"smooth_l1"`` or ``"l1"`` (what the official runs used, see the module docstring)
    weights : ``(classification, regression, freespace)`` multipliers
    """

    focal_gamma: float = 2.0
    regression: str = "smooth_l1"
    weights: tuple[float, float, float] = (1.0, 100.0, 100.0)

    def __post_init__(self) -> None:
        if self.regression not in _REGRESSION:
            raise ValueError(f"LossConfig.regression must be one of {_REGRESSION}, got {self.regression!r}")
        if self.focal_gamma < 0:
            raise ValueError(f"LossConfig.focal_gamma must be >= 0, got {self.focal_gamma}")
        if len(self.weights) != 3 or min(self.weights) < 0:
            raise ValueError(f"LossConfig.weights must be three non-negative numbers (classification, regression, "
                             f"freespace), got {self.weights}")


class LossTerms(NamedTuple):
    """Weighted loss terms of a batch; ``total`` is their sum (the one to back-propagate)."""

    total: torch.Tensor
    classification: torch.Tensor
    regression: torch.Tensor
    freespace: torch.Tensor


def focal_loss(prob: torch.Tensor, target: torch.Tensor, gamma: float = 2.0) -> torch.Tensor:
    """``sum -(1 - p_t)^gamma log(p_t + 1e-6)``, ``p_t = prob`` where ``target == 1`` else ``1 - prob``."""
    prob, target = prob.float(), target.float()
    pt = torch.where(target == 1, prob, 1 - prob)
    return (-(1 - pt) ** gamma * torch.log(pt + 1e-6)).sum()


def regression_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                    kind: str = "smooth_l1") -> torch.Tensor:
    """Offset loss over the positive cells, per positive cell.

    Parameters
    ----------
    pred, target : float ``(B, n_reg, H, W)``
    mask : ``(B, H, W)``, 1 on positive cells
    kind : ``"smooth_l1"`` (beta 1) or ``"l1"``

    Returns
    -------
    ``sum(elementwise(mask * pred, target)) / sum(mask)`` (not divided when there is no positive cell).
    """
    m = mask.float()[:, None]                                       # (B, 1, H, W)
    pred, target = pred.float() * m, target.float()
    if kind == "smooth_l1":
        loss = F.smooth_l1_loss(pred, target, reduction="sum", beta=1.0)
    elif kind == "l1":
        loss = F.l1_loss(pred, target, reduction="sum")
    else:
        raise ValueError(f"regression kind must be one of {_REGRESSION}, got {kind!r}")
    n = m.sum()
    return loss / n if n > 0 else loss


def freespace_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``B x mean BCEWithLogits`` over every pixel of the batch (``logits``, ``target`` ``(B, ...)``)."""
    x = logits.float().reshape(logits.shape[0], -1)
    t = target.float().reshape(target.shape[0], -1)
    if x.shape != t.shape:
        raise ValueError(f"freespace logits {tuple(logits.shape)} and target {tuple(target.shape)} differ in size")
    return F.binary_cross_entropy_with_logits(x, t, reduction="mean") * logits.shape[0]


def detection_loss(detection: torch.Tensor, target: torch.Tensor, cfg: LossConfig = LossConfig(),
                   freespace_logits: torch.Tensor | None = None,
                   freespace_target: torch.Tensor | None = None) -> LossTerms:
    """The weighted RADIal loss of a batch.

    Parameters
    ----------
    detection : float ``(B, 1 + n_reg, H, W)``
        The detection head's output: probability, then normalised offsets.
    target : float ``(B, 1 + n_reg, H, W)``
        :func:`radarpc.models.targets.encode_batch` of the labels.
    cfg : LossConfig
    freespace_logits : float ``(B, 1, 256, 224)`` or None
        The freespace head's logits; None for a model without freespace (the term is then 0).
    freespace_target : bool ``(B, 256, 224)`` or None

    Returns
    -------
    LossTerms, each already multiplied by its weight.
    """
    if detection.shape != target.shape or detection.ndim != 4:
        raise ValueError(f"detection {tuple(detection.shape)} and target {tuple(target.shape)} must both be "
                         "(B, 1 + n_reg, H, W)")
    w_cls, w_reg, w_fs = cfg.weights
    cls = w_cls * focal_loss(detection[:, 0], target[:, 0], cfg.focal_gamma)
    reg = w_reg * regression_loss(detection[:, 1:], target[:, 1:], target[:, 0], cfg.regression)
    if freespace_logits is None:
        fs = cls.new_zeros(())
    else:
        if freespace_target is None:
            raise ValueError("freespace_target is needed with freespace_logits")
        fs = w_fs * freespace_loss(freespace_logits, freespace_target)
    return LossTerms(cls + reg + fs, cls, reg, fs)
