"""Every figure of radarpc: one frame's RD spectrum, CFAR peaks and point cloud, and the summary
figures of ``radarpc info`` for RADIal and ColoRadar roots.

The drawing functions take arrays (or the small dataclasses that hold them) and write a PNG
atomically (:func:`radarpc.io.atomic_write`); they compute nothing of radar or dataset and read no
dataset (the learning curves read the runs' ``log.csv``). ``radarpc show`` draws a RADIal frame
(:func:`plot_frame_view`), a ColoRadar frame with its LiDAR and optionally a method's predicted
cloud (:func:`plot_coloradar_view`), or the OS-CFAR tuning search of a prediction folder
(:func:`plot_oscfar_tuning`); ``radarpc evaluate-points --figures`` draws a frame of each scene
with the truth and every method's cloud side by side (:func:`plot_cloud_comparison`, the view
computed by :func:`radarpc.eval.comparison.comparison_view`) and the empirical CDFs of the
per-frame Chamfer distance and EMD (:func:`plot_cdfs`, the curves computed by
:func:`radarpc.eval.comparison.cdf_panels`). Figures are built on matplotlib's object API
(:class:`matplotlib.figure.Figure`, saved through the Agg canvas), so that neither pyplot's figure
registry nor the global backend is touched. :mod:`radarpc.pipelines.frames` computes the inputs of
the frame figures from a dataset root (and optionally a point store or a prediction folder);
:mod:`radarpc.data.summary` those of the summary figures.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from radarpc.boxes import BOX_LENGTH_M, BOX_WIDTH_M
from radarpc.data.radial import LabelTable
from radarpc.data.summary import ColoRadarView, FrameView, RadialSummary, TuningTable
from radarpc.eval.comparison import CDFPanel, ComparisonView, angle_edges_deg, range_edges
from radarpc.eval.curves import DensityCurve, seed_statistics
from radarpc.io import atomic_write
from radarpc.points import PointCloudBatch
from radarpc.sensors.radial import DDMARadarConfig

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "COLOR_BY",
    "figure_format",
    "save_figure",
    "plot_detection_frame",
    "radial_box_corners",
    "rd_extent",
    "doppler_mps_of_column",
    "peak_marker_range_m",
    "FramePlot",
    "plot_frame_view",
    "plot_radial_info",
    "plot_coloradar_info",
    "plot_coloradar_view",
    "plot_oscfar_tuning",
    "plot_cloud_comparison",
    "plot_cdfs",
    "DensityPanel",
    "plot_density_curves",
    "RateCurve",
    "RatePanel",
    "plot_rate_curves",
]

COLOR_BY = ("velocity", "amplitude")
"""What the frame figure colours the points by."""


def _figure(figsize: tuple[float, float]) -> "Figure":
    """A figure outside pyplot (matplotlib is imported on first use: the CLI starts faster)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


_EXTERNAL_FORMATS = frozenset({"pgf"})
"""Formats matplotlib lists but writes only with an outside program (pgf: a LaTeX installation)."""


def figure_format(out: str | os.PathLike) -> str:
    """The file format the suffix of ``out`` names (``.png`` -> ``"png"``, ``.PDF`` -> ``"pdf"``).

    Any format matplotlib writes by itself is accepted (png, pdf, svg, jpg, eps, tiff, webp, ...).
    Call it before computing a figure, so that a bad path fails at once.

    Raises
    ------
    ValueError
        ``out`` has no suffix, or one that is not such a format; the message names the path and
        the supported suffixes.
    """
    from matplotlib.backend_bases import FigureCanvasBase

    formats = sorted(set(FigureCanvasBase.get_supported_filetypes()) - _EXTERNAL_FORMATS)
    suffix = Path(out).suffix
    if suffix.lower().removeprefix(".") not in formats:
        what = f"its suffix {suffix!r} names no figure format" if suffix else "it has no suffix"
        raise ValueError(f"cannot write the figure {out}: {what}; give a path ending in one of "
                         + ", ".join(f".{f}" for f in formats))
    return suffix.lower().removeprefix(".")


def save_figure(fig: "Figure", out: str | os.PathLike, dpi: int, metadata: dict[str, str] | None = None) -> None:
    """Write ``fig`` at ``out`` in the format its suffix names (:func:`figure_format`: PNG for
    ``.png``, PDF for ``.pdf``, ...), atomically (temp file + rename): a reader never sees half
    a figure, and two writers never mix one. ``metadata`` is stored in the file (PNG text chunks
    such as ``"Description"``; matplotlib's ``savefig(metadata=...)``)."""
    fmt = figure_format(out)
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format=fmt, dpi=dpi, metadata=metadata)


# ---- one frame: RD + CFAR + BEV points -----------------------------------------------------------
def radial_box_corners(range_m, azimuth_deg, length: float = BOX_LENGTH_M,
                       width: float = BOX_WIDTH_M) -> np.ndarray:
    """Corners ``(V, 4, 2)`` ``(x, y)`` (x forward, y left, metres) of RADIal's vehicle boxes.

    RADIal's metrics turn a label ``(R, A)`` (``radar_R_m``, ``radar_A_deg``) into an axis-aligned
    bird's-eye box ``width`` wide and ``length`` long (:mod:`radarpc.boxes`: 1.8 m x 4 m, FFTRadNet
    ``utils/metrics.py`` ``RA_to_cartesian_box``) whose near edge is centred on the label point
    ``(X, Y) = (R cos A, R sin A)``: ``x`` in ``[X, X + length]``, ``y`` in ``[Y - width/2, Y + width/2]``.
    Corners in RADIal's order: near right, near left, far left, far right (``y`` = left)."""
    r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    a = np.radians(np.asarray(azimuth_deg, dtype=np.float64).reshape(-1))
    x, y, h = r * np.cos(a), r * np.sin(a), 0.5 * width
    return np.stack([np.stack([x, y - h], -1), np.stack([x, y + h], -1),
                     np.stack([x + length, y + h], -1), np.stack([x + length, y - h], -1)], 1)


