"""Winograd F(4 x 4, 3 x 3) convolution: stride-1 3 x 3 layers with 4x fewer multiplications.

Lavin and Gray, "Fast Algorithms for Convolutional Neural Networks" (CVPR 2016). Every 4 x 4 tile
of the output of a 3 x 3 correlation comes from the 6 x 6 input tile ``d`` around it as

    Y = A^T [ sum_c (G g_c G^T) (.) (B^T d_c B) ] A,

so each tile and channel pair costs 36 multiplications instead of 4 x 4 x 9 = 144, and the sum over
input channels ``c`` is one matrix product per position of the 6 x 6 transformed tile (36 of them,
batched). ``B^T``, ``G`` and ``A^T`` below are the paper's matrices for the interpolation points 0,
+-1, +-2 and infinity.
The transforms add rounding: in float32 the result differs from a direct convolution by about 1e-5
relative to the largest output, against about 1e-6 for the direct one (the tests bound it).

This is a CPU inference path for wide layers on large maps (the FFTRadNet stem, decoder and
detection head): on GPUs cuDNN already picks Winograd kernels itself. The input and output
transforms are short sums of strided slices; compiled by Inductor (``compiled=True``, the default)
they become one pass each over a block of ``tile_rows`` tile rows, small enough to stay in cache.
The first call of each layer shape compiles (seconds to a minute); eager transforms give the same
result slower. Inference only: the layers hold their transformed weights as buffers, and autograd
through them is refused.
"""
from __future__ import annotations

import copy
import functools
import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.dsp.beamform import reduced_fp32_matmul

__all__ = ["BT", "G", "AT", "winograd_weight", "winograd_conv3x3", "WinogradConv2d", "supports_winograd",
           "winograd_for_inference"]

# B^T (6 x 6), G (6 x 3), A^T (4 x 6) of F(4 x 4, 3 x 3) (Lavin and Gray)
BT = ((4, 0, -5, 0, 1, 0),
      (0, -4, -4, 1, 1, 0),
      (0, 4, -4, -1, 1, 0),
      (0, -2, -1, 2, 1, 0),
      (0, 2, -1, -2, 1, 0),
      (0, 4, 0, -5, 0, 1))
G = ((1 / 4, 0, 0),
     (-1 / 6, -1 / 6, -1 / 6),
     (-1 / 6, 1 / 6, -1 / 6),
     (1 / 24, 1 / 12, 1 / 6),
     (1 / 24, -1 / 12, 1 / 6),
     (0, 0, 1))
AT = ((1, 1, 1, 1, 1, 0),
      (0, 1, -1, 2, -2, 0),
      (0, 1, 1, 4, 4, 0),
      (0, 1, -1, 8, -8, 1))
TILE = 4            # output tile side m; the input tile side is m + 3 - 1 = 6


def winograd_weight(weight: torch.Tensor) -> torch.Tensor:
    """The transformed kernel ``U = G g G^T`` of a 3 x 3 convolution weight.

    Parameters
    ----------
    weight : (K, C, 3, 3) tensor
        An ``nn.Conv2d`` weight (output channels, input channels, kernel rows, kernel columns).

    Returns
    -------
    (36, C, K) tensor, ``weight``'s dtype and device
        ``U[6 i + j, c, k] = (G weight[k, c] G^T)[i, j]``, computed in float64 and rounded once.
    """
    if weight.ndim != 4 or tuple(weight.shape[2:]) != (3, 3):
        raise ValueError(f"winograd_weight: expected a (K, C, 3, 3) weight, got {tuple(weight.shape)}")
    g = torch.tensor(G, dtype=torch.float64, device=weight.device)
    u = torch.einsum("ia,kcab,jb->ijck", g, weight.detach().double(), g)       # (6, 6, C, K)
    return u.reshape(36, weight.shape[1], weight.shape[0]).to(weight.dtype).contiguous()


def _combine(coefficients: tuple[float, ...], terms: list[torch.Tensor]) -> torch.Tensor:
    """``sum_a coefficients[a] terms[a]`` over the non-zero coefficients (ones without a multiply)."""
    out = None
    for c, t in zip(coefficients, terms):
        if c == 0:
            continue
        t = t if c == 1 else -t if c == -1 else c * t
        out = t if out is None else out + t
    return out


