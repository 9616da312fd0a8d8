"""The screened beamformer: a bfloat16 GEMM screens the angle grid, a rigorous bound keeps the
directions that can still hold the maximum, and only those are evaluated exactly.

It gives the ``k_j`` and ``Ae_j`` of the exact :func:`radarpc.dsp.beamform.beamform_peaks` (eqs. 6-7;
the exact argmax, up to float32 rounding of near-ties), not an approximation, and is faster where
bfloat16 GEMMs are (measured on CPUs with AMX). Its selection step runs in the C kernel of
:mod:`radarpc.dsp.accel.native` when that is built and :func:`radarpc.dsp.accel.enabled`, else in
torch (:func:`_screen_select`, the kernel's reference).

:func:`measured_choice` is the one-off timing behind the ``"auto"`` beamforming mode: it measures
the exact, subspace and screened beamformers on this device and dictionary and picks the fastest.
The core's :func:`radarpc.dsp.beamform_modes.beamform` runs the beamformer a mode names.
"""
from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable

import torch

from radarpc.dsp.accel import enabled as accel_enabled, native
from radarpc.dsp.accel.subspace import beamform_peaks_subspace
from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import beamform_peaks
from radarpc.dsp.dictionary import (SNAPSHOT_BLOCK, BeamformResult, DictionaryTables, column_to_direction,
                                    range_exponents, row_norms, scaled_snapshots, tables_for)

__all__ = ["beamform_peaks_screened", "screen_bound", "measured_choice", "measure_beamformers", "time_modes",
           "choose_beamformer", "probe_snapshots", "MAX_SCREEN_CANDIDATES"]

# The screen's bfloat16 GEMM runs on this many blocks at once (larger GEMMs run closer to peak).
_SCREEN_GEMM_BLOCKS = 8

# A snapshot whose screen leaves candidates in more azimuths than this is beamformed exactly over
# the whole grid instead: a flat spectrum (noise-like or all-zero snapshots) leaves many
# candidates, and beyond ~6 azimuths (~20 exact dot products) one GEMM row over the whole grid is
# cheaper (measured on full RADIal frames at densities 0.057 and 0.56, docs/results/pointcloud.md).
MAX_SCREEN_CANDIDATES = 6

_BF16_UNIT_ROUNDOFF = 2.0 ** -8     # round-to-nearest to 8 significant bits
_FP32_UNIT_ROUNDOFF = 2.0 ** -24

# The screen's candidate threshold is lowered by this fraction of the screen's peak: it covers the
# float32 evaluation of the screen powers q^2 and of the threshold (each ~2^-24 relative).
_SCREEN_SLACK = 2.0 ** -20
# Below this threshold (a screen with no usable peak) every direction is a candidate, so that no
# comparison is made among subnormal float32 powers.
_SCREEN_TINY_NEED = 2.0 ** -40


def screen_bound(snapshots: torch.Tensor, row_norm_max: float) -> tuple[float, torch.Tensor]:
    """Error bound of the bfloat16 screen: ``| |s^_k| - |s_k| | <= alpha |s^_k| + beta_j``.

    ``s^ = B v`` computed from ``v`` and ``B`` rounded to bfloat16 (unit roundoff ``u = 2^-8``),
    products accumulated in float32 in any order (``gamma_n = n 2^-24 / (1 - n 2^-24)``,
    ``n = 2 n_virtual`` terms) and the sum rounded to bfloat16. Per real output ``y`` (``Re`` or
    ``Im`` of ``s_k``)::

        |y^ - y| <= u / (1 - u) |y^| + c sum_p |x_p| |W_pk|,   c = 2u + u^2 + gamma_n (1 + u)^2,

    and ``sum_p |x_p| |W_pk| <= ||v_j||_2 ||B[k]||_2`` (Cauchy-Schwarz; each real column of the
    stacked form has the norm of ``B[k]``). Over the two components,
    ``alpha = u / (1 - u)`` and ``beta_j = sqrt(2) c ||v_j|| max_k ||B[k]||``. ``beta`` is
    inflated by ``1 + gamma_(n+2)`` for the float32 evaluation of ``||v_j||`` (and ``2^-20`` for
    its own rounding), and gets an absolute ``2^-124 (n + sqrt(n) (max_k ||B[k]|| + ||v_j||))``
    for GEMM kernels that flush subnormal inputs, products or partial sums to zero (AMX and
    AVX512-BF16 do). Norms of snapshots outside ``[2^-40, 2^40]`` are taken on a power-of-two
    rescaled copy, so they neither underflow nor overflow.

    Returns
    -------
    alpha : float
    beta : Tensor ``(P,)`` float32
    """
    v = snapshots.resolve_conj()
    vnorm = row_norms(v)
    exps = range_exponents(v, vnorm)
    if exps is not None:
        vnorm = torch.ldexp(row_norms(scaled_snapshots(v, exps)), exps).to(vnorm.dtype)
    return _bound_terms(vnorm, 2 * snapshots.shape[1], row_norm_max)