def rd_extent(cfg: DDMARadarConfig, n_cols: int) -> tuple[float, float, float, float]:
    """``imshow`` extent (m/s, m) of an ``(Nr, n_cols)`` RD image drawn Doppler-centred
    (``np.fft.fftshift`` along the Doppler axis, origin lower): column ``j`` is centred on
    ``(j - n_cols // 2) * velocity_res_mps`` (:func:`doppler_mps_of_column` of its unshifted bin),
    row ``r`` spans ``[(r - 0.5) res, (r + 0.5) res]``, centred on ``r * res`` = the points' ``range_m``."""
    res, dv, h = cfg.range_res_m, cfg.velocity_res_mps, n_cols // 2
    return ((-h - 0.5) * dv, (n_cols - h - 0.5) * dv, -0.5 * res, (cfg.n_range - 0.5) * res)


def doppler_mps_of_column(cfg: DDMARadarConfig, col, n_cols: int) -> np.ndarray:
    """Where unshifted Doppler bin ``col`` of an ``n_cols``-bin axis is drawn (m/s): the signed bin
    ``((col + n_cols // 2) mod n_cols - n_cols // 2)`` times ``velocity_res_mps``. On the full axis
    (``n_cols = n_doppler``) this is Tx 0's radial velocity of the bin
    (:meth:`DDMARadarConfig.velocity_of_bin`); on the consolidated axis (``slot_width``) the velocity
    modulo ``slot_width * velocity_res_mps``."""
    h = n_cols // 2
    return ((np.asarray(col, dtype=np.float64) + h) % n_cols - h) * cfg.velocity_res_mps


def _bins_axis(ax, cfg: DDMARadarConfig, n_cols: int, label: str) -> None:
    """A top axis in Doppler bins (the cube's unshifted index, ``mod n_cols``) over an m/s axis."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    dv = cfg.velocity_res_mps
    top = ax.secondary_xaxis("top", functions=(lambda v: v / dv, lambda b: b * dv))
    top.xaxis.set_major_locator(MaxNLocator(nbins=6, integer=True))
    top.xaxis.set_major_formatter(FuncFormatter(lambda b, _: f"{int(round(b)) % n_cols}"))
    top.set_xlabel(label, fontsize=9)


def peak_marker_range_m(cfg: DDMARadarConfig, range_bin: np.ndarray) -> np.ndarray:
    """Vertical position of the CFAR-peak markers: ``r * res``, as ``range_m`` and :func:`rd_extent`."""
    return np.asarray(range_bin, dtype=np.float64) * cfg.range_res_m


@dataclass(frozen=True)
class FramePlot:
    """What :func:`plot_frame_view` drew."""

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


def _tau_text(tau: float) -> str:
    """The CFAR threshold with its unit: a linear SNR (power ratio) and the same in dB."""
    return f"tau = {tau:.3g} (linear SNR, {10.0 * np.log10(tau):.2f} dB)"


def _bev_extent(cfg: DDMARadarConfig, y: np.ndarray, box_y: np.ndarray, box_x: np.ndarray) -> tuple[float, float]:
    """Lateral half-width and forward extent (m) of the BEV panel: forward to the maximum range or
    the farthest box end; laterally every box and 98 % of the points (a few wide-angle points must
    not squash the panel to +-max range), at least 0.3 and at most 0.6 times the forward extent (a
    readable panel at equal aspect; what lies wider is counted below the panel)."""
    rmax = cfg.max_range_m
    top = max(rmax, float(box_x.max()) if box_x.size else 0.0)
    wide = [float(np.abs(box_y).max())] if box_y.size else []
    if y.size:
        wide.append(float(np.quantile(np.abs(y), 0.98)))
    half = min(max(1.1 * max(wide, default=0.0) + 2.0, 0.3 * top), 0.6 * top)
    return half, top


def plot_frame_view(view: FrameView, out: str | os.PathLike, color_by: str = "velocity") -> FramePlot:
    """Draw a :class:`~radarpc.data.summary.FrameView` to ``out`` (PNG, atomic), 18 x 7 in at 80 dpi.

    Panels: (a) ``A(r, d)`` in dB against Doppler in m/s (Doppler-centred; the cube's bin index on
    the top axis) with the encoded set overlaid cell by cell, (b) the envelope ``E(r, l)`` in dB
    with the CFAR peaks ``P(tau)``, against the consolidated Doppler in m/s (modulo the slot width;
    ``l`` on the top axis), (c) the points in bird's-eye view (x forward, y left, left drawn on the
    left) coloured by radial velocity or by angle-spectrum amplitude, with RADIal's 4 m x 1.8 m
    vehicle boxes (:func:`radial_box_corners`). Range bin ``r`` is drawn centred on
    ``r * range_res_m`` (the points' ``range_m``) in both RD panels.
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch, Polygon

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
    boxes = radial_box_corners(view.vehicles_ra[:, 0], view.vehicles_ra[:, 1])       # (V, 4, 2)
    nd, w = cfg.n_doppler, cfg.slot_width

    def shift(a):  # Doppler-centred columns, as rd_extent draws them
        return np.fft.fftshift(a, axes=1)

    fig = _figure((18, 7))
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.4, 0.9, 1.2]})
    im0 = ax[0].imshow(shift(_db(view.rd_magnitude)), aspect="auto", origin="lower", cmap="viridis",
                       extent=rd_extent(cfg, nd))
    # S(tau) as an exact per-cell overlay (markers would hide the spectrum on a 512 x 256 grid)
    ax[0].imshow(np.ma.masked_where(~shift(mask_full), shift(mask_full).astype(float)), aspect="auto",
                 origin="lower", cmap=ListedColormap(["red"]), alpha=0.85, interpolation="nearest",
                 extent=rd_extent(cfg, nd))
    ax[0].legend(handles=[Patch(color="red", label=f"{view.set_name}: {int(mask_full.sum())} cells")],
                 loc="upper right", fontsize=10)
    ax[0].set(xlabel=f"Doppler of the full axis [m/s] (Tx 0's velocity; bin = {cfg.velocity_res_mps:.3f} m/s)",
              ylabel="range [m]", title="sum_rx |R| [dB]")
    _bins_axis(ax[0], cfg, nd, "Doppler bin d of the cube")
    fig.colorbar(im0, ax=ax[0], label="sum_rx |R| [dB]")
    im1 = ax[1].imshow(shift(_db(e)), aspect="auto", origin="lower", cmap="magma", extent=rd_extent(cfg, w))
    pr, pl = np.nonzero(pk)
    ax[1].scatter(doppler_mps_of_column(cfg, pl, w), peak_marker_range_m(cfg, pr), s=14, marker="x", c="cyan",
                  linewidths=0.8, label=f"P(tau): {int(pk.sum())} CFAR peaks")
    ax[1].set(xlabel=f"consolidated Doppler [m/s] (mod {w * cfg.velocity_res_mps:.2f} m/s)", ylabel="range [m]",
              title="envelope E(r, l) [dB] + CFAR peaks")
    _bins_axis(ax[1], cfg, w, "consolidated Doppler bin l")
    ax[1].legend(loc="upper right", fontsize=10)
    fig.colorbar(im1, ax=ax[1], label="E(r, l) [dB]")
    if color_by == "velocity":  # symmetric colour scale: white = 0 m/s
        vmax = max(float(np.abs(cval).max()) if cval.size else 0.0, cfg.velocity_res_mps)
        sc = ax[2].scatter(y, x, c=cval, s=6, cmap="coolwarm", vmin=-vmax, vmax=vmax)
    else:
        sc = ax[2].scatter(y, x, c=cval, s=6, cmap="viridis")
    fig.colorbar(sc, ax=ax[2], label="radial velocity [m/s]" if color_by == "velocity" else "amplitude Ae [dB]")
    for b in boxes:
        ax[2].add_patch(Polygon(b[:, ::-1], closed=True, fill=False, edgecolor="k", linewidth=1.4, clip_on=True))
    half, top = _bev_extent(cfg, y, boxes[..., 1], boxes[..., 0])
    hidden = int(np.sum((np.abs(y) > half) | (x > top)))
    ax[2].set_xlim(half, -half)                                 # left of the car drawn on the left
    ax[2].set_ylim(0.0, top)
    ax[2].set_aspect("equal", adjustable="box")
    ax[2].set(xlabel="y [m] (left +)" + (f"; {hidden} points beyond +-{half:.0f} m not shown" if hidden else ""),
              ylabel="x [m] (forward)",
              title=f"BEV: {len(x)} points, density {density:.4f}\n{_tau_text(tau_used)}")
    ax[2].legend(handles=[Patch(facecolor="none", edgecolor="k", linewidth=1.4,
                                label=f"vehicles ({len(boxes)}): 4 m x 1.8 m boxes")],
                 loc="upper left", fontsize=10, framealpha=0.8)
    fig.suptitle(view.title, fontsize=13)
    fig.tight_layout()
    save_figure(fig, out, dpi=80)
    peak_density = float(pk.sum()) * cfg.n_tx / (cfg.n_range * cfg.n_doppler)
    return FramePlot(path=out, frame=view.frame, n_points=int(len(x)), n_peaks=int(pk.sum()),
                     density=density, tau=tau_used, n_vehicles=int(len(boxes)), peak_density=peak_density)


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
    save_figure(fig, out, dpi=90)
    return out


