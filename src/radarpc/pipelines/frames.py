"""One frame of a dataset root, computed for its figure (``radarpc show``); :mod:`radarpc.viz` draws it.

:func:`frame_view` loads a RADIal frame and runs the point-cloud stage on it (or reads its points
from a point store): the RD spectrum, the CFAR envelope and peaks, the points and the labelled
vehicles of :class:`radarpc.data.summary.FrameView`, for :func:`radarpc.viz.plot_frame_view`.
:func:`coloradar_view_with_prediction` reads a ColoRadar radar frame with its paired LiDAR scan
(:func:`radarpc.data.summary.coloradar_frame_view`) and adds a prediction folder's cloud of that
frame, for :func:`radarpc.viz.plot_coloradar_view`. :func:`scene_frames` picks one frame per scene
of a ColoRadar split and :func:`comparison_views` reads, for each, the radar cube, the LiDAR truth
and every prediction folder's cloud (:func:`radarpc.eval.comparison.comparison_view`), for
:func:`radarpc.viz.plot_cloud_comparison`.
"""
from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from radarpc.data.point_dataset import check_store_root
from radarpc.data.pointstore import PointStore
from radarpc.data.radial import RADIal
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
from radarpc.data.summary import ColoRadarView, FrameView, coloradar_frame_view
from radarpc.dsp.ddma import rx_magnitude_sum
from radarpc.dsp.sparse_rd import encoded_cells
from radarpc.data.coloradar import ColoRadar
from radarpc.eval.comparison import ComparisonView, comparison_view
from radarpc.eval.predictions import INDEX_FILE, load_prediction, prediction_path
from radarpc.io import load_array
from radarpc.machine import check_device
from radarpc.pipelines.pointclouds import ConvertSettings, build_point_cloud, calibrate_tau

__all__ = ["frame_view", "coloradar_view_with_prediction", "scene_frames", "comparison_views"]


def frame_view(root: str | os.PathLike, frame: int, settings: ConvertSettings | None = None, *,
               store: str | os.PathLike | None = None, device: torch.device | str = "cpu",
               tau: float | None = None) -> FrameView:
    """Load frame ``frame`` (numSample) of ``root`` and compute what
    :func:`radarpc.viz.plot_frame_view` draws.

    Parameters
    ----------
    root : path-like
        RADIal-layout root.
    frame : int
        RADIal numSample of the frame.
    settings : ConvertSettings, optional
        Threshold or density, enrichments and CFAR geometry (``split`` is ignored: any frame of
        the root can be shown; per-dataset mode calibrates on the training split at every call
        unless ``tau`` is given).
    store : path-like, optional
        Instead of ``settings``: a point store made from ``root``; the points are read from it
        and the CFAR panels use its CFAR geometry and the frame's stored threshold.
    device : torch.device or str
    tau : float, optional
        Per-dataset mode: the tau already calibrated (e.g. ``ConvertResult.tau`` or a store's
        ``metadata.tau``), so that viewing many frames does not recalibrate each time.

    Raises
    ------
    ValueError
        Not exactly one of ``settings`` and ``store``; ``frame`` not in ``root`` or the store.
    """
    root = Path(root)
    if (settings is None) == (store is None):
        raise ValueError("give exactly one of settings (a threshold or density) and store (a point store)")
    ds = RADIal(root, split="all")
    try:
        i = ds.index_of(int(frame))
    except KeyError:
        raise ValueError(f"frame {frame} is not in {root} (numSample from {ds.frame_ids[0] if ds.frame_ids else '-'} "
                         f"to {ds.frame_ids[-1] if ds.frame_ids else '-'})") from None
    rd, labels, _ = ds[i]
    dev = check_device(device)
    stored = None
    if store is not None:
        pstore = PointStore(store)
        stored = pstore[pstore.index_of(int(frame))] if int(frame) in pstore.frames else None
        if stored is None:
            raise ValueError(f"frame {frame} is not in the point store {store}")
        m = pstore.metadata
        check_store_root(pstore, root)     # its points must not be drawn over another dataset's spectrum
        settings = ConvertSettings(tau=float(stored.tau[0]), enrich=m.enrich, window=m.window, guard=m.guard,
                                   envelope=m.envelope)
    if settings.mode == "per-dataset":
        tau = calibrate_tau(root, settings, device=dev) if tau is None else float(tau)
    else:
        tau = settings.tau
    spc = build_point_cloud(ds, settings, tau, dev)
    rd_b = rd.unsqueeze(0).to(dev)                                          # (1, Nr, Nd, Nrx)
    with torch.no_grad():
        env, _, peaks = spc.detect(rd_b)                                    # (1, Nr, W) each
        cloud = spc(rd_b) if stored is None else stored
    cloud = cloud.to("cpu")
    lab = labels.cpu().numpy()
    cols = [LABEL_TENSOR_COLUMNS.index("radar_R_m"), LABEL_TENSOR_COLUMNS.index("radar_A_deg")]
    how = (f"points of {Path(store).name}" if store is not None else
           f"target density {settings.density:g} ({settings.mode})" if settings.density is not None
           else "fixed threshold")
    return FrameView(
        title=f"RADIal root '{root.name}': frame {frame} (numSample), sequence {ds.sequences[i]}; {how}",
        frame=int(frame), sensor=ds.sensor,
        rd_magnitude=rx_magnitude_sum(rd_b)[0].cpu().numpy(), encoded=encoded_cells(cloud, ds.sensor).numpy(),
        set_name="S*(tau)" if settings.point_cloud_config().neighbourhood is not None else "S(tau)",
        envelope=env[0].cpu().numpy(), peaks=peaks[0].cpu().numpy(), cloud=cloud, vehicles_ra=lab[:, cols])


