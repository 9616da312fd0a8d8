"""Sparse MIMO processing: angle spectra of virtual snapshots with a calibrated dictionary.

``s_j = |B v_j|`` (eq. 5) with ``B`` the ``(n_az * n_el, n_virtual)`` dictionary of
:meth:`radarpc.sensors.radial.Calibration.dictionary` (taper folded in, row ``k = az * n_el + el``);
``k_j = argmax_k s_j[k]`` (eq. 6) and ``Ae_j = s_j[k_j]`` (eq. 7); the sector descriptor of
eq. 10 max-pools ``s_j`` reshaped to ``(n_az, n_el)`` into ``n_az_sec x n_el_sec`` sectors.

Two ways to the same ``k_j`` and ``Ae_j`` (:data:`BEAMFORMING_MODES`):

* ``"exact"``: the whole spectrum of every snapshot in float32, the complex product as three real
  GEMMs (Gauss's trick, :func:`beamform_peaks`);
* ``"screened"``: a bfloat16 GEMM screens the grid, a rigorous bound on its error leaves the few
  directions that can still hold the maximum, and those are evaluated exactly
  (:func:`beamform_peaks_screened`). The result is the exact argmax (up to float32 rounding of
  near-ties), not an approximation; it is faster where bfloat16 GEMMs are (measured on AMX CPUs).

``"auto"`` picks ``"screened"`` where it was measured faster (CPUs with AMX) and no sector
descriptor is asked for (sectors need the whole spectrum), else ``"exact"``.
"""
from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from radarpc.dsp import native
from radarpc.dsp.workspace import Workspace

__all__ = ["angle_spectrum", "BeamformResult", "DictionaryTables", "dictionary_tables", "beamform",
           "beamform_peaks", "beamform_peaks_screened", "screen_bound", "sector_pool", "stack_real",
           "column_to_direction", "prefers_screened", "reduced_fp32_matmul", "resolve_beamforming",
           "check_beamforming", "BEAMFORMING_MODES", "MAX_SCREEN_CANDIDATES"]

BEAMFORMING_MODES = ("auto", "exact", "screened")

# Snapshots per GEMM block: the (block, n_az n_el) float32 buffers stay a few MB for RADIal.
_BLOCK = 1024
# The screen's bfloat16 GEMM runs on this many blocks at once (larger GEMMs run closer to peak).
_SCREEN_GEMM_BLOCKS = 8

# A snapshot whose screen leaves candidates in more azimuths than this is beamformed exactly over
# the whole grid instead: a flat spectrum (noise-like or all-zero snapshots) leaves many
# candidates, and beyond ~6 azimuths (~20 exact dot products) one GEMM row over the whole grid is
# cheaper (measured on full RADIal frames at densities 0.057 and 0.56, docs/results/pointcloud.md).
MAX_SCREEN_CANDIDATES = 6

_BF16_UNIT_ROUNDOFF = 2.0 ** -8     # round-to-nearest to 8 significant bits
_FP32_UNIT_ROUNDOFF = 2.0 ** -24

# Snapshots whose 2-norm lies in [2^-40, 2^40] are beamformed as they are: every float32 value
# the beamformers form from them (squared entries that matter, |B v|^2 over the grid) stays in the
# normal range. Others are first scaled by a power of two (exact) so that their largest |Re| or
# |Im| lies in [0.5, 1), and the amplitudes scaled back (:func:`_range_exponents`).
_SAFE_NORM = (2.0 ** -40, 2.0 ** 40)
# The screen's candidate threshold is lowered by this fraction of the screen's peak: it covers the
# float32 evaluation of the screen powers q^2 and of the threshold (each ~2^-24 relative).
_SCREEN_SLACK = 2.0 ** -20
# Below this threshold (a screen with no usable peak) every direction is a candidate, so that no
# comparison is made among subnormal float32 powers.
_SCREEN_TINY_NEED = 2.0 ** -40


def _check(snapshots: torch.Tensor, dictionary: torch.Tensor) -> None:
    if not snapshots.is_complex() or not dictionary.is_complex():
        raise ValueError(f"snapshots and dictionary must be complex, got {snapshots.dtype} and "
                         f"{dictionary.dtype}")
    if snapshots.ndim != 2 or dictionary.ndim != 2 or snapshots.shape[1] != dictionary.shape[1]:
        raise ValueError(f"snapshots (P, n_virtual) and dictionary (n_dir, n_virtual) must share "
                         f"n_virtual, got {tuple(snapshots.shape)} and {tuple(dictionary.shape)}")


