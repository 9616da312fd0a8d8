"""Eval-mode BatchNorm: folding it into the convolution before it, and making it non-trivial.

An eval-mode ``BatchNorm2d`` is a per-channel affine map ``y = (x - mu) g / sqrt(v + eps) + beta``,
so it folds exactly (in real arithmetic) into a preceding convolution. A freshly built one is the
identity (``mu = 0``, ``v = 1``, ``g = 1``, ``beta = 0``), which would let a check of a fold or of a
weight conversion pass without testing anything: :func:`randomise_batchnorm_` gives it statistics.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["fold_batchnorm", "randomise_batchnorm_"]


def fold_batchnorm(conv: nn.Conv2d | nn.ConvTranspose2d, bn: nn.BatchNorm2d) -> None:
    """Make ``conv`` compute ``bn(conv(x))`` in eval mode, in place; ``bn`` is then to be dropped.

    ``w' = w g / sqrt(v + eps)``, ``b' = (b - mu) g / sqrt(v + eps) + beta``, scaled along the
    output channels: dim 0 of a convolution's weight, dim 1 of a transposed convolution's.
    """
    if isinstance(conv, nn.ConvTranspose2d) and conv.groups != 1:
        # a grouped transposed weight is (C_in, C_out / groups, k, k): dim 1 is not the output channel
        raise ValueError(f"fold_batchnorm: a transposed convolution with groups={conv.groups} is not supported")
    if bn.running_mean is None or bn.running_var is None:
        raise ValueError("fold_batchnorm: the BatchNorm tracks no running statistics (track_running_stats=False)")
    gamma = bn.weight if bn.affine else torch.ones_like(bn.running_var)
    beta = bn.bias if bn.affine else torch.zeros_like(bn.running_mean)
    scale = gamma / torch.sqrt(bn.running_var + bn.eps)                          # (C_out,)
    shape = (1, -1, 1, 1) if isinstance(conv, nn.ConvTranspose2d) else (-1, 1, 1, 1)
    bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
    conv.weight = nn.Parameter((conv.weight * scale.view(shape)).detach())
    conv.bias = nn.Parameter(((bias - bn.running_mean) * scale + beta).detach())


def randomise_batchnorm_(model: nn.Module, generator: torch.Generator) -> nn.Module:
    """Draw non-trivial running statistics and affine parameters for every BatchNorm of ``model``.

    ``mu ~ 0.1 N(0, 1)``, ``v ~ U(0.5, 1.5)``, ``g ~ U(0.5, 1.5)``, ``beta ~ 0.1 N(0, 1)``: every
    channel is rescaled and shifted, yet activations keep their order of magnitude through a deep
    network. For checks only (folding, weight conversion); returns ``model``.
    """
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                n = m.num_features
                if m.track_running_stats:
                    m.running_mean.copy_(0.1 * torch.randn(n, generator=generator))
                    m.running_var.copy_(0.5 + torch.rand(n, generator=generator))
                if m.affine:
                    m.weight.copy_(0.5 + torch.rand(n, generator=generator))
                    m.bias.copy_(0.1 * torch.randn(n, generator=generator))
    return model