def coloradar_view_with_prediction(root: str | os.PathLike, frame: int, run: str | None = None,
                                   pred: str | os.PathLike | None = None) -> ColoRadarView:
    """Radar frame ``frame`` of ``run`` (default the first run) of a ColoRadar root with its paired
    LiDAR scan (:func:`radarpc.data.summary.coloradar_frame_view`); ``pred``, a prediction folder
    (:mod:`radarpc.eval.predictions`), adds its cloud for that frame, labelled with the folder's
    method and name.
    """
    view = coloradar_frame_view(root, frame, run)
    if pred is None:
        return view
    pts = load_prediction(pred, view.run, view.radar_index)
    method = _prediction_method(pred)
    return replace(view, pred_xyz=np.asarray(pts, dtype=np.float64),
                   pred_label=f"{method} ({Path(pred).name})" if method else Path(pred).name)


def _prediction_method(pred: str | os.PathLike) -> str:
    try:
        return str(json.loads((Path(pred) / INDEX_FILE).read_text()).get("method", ""))
    except (OSError, ValueError, AttributeError):
        return ""


def scene_frames(ds: ColoRadar, items: Sequence[int] | None = None) -> dict[str, int]:
    """One item of a ColoRadar split per scene, ``{scene: item index}`` (scenes sorted): the middle
    item of the scene's first run in the split, among ``items`` (default all, e.g. the frames a
    prediction folder lists)."""
    first: dict[str, list[int]] = {}
    for i in range(len(ds)) if items is None else sorted(items):
        k = ds.index[i][0]
        run = ds.runs[k]
        chosen = first.setdefault(run.scene, [])
        if not chosen or ds.runs[ds.index[chosen[0]][0]].name == run.name:
            chosen.append(i)
    return {scene: chosen[len(chosen) // 2] for scene, chosen in sorted(first.items())}


def comparison_views(root: str | os.PathLike, split: str, preds: Mapping[str, str | os.PathLike], *,
                     notes: Mapping[str, Mapping[tuple[str, int], str]] | None = None,
                     max_points: int = 50_000, items: Sequence[int] | None = None) -> list[ComparisonView]:
    """The comparison figure's view of one frame per scene (:func:`scene_frames`) of a ColoRadar split.

    Parameters
    ----------
    root, split
        The dataset and split the predictions were made on.
    preds : mapping of str to path-like
        Method name -> prediction folder (:mod:`radarpc.eval.predictions`), in the order to draw.
    notes : mapping, optional
        Method name -> ``{(run, frame): note}`` (e.g. the frame's Chamfer distance).
    max_points : int
        Points drawn per cloud at most.
    items : sequence of int, optional
        The split's items to choose from (default all): the frames every folder holds.

    Raises
    ------
    radarpc.io.DataFileError
        A folder lacks a frame's cloud, or holds a malformed one (an empty cloud is drawn as such).
    """
    ds = ColoRadar(root, split, cube_size=None)
    if len(ds) == 0:
        raise ValueError(f"split {split!r} of {root} has no paired radar/LiDAR frame")
    views = []
    for scene, i in scene_frames(ds, items).items():
        k, ri, li = ds.index[i]
        run = ds.runs[k]
        cube = ds.cube(i)
        clouds = {name: load_array(prediction_path(folder, run.name, ri), shape=(None, 3), complex_=False)
                  for name, folder in preds.items()}
        frame_notes = {name: n.get((run.name, int(ri)), "") for name, n in (notes or {}).items()}
        views.append(comparison_view(
            cube.intensity_db.cpu().numpy(), cube.range_m.cpu().numpy(), np.degrees(cube.azimuth_rad.cpu().numpy()),
            np.degrees(cube.elevation_rad.cpu().numpy()), ds.lidar_points(i), clouds, run=run.name, scene=scene,
            frame=ri, lidar_index=li, fov=ds.fov, split=split, notes=frame_notes, max_points=max_points))
    return views
