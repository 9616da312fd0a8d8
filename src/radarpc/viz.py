"""Every figure of radarpc: one frame's RD spectrum, CFAR peaks and point cloud, and the summary
figures of ``radarpc info`` for RADIal and ColoRadar roots.

The drawing functions take arrays (or the small dataclasses that hold them) and write a PNG
atomically (:func:`radarpc.io.atomic_write`). Figures are built on matplotlib's object API
(:class:`matplotlib.figure.Figure`, saved through the Agg canvas), so that neither pyplot's figure
registry nor the global backend is touched. :func:`frame_view` prepares the inputs of the frame
figure from a dataset root (and optionally a point store); :mod:`radarpc.data.summary` those of the
summary figures.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from radarpc.data.point_dataset import check_store_root
from radarpc.data.pointstore import PointStore
from radarpc.data.radial import LabelTable, RADIal
from radarpc.data.radial_format import LABEL_TENSOR_COLUMNS
from radarpc.data.summary import ColoRadarView, RadialSummary
from radarpc.dsp.ddma import rx_magnitude_sum
from radarpc.dsp.sparse_rd import sparse_rd_mask
from radarpc.io import atomic_write
from radarpc.machine import check_device
from radarpc.pipelines.pointclouds import ConvertSettings, build_point_cloud, calibrate_tau
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import DDMARadarConfig

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "COLOR_BY",
    "rd_extent",
    "peak_marker_range_m",
    "encoded_cells",
    "FrameView",
    "frame_view",
    "FramePlot",
    "plot_frame_view",
    "plot_frame",
    "plot_radial_info",
    "plot_coloradar_info",
]

COLOR_BY = ("velocity", "amplitude")
"""What the frame figure colours the points by."""


def _figure(figsize: tuple[float, float]) -> "Figure":
    """A figure outside pyplot (matplotlib is imported on first use: the CLI starts faster)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _save(fig: "Figure", out: Path, dpi: int) -> None:
    """Write ``fig`` as a PNG at ``out`` (temp file + rename)."""
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi)


# ---- one frame: RD + CFAR + BEV points -----------------------------------------------------------
def rd_extent(cfg: DDMARadarConfig, n_cols: int) -> tuple[float, float, float, float]:
    """``imshow`` extent of an ``(Nr, n_cols)`` RD image (origin lower): row ``r`` spans
    ``[(r - 0.5) res, (r + 0.5) res]``, centred on ``r * res`` = the points' ``range_m``."""
    res = cfg.range_res_m
    return (-0.5, n_cols - 0.5, -0.5 * res, (cfg.n_range - 0.5) * res)


def peak_marker_range_m(cfg: DDMARadarConfig, range_bin: np.ndarray) -> np.ndarray:
    """Vertical position of the CFAR-peak markers: ``r * res``, as ``range_m`` and :func:`rd_extent`."""
    return np.asarray(range_bin, dtype=np.float64) * cfg.range_res_m


def encoded_cells(cloud: PointCloudBatch, cfg: DDMARadarConfig) -> torch.Tensor:
    """The full-grid set a one-frame cloud encodes, ``S(tau)`` (``S*(tau)`` with ``rdN`` points):
    :func:`radarpc.dsp.sparse_rd.sparse_rd_mask` of the points' consolidated cells and their ``d0``.

    Parameters
    ----------
    cloud : PointCloudBatch
        One frame (e.g. ``SpectralPointCloud(rd)`` of one cube, or ``PointStore[i]``); any point order.
    cfg : DDMARadarConfig

    Returns
    -------
    BoolTensor ``(Nr, Nd)``, on the CPU
    """
    r, l = cloud.range_bin.cpu().long(), cloud.doppler_bin.cpu().long()
    kept = torch.zeros(cfg.n_range, cfg.slot_width, dtype=torch.bool)
    kept[r, l] = True
    order = torch.argsort(r * cfg.slot_width + l)          # d0 in torch.nonzero(kept) order
    return sparse_rd_mask(kept, cfg, cloud.doppler_full.cpu().long()[order])[0]