def _bound_terms(vnorm: torch.Tensor, n: int, row_norm_max: float) -> tuple[float, torch.Tensor]:
    """``alpha`` and ``beta_j`` of :func:`screen_bound` from the float32 row norms ``vnorm`` of
    snapshots with ``n`` real entries each."""
    u = _BF16_UNIT_ROUNDOFF
    gamma = n * _FP32_UNIT_ROUNDOFF / (1.0 - n * _FP32_UNIT_ROUNDOFF)
    c = 2.0 * u + u * u + gamma * (1.0 + u) ** 2
    alpha = u / (1.0 - u)
    m = (n + 2) * _FP32_UNIT_ROUNDOFF
    norm_safety = (1.0 + m / (1.0 - m)) * (1.0 + 2.0 ** -20)       # float32 ||v||, then beta's rounding
    vnorm = vnorm.to(torch.float32)
    flush = 2.0 ** -124 * (n + math.sqrt(n) * (row_norm_max + vnorm))
    beta = vnorm * (math.sqrt(2.0) * c * row_norm_max * norm_safety) + flush
    return alpha, beta


@contextlib.contextmanager
def _fp32_accumulation(device: torch.device):
    """cuBLAS may reduce bfloat16 products in reduced precision unless told not to; the screen's
    bound assumes float32 accumulation."""
    if device.type != "cuda":
        yield
        return
    prev = torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction
    torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_bf16_reduced_precision_reduction = prev


def _screen_threshold(q2_max: torch.Tensor, beta: torch.Tensor, alpha: float) -> torch.Tensor:
    """Squared candidate threshold ``need_j^2`` (float32 ``(m,)``) from the screen's peak power
    ``max_k q_jk^2`` (float32) and ``beta_j``, evaluated in float64 as the C kernel does::

        Q_j = sqrt(max_k q_jk^2),   need_j = ((1 - alpha) Q_j - 2 beta_j) / (1 + alpha) - 2^-20 Q_j

    (``k`` is a candidate when ``(1 + alpha) q_jk + beta_j >= (1 - alpha) Q_j - beta_j``; the last
    term covers the float32 rounding of the powers and of ``need_j^2``), and ``-1`` (every
    direction a candidate) when ``need_j <= 2^-40``."""
    q = q2_max.double().sqrt()
    need = ((1.0 - alpha) * q - 2.0 * beta.double()) / (1.0 + alpha) - _SCREEN_SLACK * q
    return torch.where(need > _SCREEN_TINY_NEED, need.square(), torch.full_like(need, -1.0)).to(torch.float32)


