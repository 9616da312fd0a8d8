"""Sparse MIMO processing: angle spectra of virtual snapshots with a calibrated dictionary.

``s_j = |B v_j|`` (eq. 5) with ``B`` the ``(n_az * n_el, n_virtual)`` dictionary of
:meth:`radarpc.sensors.radial.Calibration.dictionary` (taper folded in, row ``k = az * n_el + el``);
``k_j = argmax_k s_j[k]`` (eq. 6) and ``Ae_j = s_j[k_j]`` (eq. 7); the sector descriptor of
eq. 10 max-pools ``s_j`` reshaped to ``(n_az, n_el)`` into ``n_az_sec x n_el_sec`` sectors.

:func:`beamform_peaks` is the exact path: the whole spectrum of every snapshot in float32, the
complex product as three real GEMMs (Gauss's trick), then every direction within the GEMMs'
rounding bound of the maximum is decided by :func:`certified_argmax` (float64 with a bound, exact
rational arithmetic when needed), so ``k_j`` is the argmax of the exact spectrum of the complex64
inputs, ties to the first elevation-major column. The beamforming modes (:data:`BEAMFORMING_MODES`)
choose between it (``"exact"``), the screened bfloat16 beamformer of
:mod:`radarpc.dsp.accel.screened` (``"screened"``) and the subspace beamformer of
:mod:`radarpc.dsp.accel.subspace` (``"subspace"``: the same ``k_j`` and ``Ae_j`` through the same
certified decision); ``"auto"`` runs the one measured fastest on the device and no sector
descriptor is asked for. The mode's entry point is :func:`radarpc.dsp.beamform_modes.beamform`.
The dictionary's forms and the result type (:class:`DictionaryTables`, :func:`dictionary_tables`,
:func:`stack_real`, :func:`column_to_direction`, :class:`BeamformResult`) are defined in
:mod:`radarpc.dsp.dictionary`, which every beamformer shares, and are importable from here too.
"""
from __future__ import annotations

import math
import warnings
from fractions import Fraction

import torch
import torch.nn.functional as F

from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.dictionary import (SNAPSHOT_BLOCK, BeamformResult, DictionaryTables, check_snapshots,
                                    column_to_direction, dictionary_tables, range_exponents, row_norms,
                                    scaled_snapshots, stack_real, tables_for)

__all__ = ["angle_spectrum", "BeamformResult", "DictionaryTables", "dictionary_tables",
           "beamform_peaks", "sector_pool", "stack_real", "column_to_direction", "reduced_fp32_matmul",
           "check_beamforming", "BEAMFORMING_MODES", "certified_argmax", "exact_bound"]