@dataclass(frozen=True)
class FrameView:
    """What the frame figure draws, on the CPU."""

    title: str                      # figure title: root name, frame, sequence
    frame: int                      # RADIal numSample
    sensor: DDMARadarConfig
    rd_magnitude: np.ndarray        # (Nr, Nd) A = sum_rx |R|
    encoded: np.ndarray             # (Nr, Nd) bool, the set the cloud encodes (encoded_cells)
    set_name: str                   # "S(tau)" or "S*(tau)"
    envelope: np.ndarray            # (Nr, W) E(r, l)
    peaks: np.ndarray               # (Nr, W) bool, P(tau)
    cloud: PointCloudBatch          # the frame's points
    vehicles_xy: np.ndarray         # (V, 2) radar_X_m, radar_Y_m of the labelled vehicles


def frame_view(root: str | os.PathLike, frame: int, settings: ConvertSettings | None = None, *,
               store: str | os.PathLike | None = None, device: torch.device | str = "cpu",
               tau: float | None = None) -> FrameView:
    """Load frame ``frame`` (numSample) of ``root`` and compute what :func:`plot_frame_view` draws.

    Parameters are those of :func:`plot_frame`.
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
    cols = [LABEL_TENSOR_COLUMNS.index("radar_X_m"), LABEL_TENSOR_COLUMNS.index("radar_Y_m")]
    return FrameView(
        title=f"{root.name}, frame {frame} ({ds.sequences[i]})", frame=int(frame), sensor=ds.sensor,
        rd_magnitude=rx_magnitude_sum(rd_b)[0].cpu().numpy(), encoded=encoded_cells(cloud, ds.sensor).numpy(),
        set_name="S*(tau)" if settings.point_cloud_config().neighbourhood is not None else "S(tau)",
        envelope=env[0].cpu().numpy(), peaks=peaks[0].cpu().numpy(), cloud=cloud, vehicles_xy=lab[:, cols])


@dataclass(frozen=True)
class FramePlot:
    """What :func:`plot_frame` drew."""

    path: Path               # the PNG
    frame: int               # RADIal numSample
    n_points: int            # points of the cloud
    n_peaks: int             # consolidated CFAR peaks |P(tau)|
    density: float           # density of the encoded set: |S*(tau)| / (Nr * ND) with rdN, else |S(tau)| / (Nr * ND)
    tau: float               # threshold used
    n_vehicles: int          # labelled vehicles drawn
    peak_density: float = float("nan")   # |S(tau)| / (Nr * ND), CFAR peaks alone


def _db(a: np.ndarray) -> np.ndarray:
    """Magnitudes -> dB, floored 240 dB below the peak."""
    return 20.0 * np.log10(np.maximum(a, 1e-12 * max(float(a.max()), 1e-30)))


def plot_frame_view(view: FrameView, out: str | os.PathLike, color_by: str = "velocity") -> FramePlot:
    """Draw a :class:`FrameView` to ``out`` (PNG, atomic), 17 x 6.5 in at 80 dpi.

    Panels: (a) ``A(r, d)`` in dB on the full Doppler axis with the encoded set overlaid cell by
    cell, (b) the envelope ``E(r, l)`` in dB with the CFAR peaks ``P(tau)``, (c) the points in
    bird's-eye view (x forward, y left, left drawn on the left) coloured by radial velocity or by
    angle-spectrum amplitude, with the labelled vehicle centres. Range bin ``r`` is drawn centred on
    ``r * range_res_m`` (the points' ``range_m``) in both RD panels.
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    if color_by not in COLOR_BY:
        raise ValueError(f"color_by must be one of {COLOR_BY}, got {color_by!r}")
    out = Path(out)
    cfg, cloud = view.sensor, view.cloud
    mask_full, e, pk = view.encoded, view.envelope, view.peaks
    tau_used = float(cloud.tau[0])
    density = float(cloud.density[0])
    x, y = cloud.x.numpy(), cloud.y.numpy()
    if color_by == "velocity":
        cval = cloud.velocity_mps.numpy()
    else:  # Ae in dB: amplitudes span decades
        cval = 20.0 * np.log10(np.maximum(cloud.amplitude.numpy(), 1e-30))
    gx, gy = view.vehicles_xy[:, 0], view.vehicles_xy[:, 1]

    fig = _figure((17, 6.5))
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.4, 0.8, 1.4]})
    rmax = cfg.max_range_m
    im0 = ax[0].imshow(_db(view.rd_magnitude), aspect="auto", origin="lower", cmap="viridis",
                       extent=rd_extent(cfg, cfg.n_doppler))
    # S(tau) as an exact per-cell overlay (markers would hide the spectrum on a 512 x 256 grid)
    ax[0].imshow(np.ma.masked_where(~mask_full, mask_full.astype(float)), aspect="auto", origin="lower",
                 cmap=ListedColormap(["red"]), alpha=0.85, interpolation="nearest",
                 extent=rd_extent(cfg, cfg.n_doppler))
    ax[0].legend(handles=[Patch(color="red", label=f"{view.set_name}: {int(mask_full.sum())} cells")],
                 loc="upper right", fontsize=8)
    ax[0].set(xlabel="Doppler bin (full axis)", ylabel="range [m]",
              title=f"sum_rx |R| [dB], frame {view.frame}")
    fig.colorbar(im0, ax=ax[0], label="dB")
    im1 = ax[1].imshow(_db(e), aspect="auto", origin="lower", cmap="magma",
                       extent=rd_extent(cfg, cfg.slot_width))
    pr, pl = np.nonzero(pk)
    ax[1].scatter(pl, peak_marker_range_m(cfg, pr), s=8, marker="x", c="cyan", linewidths=0.6,
                  label=f"P(tau): {int(pk.sum())} peaks")
    ax[1].set(xlabel="consolidated Doppler l", ylabel="range [m]", title="envelope E(r, l) [dB] + CFAR")
    ax[1].legend(loc="upper right", fontsize=8)
    fig.colorbar(im1, ax=ax[1], label="dB")
    if color_by == "velocity":  # symmetric colour scale: white = 0 m/s
        vmax = max(float(np.abs(cval).max()) if cval.size else 0.0, cfg.velocity_res_mps)
        sc = ax[2].scatter(y, x, c=cval, s=5, cmap="coolwarm", vmin=-vmax, vmax=vmax)
    else:
        sc = ax[2].scatter(y, x, c=cval, s=5, cmap="viridis")
    fig.colorbar(sc, ax=ax[2], label="radial velocity [m/s]" if color_by == "velocity" else "amplitude Ae [dB]")
    ax[2].scatter(gy, gx, s=140, marker="s", facecolors="none", edgecolors="k", linewidths=1.5,
                  label=f"labelled vehicles ({len(gx)})")
    ax[2].set(xlabel="y [m] (left +)", ylabel="x [m] (forward)",
              title=f"BEV: {len(x)} points, density {density:.4f}, tau {tau_used:.3g}")
    # lateral half-width: every point and label, and at least 40 % of the range (a readable panel)
    half = max(0.4 * rmax, 1.05 * float(np.abs(np.concatenate([y, gy])).max()) if len(y) + len(gy) else 0.0)
    ax[2].set_xlim(min(half, rmax), -min(half, rmax))  # left of the car drawn on the left
    ax[2].set_ylim(0.0, rmax)
    ax[2].set_aspect("equal")
    ax[2].legend(loc="upper left", fontsize=7, framealpha=0.6)
    fig.suptitle(view.title)
    fig.tight_layout()
    _save(fig, out, dpi=80)
    peak_density = float(pk.sum()) * cfg.n_tx / (cfg.n_range * cfg.n_doppler)
    return FramePlot(path=out, frame=view.frame, n_points=int(len(x)), n_peaks=int(pk.sum()),
                     density=density, tau=tau_used, n_vehicles=int(len(gx)), peak_density=peak_density)