def _input_transform(rows: torch.Tensor, pad_top: int, n_rows: int, n_cols: int) -> torch.Tensor:
    """``V = B^T d B`` of every tile of ``n_rows`` x ``n_cols`` tiles.

    ``rows``: ``(B, h, W, C)``, the input rows these tiles read; the zero row above the image is
    missing when ``pad_top`` is 1, zero rows below are added as needed. Returns ``(36, T, C)``,
    ``T = B n_rows n_cols`` tiles in (batch, tile row, tile column) order.
    """
    _, h, w, c = rows.shape
    rows = F.pad(rows, (0, 0, 1, TILE * n_cols + 1 - w, pad_top, TILE * n_rows + 2 - h - pad_top))
    d = [[rows[:, a:a + TILE * n_rows:TILE, b:b + TILE * n_cols:TILE] for b in range(6)] for a in range(6)]
    bt_d = [[_combine(BT[i], [d[a][b] for a in range(6)]) for b in range(6)] for i in range(6)]   # B^T d
    v = torch.stack([_combine(BT[j], bt_d[i]) for i in range(6) for j in range(6)])             # (B^T d) B
    return v.reshape(36, -1, c)


def _output_transform(m: torch.Tensor, bias: torch.Tensor | None, out: torch.Tensor, relu: bool = False) -> None:
    """``Y = A^T M A`` (+ bias, then ReLU if ``relu``) of every tile, written into ``out`` ``(B, h, W, K)``
    (the rows of these tiles, the last tile row and column cropped to the image); ``m``: ``(36, T, K)``."""
    b, h, w, k = out.shape
    n_rows = -(-h // TILE)
    n_cols = m.shape[1] // (b * n_rows)
    m = m.view(6, 6, b, n_rows, n_cols, k)
    at_m = [[_combine(AT[p], [m[i, j] for i in range(6)]) for j in range(6)] for p in range(TILE)]   # A^T M
    y = torch.stack([torch.stack([_combine(AT[q], at_m[p]) for q in range(TILE)], dim=3)
                     for p in range(TILE)], dim=2)                                # (B, n_rows, 4, n_cols, 4, K)
    y = y.reshape(b, TILE * n_rows, TILE * n_cols, k)[:, :h, :w]
    y = y if bias is None else y + bias
    out.copy_(y.clamp_min(0) if relu else y)


def warn_if_reduced_fp32(x: torch.Tensor, who: str, what: str) -> None:
    """Warn (naming ``who`` and what loses precision, ``what``) when ``x`` is float32 and float32
    matmuls on its device run at reduced precision (TF32, or bf16 through oneDNN): the inference
    rewrites' products then lose far more than the layers they replace."""
    if x.dtype == torch.float32 and reduced_fp32_matmul(x.device):
        warnings.warn(f"{who}: float32 matmul precision is reduced (torch.set_float32_matmul_precision or a backend's "
                      f"fp32_precision); {what} then lose far more than the direct layers would: set "
                      f"torch.set_float32_matmul_precision('highest')", RuntimeWarning, stacklevel=3)


def many_graphs():
    """A context in which Dynamo keeps many graphs of one function (every layer shape and block
    position is its own, more than its default 8); the setting's name changed in torch 2.6."""
    cfg = torch._dynamo.config
    if hasattr(cfg, "recompile_limit"):
        return cfg.patch(recompile_limit=4096, accumulated_recompile_limit=65536)
    return cfg.patch(cache_size_limit=4096, accumulated_cache_size_limit=65536)


@functools.cache
def _compiled_transforms():
    # static shapes: one graph per layer shape and block position (first, middle, last)
    return (torch.compile(_input_transform, dynamic=False), torch.compile(_output_transform, dynamic=False))


def winograd_conv3x3(x: torch.Tensor, u: torch.Tensor, bias: torch.Tensor | None = None, *,
                     tile_rows: int = 4, compiled: bool = True, relu: bool = False) -> torch.Tensor:
    """A stride-1, zero-padded (1 pixel) 3 x 3 convolution, ``F.conv2d(x, weight, bias, padding=1)``.

    Parameters
    ----------
    x : (B, C, H, W) float32 or float64 tensor
        Any memory format; with channels innermost (channels-last, or a crop of it) no copy is made.
        Not under autograd (inference only).
    u : (36, C, K) tensor
        ``winograd_weight(weight)``, same dtype and device as ``x``.
    bias : (K,) tensor, optional
        Same dtype and device as ``x``.
    tile_rows : int
        Tile rows (4 image rows each) transformed and multiplied per block; small blocks keep the
        transformed tiles in cache.
    compiled : bool
        Run the transforms as Inductor-compiled kernels (fast; compiles on the first call of each
        shape, with a C++ compiler on CPUs) instead of eager torch operations (same result, slower).
    relu : bool
        Apply ReLU to the output in the output transform (saves a pass over the output).

    Returns
    -------
    (B, K, H, W) tensor in channels-last memory format.

    Notes
    -----
    The transforms multiply rounding errors (the terms reach several hundred times the outputs),
    so half precisions are refused, and under a reduced float32 matmul precision (TF32, or bf16
    through oneDNN on CPUs with AMX) a ``RuntimeWarning`` says the result is far from float32's.
    """
    if x.ndim != 4 or x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"winograd_conv3x3: x must be a (B, C, H, W) float32 or float64 tensor, "
                         f"got {x.dtype} {tuple(x.shape)}")
    if torch.is_grad_enabled() and (x.requires_grad or u.requires_grad
                                    or (bias is not None and bias.requires_grad)):
        raise RuntimeError("winograd_conv3x3 is inference only (no backward): call it under "
                           "torch.no_grad() or torch.inference_mode(), or train the nn.Conv2d")
    if u.ndim != 3 or u.shape[0] != 36 or u.shape[1] != x.shape[1]:
        raise ValueError(f"winograd_conv3x3: u must be (36, C={x.shape[1]}, K) from winograd_weight, "
                         f"got {tuple(u.shape)}")
    if u.dtype != x.dtype or u.device != x.device:
        raise ValueError(f"winograd_conv3x3: u is {u.dtype} on {u.device}, x is {x.dtype} on {x.device}")
    if bias is not None and (tuple(bias.shape) != (u.shape[2],) or bias.dtype != x.dtype or bias.device != x.device):
        raise ValueError(f"winograd_conv3x3: bias must be ({u.shape[2]},) {x.dtype} on {x.device}, "
                         f"got {tuple(bias.shape)} {bias.dtype} on {bias.device}")
    if tile_rows < 1:
        raise ValueError(f"winograd_conv3x3: tile_rows must be >= 1, got {tile_rows}")
    warn_if_reduced_fp32(x, "winograd_conv3x3", "the transformed products")
    return torch.ops.radarpc.winograd_conv3x3(x, u, bias, tile_rows, compiled, relu)


