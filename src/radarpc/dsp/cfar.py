"""CFAR detectors (cell-averaging and ordered-statistic), N-D, batched, on any torch device.

Window convention (both detectors, every axis): ``window`` is the *full* side length of the
training window and ``guard`` the *full* side length of the guard window, both odd and centred
on the cell under test (CUT). ``window=9, guard=3`` means training cells at offsets
``-4..4`` whose offset is not inside ``-1..1`` on every axis at once: a 9 x 9 square minus the
3 x 3 square around the CUT = 72 training cells in 2-D. The CUT itself is always inside the guard.

Borders: training cells that fall outside the array are *excluded*; the noise estimate is the
statistic of the valid training cells only (for CA-CFAR the mean over the valid ones, which is
what RADIal's ``convolve2d(..., mode='same') / convolve2d(ones, ...)`` computes). No wrap-around.

Note on RADIal's ``rpl.py``: its ``win_param=(9, 9, 3, 3)`` are *half* widths (a 19 x 19 window
with a 7 x 7 guard). radarpc follows the seed paper's wording ("9 x 9 window with a 3 x 3
guard") with full widths; pass ``window=(19, 19), guard=(7, 7)`` to reproduce rpl.py exactly
(CLI: ``--cfar radial``, which also selects rpl.py's all-slot envelope). RADIal's threshold
``tau = 1.585`` (2 dB) was chosen for *that* geometry and envelope.

SNR is the linear ratio of the cell's power to the noise estimate; a cell is detected when
``snr > tau`` (RADIal's default threshold 2 dB is ``tau = 10 ** 0.2 = 1.585``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import product
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["CFARResult", "RADIAL_TAU", "ca_cfar", "os_cfar", "check_window", "check_tau"]

Array = torch.Tensor | np.ndarray

RADIAL_TAU = 10 ** (2 / 10)
"""RADIal rpl.py's CA-CFAR threshold, 2 dB as a linear SNR (for its 19 x 19 / 7 x 7 geometry)."""

# OS-CFAR sorts every cell's training values: the stacked neighbourhoods are built in blocks of
# at most this many bytes.
_OS_STACK_BYTES = 1 << 27


@dataclass
class CFARResult:
    """Output of a CFAR detector, of the same kind (torch or numpy) as the input power.

    Attributes
    ----------
    noise : Tensor or ndarray, ``(..., *spatial)``
        Noise-power estimate of every cell (``+inf`` where the cell has no valid training cell).
    snr : Tensor or ndarray, ``(..., *spatial)``
        ``power / noise`` (``0`` where both are 0 or noise is infinite, ``+inf`` where only the
        noise is 0).
    """

    noise: Array
    snr: Array

    def mask(self, tau: float | Array) -> Array:
        """Detections ``snr > tau``; ``tau`` may be a scalar or broadcast against ``snr``."""
        if isinstance(tau, (int, float)) and not tau > 0:
            raise ValueError(f"CFAR threshold tau must be > 0 (linear SNR), got {tau}")
        if isinstance(self.snr, np.ndarray):
            return self.snr > np.asarray(tau)
        return self.snr > torch.as_tensor(tau, dtype=self.snr.dtype, device=self.snr.device)


# ---- validation --------------------------------------------------------------------------------
def _as_sizes(name: str, v: int | Sequence[int]) -> tuple[int, ...]:
    t = (v,) if isinstance(v, (int, np.integer)) else tuple(v)
    if not t or any(isinstance(x, bool) or not isinstance(x, (int, np.integer)) for x in t):
        raise ValueError(f"CFAR {name} must be an odd int or a tuple of odd ints, got {v!r}")
    t = tuple(int(x) for x in t)
    if any(x < 1 or x % 2 == 0 for x in t):
        raise ValueError(f"CFAR {name}={t}: every size must be a positive odd number "
                         f"(full side length, 9 means offsets -4..4)")
    return t


def check_tau(tau: float) -> float:
    """Validate a CFAR threshold: a finite linear SNR ``> 0`` (2 dB = 1.585); returns it as float."""
    if isinstance(tau, bool) or not isinstance(tau, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(float(tau)) and float(tau) > 0):
        raise ValueError(f"tau must be a finite linear SNR threshold > 0 (2 dB = 1.585), got {tau!r}")
    return float(tau)