def plot_frame(root: str | os.PathLike, frame: int, out: str | os.PathLike, settings: ConvertSettings | None = None,
               *, store: str | os.PathLike | None = None, color_by: str = "velocity",
               device: torch.device | str = "cpu", tau: float | None = None) -> FramePlot:
    """Draw frame ``frame`` (numSample) of ``root`` to ``out``: :func:`frame_view` then
    :func:`plot_frame_view`.

    Parameters
    ----------
    root : path-like
        RADIal-layout root.
    frame : int
        RADIal numSample of the frame.
    out : path-like
        PNG to write.
    settings : ConvertSettings, optional
        Threshold or density, enrichments and CFAR geometry (``split`` is ignored: any frame of
        the root can be shown; per-dataset mode calibrates on the training split at every call
        unless ``tau`` is given).
    store : path-like, optional
        Instead of ``settings``: a point store made from ``root``; the points are read from it
        and the CFAR panels use its CFAR geometry and the frame's stored threshold.
    color_by : {"velocity", "amplitude"}
    device : torch.device or str
    tau : float, optional
        Per-dataset mode: the tau already calibrated (e.g. ``ConvertResult.tau`` or a store's
        ``metadata.tau``), so that plotting many frames does not recalibrate each time.
    """
    if color_by not in COLOR_BY:
        raise ValueError(f"color_by must be one of {COLOR_BY}, got {color_by!r}")
    if Path(out).is_dir():
        raise IsADirectoryError(f"the figure path {out} is a directory; give the path of a .png file")
    view = frame_view(root, frame, settings, store=store, device=device, tau=tau)
    return plot_frame_view(view, out, color_by)


