"""Sparse MIMO processing: angle spectra of virtual snapshots with a calibrated dictionary.

``s_j = |B v_j|`` (eq. 5) with ``B`` the ``(n_az * n_el, n_virtual)`` dictionary of
:meth:`radarpc.sensors.radial.Calibration.dictionary` (taper folded in, row ``k = az * n_el + el``);
``k_j = argmax_k s_j[k]`` (eq. 6) and ``Ae_j = s_j[k_j]`` (eq. 7); the sector descriptor of
eq. 10 max-pools ``s_j`` reshaped to ``(n_az, n_el)`` into ``n_az_sec x n_el_sec`` sectors.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["angle_spectrum", "BeamformResult", "beamform_peaks", "beamform_peaks_refined", "sector_pool",
           "stack_real", "BEAMFORMING_MODES", "REFINE_CANDIDATES", "check_beamforming"]

# "exact": float32 GEMM over the whole grid; "bf16-refine": bfloat16 GEMM, then the top
# REFINE_CANDIDATES directions of each snapshot recomputed exactly (:func:`beamform_peaks_refined`).
BEAMFORMING_MODES = ("exact", "bf16-refine")
REFINE_CANDIDATES = 4

# Snapshots per GEMM block: the (block, 2 n_az n_el) float32 buffer stays ~7 MB for RADIal.
_BLOCK = 1024


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
    """Per-snapshot outputs of :func:`beamform_peaks`.

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


def beamform_peaks(snapshots: torch.Tensor, dictionary_t: torch.Tensor, grid: tuple[int, int],
                   sectors: tuple[int, int] | None = None, *,
                   stacked: torch.Tensor | None = None) -> BeamformResult:
    """Dominant direction, its amplitude and optional sector maxima, without keeping spectra.

    Works on the power ``|B v|^2 = Re^2 + Im^2`` block by block in preallocated buffers (argmax
    and max-pooling commute with the monotone square root), taking the square root only of the
    kept values. The complex product is one real GEMM (:func:`stack_real`).

    Parameters
    ----------
    snapshots : Tensor, complex, ``(P, n_virtual)``
    dictionary_t : Tensor, complex, ``(n_virtual, n_az * n_el)``
        ``B`` transposed, as stored by :class:`~radarpc.dsp.pointcloud.SpectralPointCloud`.
    grid : (n_az, n_el)
    sectors : (n_az_sec, n_el_sec), optional
    stacked : Tensor, real, ``(2 n_virtual, 2 n_az n_el)``, optional
        ``stack_real(dictionary_t)`` precomputed (in the snapshots' real dtype).
    """
    _check(snapshots, dictionary_t.transpose(0, 1))
    real = snapshots.real.dtype
    if stacked is None or stacked.dtype != real:
        stacked = stack_real(dictionary_t.to(snapshots.dtype))
    k_dir = dictionary_t.shape[1]
    p = snapshots.shape[0]
    dev = snapshots.device
    x = torch.view_as_real(snapshots.resolve_conj().contiguous()).reshape(p, 2 * snapshots.shape[1])  # (P, 2N)
    index = torch.empty(p, dtype=torch.long, device=dev)
    power = torch.empty(p, dtype=real, device=dev)
    sec = None
    if sectors is not None:
        sec = torch.empty(p, sectors[0] * sectors[1], dtype=real, device=dev)
    blk = min(_BLOCK, max(p, 1))
    y = torch.empty(blk, 2 * k_dir, dtype=real, device=dev)       # [Re s | Im s]
    pw = torch.empty(blk, k_dir, dtype=real, device=dev)           # |s|^2
    for i in range(0, p, blk):
        m = min(blk, p - i)
        yi, pi = y[:m], pw[:m]
        torch.mm(x[i:i + m], stacked, out=yi)
        torch.mul(yi[:, :k_dir], yi[:, :k_dir], out=pi).addcmul_(yi[:, k_dir:], yi[:, k_dir:])
        torch.max(pi, dim=1, out=(power[i:i + m], index[i:i + m]))
        if sec is not None:
            sec[i:i + m] = sector_pool(pi, grid, sectors)
    return BeamformResult(index=index, amplitude=power.sqrt(),
                          sectors=None if sec is None else sec.sqrt())


def check_beamforming(mode: str) -> str:
    """``mode`` if it is one of :data:`BEAMFORMING_MODES`, else ``ValueError``."""
    if mode not in BEAMFORMING_MODES:
        raise ValueError(f"beamforming must be one of {BEAMFORMING_MODES}, got {mode!r}")
    return mode


