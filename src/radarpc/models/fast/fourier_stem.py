"""FFTRadNet's pre-encoder, stem convolution and ReLU as one map, evaluated per Doppler frequency.

Between the input and the first ReLU, FFTRadNet applies two linear layers (BN folded): the MIMO
pre-encoder, circular in Doppler,

    z[o, r, d] = b1[o] + sum_{c, t} P[o, c, t] x[c, r, (d + s_t) mod N],      s_t = t * slot_width - shift,

and the 3 x 3 stem, zero-padded,

    y[p, r, d] = b2[p] + sum_{o, i, j} S[p, o, i, j] z[o, r + i - 1, d + j - 1].

If the stem were circular in Doppler too, both would be products per Doppler frequency ``k``
(``X_k = sum_d x[d] exp(-2 pi i k d / N)``): ``Z_k = P_k X_k`` with
``P_k = sum_t P[:, :, t] exp(2 pi i k s_t / N)``, and ``Y_k[r] = sum_i S_k^i Z_k[r + i - 1]`` with
``S_k^i = sum_j S[:, :, i, j] exp(2 pi i k (j - 1) / N)``, so

    Y_k[r] = sum_i Q_k^i X_k[r + i - 1],      Q_k^i = S_k^i P_k  (K x C, formed once in float64),

a 3-tap range convolution from the C input channels per frequency: 3 C K complex
multiply-adds per output and frequency instead of the C T (pre-encoder) and 9 K (stem) per output
and Doppler bin of the two layers. On full RADIal (C = 32, K = 192, T = 12, N = 256) that is
4.9 real GMAC against 10.3 + 43.5 (about 4.2 + 10.9 with the stem as Winograd). The biases are
constant in Doppler and enter frequency 0 only (``b1`` through the rows of the stem that lie
inside the image). The stem's zero padding differs from the circular one only at ``d = 0``, which
must not see ``z[..., N - 1]``, and ``d = N - 1``, which must not see ``z[..., 0]``: those two
columns of ``z`` are computed directly and their terms subtracted. The result equals the two
layers in real arithmetic; in float32 it differs by rounding only (the tests bound it).

This is an inference path (CPU especially: the transforms are ``torch.fft``'s, the products one
batched GEMM); :func:`fourier_stem_for_inference` puts it into a copy of a model.
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from radarpc.models.fast.batchnorm import fuse_fftradnet
from radarpc.models.fftradnet import FFTRadNet, MIMOPreEncoder
from radarpc.models.fast.winograd import many_graphs, supports_winograd, warn_if_reduced_fp32

__all__ = ["doppler_shifts", "stem_gmac", "FourierStem", "fourier_stem_for_inference"]


def doppler_shifts(pre_encoder: MIMOPreEncoder, n_doppler: int) -> list[int]:
    """The Doppler offsets ``s_t`` of the pre-encoder's taps: output bin ``d`` reads input bin
    ``(d + s_t) mod n_doppler`` through tap ``t`` (the official circular pad and centre crop)."""
    conv = pre_encoder.conv
    n_taps, dilation = conv.kernel_size[1], conv.dilation[1]
    width = n_doppler + 2 * pre_encoder.pad - (n_taps - 1) * dilation      # the conv's output width
    start = int(width / 2 - n_doppler / 2)                                 # MIMOPreEncoder's crop, same arithmetic
    return [start + t * dilation - pre_encoder.pad for t in range(n_taps)]


def _padded_spectra(x: torch.Tensor) -> torch.Tensor:
    """``x (B, C, R, N)`` -> its Doppler spectra ``(F, B, R + 2, 2, C)``, ``F = N / 2 + 1``, real and
    imaginary parts, with zero rows above and below each batch's range rows."""
    b, c, r, _ = x.shape
    xf = torch.view_as_real(torch.fft.rfft(x, dim=3))                      # (B, C, R, F, 2)
    padded = xf.new_zeros(xf.shape[3], b, r + 2, 2, c)
    padded[:, :, 1:r + 1] = xf.permute(3, 0, 2, 4, 1)
    return padded


