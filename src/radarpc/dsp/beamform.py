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

__all__ = ["angle_spectrum", "BeamformResult", "beamform_peaks", "sector_pool"]

# Snapshots per matmul block: bounds the (block, n_az * n_el) complex intermediate (~30 MB).
_BLOCK = 4096


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
    x = spectrum.reshape(-1, 1, n_az, n_el)
    return F.adaptive_max_pool2d(x, (n_as, n_es)).reshape(spectrum.shape[0], n_as * n_es)


def beamform_peaks(snapshots: torch.Tensor, dictionary_t: torch.Tensor, grid: tuple[int, int],
                   sectors: tuple[int, int] | None = None) -> BeamformResult:
    """Dominant direction, its amplitude and optional sector maxima, without keeping spectra.

    Works on the power ``|B v|^2 = Re^2 + Im^2`` block by block (argmax and max-pooling commute
    with the monotone square root), taking the square root only of the kept values.

    Parameters
    ----------
    snapshots : Tensor, complex, ``(P, n_virtual)``
    dictionary_t : Tensor, complex, ``(n_virtual, n_az * n_el)``
        ``B`` transposed (contiguous), as stored by :class:`~radarpc.dsp.pointcloud.SpectralPointCloud`.
    grid : (n_az, n_el)
    sectors : (n_az_sec, n_el_sec), optional
    """
    _check(snapshots, dictionary_t.transpose(0, 1))
    bt = dictionary_t.to(snapshots.dtype)
    p = snapshots.shape[0]
    real = snapshots.real.dtype
    index = torch.empty(p, dtype=torch.long, device=snapshots.device)
    power = torch.empty(p, dtype=real, device=snapshots.device)
    sec = None
    if sectors is not None:
        sec = torch.empty(p, sectors[0] * sectors[1], dtype=real, device=snapshots.device)
    for i in range(0, p, _BLOCK):
        s = torch.view_as_real(snapshots[i:i + _BLOCK] @ bt)        # (blk, n_dir, 2)
        pw = s.square().sum(-1)                                    # (blk, n_dir) = |B v|^2
        pmax, k = pw.max(dim=1)
        index[i:i + _BLOCK] = k
        power[i:i + _BLOCK] = pmax
        if sec is not None:
            sec[i:i + _BLOCK] = sector_pool(pw, grid, sectors)
    return BeamformResult(index=index, amplitude=power.sqrt(),
                          sectors=None if sec is None else sec.sqrt())
