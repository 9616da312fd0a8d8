"""Optional native CPU kernels: the RD magnitude sum and the screened beamformer's selection.

Two C extensions, built by ``setup.py`` when a compiler is present and skipped otherwise:

* :mod:`radarpc.dsp.accel._rxsum` computes ``A(r, d) = sum_rx |R(rx, r, d)|`` in one pass over a
  complex64 cube: ``re``/``im`` deinterleaved in SIMD registers, exact IEEE ``sqrt`` of
  ``re^2 + im^2`` per receiver, then the receiver sum (:func:`rx_magnitude_sum_native`, behind
  :func:`radarpc.dsp.ddma.rx_magnitude_sum`, whose torch path is the reference). On a
  2-core Sapphire Rapids VM it takes ~0.6 ms per full RADIal frame (512 x 256 x 16) with 2
  threads, the speed of one read of the cube, against ~2.2 ms for the blocked torch code
  (``benchmarks/rx_magnitude_sum.py``).
* :mod:`radarpc.dsp.accel._screen` runs everything of
  :func:`radarpc.dsp.accel.screened.beamform_peaks_screened` after its bfloat16 GEMM, one snapshot
  at a time in a single read of its screen row: power, best elevation per azimuth, the
  certified candidate set, the exact dot products of the candidates and their argmax
  (:func:`screen_select_native`; the torch selection in :mod:`radarpc.dsp.accel.screened` is
  its reference and fallback).

Both release the GIL and split their work over a module-level thread pool. With the switch of
:mod:`radarpc.dsp.accel` off (``RADARPC_NO_NATIVE=1`` or :func:`radarpc.dsp.accel.disabled`),
:func:`native_available` returns ``False`` (checked at every call), so the torch paths can be
compared on the same install.
"""
from __future__ import annotations

import math
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor, wait
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING

import torch

from radarpc.dsp.accel import DISABLE_ENV, enabled

if TYPE_CHECKING:
    from radarpc.dsp.dictionary import SubspaceTables

__all__ = [
    "KERNELS",
    "native_available",
    "native_kernels",
    "native_supports",
    "rx_magnitude_sum_native",
    "screen_select_native",
    "certify_select_native",
    "subspace_select_native",
]

_rxsum: ModuleType | None
_screen: ModuleType | None
try:
    from radarpc.dsp.accel import _rxsum
except ImportError:                      # built without a compiler (setup.py: optional=True)
    _rxsum = None
try:
    from radarpc.dsp.accel import _screen
except ImportError:
    _screen = None

KERNELS = ("auto", "avx", "scalar")
"""Kernel names accepted by :func:`rx_magnitude_sum_native` and :func:`screen_select_native`:
``auto`` picks the fastest one this CPU allows (``avx`` needs an x86 CPU with AVX and a GCC/Clang
build, and for the magnitude sum ``Nrx % 8 == 0``, 8 cells per step; ``scalar`` runs anywhere)."""

# Input bytes per work item. The threads take items from a shared queue until it is empty
# (dynamic sharing: a thread slowed down by another process, or by torch's OpenMP workers still
# spinning after a parallel op, simply takes fewer items; measured 0.73 vs 1.10 ms/frame right
# after a torch op, same speed otherwise). An item of 2 MB (~0.15 ms) keeps the per-item cost
# (a few us) near 1 %.
_CHUNK_BYTES = 1 << 21
# Items start on multiples of this many cells so that the SIMD blocks (8 cells), hence the
# values, do not depend on the split.
_CHUNK_ALIGN = 16

_pool: ThreadPoolExecutor | None = None
_pool_workers = 0
_pool_pid = 0
_pool_lock = threading.Lock()


def native_available() -> bool:
    """Whether the compiled extensions are importable and the switch :func:`radarpc.dsp.accel.enabled` is on.

    Returns
    -------
    bool
        ``True`` when :func:`rx_magnitude_sum_native` and :func:`screen_select_native` can run
        (both extensions come from the same compiler, so they are built together or not at all).
    """
    return _rxsum is not None and _screen is not None and enabled()


