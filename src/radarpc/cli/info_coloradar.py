"""``radarpc info ROOT`` on a ColoRadar root: runs, frames, scenes, splits, LiDAR points per frame,
a summary figure (LiDAR bird's-eye view with the radar frustum, radar cube and cascade heatmap
slices) and with ``--check`` a scan of every file. Called by :mod:`radarpc.cli.info` when ROOT holds
``calib/`` and no ``labels.csv``. The figure goes to ``--plot PATH``, by default
``./info_{root name}.png`` in the current directory (never into the dataset root); ``--no-plot``
skips it."""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarpc.data.coloradar import (
    SPLITS,
    ColoRadarRun,
    crop_to_frustum,
    find_runs,
    lidar_to_radar,
    pair_radar_lidar,
    radar_cube,
    split_runs,
)
from radarpc.io import DataFileError, atomic_write
from radarpc.sensors.coloradar import AWR1843_FOV, ColoRadarCalib, load_calib

__all__ = ["RunSummary", "summarize_run", "check_run", "plot_coloradar", "default_plot_path", "info_coloradar"]


@dataclass(frozen=True)
class RunSummary:
    """What ``radarpc info`` prints for one run."""

    name: str
    scene: str
    split: str
    radar_frames: int
    heatmaps: int
    lidar_scans: int
    pairs: int
    duration_s: float
    lidar_points: tuple[float, float] | None        # mean raw / mean in-frustum points of sampled scans


def summarize_run(run: ColoRadarRun, split: str, *, sample: int = 3) -> RunSummary:
    """Counts from the timestamp files plus LiDAR point counts of ``sample`` paired scans."""
    n_r = run.num_radar_frames if run.has_adc else 0
    n_h = len(run.heatmap_timestamps) if run.has_heatmaps else 0
    n_l = run.num_lidar_frames
    pairs = pair_radar_lidar(run) if n_r else np.zeros((0, 2), np.int64)
    t = run.lidar_timestamps
    pts = None
    if len(pairs):
        idx = np.unique(np.linspace(0, len(pairs) - 1, min(sample, len(pairs))).astype(int))
        raw, crop = [], []
        for k in idx:
            cloud = run.lidar(int(pairs[k, 1]))
            raw.append(len(cloud))
            crop.append(len(crop_to_frustum(lidar_to_radar(cloud, run.calib)[:, :3], AWR1843_FOV)))
        pts = (float(np.mean(raw)), float(np.mean(crop)))
    return RunSummary(run.name, run.scene, split, n_r, n_h, n_l, len(pairs), float(t[-1] - t[0]), pts)


def check_run(run: ColoRadarRun, progress=None) -> list[str]:
    """Open every frame of a run; return one line per bad or missing file."""
    bad: list[str] = []
    jobs = []
    if run.has_adc:
        jobs += [("adc", i) for i in range(run.num_radar_frames)]
    if run.has_heatmaps:
        jobs += [("heatmap", i) for i in range(len(run.heatmap_timestamps))]
    jobs += [("lidar", i) for i in range(run.num_lidar_frames)]
    try:
        run.poses
    except DataFileError as e:
        bad.append(str(e))
    for kind, i in jobs:
        try:
            getattr(run, kind)(i)
        except DataFileError as e:
            bad.append(str(e))
        if progress is not None:
            progress.update(1)
    return bad


