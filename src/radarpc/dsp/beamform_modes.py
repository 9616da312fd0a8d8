"""The beamforming modes of the point-cloud stage: :func:`beamform` runs the beamformer a mode names.

The modes (:data:`radarpc.dsp.beamform.BEAMFORMING_MODES`) give the same points, only the speed
differs: ``"exact"`` runs the core's :func:`radarpc.dsp.beamform.beamform_peaks`; ``"screened"``
and ``"subspace"`` the accelerated beamformers of :mod:`radarpc.dsp.accel.screened` and
:mod:`radarpc.dsp.accel.subspace`, which reach the same ``k_j`` and ``Ae_j``; ``"auto"`` the one a
one-off measurement on the device found fastest (:func:`radarpc.dsp.accel.screened.measured_choice`),
the exact one when the accelerated paths are off (``RADARPC_NO_NATIVE``,
:func:`radarpc.dsp.accel.disabled`). This module is the core's door to them: the beamformers build
on :mod:`radarpc.dsp.dictionary` and the exact path, and none of them imports this module.
"""
from __future__ import annotations

import torch

from radarpc.dsp.accel.screened import beamform_peaks_screened, measured_choice
from radarpc.dsp.accel.subspace import beamform_peaks_subspace
from radarpc.dsp.accel.workspace import Workspace
from radarpc.dsp.beamform import beamform_peaks, check_beamforming
from radarpc.dsp.dictionary import BeamformResult, DictionaryTables

__all__ = ["beamform", "resolve_beamforming"]


def resolve_beamforming(mode: str, device: torch.device | str, sectors: tuple[int, int] | None,
                        tables: DictionaryTables | None = None) -> str:
    """The beamformer that runs: ``"exact"``, ``"screened"`` or ``"subspace"``.

    Sector descriptors need the whole spectrum, so they always run ``"exact"``; an explicit mode
    runs as asked; ``"auto"`` runs :func:`~radarpc.dsp.accel.screened.measured_choice` for ``tables``
    on ``device`` (``"exact"`` without ``tables``, or with the accelerated paths off). Every mode
    gives the same points.
    """
    check_beamforming(mode)
    if sectors is not None or mode == "exact":
        return "exact"
    if mode != "auto":
        return mode
    if tables is None:
        return "exact"
    return measured_choice(tables, device)


def beamform(snapshots: torch.Tensor, tables: torch.Tensor | DictionaryTables, grid: tuple[int, int],
             sectors: tuple[int, int] | None = None, mode: str = "auto", *,
             workspace: Workspace | None = None) -> BeamformResult:
    """:func:`~radarpc.dsp.beamform.beamform_peaks`,
    :func:`~radarpc.dsp.accel.screened.beamform_peaks_screened` or
    :func:`~radarpc.dsp.accel.subspace.beamform_peaks_subspace`, as :func:`resolve_beamforming` picks
    (the accelerated two take complex64 snapshots; others run the exact one)."""
    t = tables if isinstance(tables, DictionaryTables) else None
    chosen = resolve_beamforming(mode, snapshots.device, sectors, t)
    if chosen == "screened" and snapshots.dtype == torch.complex64:
        return beamform_peaks_screened(snapshots, tables, grid, workspace=workspace)
    if chosen == "subspace" and snapshots.dtype == torch.complex64:
        return beamform_peaks_subspace(snapshots, tables, grid, workspace=workspace)
    return beamform_peaks(snapshots, tables, grid, sectors, workspace=workspace)