def _screen_select(y16: torch.Tensor, v: torch.Tensor, t: DictionaryTables, beta: torch.Tensor,
                   alpha: float, max_candidates: int, index: torch.Tensor, amplitude: torch.Tensor,
                   ws: Workspace) -> torch.Tensor | None:
    """Steps 2-4 of :func:`beamform_peaks_screened` in torch for one block of ``m`` screen rows
    ``y16`` ``(m, 2K)``: writes ``index`` and ``amplitude`` ``(m,)`` of the rows it settles and
    returns the block-relative indices of the rows left to the whole-grid beamformer (or None).
    :func:`radarpc.dsp.accel.native.screen_select_native` is the same step in C."""
    n_az, n_el = t.grid
    k_dir = t.n_dir
    m = y16.shape[0]
    dev = y16.device
    y = ws.empty("screen.y32", (m, 2 * k_dir), torch.float32, dev).copy_(y16)   # (m, 2K) float32
    q2 = torch.mul(y[:, :k_dir], y[:, :k_dir], out=ws.empty("screen.q2", (m, k_dir), torch.float32, dev))
    q2.addcmul_(y[:, k_dir:], y[:, k_dir:])                               # q_jc^2
    q2_az = q2.view(m, n_el, n_az).amax(dim=1)                            # (m, n_az) best elevation
    need2 = _screen_threshold(q2_az.amax(dim=1), beta, alpha)[:, None]    # C_j: q_jk^2 >= need2_j
    j, az = torch.nonzero(q2_az >= need2, as_tuple=True)                 # azimuths holding candidates
    n_cand = torch.bincount(j, minlength=m)
    finite = torch.isfinite(q2_az).all(dim=1) & torch.isfinite(beta)      # NaN/inf screen or bound
    heavy = (n_cand > max_candidates) | (n_cand == 0) | ~finite
    heavy_rows = None
    if bool(heavy.any()):                                                # flat spectra: whole grid
        heavy_rows = torch.nonzero(heavy).flatten()
        light = ~heavy[j]
        j, az = j[light], az[light]
    j = j.repeat_interleave(n_el)                                        # every elevation of them
    col = (torch.arange(n_el, device=dev).repeat(az.numel()) * n_az) + az.repeat_interleave(n_el)
    keep = q2.reshape(-1).index_select(0, j * k_dir + col) >= need2.view(-1).index_select(0, j)
    j, col = j[keep], col[keep]
    k = column_to_direction(col, t.grid)
    s = torch.mul(t.rows.index_select(0, k), v.index_select(0, j)).sum(dim=1).abs()   # |B[k] v_j|
    kk = (k_dir - 1) - k                                                 # ties -> the smaller k
    key = (s.view(torch.int32).to(torch.long) << 32) | kk
    best = torch.full((m,), -1, dtype=torch.long, device=dev)
    best.scatter_reduce_(0, j, key, reduce="amax", include_self=True)
    index.copy_((k_dir - 1) - (best & 0xFFFFFFFF))
    amplitude.copy_((best >> 32).to(torch.int32).view(torch.float32))
    return heavy_rows