def _windows(padded: torch.Tensor, batch: int, r0: int, r1: int) -> torch.Tensor:
    """``A (F, r1 - r0, 3 2 C)``: row ``r`` of ``A[f]`` holds the spectra of range rows ``r - 1, r, r + 1``
    of ``batch`` (ordered row tap, re/im, channel)."""
    n_freq, _, _, _, c = padded.shape
    s = padded.stride()
    # three consecutive padded rows are contiguous: overlapping windows, copied once
    return padded.as_strided((n_freq, r1 - r0, 6 * c), (s[0], s[2], 1), padded.storage_offset() + batch * s[1]
                             + r0 * s[2]).contiguous()


def _epilogue(y: torch.Tensor, e0: torch.Tensor, e1: torch.Tensor, out: torch.Tensor) -> None:
    """``out = relu(y - edges)`` with Doppler moved inside: ``y (N, rows, K)`` (any strides, as
    ``irfft`` leaves it), ``e0``/``e1 (rows, K)`` the terms to remove at ``d = 0`` and ``N - 1``,
    ``out (rows, N, K)`` (rows of the channels-last output)."""
    n = y.shape[0]
    d = torch.arange(n, device=y.device)[:, None, None]
    y = y - torch.where(d == 0, e0, 0.0) - torch.where(d == n - 1, e1, 0.0)
    out.copy_(y.clamp_min(0).transpose(0, 1))


@functools.cache
def _compiled_epilogue():
    # static shapes: one graph per row block and size
    return torch.compile(_epilogue, dynamic=False)