def _require_native(fallback: str) -> None:
    if not native_available():
        built = _rxsum is not None and _screen is not None
        why = (f"disabled ({DISABLE_ENV}={os.environ.get(DISABLE_ENV)!r} or radarpc.dsp.accel.disabled())"
               if built else "not built (install with a C compiler: pip install -e .)")
        raise RuntimeError(f"native extensions radarpc.dsp.accel._rxsum/_screen are {why}; use {fallback}")


def native_kernels(n_rx: int = 16) -> tuple[str, ...]:
    """Kernels this build can run on this CPU for ``n_rx`` receivers, fastest first.

    Parameters
    ----------
    n_rx : int
        Number of receivers (size of the last axis), ``>= 1``.

    Returns
    -------
    tuple of str
        Subset of ``("avx", "scalar")``; empty when the extension is unavailable.
    """
    if isinstance(n_rx, bool) or not isinstance(n_rx, int) or n_rx < 1:
        raise ValueError(f"n_rx must be an int >= 1, got {n_rx!r}")
    return tuple(_rxsum.kernels(n_rx)) if native_available() else ()


def native_supports(rd: torch.Tensor) -> bool:
    """Whether :func:`rx_magnitude_sum_native` can take ``rd`` as it is (the dispatch test).

    True for a CPU, complex64, C-contiguous tensor with ``ndim >= 2`` that does not require
    grad (the kernel has no backward), when :func:`native_available`.
    """
    return (native_available() and isinstance(rd, torch.Tensor) and rd.device.type == "cpu"
            and rd.dtype == torch.complex64 and rd.ndim >= 2 and rd.is_contiguous()
            and not (rd.requires_grad and torch.is_grad_enabled()))


def _submit(work: Callable[[], None], count: int) -> list[Future]:
    """Run ``work()`` ``count`` times concurrently on the shared pool.

    The pool is created on first use, replaced when more workers are needed, and re-created in
    a forked child (whose copy has no worker threads). Submission holds the lock, so a pool is
    never shut down between being looked up and being used.
    """
    global _pool, _pool_workers, _pool_pid
    with _pool_lock:
        if _pool is None or _pool_workers < count or _pool_pid != os.getpid():
            if _pool is not None and _pool_pid == os.getpid():
                _pool.shutdown(wait=False)                  # queued work still runs
            _pool = ThreadPoolExecutor(max_workers=count, thread_name_prefix="radarpc-rxsum")
            _pool_workers, _pool_pid = count, os.getpid()
        return [_pool.submit(work) for _ in range(count)]


def _run_items(item: Callable[[int, int], None], n: int, step: int, threads: int) -> None:
    """Call ``item(start, count)`` over ``range(0, n, step)`` on ``threads`` threads.

    The calling thread and ``threads - 1`` pool threads take items from a shared queue until it is
    empty; returns when every item is done (also on error, so that the caller's buffers outlive
    the work), re-raising the first error.
    """
    starts = iter(range(0, n, step))                                 # the shared queue of items
    take = threading.Lock()

    def work() -> None:
        while True:
            with take:
                s = next(starts, None)
            if s is None:
                return
            item(s, min(step, n - s))

    helpers = min(threads, math.ceil(n / step)) - 1
    futures = _submit(work, helpers) if helpers > 0 else []
    try:
        work()                                                       # this thread works too
    finally:
        wait(futures)                                                # every item, even on error
        for f in futures:
            f.result()                                               # re-raises the first error


def _check_threads_and_kernel(threads: int | None, kernel: str) -> int:
    """``threads`` (default ``torch.get_num_threads()``) after checking it and ``kernel``."""
    if threads is None:
        threads = torch.get_num_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be an int >= 1, got {threads!r}")
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    return threads