def beamform_peaks_screened(snapshots: torch.Tensor, dictionary_t: torch.Tensor | DictionaryTables,
                            grid: tuple[int, int], *, max_candidates: int = MAX_SCREEN_CANDIDATES,
                            workspace: Workspace | None = None) -> BeamformResult:
    """``k_j`` and ``Ae_j`` of :func:`beamform_peaks`, screened by a bfloat16 GEMM and certified.

    0. snapshots whose norm lies outside ``[2^-40, 2^40]`` are scaled by a power of two (exact;
       the amplitudes are scaled back at the end), so that no float32 value below underflows or
       overflows; the exact beamformer does the same;
    1. ``s^_j = B v_j`` over the whole grid from one bfloat16 GEMM (:func:`~radarpc.dsp.beamform.stack_real` form), and
       its power ``q_jk^2 = |s^_jk|^2`` formed in float32;
    2. with the rigorous bound of :func:`screen_bound`, ``|s_jk|`` lies in
       ``[(1 - alpha) q_jk - beta_j, (1 + alpha) q_jk + beta_j]``, so the exact maximum is among
       ``C_j = {k : (1 + alpha) q_jk + beta_j >= max_k' (1 - alpha) q_jk' - beta_j}``, tested as
       ``q_jk^2 >= need_j^2`` with the threshold of :func:`_screen_threshold` (float64, lowered by
       ``2^-20 max_k q_jk`` for the float32 rounding of the powers);
    3. ``|B[k] v_j|`` is evaluated exactly (complex64 dot products) for ``k in C_j`` only, and
       ``k_j = argmax_{k in C_j}``, ``Ae_j`` its value (ties to the smaller ``k``);
    4. a snapshot whose candidates span more than ``max_candidates`` azimuths (a flat spectrum,
       e.g. zeros), or none at all, or whose screen or bound is not finite (NaN/inf), is
       beamformed over the whole grid by :func:`beamform_peaks`.

    The result is the exact argmax and maximum, up to the float32 rounding of the dot products
    (directions whose exact amplitudes tie to ~1e-7 may be ordered differently than by the GEMMs
    of :func:`beamform_peaks`). No sector descriptor: it needs every direction. ``workspace``
    holds the scratch buffers across calls, as in :func:`beamform_peaks`.
    """
    if snapshots.dtype != torch.complex64:
        raise ValueError(f"the screened beamformer works on complex64 snapshots, got {snapshots.dtype}; "
                         f"use beamform_peaks for other precisions")
    t = tables_for(snapshots, dictionary_t, grid)
    if isinstance(max_candidates, bool) or int(max_candidates) < 1:
        raise ValueError(f"max_candidates must be an integer >= 1, got {max_candidates!r}")
    ws = Workspace() if workspace is None else workspace
    k_dir = t.n_dir
    p = snapshots.shape[0]
    dev = snapshots.device
    v = snapshots.resolve_conj().contiguous()
    vnorm = row_norms(v)
    exps = range_exponents(v, vnorm)
    if exps is not None:                                              # extreme magnitudes: 2^-e v
        v = scaled_snapshots(v, exps)
        vnorm = row_norms(v)
    alpha, beta = _bound_terms(vnorm, 2 * v.shape[1], t.row_norm_max)   # screen_bound of v
    x = torch.view_as_real(v).reshape(p, 2 * v.shape[1])            # (P, 2N) interleaved
    index = torch.empty(p, dtype=torch.long, device=dev)
    amplitude = torch.empty(p, dtype=torch.float32, device=dev)
    heavy_rows = []
    blk = min(SNAPSHOT_BLOCK, max(p, 1))
    gemm_rows = min(_SCREEN_GEMM_BLOCKS * blk, max(p, 1))             # one bf16 GEMM per few blocks
    x16 = ws.empty("screen.x16", (gemm_rows, x.shape[1]), torch.bfloat16, dev)
    y16 = ws.empty("screen.y16", (gemm_rows, 2 * k_dir), torch.bfloat16, dev)
    select_natively = dev.type == "cpu" and native.native_available()
    with _fp32_accumulation(dev):
        for i in range(0, p, gemm_rows):
            g = min(gemm_rows, p - i)
            torch.mm(x16[:g].copy_(x[i:i + g]), t.screen_bf16, out=y16[:g])  # [Re | Im], el-major
            if select_natively:                                             # steps 2-4 in C, per row
                idx, amp, heavy = native.screen_select_native(y16[:g], v[i:i + g], t.rows, beta[i:i + g],
                                                              t.grid, alpha, max_candidates)
                index[i:i + g], amplitude[i:i + g] = idx, amp
                if bool(heavy.any()):
                    heavy_rows.append(torch.nonzero(heavy).flatten() + i)
                continue
            for b in range(0, g, blk):
                m = min(blk, g - b)
                heavy = _screen_select(y16[b:b + m], v[i + b:i + b + m], t, beta[i + b:i + b + m], alpha,
                                       max_candidates, index[i + b:i + b + m], amplitude[i + b:i + b + m], ws)
                if heavy is not None:
                    heavy_rows.append(heavy + (i + b))
    if heavy_rows:
        rows = torch.cat(heavy_rows)
        full = beamform_peaks(v[rows], t, grid, workspace=ws)
        index[rows] = full.index
        amplitude[rows] = full.amplitude
    if exps is not None:                                              # back to the input's scale
        amplitude = torch.ldexp(amplitude, exps).to(torch.float32)
    return BeamformResult(index=index, amplitude=amplitude, sectors=None)


# Modes "auto" chooses between, in the order that wins a tie of the measured times.
_AUTO_CANDIDATES = ("exact", "subspace", "screened")
# Snapshots of the one-off probe; a mode slower than this factor times the best on the first
# few snapshots is not timed further (a bfloat16 GEMM without native support takes seconds).
_PROBE_POINTS = 256
_PROBE_CUTOFF = 4.0
_choices: dict[tuple, str] = {}
_choices_lock = threading.Lock()


