"""What a model's forward pass costs in arithmetic: the multiply-accumulates of its convolutions.

:func:`conv_gmac` counts them with forward hooks on one real pass, so it follows whatever the
forward actually runs (a skipped head costs nothing). Divided by a CPU's best GMAC/s it gives the
fastest the network could run there.
"""
from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["conv_gmac"]


def conv_gmac(model: torch.nn.Module, *inputs: torch.Tensor, forward: Callable | None = None) -> float:
    """Multiply-accumulates of every convolution in one forward pass, in GMAC.

    Each output element of a ``Conv2d`` takes ``kernel elements x input channels per group`` MACs;
    each input element of a ``ConvTranspose2d`` feeds ``kernel elements x output channels per
    group`` outputs. Other layers are not counted.

    Parameters
    ----------
    model : torch.nn.Module
        Its ``Conv2d`` and ``ConvTranspose2d`` submodules are counted.
    *inputs : Tensor
        The pass's inputs.
    forward : callable, optional
        What to run on ``inputs`` (e.g. ``model.forward_channels``); ``model`` itself by default.

    Returns
    -------
    float
        GMAC of the pass (run under ``torch.inference_mode``).
    """
    total = [0]

    def hook(conv, inp, out):
        # weight[0]: (in / groups, kh, kw) for a convolution, (out / groups, kh, kw) for a transposed one
        n = inp[0].numel() if isinstance(conv, torch.nn.ConvTranspose2d) else out.numel()
        total[0] += n * conv.weight[0].numel()
    hooks = [m.register_forward_hook(hook) for m in model.modules()
             if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    try:
        with torch.inference_mode():
            (forward or model)(*inputs)
    finally:
        for h in hooks:
            h.remove()
    return total[0] / 1e9
