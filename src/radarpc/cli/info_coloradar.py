"""``radarpc info ROOT`` on a ColoRadar root: runs, frames, scenes, splits, LiDAR points per frame,
a summary figure (LiDAR bird's-eye view with the radar frustum, radar cube and cascade heatmap
slices) and with ``--check`` a scan of every file. Called by :mod:`radarpc.cli.info` when ROOT holds
``calib/`` and no ``labels.csv``. The figure goes to ``--plot PATH``, by default
``./info_{root name}.png`` in the current directory (never into the dataset root); ``--no-plot``
skips it."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from radarpc.cli.info_outputs import check_outputs
from radarpc.cli.text import plural
from radarpc.data.summary import check_runs, coloradar_view, open_coloradar_runs, summarize_coloradar, write_check_list
from radarpc.viz import plot_coloradar_info

__all__ = ["default_plot_path", "info_coloradar"]


def default_plot_path(root: str | Path) -> Path:
    """``./info_{root name}.png`` in the current directory: ``radarpc info`` never writes into a
    dataset root unless ``--plot`` asks for it."""
    name = Path(root).resolve().name or "root"
    return Path.cwd() / f"info_{name}.png"


def info_coloradar(args: argparse.Namespace) -> int:
    """``radarpc info`` on a ColoRadar root; returns 1 if ``--check`` found a bad file, else 0."""
    root = Path(args.root)
    check_outputs(args, default_plot_path(root))
    # --check lists every run that cannot be opened instead of stopping at the first
    unopened = [] if (getattr(args, "check", False) or getattr(args, "write_skip", None)) else None
    calib, runs = open_coloradar_runs(root, errors=unopened)
    if not runs:
        raise unopened[0]
    summary = summarize_coloradar(root, calib, runs)
    sc, cc = calib.single_chip, calib.cascade
    print(f"ColoRadar root {root} ({'simulated' if summary.simulated else 'dataset'})")
    print(f"single chip: ADC {sc.adc_shape} int16, {sc.waveform.range_bin_width():.4f} m/bin, "
          f"+-{sc.waveform.max_velocity_mps:.2f} m/s")
    if cc is not None:
        print(f"cascade:     heatmap {cc.heatmap.shape} float32, {cc.heatmap.range_bin_width:.4f} m/bin")
    print(f"{'run':<34}{'scene':<24}{'split':<7}{'radar':>6}{'heatm':>6}{'lidar':>6}{'pairs':>6}"
          f"{'dur s':>7}{'pts/scan':>10}{'in FOV':>8}")
    for s in summary.runs:
        p = s.lidar_points or (math.nan, math.nan)
        print(f"{s.name:<34}{s.scene:<24}{s.split:<7}{s.radar_frames:>6}{s.heatmaps:>6}{s.lidar_scans:>6}"
              f"{s.pairs:>6}{s.duration_s:>7.1f}{p[0]:>10.0f}{p[1]:>8.0f}")
    print(f"scenes:      {len(summary.scenes)} ({', '.join(summary.scenes)})")
    for sp, n in summary.split_runs.items():
        print(f"{sp + ':':<13}{plural(n, 'run')}, {plural(summary.split_pairs[sp], 'paired frame')}")
    for e in unopened or []:            # runs left out of the summary (counted as bad below)
        print(f"warning:     {e}")
    for run in runs:                    # timestamp lines vs data files (also counted as bad by --check)
        for e in run.count_problems():
            print(f"warning:     {e}")
    if summary.lidar_points is not None:
        raw, inside = summary.lidar_points
        print(f"LiDAR:       {raw:.0f} points per scan, {inside:.0f} inside the radar frustum (mean of sampled scans)")
    if not getattr(args, "no_plot", False):
        out = Path(args.plot) if getattr(args, "plot", None) else default_plot_path(root)
        best = max(runs, key=lambda r: r.num_lidar_frames)
        plot_coloradar_info(coloradar_view(best, calib), out)
        print(f"plot:        {out}")
    write_skip = getattr(args, "write_skip", None)
    if getattr(args, "check", False) or write_skip:
        total, bad = check_runs(runs)
        bad = [str(e) for e in unopened] + bad
        print(f"check:       {plural(total, 'file')}, {len(bad)} bad")
        for line in bad:
            print(f"  {line}")
        if write_skip:
            write_check_list(write_skip, bad)
            print(f"skip list:   {plural(len(bad), 'file')} written to {write_skip}")
        return 1 if bad else 0
    return 0
