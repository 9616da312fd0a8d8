"""The detection head's linear layers collapsed into one convolution with three outputs.

:class:`~radarpc.models.heads.DetectionHead` applies, with BN folded, five 3 x 3 convolutions and
no activation between them (as the official head): ``conv1`` (azimuth stride ``s1``), ``conv2``
(stride ``s2``), ``conv3``, ``conv4``, then the classification and regression convs (3 outputs).
Their composition is one correlation with an 11-row kernel,

    out[o, y, x] = b[o] + sum_{c, u, v} K[o, c, u, v] in[c, y + u - 5, S x + v - P],

``S = s1 s2``, ``P = 1 + s1 + 3 S``. Composing ``B`` after ``A`` (``A``'s azimuth stride so far
``s``) gives ``K_BA[o, c, u, v] = sum_{m, i, j} B[o, m, i, j] K_A[m, c, u - i, v - s j]`` and
``b_BA = b_B + sum_{m, i, j} B[o, m, i, j] b_A[m]``, formed once in float64. For the 256 -> 144 ->
96 -> 96 -> 96 -> 3 head at stride 1 that is 256 x 3 x 121 = 93k multiply-adds per output instead of
625k. It is evaluated as one matrix product of every input pixel with the 3 x 11 x 11 kernel taps
(``Z = X W``, a GEMM with ``C`` inner terms), then a sum over the taps of ``Z`` shifted.

The composition treats the intermediate maps as extending beyond the image, where the layers
zero-pad them: the two differ in the 4 outer rows and columns of the output (one per layer after
the first; the first layer's padding is the input's, which the composition keeps). Those are
taken from the layers themselves, run on 9-row and ``9 S``-column strips along the edges. The
result equals the head in real arithmetic; in float32 it differs by rounding only (the tests bound
it). At azimuth stride ``S > 1`` the product still forms every tap for every input column, ``S``
times the work the strided outputs need (the shipped models' heads have ``S = 1``). Inference
only (the composed kernel is a buffer); :func:`collapsed_head_for_inference` puts it into a copy
of a model.
"""
from __future__ import annotations

import copy
import functools

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.fast.batchnorm import fold_batchnorm
from radarpc.models.heads import DetectionHead
from radarpc.models.fast.winograd import warn_if_reduced_fp32

__all__ = ["compose_convs", "collapse_mac_ratio", "CollapsedDetectionHead", "collapsed_head_for_inference"]

BORDER = 4                   # output rows / columns where the layers' zero padding differs from the composition


def compose_convs(convs: list[nn.Conv2d]) -> tuple[torch.Tensor, torch.Tensor, int, int, int]:
    """The single correlation equal to ``convs`` applied in turn (away from the intermediate maps' borders).

    Parameters
    ----------
    convs : list of nn.Conv2d
        3 x 3 convolutions with padding 1, row stride 1 and any azimuth (column) stride, each with
        the previous one's output channels in.

    Returns
    -------
    kernel : (K, C, 1 + 2 L, 1 + 2 P) float64 tensor
        ``L`` = ``len(convs)``.
    bias : (K,) float64 tensor
    pad_rows, pad_cols, stride : int
        ``L``, ``P`` (the sum over layers of the azimuth stride before each) and the product of the
        azimuth strides: ``out = F.conv2d(x, kernel, bias, stride=(1, stride), padding=(pad_rows, pad_cols))``.
    """
    first = convs[0]
    pad_cols, stride = _column_reach([c.stride[1] for c in convs])
    kernel = first.weight.detach().double()
    f64 = dict(dtype=torch.float64, device=kernel.device)
    bias = torch.zeros(first.out_channels, **f64) if first.bias is None else first.bias.detach().double()
    dilation = first.stride[1]
    for conv in convs[1:]:
        w = conv.weight.detach().double()                                    # (K, M, 3, 3)
        # K_BA[o, c] = sum_m B[o, m] (*) K_A[m, c], B's column taps `stride` input columns apart
        kernel = F.conv_transpose2d(kernel.transpose(0, 1), w.transpose(0, 1), dilation=(1, dilation)).transpose(0, 1)
        b = torch.zeros(conv.out_channels, **f64) if conv.bias is None else conv.bias.detach().double()
        bias = b + torch.einsum("omij,m->o", w, bias)
        dilation *= conv.stride[1]
    return kernel.contiguous(), bias, len(convs), pad_cols, stride


def _column_reach(strides: list[int]) -> tuple[int, int]:
    """``(P, S)`` of 3 x 3 layers with these azimuth strides in turn: the composed kernel reaches
    ``P`` input columns to each side (each layer one column of its own input, the strides before it
    apart), and strides ``S`` (their product)."""
    reach, stride = 0, 1
    for s in strides:
        reach += stride
        stride *= s
    return reach, stride


