"""Convolutions with their activation fused, for CPU inference.

A convolution followed by an elementwise GELU or ReLU reads and writes the whole map twice; oneDNN
can apply the activation to each output block while it is still in cache (a "post-op"), which is
what Inductor does for ``torch.compile`` with freezing. :class:`ConvActivation` calls that oneDNN
operator directly (``torch.ops.mkldnn._convolution_pointwise`` and its transposed sibling) on CPUs,
for float32 inputs without autograd, and ``act(conv(x))`` everywhere else, so it stays correct on
GPUs and in torch builds without the operator. :func:`fuse_activations_for_inference` puts it into a
copy of a model wherever a convolution is followed by an activation module (the patterns it
knows are in its docstring): the pillar models' BEV backbone, FFTRadNet's bottlenecks and decoder.
"""
from __future__ import annotations

import copy
import functools

import torch
import torch.nn as nn

from radarpc.models.fftradnet import Bottleneck, FPNBackbone
from radarpc.models.heads import ConvBlock
from radarpc.models.fast.winograd import WinogradConv2d

__all__ = ["ConvActivation", "fuse_activations_for_inference"]


def _cpu_autocast() -> bool:
    try:
        return torch.is_autocast_enabled("cpu")
    except TypeError:                      # torch < 2.4 takes no device type
        return torch.is_autocast_cpu_enabled()


@functools.cache
def _onednn_pointwise_available() -> bool:
    return (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")
            and hasattr(torch.ops.mkldnn, "_convolution_transpose_pointwise"))


class ConvActivation(nn.Module):
    """``activation(conv(x))`` in one oneDNN pass where it can (module docstring).

    Parameters
    ----------
    conv : nn.Conv2d or nn.ConvTranspose2d
        Zero padding (``padding_mode="zeros"``), numeric padding.
    activation : nn.GELU or nn.ReLU
    """

    def __init__(self, conv: nn.Conv2d | nn.ConvTranspose2d, activation: nn.GELU | nn.ReLU):
        super().__init__()
        if type(conv) not in (nn.Conv2d, nn.ConvTranspose2d) or conv.padding_mode != "zeros" \
                or isinstance(conv.padding, str):
            raise ValueError(f"ConvActivation: needs an nn.Conv2d or nn.ConvTranspose2d with numeric zero padding, "
                             f"got {conv}")
        if type(activation) not in (nn.GELU, nn.ReLU):
            raise ValueError(f"ConvActivation: the activation must be nn.GELU or nn.ReLU, got {activation}")
        self.conv, self.activation = conv, activation
        # oneDNN's names: GELU's "none" is the exact (erf) one, "tanh" its approximation
        self.attr = "gelu" if isinstance(activation, nn.GELU) else "relu"
        self.algorithm = activation.approximate if isinstance(activation, nn.GELU) else None

    def _fusable(self, x: torch.Tensor) -> bool:
        # under autocast the unfused layers run in the autocast dtype: so does this one then
        return (x.device.type == "cpu" and x.dtype == torch.float32 and x.ndim == 4
                and not _cpu_autocast()
                and self.conv.weight.dtype == torch.float32
                and not (torch.is_grad_enabled() and (x.requires_grad or self.conv.weight.requires_grad))
                and _onednn_pointwise_available())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.conv
        if not self._fusable(x):
            return self.activation(c(x))
        if isinstance(c, nn.Conv2d):
            return torch.ops.mkldnn._convolution_pointwise(x, c.weight, c.bias, list(c.padding), list(c.stride),
                                                           list(c.dilation), c.groups, self.attr, [], self.algorithm)
        return torch.ops.mkldnn._convolution_transpose_pointwise(
            x, c.weight, c.bias, list(c.padding), list(c.output_padding), list(c.stride), list(c.dilation),
            c.groups, self.attr, [], self.algorithm)

    def extra_repr(self) -> str:
        return f"attr={self.attr!r}, algorithm={self.algorithm!r}"


# the modules whose forward applies ``act<i>(bn<i>(conv<i>(x)))``
_TRIPLE_MODULES = (Bottleneck, FPNBackbone, ConvBlock)


def _fuse(conv: nn.Module, act: nn.Module) -> nn.Module | None:
    """What replaces ``conv`` when ``act`` follows it, or None if the pair does not fuse."""
    if type(act) not in (nn.GELU, nn.ReLU):
        return None
    if isinstance(conv, WinogradConv2d):
        if type(act) is not nn.ReLU:
            return None
        conv.relu = True                      # applied in its output transform
        return conv
    if type(conv) in (nn.Conv2d, nn.ConvTranspose2d) and conv.padding_mode == "zeros" \
            and not isinstance(conv.padding, str):
        return ConvActivation(conv, act)
    return None


def fuse_activations_for_inference(model: nn.Module) -> nn.Module:
    """A copy of ``model`` (eval mode) with each activation module fused into the convolution before it.

    Two patterns are fused: in an ``nn.Sequential``, a plain ``nn.Conv2d``/``nn.ConvTranspose2d``,
    any ``nn.Identity`` (a folded BatchNorm), then ``nn.GELU``/``nn.ReLU`` (the pillar models'
    backbone); and children named ``conv<i>``, ``bn<i>`` (an ``nn.Identity``) and ``act<i>`` of one
    module whose forward applies them in that order (FFTRadNet's ``Bottleneck`` and ``FPNBackbone``
    stem, the decoder's ``ConvBlock``; other classes are left alone). The convolution becomes a
    :class:`ConvActivation` (or, for a :class:`~radarpc.models.fast.winograd.WinogradConv2d` and a ReLU,
    applies it in its output transform) and the activation an identity. Fold BatchNorm first (``fuse_for_inference``): a BN between
    them stops the match. ``model`` is unchanged.
    """
    m = copy.deepcopy(model).eval()
    for mod in list(m.modules()):
        if isinstance(mod, nn.Sequential):
            layers = list(mod)
            for i, conv in enumerate(layers):
                j = i + 1
                while j < len(layers) and type(layers[j]) is nn.Identity:
                    j += 1
                if j < len(layers) and (fused := _fuse(conv, layers[j])) is not None:
                    mod[i], mod[j] = fused, nn.Identity()
            continue
        if not isinstance(mod, _TRIPLE_MODULES):      # their forwards apply conv<i>, bn<i>, act<i> in turn
            continue
        for suffix in ("", "1", "2", "3", "4"):
            conv, bn, act = (getattr(mod, f"{n}{suffix}", None) for n in ("conv", "bn", "act"))
            if isinstance(conv, nn.Module) and type(bn) is nn.Identity and act is not None \
                    and (fused := _fuse(conv, act)) is not None:
                setattr(mod, f"conv{suffix}", fused)
                setattr(mod, f"act{suffix}", nn.Identity())
    return m
