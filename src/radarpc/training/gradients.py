"""How far a training mode's gradients lie from a reference mode's, from the same weights.

bf16 autocast (``train.precision``) or ``torch.compile`` (``train.compile``) computing a wrong
gradient does not fail a step; it only makes training slower or worse, which one run cannot tell
from seed noise. :func:`compare_gradients` compares a mode's gradients with the reference's (eager
fp32) weight tensor by weight tensor.
"""
from __future__ import annotations

import statistics

import torch

__all__ = ["compare_gradients"]


def compare_gradients(grads: dict[str, torch.Tensor], reference: dict[str, torch.Tensor],
                      lowest: int = 5) -> dict:
    """Median relative error and the lowest cosines of ``grads`` against ``reference``.

    Only tensors of two or more dimensions with a nonzero reference are compared: a convolution's
    bias that a BatchNorm follows has a zero gradient in exact arithmetic, so rounding is all its
    gradient holds.

    Parameters
    ----------
    grads, reference : dict of str to Tensor
        Gradients by parameter name (``reference``'s names that ``grads`` lacks are left out).
    lowest : int
        How many of the weight tensors with the lowest cosine to list, >= 1.

    Returns
    -------
    dict
        ``weights_compared``; ``median_relative_error`` of ``|g - g_ref| / |g_ref|`` and
        ``median_cosine`` over the tensors compared; ``lowest_cosines``: up to ``lowest`` rows
        ``{parameter, cosine, relative_error, norm_ratio |g| / |g_ref|}``, lowest cosine first.
    """
    if lowest < 1:
        raise ValueError(f"lowest must be >= 1, got {lowest}")
    rows = []
    for k, r in reference.items():
        if r.ndim < 2 or k not in grads or float(r.norm()) == 0.0:
            continue
        g = grads[k]
        if g.shape != r.shape:
            raise ValueError(f"gradient of {k!r} has shape {tuple(g.shape)}, the reference {tuple(r.shape)}")
        rel = float((g - r).norm() / r.norm())
        cos = float(torch.nn.functional.cosine_similarity(g.flatten(), r.flatten(), dim=0))
        ratio = float(g.norm() / r.norm())
        rows.append((cos, rel, ratio, k))
    if not rows:
        raise ValueError("no weight tensor to compare: every reference gradient is 1-D, zero or missing")
    rows.sort()
    return {"weights_compared": len(rows),
            "median_relative_error": statistics.median(r[1] for r in rows),
            "median_cosine": statistics.median(r[0] for r in rows),
            "lowest_cosines": [{"parameter": k, "cosine": c, "relative_error": e, "norm_ratio": q}
                               for c, e, q, k in rows[:lowest]]}