def plot_coloradar(root: Path, calib: ColoRadarCalib, run: ColoRadarRun, out: Path) -> None:
    """Summary PNG: LiDAR BEV (radar frame) with the frustum, radar cube and heatmap slices."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = pair_radar_lidar(run)
    ri, li = (int(v) for v in pairs[len(pairs) // 2]) if len(pairs) else (0, 0)
    n_ax = 2 + int(run.has_heatmaps and calib.cascade is not None)
    fig, axes = plt.subplots(1, n_ax, figsize=(5.5 * n_ax, 5))
    pts = lidar_to_radar(run.lidar(li), calib)[:, :3]
    inside = crop_to_frustum(pts, AWR1843_FOV)
    ax = axes[0]
    lim = AWR1843_FOV.max_range_m + 2
    near = np.abs(pts[:, :2]).max(1) < lim
    ax.scatter(pts[near, 1], pts[near, 0], s=0.3, c="0.75", label="LiDAR (radar frame)")
    ax.scatter(inside[:, 1], inside[:, 0], s=0.5, c=inside[:, 2], cmap="viridis", label="inside frustum")
    a = np.radians(np.linspace(*AWR1843_FOV.azimuth_deg, 181))
    r = AWR1843_FOV.max_range_m
    ax.plot(np.r_[0, r * np.sin(a), 0], np.r_[0, r * np.cos(a), 0], "r-", lw=1, label="radar frustum")
    ax.set(xlim=(lim, -lim), ylim=(-lim, lim), aspect="equal", xlabel="y (m, left)", ylabel="x (m, forward)",
           title=f"{run.name} LiDAR {li}: {len(inside)} pts in frustum")
    ax.legend(loc="lower left", fontsize=7, markerscale=8)
    ax = axes[1]
    if run.has_adc:
        cube = radar_cube(run.adc(ri), calib.single_chip)
        img = cube.intensity_db.amax(-1).numpy()                    # (R, A)
        rr = cube.range_m.numpy()
        az = np.degrees(cube.azimuth_rad.numpy())
        ax.imshow(img, origin="lower", aspect="auto", cmap="magma",
                  extent=(-0.5, img.shape[1] - 0.5, float(rr[0]), float(rr[-1])))
        ax.set_xticks(range(img.shape[1]), [f"{a:.0f}" for a in az])
        ax.set(xlabel="azimuth bin centre (deg; sin-spaced FFT bins)", ylabel="range (m)",
               title=f"single-chip cube {ri}: max over elevation (dB)")
    if n_ax == 3:
        ax = axes[2]
        hm = run.heatmap(min(ri, len(run.heatmap_timestamps) - 1))
        hm_cfg = calib.cascade.heatmap
        img = 10 * np.log10(np.maximum(hm[..., 0].max(0), 1e-6))     # (A, R)
        az = np.degrees(hm_cfg.azimuth_bins)
        ax.imshow(img.T, origin="lower", aspect="auto", cmap="magma",
                  extent=(float(az[0]), float(az[-1]), 0.0, hm_cfg.num_range_bins * hm_cfg.range_bin_width))
        ax.set(xlabel="azimuth (deg)", ylabel="range (m)", title="cascade heatmap: max over elevation (dB)")
    fig.tight_layout()
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)


def default_plot_path(root: str | Path) -> Path:
    """``./info_{root name}.png`` in the current directory: ``radarpc info`` never writes into a
    dataset root unless ``--plot`` asks for it."""
    name = Path(root).resolve().name or "root"
    return Path.cwd() / f"info_{name}.png"


def info_coloradar(args: argparse.Namespace) -> int:
    """``radarpc info`` on a ColoRadar root; returns 1 if ``--check`` found a bad file, else 0."""
    root = Path(args.root)
    calib = load_calib(root / "calib")
    names = find_runs(root)
    if not names:
        raise DataFileError(root, "holds calib/ but no run folder (expected e.g. lab_run0/ with lidar/, single_chip/)")
    split_of = {n: s for s in SPLITS for n in split_runs(names, s)}
    runs = [ColoRadarRun(root / n, calib) for n in names]
    sc, cc = calib.single_chip, calib.cascade
    print(f"ColoRadar root {root} ({'simulated' if (root / 'simulation.json').is_file() else 'dataset'})")
    print(f"single chip: ADC {sc.adc_shape} int16, {sc.waveform.range_bin_width():.4f} m/bin, "
          f"+-{sc.waveform.max_velocity_mps:.2f} m/s")
    if cc is not None:
        print(f"cascade:     heatmap {cc.heatmap.shape} float32, {cc.heatmap.range_bin_width:.4f} m/bin")
    print(f"{'run':<34}{'scene':<24}{'split':<7}{'radar':>6}{'heatm':>6}{'lidar':>6}{'pairs':>6}"
          f"{'dur s':>7}{'pts/scan':>10}{'in FOV':>8}")
    sums = []
    for run in runs:
        s = summarize_run(run, split_of[run.name])
        sums.append(s)
        p = s.lidar_points or (math.nan, math.nan)
        print(f"{s.name:<34}{s.scene:<24}{s.split:<7}{s.radar_frames:>6}{s.heatmaps:>6}{s.lidar_scans:>6}"
              f"{s.pairs:>6}{s.duration_s:>7.1f}{p[0]:>10.0f}{p[1]:>8.0f}")
    scenes = sorted({s.scene for s in sums})
    print(f"scenes:      {len(scenes)} ({', '.join(scenes)})")
    for sp in SPLITS:
        ss = [s for s in sums if s.split == sp]
        print(f"{sp + ':':<13}{len(ss)} runs, {sum(s.pairs for s in ss)} paired frames")
    pts = [s.lidar_points for s in sums if s.lidar_points]
    if pts:
        print(f"LiDAR:       {np.mean([p[0] for p in pts]):.0f} points per scan, "
              f"{np.mean([p[1] for p in pts]):.0f} inside the radar frustum (mean of sampled scans)")
    if not getattr(args, "no_plot", False):
        out = Path(args.plot) if getattr(args, "plot", None) else default_plot_path(root)
        best = max(runs, key=lambda r: r.num_lidar_frames)
        plot_coloradar(root, calib, best, out)
        print(f"plot:        {out}")
    write_skip = getattr(args, "write_skip", None)
    if getattr(args, "check", False) or write_skip:
        from tqdm import tqdm
        total = sum((r.num_radar_frames if r.has_adc else 0)
                    + (len(r.heatmap_timestamps) if r.has_heatmaps else 0) + r.num_lidar_frames for r in runs)
        bad: list[str] = []
        with tqdm(total=total, desc="check", unit="file") as bar:
            for run in runs:
                bad += check_run(run, bar)
        print(f"check:       {total} files, {len(bad)} bad")
        for line in bad:
            print(f"  {line}")
        if write_skip:
            with atomic_write(write_skip, "w") as f:
                f.write("".join(line + "\n" for line in bad))
            print(f"skip list:   {len(bad)} file(s) written to {write_skip}")
        return 1 if bad else 0
    return 0