def probe_snapshots(tables: DictionaryTables, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` complex64 snapshots like a frame's CFAR points: one steering vector of the dictionary
    (the conjugate of a random row) 10 to 40 dB above unit complex noise per channel, a quarter of
    them with a second, weaker one, one in twenty pure noise (simulated RADIal frames under
    RADIal's CFAR: the median point's peak is 0.86 of ``||v|| max_k ||B[k]||``, i.e. strong)."""
    g = torch.Generator().manual_seed(seed)
    rows = tables.rows.to("cpu")
    n_ch = rows.shape[1]
    k1, k2 = (torch.randint(0, rows.shape[0], (n,), generator=g) for _ in range(2))
    snr = 10.0 ** (0.5 + torch.rand(n, generator=g) * 1.5) * (torch.rand(n, generator=g) > 0.05)
    amp = snr * math.sqrt(n_ch) / max(tables.row_norm_max, 1e-30)
    amp2 = amp * torch.rand(n, generator=g) * (torch.rand(n, generator=g) < 0.25)
    noise = torch.randn(n, n_ch, dtype=torch.complex64, generator=g)
    return (amp[:, None] * rows[k1].conj() + amp2[:, None] * rows[k2].conj() + noise).to(torch.complex64)


def measure_beamformers(tables: DictionaryTables, device: torch.device | str, points: int = _PROBE_POINTS,
                        modes: tuple[str, ...] = _AUTO_CANDIDATES) -> dict[str, float]:
    """Seconds per snapshot of each beamformer in ``modes`` on :func:`probe_snapshots` (``points``
    of them) with ``tables`` on ``device``: best of two timed calls after a warm-up. A mode that
    takes more than ``_PROBE_CUTOFF`` times the best so far on the first 16 snapshots is reported
    with that time (extrapolated) and not timed further."""
    device = torch.device(device)
    t = tables.to(device) if tables.rows.device != device else tables
    v = probe_snapshots(tables, points).to(device)
    ws = Workspace()
    run = {"exact": lambda x: beamform_peaks(x, t, t.grid, workspace=ws),
           "screened": lambda x: beamform_peaks_screened(x, t, t.grid, workspace=ws),
           "subspace": lambda x: beamform_peaks_subspace(x, t, t.grid, workspace=ws)}

    def clock(f, x) -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        f(x)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return (time.perf_counter() - t0) / len(x)

    return time_modes({m: run[m] for m in modes}, v, clock)


def time_modes(run: dict[str, Callable[[torch.Tensor], object]], v: torch.Tensor,
               clock: Callable[[Callable[[torch.Tensor], object], torch.Tensor], float]) -> dict[str, float]:
    """Seconds per snapshot of each ``run[mode]`` on ``v`` (``clock(f, x)`` times one call), in order:
    after a 1-snapshot warm-up, the best of two calls on the first 16 snapshots; a mode slower than
    ``_PROBE_CUTOFF`` times the best mode so far there keeps that time (it cannot win), the others
    get the best of two calls on all of ``v``. Two calls, so that a one-off stall (a page fault
    storm, another process) does not rule a mode out."""
    out: dict[str, float] = {}
    for mode, f in run.items():
        f(v[:1])                                                       # builds any lazy tables
        first = min(clock(f, v[:16]), clock(f, v[:16]))
        if out and first > _PROBE_CUTOFF * min(out.values()):
            out[mode] = first
            continue
        f(v)
        out[mode] = min(clock(f, v), clock(f, v))
    return out


def choose_beamformer(seconds_per_point: dict[str, float]) -> str:
    """The fastest mode of measured ``seconds_per_point`` (a tie goes to the earlier of
    ``"exact"``, ``"subspace"``, ``"screened"``): deterministic given the measurements."""
    known = [m for m in _AUTO_CANDIDATES if m in seconds_per_point]
    if not known:
        raise ValueError(f"no timing of {_AUTO_CANDIDATES} in {sorted(seconds_per_point)}")
    for m in known:
        val = seconds_per_point[m]
        if not (isinstance(val, (int, float)) and math.isfinite(val) and val >= 0):
            raise ValueError(f"timing of {m!r} must be a finite number >= 0, got {val!r}")
    return min(known, key=lambda m: (seconds_per_point[m], known.index(m)))


def measured_choice(tables: DictionaryTables, device: torch.device | str) -> str:
    """:func:`choose_beamformer` of :func:`measure_beamformers`, measured once per process for each
    (device, grid, channels) and cached; ``"exact"`` when the accelerated paths are off."""
    device = torch.device(device)
    if not accel_enabled():
        return "exact"
    key = (str(device), tuple(tables.grid), int(tables.rows.shape[1]))
    with _choices_lock:
        if key not in _choices:
            _choices[key] = choose_beamformer(measure_beamformers(tables, device))
        return _choices[key]