# ---- ColoRadar: radarpc info and radarpc show ---------------------------------------------------
LIDAR_OUTSIDE_COLOR = "0.7"
LIDAR_INSIDE_COLOR = "tab:blue"
PRED_COLOR = "tab:red"
FRUSTUM_COLOR = "tab:green"


def _frustum_bev(ax, fov) -> None:
    a = np.radians(np.linspace(*fov.azimuth_deg, 181))
    r = fov.max_range_m
    ax.plot(np.r_[0, r * np.sin(a), 0], np.r_[0, r * np.cos(a), 0], "-", color=FRUSTUM_COLOR, lw=1.2,
            label=f"radar frustum ({fov.max_range_m:.1f} m)")


def _lidar_bev(ax, view: ColoRadarView, lim: float) -> None:
    """LiDAR (grey outside the frustum, blue inside), the prediction (red) and the frustum, x
    forward up, y left on the left; legend colours are the scatter colours."""
    pts, inside = view.lidar_xyz, view.inside_xyz
    near = np.abs(pts[:, :2]).max(1) < lim
    ax.scatter(pts[near, 1], pts[near, 0], s=0.5, c=LIDAR_OUTSIDE_COLOR, label="LiDAR outside the frustum")
    ax.scatter(inside[:, 1], inside[:, 0], s=1.0, c=LIDAR_INSIDE_COLOR, label=f"LiDAR in the frustum ({len(inside)})")
    if view.pred_xyz is not None:
        q = view.pred_xyz
        ax.scatter(q[:, 1], q[:, 0], s=6, c=PRED_COLOR, label=f"prediction ({len(q)}): {view.pred_label}")
    _frustum_bev(ax, view.fov)
    ax.set(xlim=(lim, -lim), ylim=(-0.25 * lim, lim), aspect="equal", xlabel="y [m] (left +)",
           ylabel="x [m] (forward)")
    ax.legend(loc="lower left", fontsize=9, markerscale=6, framealpha=0.85)


def _cube_panel(fig, ax, view: ColoRadarView) -> None:
    """The single-chip cube, max over elevation (dB), on its true (sin-spaced) azimuth bins."""
    img, rr, az = view.cube_db, view.cube_range_m, view.cube_azimuth_deg
    im = ax.pcolormesh(angle_edges_deg(az), range_edges(rr), img, cmap="magma", shading="flat")
    ax.set_xlim(ax.get_xlim()[::-1])                           # left (+azimuth) on the left, as in the BEV
    ax.set(xlabel="azimuth [deg] (left +; sin-spaced FFT bins)", ylabel="range [m]",
           title=f"single-chip cube, frame {view.radar_index}: max over elevation")
    fig.colorbar(im, ax=ax, label="intensity [dB] (10 log10(P / noise + 1))")