BEAMFORMING_MODES = ("auto", "exact", "screened", "subspace")
"""``"exact"``: :func:`beamform_peaks`; ``"screened"``: the screened bfloat16 beamformer
(:mod:`radarpc.dsp.accel.screened`); ``"subspace"``: the certified block low-rank screen
(:mod:`radarpc.dsp.accel.subspace`); ``"auto"``: whichever of them a one-off measurement on this
device and dictionary found fastest (:func:`radarpc.dsp.accel.screened.measured_choice`)."""


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
    check_snapshots(snapshots, dictionary)
    return torch.abs(snapshots @ dictionary.to(snapshots.dtype).transpose(0, 1))


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
    t = tables_for(snapshots, dictionary_t, grid)
    ws = Workspace() if workspace is None else workspace
    real = t.re.dtype
    k_dir = t.n_dir
    p, n = snapshots.shape
    dev = snapshots.device
    exps = range_exponents(snapshots, row_norms(snapshots))
    if exps is not None:                                              # extreme magnitudes: 2^-e v
        snapshots = scaled_snapshots(snapshots, exps)
    a = ws.empty("exact.re", (p, n), real, dev).copy_(snapshots.real)        # (P, N)
    b = ws.empty("exact.im", (p, n), real, dev).copy_(snapshots.imag)
    index = torch.empty(p, dtype=torch.long, device=dev)
    power = torch.empty(p, dtype=real, device=dev)
    sec = None
    if sectors is not None:
        sec = torch.empty(p, sectors[0] * sectors[1], dtype=real, device=dev)
    blk = min(SNAPSHOT_BLOCK, max(p, 1))
    t1, t2, t3 = (ws.empty(f"exact.t{q}", (blk, k_dir), real, dev) for q in (1, 2, 3))
    ab = ws.empty("exact.a+b", (blk, n), real, dev)
    reduced = reduced_fp32_matmul(dev)
    if reduced:
        warnings.warn(_REDUCED_PRECISION_WARNING, RuntimeWarning, stacklevel=2)
    certify = snapshots.dtype == torch.complex64 and not reduced and p > 0
    if certify:                                                       # |s^ - s| <= e_j (exact_bound)
        e = row_norms(snapshots).double() * ((1.0 + 2.0 ** -14) * exact_bound(n) * t.row_norm_max)
        pairs_j, pairs_c = [], []
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
        if certify:                                                   # every column that may hold the max
            top = power[i:i + m].double().sqrt()
            need = top * (1.0 - 2.0 ** -20) - 2.0 * e[i:i + m]
            need2 = torch.where(need > 0, need.square(), torch.full_like(need, -1.0)).to(real)
            jj, cc = torch.nonzero(pw >= need2[:, None], as_tuple=True)
            pairs_j.append(jj + i)
            pairs_c.append(cc)
        if sec is not None:
            sec[i:i + m] = _sector_pool_elevation_major(pw, grid, sectors)
    index = column_to_direction(index, t.grid)
    amplitude = power.sqrt()
    if certify:                                                       # the exact argmax among them
        j, k = torch.cat(pairs_j), column_to_direction(torch.cat(pairs_c), t.grid)
        ok = torch.isfinite(power)                                    # NaN/inf rows keep the GEMM's answer
        if bool(ok.all()):
            index, amplitude = certified_argmax(snapshots, t.rows, t.grid, j, k)
        else:
            keep = ok[j]
            remap = torch.cumsum(ok, 0) - 1
            idx, amp = certified_argmax(snapshots[ok], t.rows, t.grid, remap[j[keep]], k[keep])
            index[ok], amplitude[ok] = idx, amp
    if sec is not None:
        sec = sec.sqrt()
    if exps is not None:                                              # back to the input's scale
        amplitude = torch.ldexp(amplitude, exps).to(real)
        sec = None if sec is None else torch.ldexp(sec, exps[:, None]).to(real)
    return BeamformResult(index=index, amplitude=amplitude, sectors=sec)



# ---- the certified decision --------------------------------------------------------------------
_U32 = 2.0 ** -24
_U64 = 2.0 ** -53


def exact_bound(n: int) -> float:
    """``kappa`` such that the float32 spectrum of :func:`beamform_peaks` is within
    ``kappa ||v|| ||B[k]||`` of ``|B[k] v|`` for every direction (``n`` complex channels).

    Per real output the three GEMMs of Gauss's trick and the two subtractions give
    ``|dRe|, |dIm| <= (3 gamma_n + 8u) S`` with ``S = sum_i (|a_i| + |b_i|)(|C_ik| + |D_ik|)
    <= 2 ||v|| ||B[k]||`` (Cauchy-Schwarz), hence ``| |s^| - |s| | <= 2 sqrt(2) (3 gamma_n + 8u)
    ||v|| ||B[k]||``; inflated by ``2^-20`` for the float32 evaluation of the norms."""
    gamma = n * _U32 / (1.0 - n * _U32)
    return 2.0 * math.sqrt(2.0) * (3.0 * gamma + 8.0 * _U32 * (1.0 + gamma)) * (1.0 + 2.0 ** -20)


def _exact_power(row: torch.Tensor, v: torch.Tensor) -> Fraction:
    """``|row . v|^2`` as an exact rational (complex64 entries are exact binary fractions)."""
    br, bi = torch.view_as_real(row.resolve_conj()).double().unbind(-1)
    vr, vi = torch.view_as_real(v.resolve_conj()).double().unbind(-1)
    re = sum(Fraction(a) * Fraction(c) - Fraction(b) * Fraction(d)
             for a, b, c, d in zip(br.tolist(), bi.tolist(), vr.tolist(), vi.tolist()))
    im = sum(Fraction(a) * Fraction(d) + Fraction(b) * Fraction(c)
             for a, b, c, d in zip(br.tolist(), bi.tolist(), vr.tolist(), vi.tolist()))
    return re * re + im * im