def beamform_peaks_refined(snapshots: torch.Tensor, dictionary_t: torch.Tensor, grid: tuple[int, int],
                           sectors: tuple[int, int] | None = None, *, stacked: torch.Tensor | None = None,
                           candidates: int = REFINE_CANDIDATES) -> BeamformResult:
    """:func:`beamform_peaks` with a bfloat16 spectrum and an exact re-ranking of its top candidates.

    1. ``p_j ~ |B v_j|^2`` over the whole grid from one bfloat16 GEMM (inputs rounded to bfloat16,
       8 significant bits, unit roundoff ``2^-8 ~ 0.4 %``; the product is converted to float32
       before squaring);
    2. ``C_j`` = the ``candidates`` directions of largest ``p_j``;
    3. ``s_j[k] = |B[k] v_j|`` recomputed exactly (snapshot dtype, e.g. complex64) for ``k in C_j``
       only (a gather of ``candidates`` dictionary columns and as many dot products per snapshot);
    4. ``k_j = argmax_{k in C_j} s_j[k]`` and ``Ae_j = s_j[k_j]`` (eqs. 6-7).

    ``k_j`` equals the exact argmax whenever the exact maximum is among the bfloat16 top
    ``candidates`` (it is unless the peak is within the bfloat16 error of ``candidates`` other
    directions), and then ``Ae_j`` equals the exact amplitude to float32 rounding. The sector
    descriptor (eq. 10), if asked for, is max-pooled from the *bfloat16* spectrum and is therefore
    approximate: a relative error of a few 1e-3 on the strong sectors, larger on weak sidelobe
    sectors (the rounding error scales with ``sum |v| |B|``, not with ``|B v|``).

    Parameters
    ----------
    snapshots : Tensor, complex, ``(P, n_virtual)``
    dictionary_t : Tensor, complex, ``(n_virtual, n_az * n_el)``
    grid : (n_az, n_el)
    sectors : (n_az_sec, n_el_sec), optional
    stacked : Tensor, real, ``(2 n_virtual, 2 n_az n_el)``, optional
        ``stack_real(dictionary_t)`` precomputed, any real dtype (cast to bfloat16 here).
    candidates : int
        Number of bfloat16 candidates re-ranked exactly per snapshot (>= 1; clipped to the grid).
    """
    _check(snapshots, dictionary_t.transpose(0, 1))
    if isinstance(candidates, bool) or int(candidates) < 1:
        raise ValueError(f"candidates must be an integer >= 1, got {candidates!r}")
    real = snapshots.real.dtype
    k_dir = dictionary_t.shape[1]
    kc = min(int(candidates), k_dir)
    if stacked is None:
        stacked = stack_real(dictionary_t.to(snapshots.dtype))
    w16 = stacked.to(torch.bfloat16)                                # (2N, 2K)
    b_rows = dictionary_t.to(snapshots.dtype).transpose(0, 1).contiguous()  # (K, N): row k is B[k]
    p = snapshots.shape[0]
    dev = snapshots.device
    v = snapshots.resolve_conj().contiguous()
    x = torch.view_as_real(v).reshape(p, 2 * snapshots.shape[1])   # (P, 2N)
    index = torch.empty(p, dtype=torch.long, device=dev)
    amplitude = torch.empty(p, dtype=real, device=dev)
    sec = None
    if sectors is not None:
        sec = torch.empty(p, sectors[0] * sectors[1], dtype=real, device=dev)
    blk = min(_BLOCK, max(p, 1))
    # preallocated block buffers (fresh large allocations per block cost more than the bf16 GEMM)
    x16 = torch.empty(blk, x.shape[1], dtype=torch.bfloat16, device=dev)
    y16 = torch.empty(blk, 2 * k_dir, dtype=torch.bfloat16, device=dev)
    y32 = torch.empty(blk, 2 * k_dir, dtype=torch.float32, device=dev)
    pw_buf = torch.empty(blk, k_dir, dtype=torch.float32, device=dev)
    for i in range(0, p, blk):
        m = min(blk, p - i)
        x16[:m].copy_(x[i:i + m])
        torch.mm(x16[:m], w16, out=y16[:m])
        y = y32[:m].copy_(y16[:m])                                             # (m, 2K) [Re | Im], float32
        pw = torch.mul(y[:, :k_dir], y[:, :k_dir], out=pw_buf[:m]).addcmul_(y[:, k_dir:], y[:, k_dir:])
        cand = torch.topk(pw, kc, dim=1, sorted=False).indices                 # (m, kc)
        s = torch.einsum("mcn,mn->mc", b_rows[cand], v[i:i + m])              # (m, kc) exact B[k] v
        a, j = torch.max(s.abs(), dim=1)                                       # (m,)
        amplitude[i:i + m] = a
        index[i:i + m] = cand.gather(1, j.unsqueeze(1)).squeeze(1)
        if sec is not None:
            sec[i:i + m] = sector_pool(pw, grid, sectors).sqrt().to(real)
    return BeamformResult(index=index, amplitude=amplitude, sectors=sec)
