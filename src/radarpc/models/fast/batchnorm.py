"""Eval-mode BatchNorm: folding it into the convolution before it, and making it non-trivial.

An eval-mode ``BatchNorm2d`` is a per-channel affine map ``y = (x - mu) g / sqrt(v + eps) + beta``,
so it folds exactly (in real arithmetic) into a preceding convolution. A freshly built one is the
identity (``mu = 0``, ``v = 1``, ``g = 1``, ``beta = 0``), which would let a check of a fold or of a
weight conversion pass without testing anything: :func:`randomise_batchnorm_` gives it statistics.
:func:`fuse_for_inference` folds every BatchNorm of an FFTRadNet or a PointPillars model.
"""
from __future__ import annotations

import copy

import torch
from torch import nn

from radarpc.models.fftradnet import FFTRadNet
from radarpc.models.pillars import PointPillars

__all__ = ["fold_batchnorm", "randomise_batchnorm_", "fuse_fftradnet", "fuse_pillars", "fuse_for_inference"]


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


# ---- whole models ---------------------------------------------------------------------------------
def fuse_fftradnet(model: FFTRadNet) -> FFTRadNet:
    """A copy of ``model`` in eval mode with every BatchNorm folded into the conv before it.

    Exact in real arithmetic (eval-mode BN is a per-channel affine map); in fp32 the outputs differ
    by rounding only. The pre-encoder's BN follows a crop, which commutes with a per-channel map.
    """
    m = copy.deepcopy(model).eval()
    with torch.no_grad():
        for mod in m.modules():
            for conv_name, bn_name in (("conv", "bn"), ("conv1", "bn1"), ("conv2", "bn2"), ("conv3", "bn3"),
                                       ("conv4", "bn4")):
                conv, bn = getattr(mod, conv_name, None), getattr(mod, bn_name, None)
                if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                    fold_batchnorm(conv, bn)
                    setattr(mod, bn_name, nn.Identity())
            if isinstance(mod, nn.Sequential) and len(mod) == 2 and isinstance(mod[0], nn.Conv2d) \
                    and isinstance(mod[1], nn.BatchNorm2d):                 # bottleneck shortcuts
                fold_batchnorm(mod[0], mod[1])
                mod[1] = nn.Identity()
    return m


def fuse_pillars(model: PointPillars) -> PointPillars:
    """A copy of ``model`` in eval mode with every BatchNorm folded into the linear map before it.

    Eval-mode BN is a per-channel affine map, so the fold is exact in real arithmetic (fp32 outputs
    differ by rounding only): the point encoder becomes one ``Linear`` with bias
    (``W' = diag(g / s) W diag(1 / s_in)``), every conv and transposed conv of the backbone and
    heads gets ``w' = w g / s``, ``b' = (b - mu) g / s + beta`` with ``s = sqrt(var + eps)``.
    """
    m = copy.deepcopy(model).eval()
    with torch.no_grad():
        vfe = m.vfe
        s_in = torch.sqrt(vfe.input_norm.running_var + vfe.input_norm.eps)            # (F,)
        w = vfe.linear.weight / s_in                                                  # (C, F)
        b = -(w @ vfe.input_norm.running_mean)                                        # (C,)
        g = vfe.norm.weight / torch.sqrt(vfe.norm.running_var + vfe.norm.eps)         # (C,)
        fused = nn.Linear(w.shape[1], w.shape[0], bias=True).to(w)
        fused.weight.copy_(w * g[:, None])
        fused.bias.copy_((b - vfe.norm.running_mean) * g + vfe.norm.bias)
        vfe.linear, vfe.input_norm, vfe.norm = fused, nn.Identity(), nn.Identity()
        for mod in m.modules():
            if isinstance(mod, nn.Sequential):                                    # backbone: conv, BN, GELU
                for i in range(len(mod) - 1):
                    if isinstance(mod[i], (nn.Conv2d, nn.ConvTranspose2d)) and isinstance(mod[i + 1], nn.BatchNorm2d):
                        fold_batchnorm(mod[i], mod[i + 1])
                        mod[i + 1] = nn.Identity()
            for k in range(1, 5):                                                 # heads: conv{k}, bn{k}
                conv, bn = getattr(mod, f"conv{k}", None), getattr(mod, f"bn{k}", None)
                if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                    fold_batchnorm(conv, bn)
                    setattr(mod, f"bn{k}", nn.Identity())
    return m


def fuse_for_inference(model: nn.Module) -> nn.Module:
    """A copy of ``model`` in eval mode with every BatchNorm folded (:func:`fuse_fftradnet`,
    :func:`fuse_pillars`); ``model`` is unchanged.

    Raises
    ------
    TypeError
        ``model`` is not a model whose BatchNorm layout is known here.
    """
    if isinstance(model, FFTRadNet):
        return fuse_fftradnet(model)
    if isinstance(model, PointPillars):
        return fuse_pillars(model)
    raise TypeError(f"fuse_for_inference: expected an FFTRadNet or a PointPillars model, got {type(model).__name__}")