def _candidate_values(v: torch.Tensor, rows: torch.Tensor, j: torch.Tensor, k: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Float64 ``f = |B[k] v_j|`` and its bound ``beta`` (as the native kernel: products of
    float32 values are exact in float64, the sums are off by ``gamma_2N S``)."""
    b = torch.view_as_real(rows.index_select(0, k)).double()                  # (C, N, 2)
    x = torch.view_as_real(v.index_select(0, j).resolve_conj()).double()      # (C, N, 2)
    re = (b[..., 0] * x[..., 0] - b[..., 1] * x[..., 1]).sum(1)
    im = (b[..., 0] * x[..., 1] + b[..., 1] * x[..., 0]).sum(1)
    f = torch.sqrt(re * re + im * im)
    m = (2 * v.shape[1] + 2) * _U64
    s = ((b[..., 0].abs() + b[..., 1].abs()) * (x[..., 0].abs() + x[..., 1].abs())).sum(1)
    return f, 1.5 * (m / (1.0 - m)) * s * (1.0 + 2.0 ** -40) + 2.0 ** -50 * f


def certified_argmax(snapshots: torch.Tensor, rows: torch.Tensor, grid: tuple[int, int], j: torch.Tensor,
                     k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact ``k_j = argmax_k |B[k] v_j|`` among candidate directions, and ``Ae_j``.

    ``(j, k)`` lists candidate pairs, ``j`` ascending, every point ``0 .. P-1`` at least once; the
    caller guarantees (by a rigorous bound) that the true maximum of each point is among its
    candidates. Each candidate is evaluated in float64 with an error bound; a point whose best
    interval is reached by another candidate's is decided in exact rational arithmetic. Ties go to
    the smaller elevation-major column ``el n_az + az``, the first maximum of
    :func:`beamform_peaks`'s GEMM columns. So the result is the argmax of the exact spectrum of the
    complex64 inputs, whatever computed the candidates. ``Ae_j`` is the float64 value rounded to
    float32. Runs natively on CPU when :func:`radarpc.dsp.accel.native.native_available`.
    """
    from radarpc.dsp.accel import native                              # accel.native needs no dsp module
    n_az, n_el = grid
    p = snapshots.shape[0]
    v = snapshots.resolve_conj().contiguous()
    if v.device.type == "cpu" and v.dtype == torch.complex64 and native.native_available():
        ptr = torch.zeros(p + 1, dtype=torch.long)
        torch.cumsum(torch.bincount(j, minlength=p), 0, out=ptr[1:])
        index, amplitude, ambiguous = native.certify_select_native(v, rows, grid, ptr, k.contiguous())
        f = b = None
    else:
        f, b = _candidate_values(v, rows, j, k)
        c = (k % n_el) * n_az + torch.div(k, n_el, rounding_mode="floor")
        fmax = torch.full((p,), -1.0, dtype=torch.float64, device=v.device).scatter_reduce(0, j, f, "amax")
        at_max = f == fmax[j]
        big = torch.full_like(c, n_az * n_el)
        best_c = big[:p].clone().scatter_reduce(0, j, torch.where(at_max, c, big), "amin")
        first = at_max & (c == best_c[j])
        fb = torch.zeros(p, dtype=torch.float64, device=v.device).scatter(0, j[first], b[first])
        index = column_to_direction(best_c, grid)
        amplitude = fmax.to(torch.float32)
        reach = (f + b >= fmax[j] - fb[j]) & ~first & ((b > 0) | (fb[j] > 0))
        ambiguous = torch.zeros(p, dtype=torch.bool, device=v.device).index_fill_(0, j[reach], True)
        f = b = None
    amb = torch.nonzero(ambiguous).flatten().tolist()
    if amb:                                                          # rare: decide exactly
        amb_t = torch.tensor(amb, dtype=torch.long, device=j.device)
        sel = torch.isin(j, amb_t)
        jj, kk = j[sel], k[sel]
        f, b = _candidate_values(v, rows, jj, kk)
        for q in amb:
            m = jj == q
            fq, bq, kq = f[m], b[m], kk[m]
            top = int(torch.argmax(fq))
            close = torch.nonzero(fq + bq >= fq[top] - bq[top]).flatten().tolist()
            best = max(close, key=lambda i: (_exact_power(rows[int(kq[i])], v[q]),
                                             -((int(kq[i]) % n_el) * n_az + int(kq[i]) // n_el)))
            index[q] = kq[best]
            amplitude[q] = float(fq[best])
    return index, amplitude


def check_beamforming(mode: str) -> str:
    """``mode`` if it is one of :data:`BEAMFORMING_MODES`, else ``ValueError``."""
    if mode not in BEAMFORMING_MODES:
        raise ValueError(f"beamforming must be one of {BEAMFORMING_MODES}, got {mode!r}")
    return mode