def plot_coloradar_info(view: ColoRadarView, out: str | os.PathLike) -> Path:
    """The ColoRadar summary figure (PNG, atomic, 6 in per panel x 5 in at 110 dpi): the LiDAR
    scan in bird's-eye view (radar frame) with the frustum, the single-chip cube and, if the view
    has one, the cascade heatmap (both max over elevation, dB, with colour bars)."""
    out = Path(out)
    n_ax = 2 + int(view.heatmap_db is not None)
    fig = _figure((6 * n_ax, 5))
    axes = fig.subplots(1, n_ax)
    ax = axes[0]
    _lidar_bev(ax, view, view.fov.max_range_m + 2)
    ax.set_title(f"{view.run} LiDAR {view.lidar_index}: {len(view.inside_xyz)} pts in frustum")
    if view.cube_db is not None:
        _cube_panel(fig, axes[1], view)
    else:
        axes[1].text(0.5, 0.5, "no single-chip radar frames", ha="center", va="center")
        axes[1].set_axis_off()
    if view.heatmap_db is not None:
        ax = axes[2]
        az = view.heatmap_azimuth_deg
        im = ax.imshow(view.heatmap_db.T, origin="lower", aspect="auto", cmap="magma",
                       extent=(float(az[0]), float(az[-1]), 0.0, view.heatmap_max_range_m))
        ax.set_xlim(ax.get_xlim()[::-1])
        ax.set(xlabel="azimuth [deg] (left +)", ylabel="range [m]", title="cascade heatmap: max over elevation")
        fig.colorbar(im, ax=ax, label="intensity [dB]")
    if view.root_name:
        fig.suptitle(f"ColoRadar root '{view.root_name}', run {view.run}: radar frame {view.radar_index}, "
                     f"LiDAR scan {view.lidar_index}")
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
    return out


def plot_coloradar_view(view: ColoRadarView, out: str | os.PathLike) -> Path:
    """One ColoRadar frame (PNG, atomic, 18 x 6 in at 100 dpi): (a) the single-chip cube, max over
    elevation (dB), range against azimuth, (b) the bird's-eye view of the paired LiDAR scan (grey
    outside the frustum, blue inside) with the predicted cloud (red) if the view has one, (c) the
    side view (x forward, z up) of the in-frustum LiDAR and the prediction."""
    if view.cube_db is None:
        raise ValueError(f"run {view.run} has no single-chip radar frame to draw")
    out = Path(out)
    fig = _figure((18, 6))
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.0, 1.1, 1.1]})
    _cube_panel(fig, ax[0], view)
    lim = view.fov.max_range_m + 1
    _lidar_bev(ax[1], view, lim)
    ax[1].set_title("bird's-eye view (radar frame)")
    inside = view.inside_xyz
    ax[2].scatter(inside[:, 0], inside[:, 2], s=1.0, c=LIDAR_INSIDE_COLOR, label=f"LiDAR in the frustum ({len(inside)})")
    if view.pred_xyz is not None:
        q = view.pred_xyz
        ax[2].scatter(q[:, 0], q[:, 2], s=6, c=PRED_COLOR, label=f"prediction ({len(q)})")
    e = np.radians(view.fov.elevation_deg)
    r = view.fov.max_range_m
    ax[2].plot([0, r * np.cos(e[0]), np.nan, 0, r * np.cos(e[1])], [0, r * np.sin(e[0]), np.nan, 0, r * np.sin(e[1])],
               "-", color=FRUSTUM_COLOR, lw=1.2, label=f"frustum, elevation {view.fov.elevation_deg[0]:g} to "
                                                      f"{view.fov.elevation_deg[1]:g} deg")
    ax[2].set(xlim=(0, lim), ylim=(-0.5 * lim, 0.5 * lim), aspect="equal", xlabel="x [m] (forward)",
              ylabel="z [m] (up)", title="side view (radar frame)")
    ax[2].legend(loc="upper left", fontsize=9, markerscale=6, framealpha=0.85)
    dt = "" if not np.isfinite(view.lidar_dt_s) else f" ({1e3 * view.lidar_dt_s:+.0f} ms)"
    fig.suptitle(f"ColoRadar root '{view.root_name}', run {view.run}: radar frame {view.radar_index}, "
                 f"paired LiDAR scan {view.lidar_index}{dt}", fontsize=13)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