def angle_spectrum(snapshots: torch.Tensor, dictionary: torch.Tensor) -> torch.Tensor:
    """Angle spectra ``s_j = |B v_j|`` of every snapshot.

    Parameters
    ----------
    snapshots : Tensor, complex, ``(P, n_virtual)``
    dictionary : Tensor, complex, ``(n_dir, n_virtual)``
        ``B``, one row per direction.

    Returns
    -------
    Tensor, real, ``(P, n_dir)``
    """
    _check(snapshots, dictionary)
    return torch.abs(snapshots @ dictionary.to(snapshots.dtype).transpose(0, 1))


@dataclass
class BeamformResult:
    """Per-snapshot outputs of :func:`beamform`.

    Attributes
    ----------
    index : LongTensor ``(P,)``          dominant direction ``k_j`` (eq. 6)
    amplitude : Tensor ``(P,)``          ``Ae_j = s_j[k_j]`` (eq. 7)
    sectors : Tensor ``(P, n_az_sec * n_el_sec)`` or None   sector maxima of ``s_j`` (eq. 10)
    """

    index: torch.Tensor
    amplitude: torch.Tensor
    sectors: torch.Tensor | None


def sector_pool(spectrum: torch.Tensor, grid: tuple[int, int], sectors: tuple[int, int]) -> torch.Tensor:
    """Max-pool angle spectra over ``n_az_sec x n_el_sec`` angular sectors (eq. 10).

    ``spectrum`` ``(P, n_az * n_el)`` is reshaped to ``(P, n_az, n_el)``; sector ``(u, v)`` covers
    azimuth rows ``floor(u n_az / n_az_sec) .. ceil((u + 1) n_az / n_az_sec) - 1`` (likewise in
    elevation), i.e. adaptive max pooling: equal non-overlapping sectors when the grid divides,
    otherwise sectors of nearly equal size that may share one boundary row (181 azimuths into 32
    sectors). Returns ``(P, n_az_sec * n_el_sec)``, sector ``u * n_el_sec + v``.
    """
    n_az, n_el = grid
    n_as, n_es = sectors
    if not (1 <= n_as <= n_az and 1 <= n_es <= n_el):
        raise ValueError(f"angle sectors {sectors} must be between (1, 1) and the grid {grid}")
    if n_es == 1:  # separable: elevation max first, then 1-D pooling over azimuth (faster)
        x = spectrum.reshape(-1, n_az, n_el).amax(dim=-1).unsqueeze(1)   # (P, 1, n_az)
        return F.adaptive_max_pool1d(x, n_as).reshape(spectrum.shape[0], n_as)
    x = spectrum.reshape(-1, 1, n_az, n_el)
    return F.adaptive_max_pool2d(x, (n_as, n_es)).reshape(spectrum.shape[0], n_as * n_es)


def stack_real(dictionary_t: torch.Tensor) -> torch.Tensor:
    """Real form of a complex ``B^T`` ``(N, K)`` for one real GEMM: ``(2N, 2K)``.

    Row ``2n`` is ``[Re B^T[n], Im B^T[n]]`` and row ``2n + 1`` is ``[-Im B^T[n], Re B^T[n]]``, so that
    ``view_as_real(v).reshape(P, 2N) @ W = [Re (B v)^T | Im (B v)^T]`` (the interleaved real view of
    the snapshots needs no copy, and the output halves are contiguous column blocks).
    """
    n, k = dictionary_t.shape
    re, im = dictionary_t.real, dictionary_t.imag
    w = torch.empty(n, 2, 2 * k, dtype=re.dtype, device=re.device)
    w[:, 0, :k], w[:, 0, k:] = re, im
    w[:, 1, :k], w[:, 1, k:] = -im, re
    return w.reshape(2 * n, 2 * k)


