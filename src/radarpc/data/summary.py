"""What a dataset root holds: the counts ``radarpc info`` prints, the file scan of ``--check`` on
ColoRadar roots, and the arrays its summary figures draw (:mod:`radarpc.viz` draws them); also
:class:`FrameView`, what the RADIal frame figure draws (:func:`radarpc.pipelines.frames.frame_view`
computes it).

RADIal roots: :func:`summarize_radial` reads ``labels.csv`` and ``sensor.json`` only;
:func:`first_rd_power_db` loads the first readable RD cube. ColoRadar roots: :func:`summarize_coloradar`
counts every run from its timestamp files and a few LiDAR scans, :func:`check_runs` opens every
file, :func:`coloradar_view` prepares one LiDAR scan, radar cube and heatmap of a run (the middle
pair for ``radarpc info``, a chosen radar frame for ``radarpc show``: :func:`coloradar_frame_view`).
:func:`read_tuning` reads the OS-CFAR grid search of a prediction folder (``tuning.json``).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from radarpc.data.coloradar import (
    DISJOINT_SPLITS as COLORADAR_SPLITS,
    ColoRadarRun,
    crop_to_frustum,
    find_runs,
    lidar_to_radar,
    pair_radar_lidar,
    split_runs,
)
from radarpc.data.radial import (
    SPLIT_CHOICES as RADIAL_SPLITS,
    LabelTable,
    find_fft_file,
    load_rd,
    read_labels,
    root_sensor,
    split_of_sequence,
)
from radarpc.data.radial_truth import LabelStatistics, label_statistics
from radarpc.io import DataFileError, atomic_write
from radarpc.data.coloradar_format import load_calib
from radarpc.dsp.tdm import radar_cube
from radarpc.points import PointCloudBatch
from radarpc.sensors.coloradar import AWR1843_FOV, ColoRadarCalib, RadarFOV
from radarpc.sensors.radial import DDMARadarConfig

__all__ = [
    "RadialSummary",
    "summarize_radial",
    "first_rd_power_db",
    "FrameView",
    "RunSummary",
    "summarize_run",
    "ColoRadarSummary",
    "open_coloradar_runs",
    "summarize_coloradar",
    "check_run",
    "check_runs",
    "write_check_list",
    "ColoRadarView",
    "coloradar_view",
    "coloradar_frame_view",
    "TuningTable",
    "read_tuning",
]


# ---- RADIal ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RadialSummary:
    """Counts and label ranges of a RADIal root (what ``radarpc info`` prints)."""

    root: Path
    sensor: DDMARadarConfig
    simulated: bool                            # has a sensor.json
    n_frames: int
    n_sequences: int
    split_frames: dict[str, int]               # frames per split (train/val/test, in that order)
    split_sequences: dict[str, int]            # sequences per split
    n_vehicles: int                            # label rows that are vehicles
    n_difficult: int                           # of which Difficult == 1
    n_empty_frames: int                        # frames without any vehicle
    range_m: tuple[float, float] | None        # min/max radar_R_m of vehicles
    azimuth_deg: tuple[float, float] | None    # min/max radar_A_deg
    doppler_mps: tuple[float, float] | None    # min/max radar_D
    statistics: LabelStatistics                # per-frame counts, distributions, scene mix


def summarize_radial(root: str | os.PathLike, labels: LabelTable | None = None) -> RadialSummary:
    """Summarize a RADIal root from its ``labels.csv`` and ``sensor.json`` (no cube is read), with
    the label statistics of :func:`radarpc.data.radial_truth.label_statistics` (the simulator's
    sidecars included when the root has them).

    Parameters
    ----------
    root : path-like
        RADIal-layout root.
    labels : LabelTable, optional
        ``root/labels.csv`` already read (it is read otherwise).
    """
    root = Path(root)
    sensor, meta = root_sensor(root)
    labels = labels if labels is not None else read_labels(root / "labels.csv")
    seq_of: dict[int, str] = {}
    for n, s in zip(labels.num_sample.tolist(), labels.dataset):
        seq_of.setdefault(int(n), s)
    names = sorted(set(seq_of.values()))
    n_seq = meta.n_sequences if meta is not None else None
    split_of = {s: split_of_sequence(s, names, n_sequences=n_seq) for s in names}
    splits = tuple(s for s in RADIAL_SPLITS if s != "all")   # the three disjoint splits
    split_frames = {k: 0 for k in splits}
    for s in seq_of.values():
        split_frames[split_of[s]] += 1
    split_sequences = {k: sum(1 for s in names if split_of[s] == k) for k in splits}
    veh = labels.has_vehicle
    frames_with = set(labels.num_sample[veh].tolist())

    def span(col: str) -> tuple[float, float] | None:
        v = labels.column(col)[veh]
        return (float(v.min()), float(v.max())) if v.size else None

    return RadialSummary(
        root=root, sensor=sensor, simulated=meta is not None, n_frames=len(seq_of),
        n_sequences=len(names), split_frames=split_frames, split_sequences=split_sequences,
        n_vehicles=int(veh.sum()), n_difficult=int((labels.difficult[veh] == 1).sum()),
        n_empty_frames=len(seq_of) - len(frames_with),
        range_m=span("radar_R_m"), azimuth_deg=span("radar_A_deg"), doppler_mps=span("radar_D"),
        statistics=label_statistics(labels, root))


def first_rd_power_db(root: str | os.PathLike, labels: LabelTable,
                      sensor: DDMARadarConfig) -> tuple[int, np.ndarray] | None:
    """The mean power over Rx in dB, ``10 log10(mean_rx |R|^2 + 1e-30)`` ``(Nr, Nd)``, of the first
    frame (lowest numSample of ``labels``) whose cube loads, with its numSample; None if none loads."""
    for num in np.unique(labels.num_sample).tolist():
        try:
            cube = load_rd(find_fft_file(root, num), sensor)      # (Nr, Nd, Nrx)
        except DataFileError:
            continue
        return num, 10.0 * np.log10(np.mean(np.abs(cube) ** 2, axis=2) + 1e-30)
    return None


@dataclass(frozen=True)
class FrameView:
    """What the RADIal frame figure draws (:func:`radarpc.viz.plot_frame_view`), on the CPU."""

    title: str                      # figure title: root name, frame, sequence
    frame: int                      # RADIal numSample
    sensor: DDMARadarConfig
    rd_magnitude: np.ndarray        # (Nr, Nd) A = sum_rx |R|
    encoded: np.ndarray             # (Nr, Nd) bool, the set the cloud encodes (radarpc.dsp.sparse_rd.encoded_cells)
    set_name: str                   # "S(tau)" or "S*(tau)"
    envelope: np.ndarray            # (Nr, W) E(r, l)
    peaks: np.ndarray               # (Nr, W) bool, P(tau)
    cloud: PointCloudBatch          # the frame's points
    vehicles_ra: np.ndarray         # (V, 2) radar_R_m, radar_A_deg of the labelled vehicles


# ---- ColoRadar ---------------------------------------------------------------------------------
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


@dataclass(frozen=True)
class ColoRadarSummary:
    """A ColoRadar root: its calibration, one :class:`RunSummary` per run, and the totals."""

    root: Path
    calib: ColoRadarCalib
    simulated: bool                                 # has a simulation.json
    runs: tuple[RunSummary, ...]                    # in find_runs order
    scenes: tuple[str, ...]                         # sorted
    split_runs: dict[str, int]                      # runs per split (train/val/test)
    split_pairs: dict[str, int]                     # paired radar/LiDAR frames per split
    lidar_points: tuple[float, float] | None        # mean over runs of RunSummary.lidar_points


def open_coloradar_runs(root: str | os.PathLike, errors: list[DataFileError] | None = None
                        ) -> tuple[ColoRadarCalib, list[ColoRadarRun]]:
    """The calibration of ``root/calib`` and every run of ``root`` (sorted by name).

    With ``errors`` (a list), a run that cannot be opened (e.g. an empty or decreasing
    ``timestamps.txt``) is left out and its error appended, so that a check can list every bad
    run instead of stopping at the first.

    Raises
    ------
    DataFileError
        ``root`` holds no run folder, or (without ``errors``) a run cannot be opened.
    """
    root = Path(root)
    calib = load_calib(root / "calib")
    names = find_runs(root)
    if not names:
        raise DataFileError(root, "holds calib/ but no run folder (expected e.g. lab_run0/ with lidar/, single_chip/)")
    runs = []
    for n in names:
        try:
            run = ColoRadarRun(root / n, calib)
            if errors is not None:
                run.count_problems()            # reads every timestamps file: unreadable ones raise here
            runs.append(run)
        except DataFileError as e:
            if errors is None:
                raise
            errors.append(e)
    return calib, runs


def summarize_coloradar(root: str | os.PathLike, calib: ColoRadarCalib,
                        runs: Sequence[ColoRadarRun]) -> ColoRadarSummary:
    """Summarize the runs of a ColoRadar root (from :func:`open_coloradar_runs`)."""
    root = Path(root)
    names = [r.name for r in runs]
    split_of = {n: s for s in COLORADAR_SPLITS for n in split_runs(names, s)}
    sums = tuple(summarize_run(r, split_of[r.name]) for r in runs)
    pts = [s.lidar_points for s in sums if s.lidar_points]
    return ColoRadarSummary(
        root=root, calib=calib, simulated=(root / "simulation.json").is_file(), runs=sums,
        scenes=tuple(sorted({s.scene for s in sums})),
        split_runs={sp: sum(1 for s in sums if s.split == sp) for sp in COLORADAR_SPLITS},
        split_pairs={sp: sum(s.pairs for s in sums if s.split == sp) for sp in COLORADAR_SPLITS},
        lidar_points=(float(np.mean([p[0] for p in pts])), float(np.mean([p[1] for p in pts]))) if pts else None)


def check_run(run: ColoRadarRun, progress=None) -> list[str]:
    """Open every frame of a run; return one line per bad or missing file.

    ``progress`` (a tqdm bar, optional) advances by one per file opened.
    """
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
    bad += [str(e) for e in run.count_problems()]    # timestamp lines vs data files, per stream
    for kind, i in jobs:
        try:
            getattr(run, kind)(i)
        except DataFileError as e:
            bad.append(str(e))
        if progress is not None:
            progress.update(1)
    return bad


def check_runs(runs: Sequence[ColoRadarRun], *, progress: bool = True) -> tuple[int, list[str]]:
    """Open every file of ``runs``: the number of frame files opened and one line per bad file."""
    from tqdm import tqdm

    total = sum((r.num_radar_frames if r.has_adc else 0)
                + (len(r.heatmap_timestamps) if r.has_heatmaps else 0) + r.num_lidar_frames for r in runs)
    bad: list[str] = []
    with tqdm(total=total, desc="check", unit="file", disable=not progress) as bar:
        for run in runs:
            bad += check_run(run, bar)
    return total, bad


def write_check_list(path: str | os.PathLike, lines: Sequence[str]) -> None:
    """Write the lines of :func:`check_runs` to ``path``, one per line (atomic)."""
    with atomic_write(path, "w") as f:
        f.write("".join(line + "\n" for line in lines))


@dataclass(frozen=True)
class ColoRadarView:
    """One moment of a run, as the ColoRadar summary figure draws it (radar frame, metres)."""

    run: str
    lidar_index: int
    radar_index: int
    fov: RadarFOV                           # the frustum the LiDAR is cropped to
    lidar_xyz: np.ndarray                   # (N, 3) the LiDAR scan in the radar frame
    inside_xyz: np.ndarray                  # (M, 3) its points inside the frustum
    cube_db: np.ndarray | None              # (R, A) single-chip intensity, max over elevation (dB); None without ADC
    cube_range_m: np.ndarray | None         # (R,)
    cube_azimuth_deg: np.ndarray | None     # (A,) azimuth bin centres
    heatmap_db: np.ndarray | None           # (A, R) cascade heatmap, max over elevation (dB); None without one
    heatmap_azimuth_deg: np.ndarray | None  # (A,)
    heatmap_max_range_m: float | None       # num_range_bins * range_bin_width
    root_name: str = ""                     # the root folder's name
    lidar_dt_s: float = math.nan            # LiDAR time - radar time of the pair (s)
    pred_xyz: np.ndarray | None = None      # (P, 3) a method's predicted cloud for the radar frame (radar frame)
    pred_label: str = ""                    # e.g. "os-cfar (preds/oscfar)"


def coloradar_view(run: ColoRadarRun, calib: ColoRadarCalib, radar_index: int | None = None) -> ColoRadarView:
    """One radar frame of ``run`` with its paired LiDAR scan: the scan in the radar frame and its
    frustum crop, the single-chip cube of the radar frame and the cascade heatmap of the same
    index (clipped to the last heatmap).

    ``radar_index`` None takes the middle radar/LiDAR pair (the first frames if none pair); a
    given index must be paired (:func:`radarpc.data.coloradar.pair_radar_lidar`), else ValueError.
    """
    pairs = pair_radar_lidar(run)
    if radar_index is None:
        ri, li = (int(v) for v in pairs[len(pairs) // 2]) if len(pairs) else (0, 0)
    else:
        n = run.num_radar_frames if run.has_adc else 0
        if not 0 <= int(radar_index) < n:
            raise ValueError(f"radar frame {radar_index} is not in run {run.name} (it has {n} single-chip "
                             f"frames: 0 to {n - 1})" if n else f"run {run.name} has no single-chip radar frame")
        hit = pairs[pairs[:, 0] == int(radar_index)]
        if not len(hit):
            raise ValueError(f"radar frame {radar_index} of run {run.name} has no LiDAR scan close enough in time "
                             f"(paired frames: {_ranges(pairs[:, 0])})")
        ri, li = int(radar_index), int(hit[0, 1])
    pts = lidar_to_radar(run.lidar(li), calib)[:, :3]
    cube_db = cube_range = cube_az = None
    if run.has_adc:
        cube = radar_cube(run.adc(ri), calib.single_chip)
        cube_db = cube.intensity_db.amax(-1).numpy()                 # (R, A)
        cube_range = cube.range_m.numpy()
        cube_az = np.degrees(cube.azimuth_rad.numpy())
    hm_db = hm_az = hm_range = None
    if run.has_heatmaps and calib.cascade is not None:
        hm = run.heatmap(min(ri, len(run.heatmap_timestamps) - 1))
        hm_cfg = calib.cascade.heatmap
        hm_db = 10 * np.log10(np.maximum(hm[..., 0].max(0), 1e-6))  # (A, R)
        hm_az = np.degrees(hm_cfg.azimuth_bins)
        hm_range = hm_cfg.num_range_bins * hm_cfg.range_bin_width
    dt = float(run.lidar_timestamps[li] - run.radar_timestamps[ri]) if run.has_adc and len(pairs) else math.nan
    return ColoRadarView(run=run.name, lidar_index=li, radar_index=ri, fov=AWR1843_FOV, lidar_xyz=pts,
                         inside_xyz=crop_to_frustum(pts, AWR1843_FOV), cube_db=cube_db, cube_range_m=cube_range,
                         cube_azimuth_deg=cube_az, heatmap_db=hm_db, heatmap_azimuth_deg=hm_az,
                         heatmap_max_range_m=hm_range, root_name=run.path.parent.name, lidar_dt_s=dt)


def _ranges(idx) -> str:
    """``0-4, 7, 9-12``: sorted integers as runs of consecutive values."""
    v = sorted(int(i) for i in idx)
    if not v:
        return "none"
    out, start = [], v[0]
    for a, b in zip(v, v[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}-{a}")
            start = b
    return ", ".join(out)


def coloradar_frame_view(root: str | os.PathLike, frame: int, run: str | None = None,
                         pred: tuple[np.ndarray, str] | None = None) -> ColoRadarView:
    """Radar frame ``frame`` (ADC frame index in its run, as in a prediction folder) of run ``run``
    of a ColoRadar root (default: the first run, sorted by name) and its paired LiDAR scan, for
    ``radarpc show``; ``pred`` ``((P, 3) points, label)`` is carried into the view.

    Raises
    ------
    ValueError
        Unknown run, frame out of range or without a paired LiDAR scan.
    DataFileError
        Missing or malformed calibration or frame files.
    """
    calib, runs = open_coloradar_runs(root)
    names = [r.name for r in runs]
    if run is None:
        sel = runs[0]
    elif run in names:
        sel = runs[names.index(run)]
    else:
        raise ValueError(f"run {run!r} is not in {root} (runs: {', '.join(names)})")
    view = coloradar_view(sel, calib, int(frame))
    if pred is not None:
        pts = np.asarray(pred[0], dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"a predicted cloud must be (N, 3), got shape {pts.shape}")
        view = replace(view, pred_xyz=pts, pred_label=str(pred[1]))
    return view


# ---- OS-CFAR tuning ----------------------------------------------------------------------------
@dataclass(frozen=True)
class TuningTable:
    """The OS-CFAR grid search of a prediction folder's ``tuning.json``
    (written by :mod:`radarpc.pipelines.oscfar`), one row per candidate."""

    path: Path
    split: str                      # the tuning split
    n_frames: int                   # frames the search averaged over
    tau_db: np.ndarray              # (K,) threshold of each candidate (dB)
    chamfer_m: np.ndarray           # (K,) mean Chamfer distance to the LiDAR (m)
    points_per_frame: np.ndarray    # (K,) mean predicted points per frame
    setting: tuple[str, ...]        # (K,) the candidate's other parameters, e.g. "window 9x3x3, guard 3x1x1, rank 0.75"
    best: int                       # row of the chosen candidate (lowest Chamfer distance, first on ties)


def _setting(c: dict) -> str:
    ab = c.get("angle_bins")
    return (f"window {'x'.join(map(str, c['window']))}, guard {'x'.join(map(str, c['guard']))}, "
            f"rank {c['rank']:g}" + (f", angles upsampled to {ab[0]}x{ab[1]}" if ab else ""))


def read_tuning(path: str | os.PathLike) -> TuningTable:
    """Read ``tuning.json`` (or the ``tuning.json`` of a prediction folder ``path``).

    Raises
    ------
    DataFileError
        Missing file, or not the JSON that ``radarpc baseline os-cfar`` writes.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "tuning.json"
    if not path.is_file():
        raise DataFileError(path, "OS-CFAR tuning file is missing (radarpc baseline os-cfar writes it when it tunes; "
                                  "a run given --config or reusing config.yaml does not)")
    try:
        d = json.loads(path.read_text())
        rows = d["candidates"]
        tau = np.array([float(r["config"]["tau_db"]) for r in rows])
        cd = np.array([float(r["chamfer_m"]) for r in rows])
        npts = np.array([float(r["points_per_frame"]) for r in rows])
        setting = tuple(_setting(r["config"]) for r in rows)
        split, n = str(d["split"]), int(d["frames"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError) as e:
        raise DataFileError(path, f"is not an OS-CFAR tuning file (expected 'split', 'frames' and 'candidates' "
                                  f"with config.tau_db, chamfer_m, points_per_frame; {type(e).__name__}: {e})") from e
    if not len(rows):
        raise DataFileError(path, "OS-CFAR tuning file lists no candidate")
    return TuningTable(path=path, split=split, n_frames=n, tau_db=tau, chamfer_m=cd, points_per_frame=npts,
                       setting=setting, best=int(np.argmin(cd)))