class FourierStem(nn.Module):
    """Inference only: ``relu(stem(pre_encoder(x)))`` of FFTRadNet computed per Doppler frequency.

    Parameters
    ----------
    pre_encoder : MIMOPreEncoder
        With its BatchNorm folded into the conv (:func:`radarpc.models.fast.batchnorm.fuse_fftradnet`).
    stem : nn.Conv2d
        The backbone's 3 x 3, stride-1, padding-1 convolution, BN folded, ``pre_encoder``'s output
        channels in.
    n_doppler : int
        Doppler bins ``N`` of the inputs (the weights are formed for it).
    row_block : int
        Range rows per inverse transform and epilogue pass (small blocks stay in cache).
    compiled : bool
        Inductor-compile the epilogue (ReLU, edge terms and the move to channels-last; fast,
        compiles on the first call of each shape, with a C++ compiler on CPUs) instead of running
        it eagerly.

    Notes
    -----
    ``forward(x)``: ``x (B, C, R, N)`` float32 or float64, no autograd; returns
    ``(B, K, R, N)`` in channels-last memory format, after the ReLU. The composed weights are
    buffers: the layer is for inference, not for training.
    """

    def __init__(self, pre_encoder: MIMOPreEncoder, stem: nn.Conv2d, n_doppler: int, row_block: int = 64,
                 compiled: bool = True):
        super().__init__()
        if not isinstance(pre_encoder, MIMOPreEncoder) or not isinstance(pre_encoder.bn, nn.Identity):
            raise ValueError("FourierStem: needs a MIMOPreEncoder with its BatchNorm folded "
                             "(radarpc.models.fast.batchnorm.fuse_fftradnet)")
        if not supports_winograd(stem) or stem.in_channels != pre_encoder.conv.out_channels:   # a plain 3 x 3 conv
            raise ValueError(f"FourierStem: the stem must be a 3 x 3, stride-1, padding-1 Conv2d with "
                             f"{pre_encoder.conv.out_channels} input channels, got {stem}")
        if n_doppler < 2 or row_block < 1:
            raise ValueError(f"FourierStem: n_doppler must be >= 2 and row_block >= 1, got {n_doppler}, {row_block}")
        if pre_encoder.pad > n_doppler:
            raise ValueError(f"FourierStem: the pre-encoder's circular pad {pre_encoder.pad} exceeds n_doppler={n_doppler}")
        dtype, device = stem.weight.dtype, stem.weight.device
        f64 = dict(dtype=torch.float64, device=device)
        p = pre_encoder.conv.weight.detach().double()[:, :, 0]              # (O, C, T)
        b1 = pre_encoder.conv.bias
        b1 = torch.zeros(p.shape[0], **f64) if b1 is None else b1.detach().double()
        s = stem.weight.detach().double()                                    # (K, O, 3, 3)
        b2 = torch.zeros(s.shape[0], **f64) if stem.bias is None else stem.bias.detach().double()
        shifts = doppler_shifts(pre_encoder, n_doppler)
        n, n_freq, c_in, c_out = n_doppler, n_doppler // 2 + 1, p.shape[1], s.shape[0]

        def phases(offsets):                                                 # exp(2 pi i k offset / N), (F, len)
            k = torch.arange(n_freq, **f64)[:, None]
            return torch.exp(2j * math.pi * k * torch.tensor(offsets, **f64) / n)

        p_k = torch.einsum("oct,ft->foc", p.to(torch.complex128), phases(shifts))          # (F, O, C)
        s_k = torch.einsum("poij,fj->fipo", s.to(torch.complex128), phases([-1, 0, 1]))    # (F, 3, K, O)
        q = torch.einsum("fipo,foc->ficp", s_k, p_k)                                         # (F, 3, C, K)
        # the complex product X Q as one real GEMM: rows (tap, re/im, c), columns (k, re/im) interleaved
        w = torch.empty(n_freq, 3, 2, c_in, c_out, 2, **f64)
        w[:, :, 0, :, :, 0], w[:, :, 0, :, :, 1] = q.real, q.imag
        w[:, :, 1, :, :, 0], w[:, :, 1, :, :, 1] = -q.imag, q.real
        self.register_buffer("w", w.reshape(n_freq, 6 * c_in, 2 * c_out).to(dtype))        # (F, 6C, 2K)
        # b1 through the stem's row taps i (summed over j), and b2: frequency 0, times N
        self.register_buffer("bias_taps", torch.einsum("poi,o->ip", s.sum(3), b1).to(dtype))   # (3, K)
        self.register_buffer("bias", b2.to(dtype))                                           # (K,)
        # for the two edge columns: the pre-encoder directly, and the stem's taps j = 0 and j = 2
        self.register_buffer("p", p.to(dtype))                                               # (O, C, T)
        self.register_buffer("b1", b1.to(dtype))                                             # (O,)
        self.register_buffer("s_edges", s[:, :, :, [0, 2]].permute(3, 2, 1, 0).contiguous().to(dtype))  # (2, 3, O, K)
        self.shifts, self.n_doppler, self.row_block, self.compiled = shifts, n_doppler, row_block, compiled
        self.in_channels, self.out_channels = c_in, c_out

    def extra_repr(self) -> str:
        return (f"{self.in_channels}, {self.out_channels}, n_doppler={self.n_doppler}, "
                f"row_block={self.row_block}, compiled={self.compiled}")

    def _edges(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The terms the circular stem adds at ``d = 0`` (from ``z[..., N - 1]``) and ``d = N - 1``
        (from ``z[..., 0]``), ``(B, R, K)`` each."""
        b, _, r, n = x.shape
        out = []
        for d_src, taps in ((n - 1, self.s_edges[0]), (0, self.s_edges[1])):
            cols = torch.stack([x[..., (d_src + s) % n] for s in self.shifts], dim=-1)    # (B, C, R, T)
            z = torch.einsum("bcrt,oct->bro", cols, self.p) + self.b1                      # (B, R, O)
            z = F.pad(z, (0, 0, 1, 1))                                                     # zero rows -1 and R
            out.append(sum(z[:, i:i + r] @ taps[i] for i in range(3)))                     # (B, R, K)
        return out[0], out[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != self.in_channels or x.shape[3] != self.n_doppler:
            raise ValueError(f"FourierStem: x must be (B, {self.in_channels}, R, {self.n_doppler}), "
                             f"got {tuple(x.shape)}")
        if x.dtype != self.w.dtype or x.device != self.w.device:
            raise ValueError(f"FourierStem: x is {x.dtype} on {x.device}, the weights {self.w.dtype} on {self.w.device}")
        if torch.is_grad_enabled() and x.requires_grad:
            raise RuntimeError("FourierStem is inference only (no backward): call it under torch.no_grad() "
                               "or torch.inference_mode()")
        warn_if_reduced_fp32(x, "FourierStem", "the products per frequency")
        b, _, r, n = x.shape
        k_out = self.out_channels
        epilogue = _compiled_epilogue() if self.compiled else _epilogue
        # biases: constant in Doppler, so frequency 0 only; b1 reaches row r through the stem taps inside the image
        row_bias = self.bias + self.bias_taps.sum(0).expand(r, k_out).clone()
        row_bias[0] -= self.bias_taps[0]
        row_bias[-1] -= self.bias_taps[2]
        row_bias *= n
        padded = _padded_spectra(x)                                                   # (F, B, R + 2, 2, C)
        e0, e1 = self._edges(x)
        out = x.new_empty(b, r, n, k_out)
        with many_graphs():
            for i in range(b):
                for r0 in range(0, r, self.row_block):
                    r1 = min(r, r0 + self.row_block)
                    y = torch.bmm(_windows(padded, i, r0, r1), self.w)                 # (F, rows, 2K): Y_f, (re, im)
                    y[0, :, 0::2] += row_bias[r0:r1]
                    y = torch.fft.irfft(torch.view_as_complex(y.view(-1, r1 - r0, k_out, 2)), n=n, dim=0)
                    epilogue(y, e0[i, r0:r1], e1[i, r0:r1], out[i, r0:r1])             # (rows, N, K)
        return out.permute(0, 3, 1, 2)                         # (B, K, R, N), channels-last


def stem_gmac(model: FFTRadNet) -> float:
    """GMAC a frame of ``model``'s pre-encoder and stem as layers, ``R N (O C T + K O 9)``: 53.5 on
    full RADIal cubes, where the Fourier stem is several times faster, 0.5 for ``fftradnet-s``,
    where its transforms' overheads make it slower (``docs/results/detection.md``, "Exact rewrites")."""
    cfg, conv = model.cfg, model.backbone.conv
    o, c, _, t = model.pre_encoder.conv.weight.shape
    return cfg.n_range * cfg.n_doppler * (o * c * t + conv.out_channels * o * 9) / 1e9


def fourier_stem_for_inference(model: FFTRadNet, row_block: int = 64, compiled: bool = True) -> FFTRadNet:
    """A copy of ``model`` (BN folded, eval mode) whose pre-encoder, stem and first ReLU are one
    :class:`FourierStem` (``pre_encoder`` holds it; the backbone's ``conv`` and ``act`` become
    identities). ``model`` is unchanged. Compose with
    :func:`radarpc.models.fast.winograd.winograd_for_inference` for the other 3 x 3 layers."""
    if not isinstance(model, FFTRadNet):
        raise TypeError(f"fourier_stem_for_inference: expected an FFTRadNet, got {type(model).__name__}")
    m = fuse_fftradnet(model)
    if not isinstance(m.backbone.conv, nn.Conv2d) or isinstance(m.pre_encoder, FourierStem):
        raise ValueError("fourier_stem_for_inference: the model's stem is already converted")
    m.pre_encoder = FourierStem(m.pre_encoder, m.backbone.conv, m.cfg.n_doppler, row_block, compiled)
    m.backbone.conv, m.backbone.act = nn.Identity(), nn.Identity()
    return m