@dataclass
class DictionaryTables:
    """The forms of ``B^T`` the beamformers use, computed once (:func:`dictionary_tables`).

    Attributes
    ----------
    grid : (n_az, n_el)              the angle grid, ``K = n_az n_el``, direction ``k = az n_el + el``
    rows : complex ``(K, N)``        ``B``, row ``k`` = direction ``k`` (exact dot products)
    re, im, gauss : real ``(N, K)``  ``Re B^T``, ``Im B^T`` and ``Re B^T + Im B^T`` (Gauss's trick)
    screen_bf16 : bfloat16 ``(2N, 2K)``   :func:`stack_real` of ``B^T`` rounded to bfloat16

    The GEMM forms (``re``, ``im``, ``gauss``, ``screen_bf16``) hold the directions in
    elevation-major order, column ``c = el n_az + az`` (:func:`column_to_direction`), so that
    maxima over elevation are reductions over a leading axis.
    row_norm_max : float             ``max_k ||B[k]||_2``, for the screen's error bound
    """

    grid: tuple[int, int]
    rows: torch.Tensor
    re: torch.Tensor
    im: torch.Tensor
    gauss: torch.Tensor
    screen_bf16: torch.Tensor
    row_norm_max: float

    @property
    def n_dir(self) -> int:
        return int(self.rows.shape[0])

    def to(self, device: torch.device | str) -> "DictionaryTables":
        return DictionaryTables(grid=self.grid, rows=self.rows.to(device), re=self.re.to(device),
                                im=self.im.to(device), gauss=self.gauss.to(device),
                                screen_bf16=self.screen_bf16.to(device), row_norm_max=self.row_norm_max)


def dictionary_tables(dictionary_t: torch.Tensor, grid: tuple[int, int],
                      dtype: torch.dtype = torch.complex64) -> DictionaryTables:
    """:class:`DictionaryTables` of ``B^T`` ``(n_virtual, n_az * n_el)`` complex, in ``dtype``."""
    if not dictionary_t.is_complex() or dictionary_t.ndim != 2:
        raise ValueError(f"dictionary_t must be a complex (n_virtual, n_dir) matrix, got "
                         f"{dictionary_t.dtype} {tuple(dictionary_t.shape)}")
    n_az, n_el = (int(g) for g in grid)
    if n_az < 1 or n_el < 1 or n_az * n_el != dictionary_t.shape[1]:
        raise ValueError(f"grid {tuple(grid)} does not match the dictionary's {dictionary_t.shape[1]} directions")
    bt = dictionary_t.to(dtype)
    rows = bt.transpose(0, 1).contiguous()
    norm = float(torch.linalg.vector_norm(rows.to(torch.complex128), dim=1).max()) if rows.numel() else 0.0
    bt_em = bt[:, column_to_direction(torch.arange(n_az * n_el, device=bt.device), (n_az, n_el))]
    re, im = bt_em.real.contiguous(), bt_em.imag.contiguous()
    return DictionaryTables(grid=(n_az, n_el), rows=rows, re=re, im=im, gauss=(re + im).contiguous(),
                            screen_bf16=stack_real(bt_em).to(torch.bfloat16), row_norm_max=norm)