# ---- radarpc info: RADIal ------------------------------------------------------------------------
def plot_radial_info(summary: RadialSummary, labels: LabelTable, out: str | os.PathLike,
                     rd_power_db: tuple[int, np.ndarray] | None = None) -> Path:
    """The RADIal summary figure (PNG, atomic, 11 x 8 in at 90 dpi): range and azimuth histograms of
    the vehicles, their bird's-eye positions, and an RD power map.

    Parameters
    ----------
    summary : RadialSummary
        :func:`radarpc.data.summary.summarize_radial` of the root.
    labels : LabelTable
        The root's ``labels.csv``.
    out : path-like
        PNG to write.
    rd_power_db : (int, ndarray ``(Nr, Nd)``), optional
        numSample and power map from :func:`radarpc.data.summary.first_rd_power_db`; None draws
        "no readable RD cube".
    """
    out = Path(out)
    sensor = summary.sensor
    veh = labels.has_vehicle
    r, a = labels.column("radar_R_m")[veh], labels.column("radar_A_deg")[veh]
    x, y = labels.column("radar_X_m")[veh], labels.column("radar_Y_m")[veh]
    fig = _figure((11, 8))
    ax = fig.subplots(2, 2)
    r_top = max(sensor.max_range_m, float(r.max()) if r.size else 0.0)
    ax[0, 0].hist(r, bins=40, range=(0.0, r_top), color="C0")
    ax[0, 0].set(xlabel="radar_R_m [m]", ylabel="vehicles", title="range of labels")
    ax[0, 1].hist(a, bins=36, range=(-90.0, 90.0), color="C1")
    ax[0, 1].set(xlabel="radar_A_deg [deg]", ylabel="vehicles", title="azimuth of labels")
    ax[1, 0].scatter(y, x, s=4, alpha=0.5)
    ax[1, 0].set(xlabel="radar_Y_m [m] (left +)", ylabel="radar_X_m [m] (forward)", title="vehicles, BEV")
    ax[1, 0].invert_xaxis()  # left of the car on the left of the plot
    ax[1, 0].set_aspect("equal", adjustable="datalim")
    if rd_power_db is None:
        ax[1, 1].text(0.5, 0.5, "no readable RD cube", ha="center", va="center")
        ax[1, 1].set_axis_off()
    else:
        shown, env = rd_power_db
        im = ax[1, 1].imshow(env, aspect="auto", origin="lower", cmap="viridis",
                             extent=(0, sensor.n_doppler, 0, sensor.max_range_m))
        fig.colorbar(im, ax=ax[1, 1], label="dB")
        ax[1, 1].set(xlabel="Doppler bin", ylabel="range [m]", title=f"RD envelope, frame {shown}")
    fig.suptitle(f"{summary.root.name}: {summary.n_frames} frames, {summary.n_vehicles} vehicles")
    fig.tight_layout()
    _save(fig, out, dpi=90)
    return out