def check_window(window, guard) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Validate CFAR ``window`` / ``guard`` (full odd side lengths, 1-3 axes, guard < window).

    Returns both as tuples of int. The one implementation every caller (detectors, point-cloud
    config, conversion settings, CLI) uses.
    """
    w = _as_sizes("window", window)
    g = _as_sizes("guard", guard)
    if len(w) != len(g):
        raise ValueError(f"CFAR window {w} and guard {g} must have the same number of axes")
    if len(w) > 3:
        raise ValueError(f"CFAR supports 1-D, 2-D and 3-D windows, got {len(w)} axes")
    if any(gi >= wi for gi, wi in zip(g, w)):
        raise ValueError(f"CFAR guard {g} must be smaller than window {w} on every axis")
    return w, g


def _to_power(power: Array, nd: int) -> tuple[torch.Tensor, bool]:
    is_np = isinstance(power, np.ndarray)
    if not is_np and not isinstance(power, torch.Tensor):
        raise ValueError(f"CFAR power must be a torch.Tensor or numpy array, got {type(power).__name__}")
    x = torch.from_numpy(power) if is_np else power
    if x.is_complex():
        raise ValueError("CFAR power must be real (e.g. |E|**2), got a complex array")
    if x.dtype == torch.bool or not x.is_floating_point():
        x = x.to(torch.float32)
    if x.ndim < nd:
        raise ValueError(f"CFAR power has {x.ndim} dims, the {nd}-D window needs at least {nd}")
    if any(s == 0 for s in x.shape):
        raise ValueError(f"CFAR power is empty, shape {tuple(x.shape)}")
    lo, hi = torch.aminmax(x)                       # one pass; NaN propagates into both
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError("CFAR power contains NaN or infinite values")
    if lo < 0:
        raise ValueError("CFAR power must be >= 0 (a power, not an amplitude with sign)")
    return x, is_np


def _finish(power: torch.Tensor, noise: torch.Tensor, is_np: bool) -> CFARResult:
    # power is finite and >= 0, noise >= 0 or +inf: IEEE division gives power / noise, +inf for
    # power > 0 = noise and 0 for noise = inf; only 0 / 0 = NaN is set to 0. (-inf: a -0.0 noise
    # from -0.0 powers, read as +0.)
    snr = torch.div(power, noise).nan_to_num_(nan=0.0, posinf=math.inf, neginf=math.inf)
    if is_np:
        return CFARResult(noise=noise.cpu().numpy(), snr=snr.cpu().numpy())
    return CFARResult(noise=noise, snr=snr)


# ---- sums over boxes of offsets, with zero outside the array ------------------------------------
def _window_sums(x: torch.Tensor, axis: int, length: int, starts: Sequence[int]) -> list[torch.Tensor]:
    """``[out_s for s in starts]``, ``out_s[i] = sum_{d=s}^{s+length-1} x[i + d]`` along ``axis`` (0
    outside the array), the terms added one by one in the order of ``d`` onto ``+0``.

    Shifted additions of non-negative values only: no cancellation, unlike cumulative sums. The
    window sums are formed once for every start from ``min(starts)`` to ``max(starts)``; each
    ``out_s`` is a view of them.
    """
    n = x.shape[axis]
    lo = min(starts)
    m = n + max(starts) - lo                                       # acc[j]: window starting at offset lo + j
    shape = list(x.shape)
    shape[axis] = m
    acc = x.new_zeros(shape)
    for d in range(lo, lo + length):                               # acc[j] += x[j + d] where inside the array
        j0, j1 = max(0, -d), min(m, n - d)
        if j1 > j0:
            acc.narrow(axis, j0, j1 - j0).add_(x.narrow(axis, j0 + d, j1 - j0))
    return [acc.narrow(axis, st - lo, n) for st in starts]


def _ring_sum(x: torch.Tensor, w: tuple[int, ...], g: tuple[int, ...]) -> torch.Tensor:
    """Sum of ``x`` over the training ring of every cell of the last ``len(w)`` axes.

    The ring (window minus guard) is split into disjoint boxes: box ``i`` holds the offsets whose
    first axis outside the guard is ``i`` (inside the guard on axes ``< i``, anywhere in the
    window on axes ``> i``), on the negative side (``-hw_i..-hg_i-1``) or the positive side
    (``hg_i+1..hw_i``) of axis ``i``. Both sides are windows of the same length, summed once.
    The box sums are added in the order ``i = 0, 1, ...``, negative side first.
    """
    nd = len(w)
    hw = [k // 2 for k in w]
    hg = [k // 2 for k in g]
    first = x.ndim - nd
    total = None
    for i in range(nd):
        y = x
        for j in range(nd):
            if j != i:
                h = hg[j] if j < i else hw[j]
                y = _window_sums(y, first + j, 2 * h + 1, [-h])[0]
        neg, pos = _window_sums(y, first + i, hw[i] - hg[i], [-hw[i], hg[i] + 1])
        total = neg + pos if total is None else total.add_(neg).add_(pos)
    return total


def _valid_counts(shape: tuple[int, ...], w, g, dtype: type = np.float64) -> np.ndarray:
    """Number of training cells inside the array, per cell of ``shape`` (numpy ``dtype``, on the host).

    Window and guard are boxes: the valid training cells of ``c`` are the in-array window cells
    minus the in-array guard cells, ``prod_i nw_i(c_i) - prod_i ng_i(c_i)`` with ``nw_i(c)`` the
    number of offsets ``-hw_i..hw_i`` that stay inside axis ``i`` (exact small integers).
    """
    def inside(n: int, h: int) -> np.ndarray:
        c = np.arange(n, dtype=dtype)
        return np.minimum(c, h) + np.minimum(c[::-1], h) + 1

    nw = inside(shape[0], w[0] // 2)
    ng = inside(shape[0], g[0] // 2)
    for i in range(1, len(shape)):
        nw = np.multiply.outer(nw, inside(shape[i], w[i] // 2))
        ng = np.multiply.outer(ng, inside(shape[i], g[i] // 2))
    nw -= ng
    return nw


# ---- detectors ---------------------------------------------------------------------------------
def ca_cfar(power: Array, window: int | Sequence[int] = (9, 9),
            guard: int | Sequence[int] = (3, 3)) -> CFARResult:
    """Cell-averaging CFAR over the last ``len(window)`` axes.

    ``noise(c) = mean_{t in T(c)} power(t)`` over the valid training cells ``T(c)`` of cell ``c``,
    ``snr(c) = power(c) / noise(c)``.

    Parameters
    ----------
    power : Tensor or ndarray, ``(..., *spatial)``, real, ``>= 0``
        Cell powers (e.g. ``|E|**2`` of the RD envelope); leading axes are a batch.
    window, guard : int or tuple of int
        Full (odd) training-window and guard-window side lengths per axis; see the module
        docstring. 1, 2 or 3 axes.

    Returns
    -------
    CFARResult
        Torch tensors on ``power``'s device, or numpy arrays if ``power`` was numpy.

    Examples
    --------
    >>> import torch
    >>> r = ca_cfar(torch.ones(16, 16))
    >>> bool((r.snr == 1).all())
    True
    """
    w, g = check_window(window, guard)
    x, is_np = _to_power(power, len(w))
    spatial = tuple(x.shape[x.ndim - len(w):])
    total = _ring_sum(x, w, g)
    count_np = _valid_counts(spatial, w, g, np.float32 if x.dtype == torch.float32 else np.float64)
    count = torch.from_numpy(count_np).to(device=x.device, dtype=x.dtype)  # a no-op for float32 on CPU
    noise = total.div_(count)                                      # mean over the valid training cells
    if not count_np.all():                                         # cells without training cells: noise inf
        noise = noise.masked_fill_(count == 0, math.inf)
    return _finish(x, noise, is_np)


def _ring_offsets(w, g) -> list[tuple[int, ...]]:
    hw = [k // 2 for k in w]
    hg = [k // 2 for k in g]
    return [d for d in product(*(range(-h, h + 1) for h in hw))
            if any(abs(di) > gi for di, gi in zip(d, hg))]


def _kth_smallest(v: torch.Tensor, k: int) -> torch.Tensor:
    """The ``k``-th smallest value along the last axis (``1 <= k <= n``), by ``topk`` from the
    nearer end: the largest of the ``k`` smallest, or the smallest of the ``n - k + 1`` largest
    (faster than ``kthvalue`` or a sort on CPU; the same value)."""
    n = v.shape[-1]
    if k <= n - k + 1:
        return torch.topk(v, k, dim=-1, largest=False, sorted=False).values.amax(dim=-1)
    return torch.topk(v, n - k + 1, dim=-1, largest=True, sorted=False).values.amin(dim=-1)


def os_cfar(power: Array, window: int | Sequence[int], guard: int | Sequence[int],
            rank: float | int) -> CFARResult:
    """Ordered-statistic CFAR over the last ``len(window)`` axes (1-D, 2-D or 3-D).

    The noise estimate of cell ``c`` is an order statistic of the powers of its valid training
    cells ``T(c)`` (sorted ascending, ``n = |T(c)|``):

    * ``rank`` int ``k >= 1``: the ``k``-th smallest; at borders where ``n < k`` the largest
      (``min(k, n)``-th smallest);
    * ``rank`` float ``q`` in ``(0, 1)``: the ``ceil(q * n)``-th smallest (at least the first),
      i.e. the lower ``q``-quantile, which adapts to the number of valid cells at borders.

    Parameters
    ----------
    power : Tensor or ndarray, ``(..., *spatial)``, real, ``>= 0``
    window, guard : int or tuple of int
        Full odd side lengths, as in :func:`ca_cfar`.
    rank : int or float
        See above. An int must not exceed the number of training cells of the full window.

    Returns
    -------
    CFARResult
    """
    w, g = check_window(window, guard)
    x, is_np = _to_power(power, len(w))
    offsets = _ring_offsets(w, g)
    n_full = len(offsets)
    if isinstance(rank, bool) or not isinstance(rank, (int, float, np.integer, np.floating)):
        raise ValueError(f"OS-CFAR rank must be an int k-th smallest or a float quantile, got {rank!r}")
    if isinstance(rank, (int, np.integer)):
        if not 1 <= int(rank) <= n_full:
            raise ValueError(f"OS-CFAR rank k={rank} must be in [1, {n_full}] "
                             f"(training cells of window {w} with guard {g})")
    elif not 0.0 < float(rank) < 1.0:
        raise ValueError(f"OS-CFAR quantile rank={rank} must be in (0, 1)")

    nd = len(w)
    first = x.ndim - nd
    hw = [k // 2 for k in w]
    spec: list[int] = []
    for h in reversed(hw):
        spec += [h, h]
    xp = F.pad(x, spec, value=math.inf)  # cells outside the array sort last
    spatial = tuple(x.shape[first:])
    lead = tuple(x.shape[:first])
    n_valid = _valid_counts(spatial, w, g).astype(np.int64)      # (*spatial,), on the host
    if isinstance(rank, (int, np.integer)):
        k_all = np.minimum(n_valid, int(rank))
    else:
        k_all = np.minimum(np.maximum(np.ceil(float(rank) * n_valid), 1), n_valid).astype(np.int64)
    k_all = np.maximum(k_all, 1)                                  # cells without training cells: inf below
    # The order statistic is one k for most cells; the cells with another k (at borders) are
    # selected per k. The inf padding sorts after the n_valid >= k valid values.
    k_main = int(np.bincount(k_all.ravel()).argmax())
    # Blocks along the first spatial axis bound the (..., block, *rest, n_full) neighbour stack.
    per_row = max(1, x.numel() // spatial[0]) * n_full * x.element_size()
    rows = max(1, _OS_STACK_BYTES // per_row)
    noise = torch.empty_like(x)
    for i0 in range(0, spatial[0], rows):
        m = min(rows, spatial[0] - i0)
        cols = []
        for d in offsets:
            v = xp.narrow(first, hw[0] + d[0] + i0, m)
            for j in range(1, nd):
                v = v.narrow(first + j, hw[j] + d[j], spatial[j])
            cols.append(v)
        stack = torch.stack(cols, dim=-1)                        # (..., m, *rest, n_full)
        blk = _kth_smallest(stack, k_main)                       # (..., m, *rest)
        k_blk = k_all[i0:i0 + m].ravel()
        for k in np.unique(k_blk):                               # border cells with another k, by k
            if k == k_main:
                continue
            cells = torch.from_numpy(np.flatnonzero(k_blk == k)).to(x.device)
            sub = stack.reshape(lead + (-1, n_full)).index_select(-2, cells)   # (..., S, n_full)
            blk.view(lead + (-1,)).index_copy_(-1, cells, _kth_smallest(sub, int(k)))
        noise.narrow(first, i0, m).copy_(blk)
    if not n_valid.all():
        noise.masked_fill_(torch.from_numpy(n_valid == 0).to(x.device), math.inf)
    return _finish(x, noise, is_np)