def collapse_mac_ratio(head: DetectionHead) -> float:
    """Multiply-adds of the collapsed head over those of its layers, per output cell.

    The layers: ``sum_l C_l K_l 9`` times the outputs layer ``l`` computes per output cell (``S``
    over the azimuth stride so far); the collapsed head: ``C (1 + n_reg) U V`` for each of the ``S``
    input columns of an output cell. Wide heads gain (the full size: 0.15); thin ones do not (the
    ``-s`` models: about 1), and then the product and the strips only add overhead.
    """
    convs = [head.conv1, head.conv2, head.conv3, head.conv4]
    pad_cols, total_stride = _column_reach([c.stride[1] for c in convs] + [1])
    layered, stride = 0.0, 1
    for conv in convs:
        stride *= conv.stride[1]
        layered += conv.in_channels * conv.out_channels * 9 * total_stride / stride
    n_out = head.clshead.out_channels + head.reghead.out_channels
    layered += head.clshead.in_channels * n_out * 9
    n_u, n_v = 1 + 2 * (len(convs) + 1), 1 + 2 * pad_cols
    return total_stride * head.conv1.in_channels * n_out * n_u * n_v / layered


def _shifted_sum(z: torch.Tensor, bias: torch.Tensor, rows: int, cols: int, stride: int,
                 pad_rows: int, pad_cols: int) -> torch.Tensor:
    """``out[b, y, x, o] = bias[o] + sum_{u, v} z[b, y + u - pad_rows, stride x + v - pad_cols, u, v, o]``
    (zero outside ``z``); ``z (B, H, W, U, V, K)`` -> ``(B, rows, cols, K)``."""
    _, h, w, n_u, n_v, _ = z.shape
    right = max(0, stride * (cols - 1) + n_v - pad_cols - w)
    zp = F.pad(z, (0, 0, 0, 0, 0, 0, pad_cols, right, pad_rows, max(0, rows + n_u - 1 - pad_rows - h)))
    out = bias
    for u in range(n_u):
        for v in range(n_v):
            out = out + zp[:, u:u + rows, v:v + stride * (cols - 1) + 1:stride, u, v]
    return out


@functools.cache
def _compiled_shifted_sum():
    # static shapes: one graph per map size
    return torch.compile(_shifted_sum, dynamic=False)


