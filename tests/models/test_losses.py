"""RADIal losses against hand computations."""
from __future__ import annotations

import math

import pytest
import torch

from radarpc.models.losses import LossConfig, detection_loss, focal_loss, freespace_loss, regression_loss

REL = 1e-5   # float32 arithmetic on a handful of terms


def test_focal_loss_hand():
    prob = torch.tensor([[0.9, 0.2], [0.6, 0.05]])
    target = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    pt = [0.9, 0.8, 0.4, 0.05]
    want = sum(-(1 - p) ** 2 * math.log(p + 1e-6) for p in pt)
    assert focal_loss(prob, target, 2.0).item() == pytest.approx(want, rel=REL)
    # gamma 0 is the summed cross-entropy (with RADIal's 1e-6 inside the log)
    assert focal_loss(prob, target, 0.0).item() == pytest.approx(sum(-math.log(p + 1e-6) for p in pt), rel=REL)


def test_regression_loss_hand():
    pred = torch.tensor([[[[0.5, 3.0, 100.0]], [[-0.2, 0.0, -50.0]]]])    # (1, 2, 1, 3)
    target = torch.tensor([[[[0.0, 1.0, 0.0]], [[0.3, 2.5, 0.0]]]])
    mask = torch.tensor([[[1.0, 1.0, 0.0]]])                              # third cell is negative
    # differences on positive cells: 0.5, 2.0, -0.5, -2.5; smooth L1: 0.125, 1.5, 0.125, 2.0
    assert regression_loss(pred, target, mask).item() == pytest.approx((0.125 + 1.5 + 0.125 + 2.0) / 2, rel=REL)
    assert regression_loss(pred, target, mask, "l1").item() == pytest.approx((0.5 + 2.0 + 0.5 + 2.5) / 2, rel=REL)
    # no positive cell: not divided (and 0 when the targets are 0 there)
    assert regression_loss(pred, torch.zeros_like(target), torch.zeros_like(mask)).item() == 0.0
    with pytest.raises(ValueError, match="regression kind"):
        regression_loss(pred, target, mask, "l2")


def test_freespace_loss_hand():
    logits = torch.tensor([[[[0.0, 2.0]]], [[[-1.0, 3.0]]]])               # (2, 1, 1, 2)
    target = torch.tensor([[[True, False]], [[False, True]]])
    sp = lambda x: math.log1p(math.exp(x))                                # -log sigmoid(-x)
    per = [sp(-0.0), sp(2.0), sp(-1.0), sp(-3.0)]
    assert freespace_loss(logits, target).item() == pytest.approx(2 * sum(per) / 4, rel=REL)


def test_detection_loss_weights_and_terms():
    torch.manual_seed(0)
    det = torch.cat([torch.rand(2, 1, 4, 6), torch.randn(2, 2, 4, 6)], 1)
    tgt = torch.zeros(2, 3, 4, 6)
    tgt[0, :, 1, 2] = torch.tensor([1.0, 0.3, -0.4])
    tgt[1, :, 3, 5] = torch.tensor([1.0, -1.2, 0.8])
    fs_logits, fs_t = torch.randn(2, 1, 3, 5), torch.rand(2, 3, 5) > 0.5
    cfg = LossConfig()
    terms = detection_loss(det, tgt, cfg, fs_logits, fs_t)
    assert terms.classification.item() == pytest.approx(focal_loss(det[:, 0], tgt[:, 0]).item(), rel=REL)
    assert terms.regression.item() == pytest.approx(100 * regression_loss(det[:, 1:], tgt[:, 1:], tgt[:, 0]).item(), rel=REL)
    assert terms.freespace.item() == pytest.approx(100 * freespace_loss(fs_logits, fs_t).item(), rel=REL)
    assert terms.total.item() == pytest.approx(terms.classification.item() + terms.regression.item()
                                               + terms.freespace.item(), rel=REL)
    none = detection_loss(det, tgt, cfg)
    assert none.freespace.item() == 0.0 and none.total.item() == pytest.approx(
        terms.classification.item() + terms.regression.item(), rel=REL)
    # gradients reach every input
    det.requires_grad_(True)
    detection_loss(det, tgt, cfg).total.backward()
    assert det.grad is not None and det.grad[:, 0].abs().sum() > 0


def test_bad_config_and_shapes():
    with pytest.raises(ValueError, match="LossConfig.regression must be one of"):
        LossConfig(regression="smoothL1Loss")
    with pytest.raises(ValueError, match="must both be"):
        detection_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(ValueError, match="freespace_target is needed"):
        detection_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), LossConfig(), torch.zeros(1, 1, 2, 2))