def column_to_direction(col: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Direction ``k = az n_el + el`` of elevation-major GEMM column ``col = el n_az + az``."""
    n_az, n_el = grid
    return (col % n_az) * n_el + torch.div(col, n_az, rounding_mode="floor")


def _sector_columns(n: int, n_sec: int, device: torch.device) -> torch.Tensor:
    """``(L, n_sec)`` indices covering the adaptive-pooling sectors of ``n`` cells (sector ``u``:
    ``floor(u n / n_sec) .. ceil((u + 1) n / n_sec) - 1``, shorter sectors padded with their last
    cell), so that ``x[:, idx].amax`` over the leading ``L`` axis is :func:`F.adaptive_max_pool1d`."""
    u = torch.arange(n_sec, device=device)
    start = torch.div(u * n, n_sec, rounding_mode="floor")
    end = -torch.div(-(u + 1) * n, n_sec, rounding_mode="floor")          # ceil
    width = int((end - start).max())
    offs = torch.arange(width, device=device)[:, None]
    return torch.minimum(start[None, :] + offs, end[None, :] - 1)       # (L, n_sec)


def _sector_pool_elevation_major(power: torch.Tensor, grid: tuple[int, int],
                                 sectors: tuple[int, int]) -> torch.Tensor:
    """:func:`sector_pool` of spectra whose columns are elevation-major ``(P, n_el * n_az)``."""
    n_az, n_el = grid
    n_as, n_es = sectors
    if not (1 <= n_as <= n_az and 1 <= n_es <= n_el):
        raise ValueError(f"angle sectors {sectors} must be between (1, 1) and the grid {grid}")
    x = power.view(-1, n_el, n_az)
    if n_es == 1:                                                     # best elevation, then azimuth sectors
        best = x.amax(dim=1)                                          # (P, n_az)
        idx = _sector_columns(n_az, n_as, power.device)               # (L, n_as)
        return best.index_select(1, idx.reshape(-1)).view(-1, idx.shape[0], n_as).amax(dim=1)
    pooled = F.adaptive_max_pool2d(x.unsqueeze(1), (n_es, n_as))      # (P, 1, n_es, n_as)
    return pooled.reshape(-1, n_es, n_as).transpose(1, 2).reshape(-1, n_as * n_es)


def _tables_for(snapshots: torch.Tensor, dictionary_t: torch.Tensor | DictionaryTables,
                grid: tuple[int, int]) -> DictionaryTables:
    if isinstance(dictionary_t, DictionaryTables):
        t = dictionary_t
        if tuple(t.grid) != tuple(grid):
            raise ValueError(f"grid {tuple(grid)} differs from the dictionary tables' {t.grid}")
    else:
        t = dictionary_tables(dictionary_t, grid, snapshots.dtype if snapshots.is_complex() else torch.complex64)
    _check(snapshots, t.rows)
    if t.rows.dtype != snapshots.dtype:
        raise ValueError(f"snapshots are {snapshots.dtype} but the dictionary tables are {t.rows.dtype}")
    return t


def _row_norms(snapshots: torch.Tensor) -> torch.Tensor:
    """Float32 2-norms of the rows of complex ``(P, N)`` snapshots (the interleaved real view: the
    complex-input norm is ~100x slower on CPU)."""
    return torch.linalg.vector_norm(torch.view_as_real(snapshots.resolve_conj()).flatten(1), dim=1)


def _range_exponents(snapshots: torch.Tensor, norms: torch.Tensor) -> torch.Tensor | None:
    """Per-row exponents ``e`` (int32 ``(P,)``) such that ``snapshots * 2^-e`` has its largest
    ``|Re|`` or ``|Im|`` in ``[0.5, 1)``, for the rows whose ``norms`` lie outside
    :data:`_SAFE_NORM` (``e = 0`` for the others, and for all-zero or non-finite rows); ``None``
    when every row is inside (the common case: one reduction, no copy)."""
    lo, hi = _SAFE_NORM
    out = ~((norms >= lo) & (norms <= hi))                       # NaN / inf norms are outside too
    if not bool(out.any()):
        return None
    x = torch.view_as_real(snapshots[out].resolve_conj()).flatten(1)
    amax = torch.maximum(x.amax(dim=1), -x.amin(dim=1)) if x.shape[1] else torch.zeros(len(x), device=x.device)
    _, e = torch.frexp(amax)                                     # amax = m 2^e, m in [0.5, 1)
    e = torch.where(torch.isfinite(amax), e.clamp(-126, 126), torch.zeros_like(e))
    exps = torch.zeros(snapshots.shape[0], dtype=torch.int32, device=snapshots.device)
    exps[out] = e.to(torch.int32)
    return exps


def _scaled(snapshots: torch.Tensor, exps: torch.Tensor) -> torch.Tensor:
    """``snapshots * 2^-exps`` per row, exactly (scaling by a power of two rounds nothing)."""
    x = torch.view_as_real(snapshots.resolve_conj())
    return torch.view_as_complex(torch.ldexp(x, -exps[:, None, None]).to(x.dtype).contiguous())


def reduced_fp32_matmul(device: torch.device | str) -> bool:
    """Whether float32 GEMMs on ``device`` may run in reduced precision (TF32 on CUDA, bfloat16
    through oneDNN on CPUs with AMX), as set by ``torch.set_float32_matmul_precision("high" |
    "medium")`` or by the per-backend ``fp32_precision`` settings of torch >= 2.9. The exact
    beamformer's spectrum is then not exact; :func:`beamform_peaks` warns, and does not change the
    process-wide setting itself (that would race with other threads)."""
    device = torch.device(device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                          # deprecation notes of some versions
        try:
            return torch.get_float32_matmul_precision() != "highest"
        except RuntimeError:                                     # the per-backend API is in use
            backend = torch.backends.cuda.matmul if device.type == "cuda" else torch.backends.mkldnn.matmul
            return getattr(backend, "fp32_precision", "ieee") not in ("ieee", "none")


_REDUCED_PRECISION_WARNING = (
    "float32 matmul precision is reduced (torch.set_float32_matmul_precision or a backend's "
    "fp32_precision): the exact beamformer's GEMMs may run in TF32/bfloat16 and its argmax and "
    "amplitudes are then approximate; set torch.set_float32_matmul_precision('highest') for exact results")


def beamform_peaks(snapshots: torch.Tensor, dictionary_t: torch.Tensor | DictionaryTables,
                   grid: tuple[int, int], sectors: tuple[int, int] | None = None, *,
                   workspace: Workspace | None = None) -> BeamformResult:
    """Dominant direction, its amplitude and optional sector maxima from the exact spectra.

    With ``v = a + ib`` and ``B^T = C + iD`` the product needs three real GEMMs (Gauss):
    ``T1 = a C``, ``T2 = b D``, ``T3 = (a + b)(C + D)``; ``Re = T1 - T2``, ``Im = T3 - T1 - T2``.
    The power ``|B v|^2 = Re^2 + Im^2`` is formed block by block in preallocated buffers (argmax
    and max-pooling commute with the monotone square root) and only kept values are rooted.
    Snapshots whose norm lies outside ``[2^-40, 2^40]`` are first scaled by a power of two
    (exact), so that the power neither overflows (``|B v| >= 2^64``) nor goes subnormal; the
    amplitudes and sectors are scaled back. The spectrum is exact only with full float32 GEMMs
    (torch's default): under a reduced ``torch.set_float32_matmul_precision`` a
    ``RuntimeWarning`` says so (:func:`reduced_fp32_matmul`).

    Parameters
    ----------
    snapshots : Tensor, complex, ``(P, n_virtual)``
    dictionary_t : Tensor, complex, ``(n_virtual, n_az * n_el)``, or its :class:`DictionaryTables`
        ``B`` transposed, as stored by :class:`~radarpc.dsp.pointcloud.SpectralPointCloud`.
    grid : (n_az, n_el)
    sectors : (n_az_sec, n_el_sec), optional
    workspace : Workspace, optional
        Reused scratch buffers (repeated calls then allocate no large temporaries).
    """
    t = _tables_for(snapshots, dictionary_t, grid)
    ws = Workspace() if workspace is None else workspace
    real = t.re.dtype
    k_dir = t.n_dir
    p, n = snapshots.shape
    dev = snapshots.device
    exps = _range_exponents(snapshots, _row_norms(snapshots))
    if exps is not None:                                              # extreme magnitudes: 2^-e v
        snapshots = _scaled(snapshots, exps)
    a = ws.empty("exact.re", (p, n), real, dev).copy_(snapshots.real)        # (P, N)
    b = ws.empty("exact.im", (p, n), real, dev).copy_(snapshots.imag)
    index = torch.empty(p, dtype=torch.long, device=dev)
    power = torch.empty(p, dtype=real, device=dev)
    sec = None
    if sectors is not None:
        sec = torch.empty(p, sectors[0] * sectors[1], dtype=real, device=dev)
    blk = min(_BLOCK, max(p, 1))
    t1, t2, t3 = (ws.empty(f"exact.t{q}", (blk, k_dir), real, dev) for q in (1, 2, 3))
    ab = ws.empty("exact.a+b", (blk, n), real, dev)
    if reduced_fp32_matmul(dev):
        warnings.warn(_REDUCED_PRECISION_WARNING, RuntimeWarning, stacklevel=2)
    for i in range(0, p, blk):
        m = min(blk, p - i)
        ai, bi = a[i:i + m], b[i:i + m]
        re, im, pw = t1[:m], t3[:m], t2[:m]
        torch.mm(ai, t.re, out=t1[:m])                                # T1 = a C
        torch.mm(bi, t.im, out=t2[:m])                                # T2 = b D
        torch.mm(torch.add(ai, bi, out=ab[:m]), t.gauss, out=t3[:m])  # T3 = (a + b)(C + D)
        im.sub_(t1[:m]).sub_(t2[:m])                                  # Im = T3 - T1 - T2
        re.sub_(t2[:m])                                               # Re = T1 - T2
        torch.mul(re, re, out=pw).addcmul_(im, im)                    # |s|^2, elevation-major columns
        torch.max(pw, dim=1, out=(power[i:i + m], index[i:i + m]))
        if sec is not None:
            sec[i:i + m] = _sector_pool_elevation_major(pw, grid, sectors)
    index = column_to_direction(index, t.grid)
    amplitude = power.sqrt()
    if sec is not None:
        sec = sec.sqrt()
    if exps is not None:                                              # back to the input's scale
        amplitude = torch.ldexp(amplitude, exps).to(real)
        sec = None if sec is None else torch.ldexp(sec, exps[:, None]).to(real)
    return BeamformResult(index=index, amplitude=amplitude, sectors=sec)


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
    vnorm = _row_norms(v)
    exps = _range_exponents(v, vnorm)
    if exps is not None:
        vnorm = torch.ldexp(_row_norms(_scaled(v, exps)), exps).to(vnorm.dtype)
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
    :func:`radarpc.dsp.native.screen_select_native` is the same step in C."""
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
    1. ``s^_j = B v_j`` over the whole grid from one bfloat16 GEMM (:func:`stack_real` form), and
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
    t = _tables_for(snapshots, dictionary_t, grid)
    if isinstance(max_candidates, bool) or int(max_candidates) < 1:
        raise ValueError(f"max_candidates must be an integer >= 1, got {max_candidates!r}")
    ws = Workspace() if workspace is None else workspace
    k_dir = t.n_dir
    p = snapshots.shape[0]
    dev = snapshots.device
    v = snapshots.resolve_conj().contiguous()
    vnorm = _row_norms(v)
    exps = _range_exponents(v, vnorm)
    if exps is not None:                                              # extreme magnitudes: 2^-e v
        v = _scaled(v, exps)
        vnorm = _row_norms(v)
    alpha, beta = _bound_terms(vnorm, 2 * v.shape[1], t.row_norm_max)   # screen_bound of v
    x = torch.view_as_real(v).reshape(p, 2 * v.shape[1])            # (P, 2N) interleaved
    index = torch.empty(p, dtype=torch.long, device=dev)
    amplitude = torch.empty(p, dtype=torch.float32, device=dev)
    heavy_rows = []
    blk = min(_BLOCK, max(p, 1))
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


def prefers_screened(device: torch.device | str) -> bool:
    """True where :func:`beamform_peaks_screened` was measured faster than :func:`beamform_peaks`:
    CPUs with AMX tiles (bfloat16 GEMMs ~10x float32 ones; ``docs/results/pointcloud.md``).
    CUDA is not measured (no GPU was available), so ``"auto"`` keeps ``"exact"`` there; ask for
    ``"screened"`` explicitly to try it."""
    device = torch.device(device)
    if device.type != "cpu":
        return False
    probe = getattr(torch.cpu, "_is_amx_tile_supported", None)
    return bool(probe()) if probe is not None else False


def check_beamforming(mode: str) -> str:
    """``mode`` if it is one of :data:`BEAMFORMING_MODES`, else ``ValueError``."""
    if mode not in BEAMFORMING_MODES:
        raise ValueError(f"beamforming must be one of {BEAMFORMING_MODES}, got {mode!r}")
    return mode


def resolve_beamforming(mode: str, device: torch.device | str, sectors: tuple[int, int] | None) -> str:
    """The beamformer that runs: ``"exact"`` or ``"screened"``.

    Sector descriptors need the whole spectrum, so they always run ``"exact"``; ``"auto"`` runs
    ``"screened"`` where :func:`prefers_screened` holds.
    """
    check_beamforming(mode)
    if sectors is not None or mode == "exact":
        return "exact"
    if mode == "screened":
        return "screened"
    return "screened" if prefers_screened(device) else "exact"


def beamform(snapshots: torch.Tensor, tables: torch.Tensor | DictionaryTables, grid: tuple[int, int],
             sectors: tuple[int, int] | None = None, mode: str = "auto", *,
             workspace: Workspace | None = None) -> BeamformResult:
    """:func:`beamform_peaks` or :func:`beamform_peaks_screened`, as :func:`resolve_beamforming` picks."""
    if resolve_beamforming(mode, snapshots.device, sectors) == "screened" and snapshots.dtype == torch.complex64:
        return beamform_peaks_screened(snapshots, tables, grid, workspace=workspace)
    return beamform_peaks(snapshots, tables, grid, sectors, workspace=workspace)