class CollapsedDetectionHead(nn.Module):
    """Inference only: a :class:`DetectionHead` (BN folded) as one composed correlation (module docstring).

    Parameters
    ----------
    head : DetectionHead
        The head whose BatchNorms are folded (identities), e.g. of a model passed through
        ``fuse_for_inference``; its layers are kept for the border strips (:meth:`layers`).
    compiled : bool
        Inductor-compile the sum over the shifted taps (fast; compiles once per map size, with a
        C++ compiler on CPUs) instead of running it eagerly (same result, slower).
    """

    def __init__(self, head: DetectionHead, compiled: bool = True):
        super().__init__()
        if not isinstance(head, DetectionHead):
            raise TypeError(f"CollapsedDetectionHead: expected a DetectionHead, got {type(head).__name__}")
        convs = [head.conv1, head.conv2, head.conv3, head.conv4, head.clshead, head.reghead]
        if not all(type(c) is nn.Conv2d for c in convs):
            raise ValueError("CollapsedDetectionHead: the head's layers must be plain nn.Conv2d (collapse the head "
                             "before converting layers, e.g. to Winograd)")
        if not all(isinstance(getattr(head, f"bn{i}"), nn.Identity) for i in range(1, 5)):
            raise ValueError("CollapsedDetectionHead: fold the head's BatchNorms first (fuse_for_inference)")
        if not all(c.kernel_size == (3, 3) and c.padding == (1, 1) and c.stride[0] == 1 and c.dilation == (1, 1)
                   and c.groups == 1 and c.padding_mode == "zeros" for c in convs):
            raise ValueError("CollapsedDetectionHead: every layer must be 3 x 3 with padding 1, row stride 1, "
                             "no dilation or groups (as DetectionHead builds them)")
        w = head.clshead.weight
        final = nn.Conv2d(head.clshead.in_channels, 1 + head.reghead.out_channels, 3, padding=1,
                          device=w.device, dtype=w.dtype)
        with torch.no_grad():
            final.weight.copy_(torch.cat([head.clshead.weight, head.reghead.weight]))
            final.bias.copy_(torch.cat([head.clshead.bias, head.reghead.bias]))
        kernel, bias, self.pad_rows, self.pad_cols, self.stride = compose_convs(
            [head.conv1, head.conv2, head.conv3, head.conv4, final])
        dtype = head.conv1.weight.dtype
        k, c, n_u, n_v = kernel.shape
        self.register_buffer("taps", kernel.permute(1, 2, 3, 0).reshape(c, n_u * n_v * k).to(dtype))   # (C, U V K)
        self.register_buffer("bias", bias.to(dtype))
        self.kernel_size = (n_u, n_v)
        # the layers themselves, for the border strips: plain tensors, which a later conversion of
        # the model's convolutions (e.g. to Winograd, slower on 9-pixel strips) leaves alone
        for i, conv in enumerate([head.conv1, head.conv2, head.conv3, head.conv4, final]):
            self.register_buffer(f"weight{i}", conv.weight.detach().clone())
            self.register_buffer(f"bias{i}", None if conv.bias is None else conv.bias.detach().clone())
        self.layer_strides = [c.stride[1] for c in (head.conv1, head.conv2, head.conv3, head.conv4, final)]
        self.compiled = compiled

    def extra_repr(self) -> str:
        return (f"{self.taps.shape[0]}, {self.bias.numel()}, kernel_size={self.kernel_size}, "
                f"stride=(1, {self.stride}), compiled={self.compiled}")

    def layers(self, x: torch.Tensor) -> torch.Tensor:
        """The head's own layers (BN folded): ``(B, C, H, W)`` -> ``(B, 1 + n_reg, H, W / S)``."""
        for i, stride in enumerate(self.layer_strides):
            x = F.conv2d(x, getattr(self, f"weight{i}"), getattr(self, f"bias{i}"), stride=(1, stride), padding=1)
        return torch.cat([torch.sigmoid(x[:, :1]), x[:, 1:]], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.taps.shape[0]
        b, _, h, w = x.shape if x.ndim == 4 else (0, 0, 0, 0)
        s, edge = self.stride, 2 * BORDER + 1                  # strips: 9 output rows / columns, 5 of them wrong
        if x.ndim != 4 or x.shape[1] != c or w % s or h < edge or w < edge * s:
            raise ValueError(f"CollapsedDetectionHead: x must be (B, {c}, H >= {edge}, W) with W a multiple of "
                             f"{s} and >= {edge * s}, got {tuple(x.shape)}")
        if x.dtype != self.taps.dtype or x.device != self.taps.device:
            raise ValueError(f"CollapsedDetectionHead: x is {x.dtype} on {x.device}, the weights {self.taps.dtype} "
                             f"on {self.taps.device}")
        if torch.is_grad_enabled() and x.requires_grad:
            raise RuntimeError("CollapsedDetectionHead is inference only (no backward): call it under "
                               "torch.no_grad() or torch.inference_mode()")
        warn_if_reduced_fp32(x, "CollapsedDetectionHead", "its products over the input channels")
        cols = w // s
        n_u, n_v = self.kernel_size
        z = x.permute(0, 2, 3, 1).reshape(b * h * w, c) @ self.taps              # (B H W, U V K)
        shifted_sum = _compiled_shifted_sum() if self.compiled else _shifted_sum
        out = shifted_sum(z.view(b, h, w, n_u, n_v, -1), self.bias, h, cols, s, self.pad_rows, self.pad_cols)
        out = out.permute(0, 3, 1, 2)                                            # (B, 1 + n_reg, H, W / S)
        out = torch.cat([torch.sigmoid(out[:, :1]), out[:, 1:]], dim=1)
        # the outer rows and columns from the layers themselves, on strips (both edges in one batch)
        rows = self.layers(torch.cat([x[:, :, :edge], x[:, :, -edge:]]))           # (2B, 1 + n_reg, 9, W / S)
        out[:, :, :BORDER], out[:, :, -BORDER:] = rows[:b, :, :BORDER], rows[b:, :, -BORDER:]
        sides = self.layers(torch.cat([x[..., :edge * s], x[..., -edge * s:]]))     # (2B, 1 + n_reg, H, 9)
        out[..., :BORDER], out[..., -BORDER:] = sides[:b, ..., :BORDER], sides[b:, ..., -BORDER:]
        return out


def collapsed_head_for_inference(model: nn.Module, compiled: bool = True) -> nn.Module:
    """A copy of ``model`` (eval mode) whose ``detection_head`` is a :class:`CollapsedDetectionHead`.

    ``model`` is any model with a :class:`DetectionHead` as ``detection_head`` (FFTRadNet, the
    pillar models); the head's BatchNorms are folded in the copy first. ``model`` is unchanged.
    """
    head = getattr(model, "detection_head", None)
    if not isinstance(head, DetectionHead):
        raise TypeError(f"collapsed_head_for_inference: {type(model).__name__}.detection_head is "
                        f"{type(head).__name__}, not a DetectionHead")
    m = copy.deepcopy(model).eval()
    head = m.detection_head
    with torch.no_grad():
        for i in range(1, 5):
            bn = getattr(head, f"bn{i}")
            if isinstance(bn, nn.BatchNorm2d):
                fold_batchnorm(getattr(head, f"conv{i}"), bn)
                setattr(head, f"bn{i}", nn.Identity())
    m.detection_head = CollapsedDetectionHead(head, compiled)
    return m