# ---- methods side by side ------------------------------------------------------------------------
METHOD_COLORS = ("tab:red", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
"""Colours of the methods' clouds, in the order given."""


def _cloud_label(c) -> str:
    drawn = f", {c.n_drawn:,} drawn" if c.n_drawn < c.n_points else ""
    return f"{c.name}: {c.n_points:,} points{drawn}" if c.n_points else f"{c.name}: no point (empty)"


def plot_cloud_comparison(view: ComparisonView, out: str | os.PathLike) -> Path:
    """One frame, methods side by side (atomic; 4.2 in per column x 8.4 in at 100 dpi).

    Columns: the radar cube, the LiDAR truth, then each method of ``view.methods``; top row the
    bird's-eye view (x forward up, y left on the left, metres; the cube as its intensity, max over
    elevation, on its range-azimuth cells), bottom row range against elevation (the cube's max over
    azimuth). A method's panels show the truth in light grey beneath its cloud; every panel of a
    row shares the axes, the frustum is outlined, the cube's panels carry dB colour bars.
    """
    out = Path(out)
    n_col = 2 + len(view.methods)
    fig = _figure((4.2 * n_col, 8.4))
    axes = fig.subplots(2, n_col, sharex="row", sharey="row", squeeze=False)
    fov = view.fov
    lim = fov.max_range_m + 0.5
    a = np.radians(np.linspace(*fov.azimuth_deg, 181))
    frustum_xy = (np.r_[0, fov.max_range_m * np.sin(a), 0], np.r_[0, fov.max_range_m * np.cos(a), 0])
    e0, e1 = fov.elevation_deg

    def frame_panels(k: int, title: str) -> None:
        top, bottom = axes[0, k], axes[1, k]
        top.plot(*frustum_xy, "-", color=FRUSTUM_COLOR, lw=1.0, label="frustum")
        top.set(xlim=(lim, -lim), ylim=(-0.05 * lim, lim), aspect="equal", title=title)
        bottom.plot([0, fov.max_range_m, np.nan, 0, fov.max_range_m], [e0, e0, np.nan, e1, e1], "-",
                    color=FRUSTUM_COLOR, lw=1.0, label="frustum")
        bottom.set(xlim=(0, lim), ylim=(e0 - 5, e1 + 5))
        if k == 0:
            top.set_ylabel("x [m] (forward)")
            bottom.set_ylabel("elevation [deg] (up +)")
        top.set_xlabel("y [m] (left +)")
        bottom.set_xlabel("range [m]")

    # the radar cube
    im = axes[0, 0].pcolormesh(view.bev_y, view.bev_x, view.bev_db, cmap="magma", shading="flat")
    fig.colorbar(im, ax=axes[0, 0], label="intensity [dB], max over elevation", shrink=0.8)
    im = axes[1, 0].pcolormesh(view.re_range, view.re_elevation, view.re_db.T, cmap="magma", shading="flat")
    fig.colorbar(im, ax=axes[1, 0], label="intensity [dB], max over azimuth", shrink=0.8)
    frame_panels(0, "radar cube (single chip)")
    axes[1, 0].set_title("range-elevation")

    # the truth, then each method over the truth in grey
    t = view.truth
    axes[0, 1].scatter(t.xy[:, 1], t.xy[:, 0], s=0.5, c=LIDAR_INSIDE_COLOR, label=_cloud_label(t))
    axes[1, 1].scatter(t.range_elevation[:, 0], t.range_elevation[:, 1], s=0.5, c=LIDAR_INSIDE_COLOR,
                       label=_cloud_label(t))
    frame_panels(1, "LiDAR truth (in the frustum)")
    for k, c in enumerate(view.methods):
        col = METHOD_COLORS[k % len(METHOD_COLORS)]
        top, bottom = axes[0, 2 + k], axes[1, 2 + k]
        top.scatter(t.xy[:, 1], t.xy[:, 0], s=0.3, c=LIDAR_OUTSIDE_COLOR, label="LiDAR truth")
        bottom.scatter(t.range_elevation[:, 0], t.range_elevation[:, 1], s=0.3, c=LIDAR_OUTSIDE_COLOR,
                       label="LiDAR truth")
        top.scatter(c.xy[:, 1], c.xy[:, 0], s=0.8, c=col, label=_cloud_label(c))
        bottom.scatter(c.range_elevation[:, 0], c.range_elevation[:, 1], s=0.8, c=col, label=_cloud_label(c))
        frame_panels(2 + k, c.name + (f" ({c.note})" if c.note else ""))
    for ax in axes[:, 1:].ravel():
        ax.legend(loc="lower left", fontsize=7, markerscale=8, framealpha=0.85)
    split = f" ({view.split} split)" if view.split else ""
    fig.suptitle(f"scene {view.scene}{split}: run {view.run}, radar frame {view.frame}, LiDAR scan "
                 f"{view.lidar_index}; top: bird's-eye view, bottom: range-elevation", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


def plot_cdfs(panels: list[CDFPanel], out: str | os.PathLike, *, title: str, xlabel: str, footer: str = "",
              metadata: dict[str, str] | None = None) -> Path:
    """Empirical CDFs of a per-frame score, one panel each (a scene, or all frames), one curve per
    method, as the seed's Figs. 6-7: a step at every frame's score; the curve of a method with
    empty predictions ends below 1 (those frames are never reached), which its legend says.

    Parameters
    ----------
    panels : list of CDFPanel
        From :func:`radarpc.eval.comparison.cdf_panels`.
    out : path-like
        The figure to write (its suffix names the format; folders are created).
    title : str
        The figure's title.
    xlabel : str
        The score's axis label, with its unit (e.g. ``"Chamfer distance [m]"``).
    footer : str
        Small text under the panels (what made the figure).
    metadata : dict, optional
        Stored in the file (:func:`save_figure`).
    """
    out, fig, axes = _panel_figure(out, len(panels), "plot_cdfs")
    names = list(dict.fromkeys(c.label for panel in panels for c in panel.curves))
    colour = {n: f"C{k % 10}" for k, n in enumerate(names)}           # one colour per method in every panel
    for k, (ax, panel) in enumerate(zip(axes, panels)):
        right = max((float(c.x[-1]) for c in panel.curves if c.x.size), default=1.0)
        for c in panel.curves:
            empty = f", {c.n_empty} empty" if c.n_empty else ""
            label = f"{c.label} ({c.n_frames} frames{empty})"
            if c.x.size == 0:                                        # nothing scored: a flat line at 0
                ax.plot([0.0, right], [0.0, 0.0], color=colour[c.label], label=label)
                continue
            x = np.r_[c.x[0], c.x, right]
            p = np.r_[0.0, c.p, c.p[-1]]
            ax.step(x, p, where="post", color=colour[c.label], label=label)
        ax.set(xlim=(0.0, 1.02 * right), ylim=(0.0, 1.02), xlabel=xlabel, title=panel.title)
        if k % _PANELS_PER_ROW == 0:
            ax.set_ylabel("fraction of frames with a score <= x (CDF)")
        ax.grid(alpha=0.3)
        if panel.curves:
            ax.legend(fontsize=8, loc="lower right")
    fig.suptitle(f"{title}\nempirical CDF over the frames; a frame whose prediction is empty counts as never "
                 f"reached (the curve ends at the scored fraction)", fontsize=10)
    return _save_with_footer(fig, out, footer, metadata)


# ---- OS-CFAR tuning ------------------------------------------------------------------------------
def plot_oscfar_tuning(table: TuningTable, out: str | os.PathLike) -> Path:
    """The OS-CFAR grid search (PNG, atomic, 13 x 5 in at 100 dpi): (a) mean Chamfer distance
    against the threshold ``tau_db``, one line per other setting (window, guard, rank, angle
    upsampling), the chosen setting's line and candidate highlighted; (b) mean Chamfer distance
    against mean predicted points per frame, coloured by ``tau_db`` (colour bar)."""
    out = Path(out)
    fig = _figure((13, 5))
    ax = fig.subplots(1, 2)
    b = table.best
    settings = list(dict.fromkeys(table.setting))
    for st in settings:
        rows = np.array([i for i, s in enumerate(table.setting) if s == st])
        rows = rows[np.argsort(table.tau_db[rows], kind="stable")]
        mine = st == table.setting[b]
        ax[0].plot(table.tau_db[rows], table.chamfer_m[rows], "-o", ms=3 if not mine else 5,
                   color="tab:red" if mine else "0.65", lw=2.0 if mine else 0.8, zorder=3 if mine else 2,
                   label=f"chosen: {st}" if mine else None)
    if len(settings) > 1:
        ax[0].plot([], [], "-o", ms=3, color="0.65", lw=0.8, label=f"the other {len(settings) - 1} settings")
    ax[0].scatter([table.tau_db[b]], [table.chamfer_m[b]], marker="*", s=250, c="gold", edgecolors="k", zorder=4,
                  label=f"best: tau {table.tau_db[b]:g} dB, {table.chamfer_m[b]:.3f} m")
    ax[0].set(xlabel="OS-CFAR threshold tau [dB]", ylabel="mean Chamfer distance to the LiDAR [m]",
              title="Chamfer distance against the threshold")
    ax[0].legend(fontsize=9, loc="best")
    sc = ax[1].scatter(table.points_per_frame, table.chamfer_m, c=table.tau_db, cmap="viridis", s=18)
    ax[1].scatter([table.points_per_frame[b]], [table.chamfer_m[b]], marker="*", s=250, c="gold", edgecolors="k",
                  zorder=4, label=f"best: {table.points_per_frame[b]:.0f} points per frame")
    if np.all(table.points_per_frame > 0):
        ax[1].set_xscale("log")
    ax[1].set(xlabel="mean predicted points per frame", ylabel="mean Chamfer distance to the LiDAR [m]",
              title="Chamfer distance against cloud size")
    ax[1].legend(fontsize=9, loc="best")
    fig.colorbar(sc, ax=ax[1], label="tau [dB]")
    fig.suptitle(f"OS-CFAR tuning ({table.path}): {len(table.tau_db)} candidates, mean over {table.n_frames} "
                 f"{table.split} frames", fontsize=12)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    return out


# ---- radarpc evaluate --show --------------------------------------------------------------------
def _draw_boxes(ax, range_m: np.ndarray, azimuth_deg: np.ndarray, color: str, label: str) -> None:
    from matplotlib.patches import Polygon

    for k, c in enumerate(radial_box_corners(range_m, azimuth_deg)):
        ax.add_patch(Polygon(c[:, ::-1], closed=True, fill=False, ec=color, lw=1.2,
                             label=label if k == 0 else None))


def plot_detection_frame(batch, detections, probability: torch.Tensor | None, out: str | os.PathLike, *,
                         title: str = "", range_max_m: float = 103.0) -> Path:
    """One evaluated frame: bird's-eye view with RADIal's label boxes (green) and the predicted
    boxes (red), over the frame's points when the model reads points; and the predicted vehicle
    probability on the 128 x 224 range-azimuth map with the labels marked.

    Parameters
    ----------
    batch : radarpc.experiments.radial_detection.task.DetectionBatch
        A batch of one frame (on the CPU).
    detections : radarpc.boxes.Detections
        Its decoded detections (one frame).
    probability : Tensor ``(128, 224)`` or None
        Channel 0 of the detection head's output; None (a detector without a map, the classical
        row) draws the bird's-eye view alone.
    out : path-like
        PNG to write (folders are created).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    lab = batch.labels.numpy()
    r_lab, a_lab = lab[:, 0], lab[:, 1]
    if probability is None:
        fig = _figure((5.5, 5.5))
        ax_bev = fig.subplots(1, 1)
    else:
        fig = _figure((12, 5.5))
        ax_bev, ax_ra = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.3]})
    if isinstance(batch.inputs, PointCloudBatch):
        p = batch.inputs
        ax_bev.scatter(p.y.numpy(), p.x.numpy(), s=2, c="0.5", label=f"points ({p.num_points})")
    _draw_boxes(ax_bev, r_lab, a_lab, "tab:green", "labels")
    _draw_boxes(ax_bev, detections.range_m.numpy(), detections.azimuth_deg.numpy(), "tab:red",
                "predicted (confidence >= 0.2)")
    ax_bev.set(xlim=(40, -40), ylim=(0, range_max_m), xlabel="y [m] (left +)", ylabel="x [m] (forward)",
               title="bird's-eye view")
    ax_bev.set_aspect("equal", adjustable="box")
    ax_bev.legend(loc="upper right", fontsize=8)
    if probability is not None:
        h, w = probability.shape
        im = ax_ra.imshow(probability.numpy(), origin="lower", aspect="auto", vmin=0, vmax=1, cmap="magma",
                          extent=(-w / 2 * 0.8, w / 2 * 0.8, 0, range_max_m))
        ax_ra.scatter(a_lab, r_lab, marker="o", s=40, facecolors="none", edgecolors="tab:green", label="labels")
        ax_ra.invert_xaxis()                        # left of the car on the left, as in the bird's-eye view
        ax_ra.set(xlabel="azimuth [deg] (left +)", ylabel="range [m]", title="predicted vehicle probability")
        ax_ra.legend(loc="upper right", fontsize=8)
        fig.colorbar(im, ax=ax_ra, label="predicted vehicle probability")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, out, dpi=90)
    return out


# ---- training runs ------------------------------------------------------------------------------
def plot_learning_curves(logs: dict[str, str | os.PathLike], out: str | os.PathLike,
                         against: str = "time") -> Path:
    """Validation F1 (RADIal's, and at confidence 0.2) and training loss of runs against their
    cumulative training time or their optimizer steps, from each run's ``log.csv``.

    Parameters
    ----------
    logs : dict
        Curve label -> ``log.csv`` of a run (:func:`radarpc.training.loop.fit`).
    out : path-like
        PNG to write.
    against : {"time", "step"}
        The x axis: minutes of training, or optimizer steps (for runs whose epochs were slowed by
        other work on the machine).
    """
    if against not in ("time", "step"):
        raise ValueError(f"against must be 'time' or 'step', got {against!r}")
    import csv

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = _figure((12, 4))
    ax_f1, ax_fix, ax_loss = fig.subplots(1, 3)
    for name, path in logs.items():
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            continue
        if against == "time":
            x = np.cumsum([float(r["train_time_s"]) for r in rows]) / 60
        else:
            x = np.array([int(r["step"]) for r in rows])
        for ax, key in ((ax_f1, "val_f1"), (ax_fix, "val_f1_fixed"), (ax_loss, "train_loss")):
            if key in rows[0]:
                ax.plot(x, [float(r[key]) if r[key] else np.nan for r in rows], marker="o", label=name)
    xlabel = "training time [min]" if against == "time" else "optimizer steps"
    ax_f1.set(xlabel=xlabel, ylabel="F1", title="validation F1 (AP, AR over 0.1..0.9)", ylim=(0, 1))
    ax_fix.set(xlabel=xlabel, ylabel="F1", title="validation F1 at confidence 0.2", ylim=(0, 1))
    ax_loss.set(xlabel=xlabel, ylabel="loss", title="training loss (epoch mean)", yscale="log")
    for ax in (ax_f1, ax_fix, ax_loss):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=90)
    return out


def plot_label_outcomes(metrics: dict, out: str | os.PathLike, title: str = "") -> Path:
    """What became of the labels at each confidence threshold: matched (IoU >= 0.5), missed with
    a detection within :data:`~radarpc.eval.detection.NEAR_MISS_M` (a localisation miss), or
    missed with nothing near; and the false alarms.

    Parameters
    ----------
    metrics : dict
        :meth:`radarpc.eval.detection.DetectionReport.to_dict` (``thresholds``, ``fn``, ``fn_near``,
        ``fp``, ``n_labels``, ``n_frames``), e.g. the ``metrics`` of an ``eval_{split}.json``.
    out : path-like
        PNG to write.
    title : str
    """
    from radarpc.eval.detection import NEAR_MISS_M

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    t = np.asarray(metrics["thresholds"], dtype=float)
    fp = np.asarray(metrics["fp"], float)
    fn, near = np.asarray(metrics["fn"], float), np.asarray(metrics["fn_near"], float)
    n_labels = int(metrics["n_labels"])
    fig = _figure((10, 4))
    ax, ax_fp = fig.subplots(1, 2)
    w = 0.07
    if n_labels:
        matched = n_labels - fn                # labels, not detections (TP counts detections)
        ax.bar(t, matched / n_labels, w, label="matched (IoU >= 0.5)", color="tab:green")
        ax.bar(t, near / n_labels, w, bottom=matched / n_labels,
               label=f"missed, a detection within {NEAR_MISS_M:g} m", color="tab:orange")
        ax.bar(t, (fn - near) / n_labels, w, bottom=(matched + near) / n_labels, label="missed, nothing near",
               color="tab:red")
        ax.legend(fontsize=8, loc="upper right", framealpha=0.9)
    else:                                      # nothing to match: no bar may look like a score
        ax.text(0.5, 0.5, "no labels in these frames:\nrecall and F1 are not defined", ha="center", va="center",
                transform=ax.transAxes)
    ax.set(xlabel="confidence threshold", ylabel="share of labels", ylim=(0, 1), xticks=t,
           title=f"the {n_labels} labels" if n_labels else "no labels")
    ax_fp.bar(t, fp / max(int(metrics.get("n_frames", 1)), 1), w, color="tab:gray")
    ax_fp.set(xlabel="confidence threshold", ylabel="false alarms per frame", xticks=t, title="false alarms")
    for a in (ax, ax_fp):
        a.grid(alpha=0.3, axis="y")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, out, dpi=90)
    return out


# ---- studies: scores against density ------------------------------------------------------------
@dataclass(frozen=True)
class DensityPanel:
    """One panel of :func:`plot_density_curves`: curves of a score against density and
    density-free references (a dense model), each with the score of every run (seed).

    Attributes
    ----------
    ylabel, title : str
    curves : tuple of DensityCurve
        Drawn as the mean over runs with a band of +-1 sample standard deviation and every run
        as a dot; the legend gives each curve's normalized AUC when it has one.
    references : tuple of (str, tuple of float)
        ``(label, run scores)``: a horizontal line at the mean, a band of +-1 standard deviation.
    """

    ylabel: str
    title: str
    curves: tuple[DensityCurve, ...]
    references: tuple[tuple[str, tuple[float, ...]], ...] = ()


def plot_density_curves(panels: list[DensityPanel], out: str | os.PathLike, *, title: str,
                        footer: str = "", metadata: dict[str, str] | None = None) -> Path:
    """Scores against data density (in percent of RD cells, on a log axis), one panel each: the
    mean over runs, its spread, every run, and the references as horizontal lines.

    Parameters
    ----------
    panels : list of DensityPanel
    out : path-like
        The figure to write (its suffix names the format; folders are created).
    title : str
        The figure's title.
    footer : str
        Small text under the panels (what made the figure).
    metadata : dict, optional
        Stored in the file (:func:`save_figure`).
    """
    out, fig, axes = _panel_figure(out, len(panels), "plot_density_curves")
    colours = label_colours(panels)
    for ax, panel in zip(axes, panels):
        for curve in panel.curves:
            c = colours[curve.label]
            x = 100 * np.asarray(curve.density, dtype=float)
            stats = curve.statistics
            mean = np.array([s.mean for s in stats])
            std = np.array([np.nan if s.std is None else s.std for s in stats])
            label = curve.label + ("" if curve.auc is None else f" (AUC_norm {curve.auc:.3f})")
            ax.plot(x, mean, marker="o", color=c, label=label)
            if np.isfinite(std).any():
                ax.fill_between(x, mean - std, mean + std, color=c, alpha=0.18, lw=0)
            for xi, runs in zip(x, curve.runs):
                ax.scatter(np.full(len(runs), xi), runs, s=10, color=c, alpha=0.6, lw=0)
        for label, runs in panel.references:
            c = colours[label]
            s = seed_statistics(runs)
            ax.axhline(s.mean, color=c, ls="--", label=f"{label} ({s.mean:.3f})")
            if s.std is not None:
                ax.axhspan(s.mean - s.std, s.mean + s.std, color=c, alpha=0.12, lw=0)
        ax.set_xscale("log")
        _density_axis(ax, panel)
        if panel.curves or panel.references:
            ax.legend(fontsize=8, loc="best")          # where it hides the fewest points
    fig.suptitle(f"{title}\nline: mean over runs (seeds), band: +-1 standard deviation, dots: each run; "
                 f"dashed: density-free references", fontsize=10)
    return _save_with_footer(fig, out, footer, metadata)


def label_colours(panels: list[DensityPanel]) -> dict[str, str]:
    """One matplotlib colour per curve or reference label, the same in every panel: labels in the
    order they first appear (curves before references within a panel), ``C0``, ``C1``, ... cycled."""
    labels = dict.fromkeys(label for panel in panels
                           for label in [c.label for c in panel.curves] + [r[0] for r in panel.references])
    return {label: f"C{k % 10}" for k, label in enumerate(labels)}


_PANELS_PER_ROW = 3


def _panel_figure(out, n_panels: int, what: str):
    """``(out, figure, axes)`` for ``n_panels`` in rows of at most three (a wider figure stops being
    readable), ``out`` checked and its folder made; cells past the last panel are hidden."""
    if not n_panels:
        raise ValueError(f"{what}: no panel to draw")
    out = Path(out)
    figure_format(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cols = min(n_panels, _PANELS_PER_ROW)
    rows = -(-n_panels // cols)
    fig = _figure((6.4 * cols, 4.8 * rows))
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    return out, fig, axes[:n_panels]


def _density_axis(ax, panel) -> None:
    """A log density axis ticked at the measured densities (in percent), titled and gridded."""
    ticks = sorted({100 * d for curve in panel.curves for d in curve.density})
    if ticks:
        ax.set_xticks(ticks, [f"{t:.3g}" for t in ticks])
        ax.xaxis.set_minor_formatter(_no_labels())
    ax.set(xlabel="data density |S| / (N_r N_D) [%] (log scale)", ylabel=panel.ylabel, title=panel.title)
    ax.grid(alpha=0.3, which="both")


def footer_lines(footer: str, width_in: float, fontsize: float = 6.5) -> list[str]:
    """``footer`` broken at spaces into lines that fit ``width_in`` inches at ``fontsize`` points
    (0.62 em a character, wider than DejaVu Sans' average, so that no line runs off the figure)."""
    import textwrap

    return textwrap.wrap(footer, width=max(20, int(0.98 * width_in * 72 / (0.62 * fontsize))),
                         break_on_hyphens=False)


def _save_with_footer(fig, out, footer: str | None, metadata) -> Path:
    """Write ``fig`` with ``footer`` (the provenance line) in small print under it, wrapped to its width."""
    bottom = 0.0
    if footer:
        lines = footer_lines(footer, fig.get_figwidth())
        fig.text(0.01, 0.005, "\n".join(lines), fontsize=6.5, color="0.35", ha="left", va="bottom")
        bottom = max(0.04, (0.03 + len(lines) * 6.5 * 1.25 / 72) / fig.get_figheight())
    fig.tight_layout(rect=(0, bottom, 1, 1))
    save_figure(fig, out, dpi=110, metadata=metadata)
    return out


def _no_labels():
    from matplotlib.ticker import NullFormatter

    return NullFormatter()


def _plain_log_labels():
    """Labels of a log axis as plain numbers (minor ticks labelled only on short spans, as matplotlib's)."""
    from matplotlib.ticker import LogFormatter

    return LogFormatter(labelOnlyBase=False, minor_thresholds=(1.5, 0.5))


# ---- studies: frames/s against density ----------------------------------------------------------
@dataclass(frozen=True)
class RateCurve:
    """A model's frames/s against density: the median of the timed sweeps at each density and
    their lowest and highest (:class:`radarpc.models.complexity.Rate`).

    Attributes
    ----------
    label : str
    density : tuple of float
        Densities (fractions of RD cells), increasing.
    median, low, high : tuple of float
        Frames/s at each density.
    dashed : bool
        Drawn dashed (e.g. the extraction included) rather than solid.
    """

    label: str
    density: tuple[float, ...]
    median: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    dashed: bool = False

    def __post_init__(self) -> None:
        n = len(self.density)
        if not (len(self.median) == len(self.low) == len(self.high) == n):
            raise ValueError(f"curve {self.label!r}: {n} densities, {len(self.median)} medians, {len(self.low)} "
                             f"lows and {len(self.high)} highs")


@dataclass(frozen=True)
class RatePanel:
    """One panel of :func:`plot_rate_curves`: rate curves and density-free references (a dense
    model: ``(label, median, low, high)``, a horizontal line with its range as a band)."""

    title: str
    curves: tuple[RateCurve, ...]
    references: tuple[tuple[str, float, float, float], ...] = ()
    ylabel: str = "frames/s at batch 1 (log scale)"


def plot_rate_curves(panels: list[RatePanel], out: str | os.PathLike, *, title: str, footer: str = "",
                     metadata: dict[str, str] | None = None) -> Path:
    """Frames/s against data density (both axes logarithmic), one panel each: each curve's median
    with the range of its sweeps as error bars, the references as horizontal lines.

    Parameters
    ----------
    panels : list of RatePanel
    out : path-like
        The figure to write (its suffix names the format; folders are created).
    title, footer : str
        The figure's title and the small text under it (what made the figure).
    metadata : dict, optional
        Stored in the file (:func:`save_figure`).
    """
    out, fig, axes = _panel_figure(out, len(panels), "plot_rate_curves")
    most = max(len(p.curves) + len(p.references) for p in panels)
    if most > 8:                                        # room for the legends under the panels
        w, h = fig.get_size_inches()
        fig.set_size_inches(w, h + 0.16 * ((most + 1) // 2) + 0.4)   # 0.16 in a legend row, two columns
    colours = [f"C{k}" for k in range(10)]
    for ax, panel in zip(axes, panels):
        named: dict[str, str] = {}                      # one colour per model, solid and dashed alike
        for curve in panel.curves:
            base = curve.label.split(" + ")[0]
            c = named.setdefault(base, colours[len(named) % len(colours)])
            x = 100 * np.asarray(curve.density, dtype=float)
            med = np.asarray(curve.median, dtype=float)
            err = np.stack([med - np.asarray(curve.low, dtype=float), np.asarray(curve.high, dtype=float) - med])
            ax.errorbar(x, med, yerr=np.clip(err, 0, None), marker="o", ms=4, capsize=3, color=c,
                        ls="--" if curve.dashed else "-", label=curve.label)
        for k, (label, med, low, high) in enumerate(panel.references):
            c = colours[(len(named) + k) % len(colours)]
            ax.axhline(med, color=c, ls=":", label=f"{label} ({med:.3g})")
            ax.axhspan(low, high, color=c, alpha=0.12, lw=0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(_plain_log_labels())      # 60, not 6 x 10^1
        ax.yaxis.set_minor_formatter(_plain_log_labels())
        _density_axis(ax, panel)
        entries = len(panel.curves) + len(panel.references)
        if entries > 8:                                 # below the panel: inside, it would hide the curves
            ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
        elif entries:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"{title}\nline: median of the timed sweeps, bars: their range; solid: network alone, dashed: "
                 f"with extraction; dotted: density-free references", fontsize=10)
    return _save_with_footer(fig, out, footer, metadata)
