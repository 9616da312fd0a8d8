"""``A = sum_rx |R|`` on CPU, fast: behind :func:`radarpc.dsp.ddma.rx_magnitude_sum`.

The core computes ``sqrt(re^2 + im^2)`` of every receiver of the whole cube, then sums over the
receivers: three passes over cube-sized temporaries. Here the same formula runs either in the C
kernel (:func:`radarpc.dsp.accel.native.rx_magnitude_sum_native`, one read of the cube) or, where
that kernel cannot take the input (not built, another dtype or layout), in row blocks of about
2 MB whose ``re^2, im^2`` and ``|z|`` buffers stay in cache (:func:`rx_magnitude_sum_blocked`).
Every ``|z|`` is the same IEEE-rounded value as the core's; the three differ only in the float32
rounding of the sum over the ``Nrx`` receivers (tested against the core with that bound).
"""
from __future__ import annotations

import torch

from radarpc.dsp.accel.native import native_supports, rx_magnitude_sum_native

__all__ = ["rx_magnitude_sum_fast", "rx_magnitude_sum_blocked"]

# Bytes of the cube per block of (B * Nr) rows: keeps the |.| intermediates in cache.
_CPU_BLOCK_BYTES = 1 << 21


def rx_magnitude_sum_fast(rd: torch.Tensor) -> torch.Tensor:
    """``A = sum_rx |rd|`` of a CPU cube ``(..., Nd, Nrx)`` complex -> ``(..., Nd)`` real: the C
    kernel when :func:`~radarpc.dsp.accel.native.native_supports` takes ``rd``, else
    :func:`rx_magnitude_sum_blocked`."""
    if native_supports(rd):
        return rx_magnitude_sum_native(rd)
    return rx_magnitude_sum_blocked(rd)


def rx_magnitude_sum_blocked(rd: torch.Tensor) -> torch.Tensor:
    """``A = sum_rx sqrt(re^2 + im^2)`` in blocks of rows with preallocated ``re^2 + im^2`` and
    ``sqrt`` buffers (several times faster than ``rd.abs()`` on CPU): ``(..., Nd, Nrx) -> (..., Nd)``."""
    x = torch.view_as_real(rd.resolve_conj())                   # (..., Nd, Nrx, 2)
    nd, nrx = rd.shape[-2], rd.shape[-1]
    rows = x.reshape(-1, nd, nrx, 2)                             # (B*Nr, Nd, Nrx, 2)
    n = rows.shape[0]
    out = torch.empty(n, nd, dtype=x.dtype, device=x.device)
    step = max(1, _CPU_BLOCK_BYTES // max(1, nd * nrx * 2 * x.element_size()))
    sq = torch.empty(min(step, n), nd, nrx, 2, dtype=x.dtype, device=x.device)
    mag = torch.empty(min(step, n), nd, nrx, dtype=x.dtype, device=x.device)
    for i in range(0, n, step):
        c = rows[i:i + step]
        m = c.shape[0]
        torch.mul(c, c, out=sq[:m])                              # contiguous re^2, im^2
        torch.add(sq[:m, ..., 0], sq[:m, ..., 1], out=mag[:m]).sqrt_()
        torch.sum(mag[:m], dim=-1, out=out[i:i + m])
    return out.reshape(rd.shape[:-1])