# An opaque operator to torch.compile: a model compiled around it (e.g. with Inductor's freezing)
# keeps the blocked loop and its separately compiled transforms instead of tracing them whole,
# which compiles for minutes into slower code.
@torch.library.custom_op("radarpc::winograd_conv3x3", mutates_args=())
def _winograd_conv3x3_op(x: torch.Tensor, u: torch.Tensor, bias: torch.Tensor | None, tile_rows: int,
                         compiled: bool, relu: bool) -> torch.Tensor:
    b, _, h, w = x.shape
    k = u.shape[2]
    n_rows, n_cols = -(-h // TILE), -(-w // TILE)
    input_transform, output_transform = _compiled_transforms() if compiled else (_input_transform, _output_transform)
    if x.stride(1) != 1:    # the transforms read channels innermost: strided reads are several times slower
        x = x.contiguous(memory_format=torch.channels_last)
    x_nhwc = x.permute(0, 2, 3, 1)                                            # (B, H, W, C)
    out = x.new_empty(b, h, w, k)
    with many_graphs():
        for r0 in range(0, n_rows, tile_rows):
            r1 = min(n_rows, r0 + tile_rows)
            top, bottom = max(TILE * r0 - 1, 0), min(TILE * r1 + 1, h)        # input rows of these tiles
            v = input_transform(x_nhwc[:, top:bottom], int(r0 == 0), r1 - r0, n_cols)   # (36, T, C)
            m = torch.bmm(v, u)                                               # (36, T, K)
            output_transform(m, bias, out[:, TILE * r0:min(TILE * r1, h)], relu)
    return out.permute(0, 3, 1, 2)                                            # (B, K, H, W), channels-last


@_winograd_conv3x3_op.register_fake
def _(x, u, bias, tile_rows, compiled, relu):
    return x.new_empty(x.shape[0], x.shape[2], x.shape[3], u.shape[2]).permute(0, 3, 1, 2)   # as the real one


class WinogradConv2d(nn.Module):
    """An inference-only stand-in for a stride-1, padding-1 3 x 3 ``nn.Conv2d`` (:func:`winograd_conv3x3`).

    Parameters
    ----------
    conv : nn.Conv2d
        3 x 3, stride 1, padding 1, dilation 1, groups 1, zero padding (:func:`supports_winograd`);
        its weight is transformed once (:func:`winograd_weight`) and kept with its bias as buffers.
    tile_rows, compiled
        As in :func:`winograd_conv3x3`.
    """

    def __init__(self, conv: nn.Conv2d, tile_rows: int = 4, compiled: bool = True):
        super().__init__()
        if not supports_winograd(conv):
            raise ValueError(f"WinogradConv2d: needs a 3 x 3 Conv2d with stride 1, padding 1, dilation 1, "
                             f"groups 1 and zero padding, got {conv}")
        if tile_rows < 1:
            raise ValueError(f"WinogradConv2d: tile_rows must be >= 1, got {tile_rows}")
        self.in_channels, self.out_channels = conv.in_channels, conv.out_channels
        self.tile_rows, self.compiled = tile_rows, compiled
        self.relu = False            # set by radarpc.models.fast.fused_activation to fuse a following ReLU
        self.register_buffer("u", winograd_weight(conv.weight))                   # (36, C, K)
        self.register_buffer("bias", None if conv.bias is None else conv.bias.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return winograd_conv3x3(x, self.u, self.bias, tile_rows=self.tile_rows, compiled=self.compiled,
                                relu=self.relu)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, F(4x4, 3x3), tile_rows={self.tile_rows}, relu={self.relu}"


def supports_winograd(conv: nn.Module) -> bool:
    """Whether ``conv`` is a plain ``nn.Conv2d`` (not a subclass, whose forward may differ) with a
    3 x 3 kernel, stride 1, padding 1, dilation 1, groups 1 and zero padding."""
    return (type(conv) is nn.Conv2d and conv.kernel_size == (3, 3) and conv.stride == (1, 1)
            and conv.padding == (1, 1) and conv.dilation == (1, 1) and conv.groups == 1
            and conv.padding_mode == "zeros")


def winograd_for_inference(model: nn.Module, min_channels: int = 96, tile_rows: int = 4,
                           compiled: bool = True) -> nn.Module:
    """A copy of ``model`` (eval mode) whose 3 x 3 stride-1 convolutions with at least
    ``min_channels`` input and output channels are :class:`WinogradConv2d`.

    Parameters
    ----------
    model : nn.Module
        Fold BatchNorm first (e.g. :func:`radarpc.models.fast.batchnorm.fuse_for_inference`): a
        convolution followed by BN would otherwise keep the BN as a separate pass.
    min_channels : int
        Narrower layers stay direct: the transforms' cost grows with ``C + K``, the products' saving
        with ``C K`` (measured per layer in ``docs/notebook/2026-12-04-detection.md``, "Winograd convolutions").
    tile_rows, compiled
        As in :func:`winograd_conv3x3`.

    Returns
    -------
    nn.Module
        The converted copy; ``model`` is unchanged.
    """
    m = copy.deepcopy(model).eval()
    for parent in list(m.modules()):
        for name, child in list(parent.named_children()):
            if supports_winograd(child) and min(child.in_channels, child.out_channels) >= min_channels:
                setattr(parent, name, WinogradConv2d(child, tile_rows, compiled))
    return m