# ---- radarpc info: ColoRadar ---------------------------------------------------------------------
def plot_coloradar_info(view: ColoRadarView, out: str | os.PathLike) -> Path:
    """The ColoRadar summary figure (PNG, atomic, 5.5 in per panel x 5 in at 110 dpi): the LiDAR
    scan in bird's-eye view (radar frame) with the frustum, the single-chip cube and, if the view
    has one, the cascade heatmap (both max over elevation, dB)."""
    out = Path(out)
    n_ax = 2 + int(view.heatmap_db is not None)
    fig = _figure((5.5 * n_ax, 5))
    axes = fig.subplots(1, n_ax)
    pts, inside, fov = view.lidar_xyz, view.inside_xyz, view.fov
    ax = axes[0]
    lim = fov.max_range_m + 2
    near = np.abs(pts[:, :2]).max(1) < lim
    ax.scatter(pts[near, 1], pts[near, 0], s=0.3, c="0.75", label="LiDAR (radar frame)")
    ax.scatter(inside[:, 1], inside[:, 0], s=0.5, c=inside[:, 2], cmap="viridis", label="inside frustum")
    a = np.radians(np.linspace(*fov.azimuth_deg, 181))
    r = fov.max_range_m
    ax.plot(np.r_[0, r * np.sin(a), 0], np.r_[0, r * np.cos(a), 0], "r-", lw=1, label="radar frustum")
    ax.set(xlim=(lim, -lim), ylim=(-lim, lim), aspect="equal", xlabel="y (m, left)", ylabel="x (m, forward)",
           title=f"{view.run} LiDAR {view.lidar_index}: {len(inside)} pts in frustum")
    ax.legend(loc="lower left", fontsize=7, markerscale=8)
    ax = axes[1]
    if view.cube_db is not None:
        img, rr, az = view.cube_db, view.cube_range_m, view.cube_azimuth_deg
        ax.imshow(img, origin="lower", aspect="auto", cmap="magma",
                  extent=(-0.5, img.shape[1] - 0.5, float(rr[0]), float(rr[-1])))
        ax.set_xticks(range(img.shape[1]), [f"{a:.0f}" for a in az])
        ax.set(xlabel="azimuth bin centre (deg; sin-spaced FFT bins)", ylabel="range (m)",
               title=f"single-chip cube {view.radar_index}: max over elevation (dB)")
    if view.heatmap_db is not None:
        ax = axes[2]
        az = view.heatmap_azimuth_deg
        ax.imshow(view.heatmap_db.T, origin="lower", aspect="auto", cmap="magma",
                  extent=(float(az[0]), float(az[-1]), 0.0, view.heatmap_max_range_m))
        ax.set(xlabel="azimuth (deg)", ylabel="range (m)", title="cascade heatmap: max over elevation (dB)")
    fig.tight_layout()
    _save(fig, out, dpi=110)
    return out