def _chunk_cells(n_rx: int) -> int:
    """Cells per work item: about ``_CHUNK_BYTES`` of input, a multiple of ``_CHUNK_ALIGN``."""
    return max(1, _CHUNK_BYTES // (8 * n_rx * _CHUNK_ALIGN)) * _CHUNK_ALIGN


def rx_magnitude_sum_native(rd: torch.Tensor, *, threads: int | None = None,
                            kernel: str = "auto") -> torch.Tensor:
    """``A = sum_rx |rd|`` over the last axis with the native kernel: ``(..., Nd, Nrx) -> (..., Nd)``.

    Same values as :func:`radarpc.dsp.ddma.rx_magnitude_sum` up to float32 rounding of the
    receiver sum (each ``|z| = sqrt(re^2 + im^2)`` is the IEEE-rounded value; the ``Nrx`` terms
    are added as a tree), bit for bit the same for any ``threads``. NaN and inf propagate as in
    the reference (``inf`` in any receiver gives ``inf``, ``NaN`` gives ``NaN``); squares beyond
    the float32 range overflow to ``inf``, as in the reference. NaN is not rejected here: it
    costs a pass, and :func:`radarpc.dsp.ddma.rd_envelope` checks the small envelope instead.

    Parameters
    ----------
    rd : Tensor ``(..., Nd, Nrx)`` complex64
        CPU, C-contiguous (a conjugate view is fine: ``|conj z| = |z|``).
    threads : int, optional
        Threads sharing the work: the calling thread and ``threads - 1`` threads of a
        module-level pool take 2 MB items of the cube from a shared queue. Default
        ``torch.get_num_threads()``; inputs of fewer items use fewer threads.
    kernel : str
        One of :data:`KERNELS`; ``auto`` (default) picks the fastest this CPU allows.

    Returns
    -------
    Tensor ``(..., Nd)`` float32
        On the CPU.

    Raises
    ------
    ValueError
        ``rd`` not a CPU complex64 C-contiguous tensor with ``ndim >= 2``; ``threads < 1``; an
        unknown kernel, or one this CPU / ``Nrx`` cannot run.
    RuntimeError
        The extension ``radarpc.dsp.accel._rxsum`` is not built or the switch is off.

    Notes
    -----
    The pass reads the cube once and is bound by memory bandwidth with 2 threads (about the
    speed of ``torch.view_as_real(rd).sum()``). The pool threads are not torch's: right after a
    parallel torch op, torch's OpenMP workers keep spinning for a few milliseconds and share the
    cores with them; the dynamic split limits the slowdown of a call started at that moment
    (``benchmarks/rx_magnitude_sum.py``, row ``native_after_torch_op``).

    Examples
    --------
    >>> rd = torch.randn(2, 512, 256, 16, dtype=torch.complex64)          # (B, Nr, Nd, Nrx)
    >>> rx_magnitude_sum_native(rd, threads=2).shape                      # doctest: +SKIP
    torch.Size([2, 512, 256])
    """
    if not isinstance(rd, torch.Tensor):
        raise ValueError(f"rd must be a torch.Tensor, got {type(rd).__name__}")
    if rd.device.type != "cpu":
        raise ValueError(f"rd must be on the CPU for the native kernel, got device {rd.device}")
    if rd.dtype != torch.complex64:
        raise ValueError(f"rd must be complex64, got dtype {rd.dtype}")
    if rd.ndim < 2:
        raise ValueError(f"rd must have shape (..., Nd, Nrx) with ndim >= 2, got {tuple(rd.shape)}")
    if not rd.is_contiguous():
        raise ValueError(f"rd must be C-contiguous, got shape {tuple(rd.shape)} with strides {rd.stride()} "
                         f"(call .contiguous() first)")
    threads = _check_threads_and_kernel(threads, kernel)
    _require_native("radarpc.dsp.ddma.rx_magnitude_sum")
    assert _rxsum is not None
    n_rx = rd.shape[-1]
    out = torch.empty(rd.shape[:-1], dtype=torch.float32)          # (..., Nd)
    if n_rx == 0:
        return out.zero_()
    if kernel != "auto" and kernel not in _rxsum.kernels(n_rx):
        raise ValueError(f"kernel {kernel!r} cannot run here for Nrx={n_rx}; available: {_rxsum.kernels(n_rx)}")
    n_cells = out.numel()
    if n_cells == 0:
        return out
    src, dst = rd.data_ptr(), out.data_ptr()                         # 8 bytes per complex, 4 per float
    ext = _rxsum

    def item(s: int, m: int) -> None:
        ext.rx_magnitude_sum(src + 8 * n_rx * s, dst + 4 * s, m, n_rx, kernel)

    _run_items(item, n_cells, _chunk_cells(n_rx), threads)
    return out


# Snapshots per work item of screen_select_native: ~60 us of work at RADIal's 181 x 5 grid, so
# that the per-item cost (a few us) stays small and two threads still balance on one frame.
_SCREEN_ROWS = 64


def screen_select_native(screen: torch.Tensor, snapshots: torch.Tensor, rows: torch.Tensor,
                         beta: torch.Tensor, grid: tuple[int, int], alpha: float,
                         max_candidates: int, *, threads: int | None = None, kernel: str = "auto"
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Selection step of :func:`radarpc.dsp.accel.screened.beamform_peaks_screened`, natively.

    For every snapshot ``j``: ``q_jc^2 = Re^2 + Im^2`` of its screen row, the best elevation
    per azimuth ``Q_j(az)``, ``need_j = ((1 - alpha) sqrt(max Q_j) - 2 beta_j) / (1 + alpha)``,
    the candidates ``q_jc >= need_j``, their exact amplitudes ``|B[k] v_j|`` (complex64
    products, float32 partial sums, modulus in double) and the argmax (ties to the smaller
    ``k``). Rows whose candidates span no azimuth or more than ``max_candidates`` azimuths, or
    whose screen holds NaN/inf, are flagged ``heavy`` and get ``index = -1``: the caller
    beamforms them over the whole grid.

    Parameters
    ----------
    screen : Tensor ``(P, >= 2 K)`` bfloat16
        ``[Re s^ | Im s^]`` per row, columns elevation-major (``c = el n_az + az``), ``K = n_az n_el``;
        rows may be padded (row stride ``>= 2 K``), the inner stride must be 1.
    snapshots : Tensor ``(P, N)`` complex64, C-contiguous (no conjugate view)
    rows : Tensor ``(K, N)`` complex64, C-contiguous
        ``B``, row ``k = az n_el + el``.
    beta : Tensor ``(P,)`` float32
        :func:`radarpc.dsp.accel.screened.screen_bound`'s ``beta_j``.
    grid : (n_az, n_el)
    alpha : float
        ``0 <= alpha < 1``, the bound's relative term.
    max_candidates : int
        Most azimuths with candidates a row may have before it is left to the caller.
    threads : int, optional
        Default ``torch.get_num_threads()``.
    kernel : str
        Dot-product kernel, one of :data:`KERNELS`: ``auto`` (default) picks ``avx`` where the
        CPU has it, else ``scalar``; they differ only in the float32 rounding of the sums.

    Returns
    -------
    index : LongTensor ``(P,)``        ``k_j`` (``-1`` for heavy rows)
    amplitude : Tensor ``(P,)``        ``Ae_j`` float32 (``0`` for heavy rows)
    heavy : BoolTensor ``(P,)``

    Raises
    ------
    ValueError
        Wrong device, dtype, shape or layout of an input; bad ``alpha``, ``max_candidates``,
        ``threads``; an unknown kernel, or one this CPU cannot run.
    RuntimeError
        The extensions are not built or the switch is off.
    """
    n_az, n_el = (int(g) for g in grid)
    k_dir = n_az * n_el
    for name, t in (("screen", screen), ("snapshots", snapshots), ("rows", rows), ("beta", beta)):
        if not isinstance(t, torch.Tensor) or t.device.type != "cpu":
            raise ValueError(f"{name} must be a CPU torch.Tensor for the native kernel")
    if screen.dtype != torch.bfloat16 or screen.ndim != 2 or screen.shape[1] < 2 * k_dir or screen.stride(1) != 1:
        raise ValueError(f"screen must be bfloat16 (P, >= 2 n_az n_el = {2 * k_dir}) with unit column stride, "
                         f"got {screen.dtype} {tuple(screen.shape)} strides {screen.stride()}")
    p = screen.shape[0]
    if (snapshots.dtype != torch.complex64 or snapshots.ndim != 2 or snapshots.shape[0] != p
            or not snapshots.is_contiguous() or snapshots.is_conj()):
        raise ValueError(f"snapshots must be a C-contiguous complex64 (P={p}, N) tensor without a conjugate "
                         f"view, got {snapshots.dtype} {tuple(snapshots.shape)}")
    n = snapshots.shape[1]
    if rows.dtype != torch.complex64 or tuple(rows.shape) != (k_dir, n) or not rows.is_contiguous() or rows.is_conj():
        raise ValueError(f"rows must be a C-contiguous complex64 ({k_dir}, {n}) tensor, got {rows.dtype} "
                         f"{tuple(rows.shape)}")
    if beta.dtype != torch.float32 or tuple(beta.shape) != (p,) or not beta.is_contiguous():
        raise ValueError(f"beta must be a contiguous float32 ({p},) tensor, got {beta.dtype} {tuple(beta.shape)}")
    if not (0.0 <= float(alpha) < 1.0):
        raise ValueError(f"alpha must be in [0, 1), got {alpha!r}")
    if isinstance(max_candidates, bool) or int(max_candidates) < 1:
        raise ValueError(f"max_candidates must be an integer >= 1, got {max_candidates!r}")
    threads = _check_threads_and_kernel(threads, kernel)
    _require_native("the torch selection of radarpc.dsp.accel.screened.beamform_peaks_screened")
    assert _screen is not None
    if kernel != "auto" and kernel not in _screen.kernels():
        raise ValueError(f"kernel {kernel!r} cannot run here; available: {_screen.kernels()}")
    index = torch.empty(p, dtype=torch.long)
    amplitude = torch.empty(p, dtype=torch.float32)
    heavy = torch.empty(p, dtype=torch.bool)
    if p == 0:
        return index, amplitude, heavy
    ext = _screen
    y_ptr, y_stride = screen.data_ptr(), screen.stride(0)
    v_ptr, b_ptr = snapshots.data_ptr(), beta.data_ptr()
    i_ptr, a_ptr, h_ptr = index.data_ptr(), amplitude.data_ptr(), heavy.data_ptr()
    r_ptr, a_f, m_c = rows.data_ptr(), float(alpha), int(max_candidates)

    def item(s: int, m: int) -> None:                                # bool is one byte, as uint8
        ext.screen_select(y_ptr + 2 * y_stride * s, y_stride, v_ptr + 8 * n * s, r_ptr, b_ptr + 4 * s, m,
                          n_az, n_el, n, a_f, m_c, i_ptr + 8 * s, a_ptr + 4 * s, h_ptr + s, kernel)

    _run_items(item, p, _SCREEN_ROWS, threads)
    return index, amplitude, heavy


# Points per work item of subspace_select_native (~30 us each at 751 x 11 directions).
_SUBSPACE_POINTS = 16
# Points per work item of certify_select_native (a few candidates each, ~1 us per candidate).
_CERTIFY_POINTS = 256


def certify_select_native(snapshots: torch.Tensor, rows: torch.Tensor, grid: tuple[int, int], ptr: torch.Tensor,
                          kidx: torch.Tensor, *, threads: int | None = None
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The certified decision of :func:`radarpc.dsp.beamform.certified_argmax`, natively.

    For every point ``j``, ``|B[k] v_j|`` in double for its candidates ``k`` in
    ``kidx[ptr[j]:ptr[j + 1]]`` (products of float32 values are exact in double; the sums carry
    the bound ``beta = 1.5 gamma_(2N+2) sum_i (|Re b_i| + |Im b_i|)(|Re v_i| + |Im v_i|) + 2^-50 f``),
    the largest (ties to the smaller elevation-major column ``el n_az + az``), and whether another
    candidate's interval reaches it (then the caller decides exactly).

    Parameters
    ----------
    snapshots : Tensor ``(P, N)`` complex64, C-contiguous, no conjugate view
    rows : Tensor ``(K, N)`` complex64, C-contiguous: ``B``, row ``k = az n_el + el``
    grid : (n_az, n_el)
    ptr : LongTensor ``(P + 1,)``   CSR offsets into ``kidx``, every point with >= 1 candidate
    kidx : LongTensor              candidate directions
    threads : int, optional

    Returns
    -------
    index : LongTensor ``(P,)``, amplitude : Tensor ``(P,)`` float32, ambiguous : BoolTensor ``(P,)``
    """
    n_az, n_el = (int(g) for g in grid)
    p = snapshots.shape[0]
    for name, t in (("snapshots", snapshots), ("rows", rows), ("ptr", ptr), ("kidx", kidx)):
        if not isinstance(t, torch.Tensor) or t.device.type != "cpu" or not t.is_contiguous() or t.is_conj():
            raise ValueError(f"{name} must be a contiguous CPU torch.Tensor without a conjugate view")
    n = snapshots.shape[1] if snapshots.ndim == 2 else -1
    if snapshots.dtype != torch.complex64 or snapshots.ndim != 2:
        raise ValueError(f"snapshots must be complex64 (P, N), got {snapshots.dtype} {tuple(snapshots.shape)}")
    if rows.dtype != torch.complex64 or tuple(rows.shape) != (n_az * n_el, n):
        raise ValueError(f"rows must be complex64 ({n_az * n_el}, {n}), got {rows.dtype} {tuple(rows.shape)}")
    if ptr.dtype != torch.long or tuple(ptr.shape) != (p + 1,) or kidx.dtype != torch.long or kidx.ndim != 1:
        raise ValueError(f"ptr must be int64 ({p + 1},) and kidx int64 1-D, got {ptr.dtype} {tuple(ptr.shape)} "
                         f"and {kidx.dtype} {tuple(kidx.shape)}")
    threads = _check_threads_and_kernel(threads, "auto")
    _require_native("the torch decision of radarpc.dsp.beamform.certified_argmax")
    assert _screen is not None
    index = torch.empty(p, dtype=torch.long)
    amplitude = torch.empty(p, dtype=torch.float32)
    ambiguous = torch.empty(p, dtype=torch.bool)
    if p == 0:
        return index, amplitude, ambiguous
    counts = ptr[1:] - ptr[:-1]
    if bool((counts < 1).any()) or int(ptr[0]) != 0 or int(ptr[-1]) != kidx.numel():
        raise ValueError("ptr must start at 0, end at len(kidx) and give every point >= 1 candidate")
    if bool(((kidx < 0) | (kidx >= n_az * n_el)).any()):
        raise ValueError(f"kidx must lie in [0, {n_az * n_el})")
    widest = int(counts.max())
    ext = _screen
    v_ptr, r_ptr, p_ptr, k_ptr = snapshots.data_ptr(), rows.data_ptr(), ptr.data_ptr(), kidx.data_ptr()
    i_ptr, a_ptr, m_ptr = index.data_ptr(), amplitude.data_ptr(), ambiguous.data_ptr()

    def item(s: int, m: int) -> None:
        ext.certify_select(v_ptr + 8 * n * s, r_ptr, n, p_ptr + 8 * s, k_ptr, m, n_az, n_el,
                           i_ptr + 8 * s, a_ptr + 4 * s, m_ptr + s, widest)

    _run_items(item, p, _CERTIFY_POINTS, threads)
    return index, amplitude, ambiguous


def subspace_select_native(y: torch.Tensor, tables: SubspaceTables, xn: torch.Tensor, snapshots: torch.Tensor,
                           rows: torch.Tensor, max_candidates: int, *, row_norm_max: float,
                           threads: int | None = None, kernel: str = "auto"
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Screen, selection and certified decision of
    :func:`radarpc.dsp.accel.subspace.beamform_peaks_subspace` after its first GEMM.

    For every point ``j``: ``z^_k = c_k . y_jg`` for every direction (float32), ``a_k = |z^_k|``,
    the residual bound ``R_jg`` of :func:`radarpc.dsp.accel.subspace.group_residuals`, the bound
    ``e_jk = resid_k R_jg + slack_k xn_j``, the candidates ``a_k + e_jk >= L`` with ``L`` the largest
    ``a_b - e_jb`` of the screened groups' largest ``a_b`` (and, when more than 8 remain, the largest
    ``a_k - e_jk`` among them, which is then the largest over every screened direction), then the
    decision of :func:`certify_select_native` on them. A group ``g`` whose bound
    ``cmax_g ||y_jg|| + 2 (rmax_g R_jg + smax_g xn_j)`` stays below the ``L`` of the groups screened
    before it holds no candidate and is not screened (the group with the largest bound goes
    first). When more than a few candidates remain, a float32 pass
    over them (the dot kernel of :func:`screen_select_native`, error at most
    ``2 sqrt(2) gamma_(2N+2) row_norm_max xn_j + 2^-22 f``) leaves only those that can still hold
    the maximum for the decision.

    Parameters
    ----------
    y : Tensor ``(P, >= G 2r)`` float32, unit column stride: ``[Re y_g | Im y_g]`` per group
    tables : :class:`~radarpc.dsp.dictionary.SubspaceTables` on the CPU
    xn : Tensor ``(P,)`` float32, the snapshot norms rounded up
    snapshots : Tensor ``(P, N)`` complex64;  rows : Tensor ``(K, N)`` complex64
    max_candidates : int
    row_norm_max : float, at least ``max_k ||rows[k]||``
    kernel : {"auto", "avx", "scalar"}, the float32 dot kernel (:data:`KERNELS`)

    Returns
    -------
    index, amplitude, ambiguous, heavy : ``(P,)`` each; ``heavy`` points (no candidate, more than
    ``max_candidates``, or a non-finite screen or norm) get ``index = -1``.
    """
    n_az, n_el = (int(g) for g in tables.grid)
    k_dir = n_az * n_el
    coef = tables.coef
    named = (("y", y), ("xn", xn), ("snapshots", snapshots), ("rows", rows), ("coef", coef), ("resid", tables.resid),
             ("slack", tables.slack), ("cmax", tables.cmax), ("rmax", tables.rmax), ("smax", tables.smax),
             ("gram_max", tables.gram_max))
    for name, t in named:
        if not isinstance(t, torch.Tensor) or t.device.type != "cpu":
            raise ValueError(f"{name} must be a CPU torch.Tensor for the native kernel")
    if coef.dtype != torch.float32 or coef.ndim != 4 or coef.shape[1] != 2 or not coef.is_contiguous():
        raise ValueError(f"coef must be contiguous float32 (G, 2, r, M), got {coef.dtype} {tuple(coef.shape)}")
    n_groups, _, rank, m_rows = coef.shape
    if n_groups * m_rows < k_dir:
        raise ValueError(f"coef {tuple(coef.shape)} does not cover the {k_dir} directions of grid {tuple(tables.grid)}")
    if y.dtype != torch.float32 or y.ndim != 2 or y.stride(1) != 1 or y.shape[1] < 2 * rank * n_groups:
        raise ValueError(f"y must be float32 (P, >= {2 * rank * n_groups}) with unit column stride, got "
                         f"{y.dtype} {tuple(y.shape)}")
    p = y.shape[0]
    if (snapshots.dtype != torch.complex64 or snapshots.ndim != 2 or snapshots.shape[0] != p
            or not snapshots.is_contiguous() or snapshots.is_conj()):
        raise ValueError(f"snapshots must be a C-contiguous complex64 (P={p}, N) tensor")
    n = snapshots.shape[1]
    if rows.dtype != torch.complex64 or tuple(rows.shape) != (k_dir, n) or not rows.is_contiguous() or rows.is_conj():
        raise ValueError(f"rows must be a C-contiguous complex64 ({k_dir}, {n}) tensor")
    for name, t in (("resid", tables.resid), ("slack", tables.slack)):
        if t.dtype != torch.float32 or t.numel() < k_dir or not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous float32 with >= {k_dir} entries")
    for name, t, dt in (("cmax", tables.cmax, torch.float32), ("rmax", tables.rmax, torch.float32),
                        ("smax", tables.smax, torch.float32), ("gram_max", tables.gram_max, torch.float64)):
        if t.dtype != dt or tuple(t.shape) != (n_groups,) or not t.is_contiguous():
            raise ValueError(f"{name} must be contiguous {dt} ({n_groups},), got {t.dtype} {tuple(t.shape)}")
    if xn.dtype != torch.float32 or tuple(xn.shape) != (p,) or not xn.is_contiguous():
        raise ValueError(f"xn must be contiguous float32 ({p},)")
    if isinstance(max_candidates, bool) or int(max_candidates) < 1:
        raise ValueError(f"max_candidates must be an integer >= 1, got {max_candidates!r}")
    if not math.isfinite(row_norm_max) or row_norm_max < 0:
        raise ValueError(f"row_norm_max must be a finite number >= 0, got {row_norm_max!r}")
    threads = _check_threads_and_kernel(threads, kernel)
    _require_native("the torch selection of radarpc.dsp.accel.subspace.beamform_peaks_subspace")
    assert _screen is not None
    if kernel != "auto" and kernel not in _screen.kernels():
        raise ValueError(f"kernel {kernel!r} cannot run here; available: {_screen.kernels()}")
    index = torch.empty(p, dtype=torch.long)
    amplitude = torch.empty(p, dtype=torch.float32)
    ambiguous = torch.empty(p, dtype=torch.bool)
    heavy = torch.empty(p, dtype=torch.bool)
    if p == 0:
        return index, amplitude, ambiguous, heavy
    ext = _screen
    ys = y.stride(0)
    e_max = float((tables.rmax.double() + tables.smax.double()).max())    # >= max_k (resid_k + slack_k)
    table_args = [t.data_ptr() for t in (coef, tables.resid, tables.slack, tables.cmax, tables.rmax, tables.smax,
                                         tables.gram_max)] + [float(tables.y_error), e_max]
    sizes = (n_groups, rank, m_rows, k_dir)
    mc, rn = int(max_candidates), float(row_norm_max)

    def item(s0: int, m: int) -> None:
        ext.subspace_select(y.data_ptr() + 4 * ys * s0, ys, *table_args, xn.data_ptr() + 4 * s0, *sizes, m,
                            snapshots.data_ptr() + 8 * n * s0, rows.data_ptr(), n, n_az, n_el, mc, rn,
                            index.data_ptr() + 8 * s0, amplitude.data_ptr() + 4 * s0, ambiguous.data_ptr() + s0,
                            heavy.data_ptr() + s0, kernel)

    _run_items(item, p, _SUBSPACE_POINTS, threads)
    return index, amplitude, ambiguous, heavy
