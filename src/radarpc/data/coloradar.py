"""ColoRadar reader: runs, radar cubes as RaLD computes them, paired LiDAR ground truth, Dataset.

Works on the real dataset (run folders such as ``12_21_2020_ec_hallways_run0`` next to ``calib/``)
and on the simulator's output (:mod:`radarpc.sim.coloradar_writer`) alike.

* :class:`ColoRadarRun` -- one run folder: timestamps, poses, single-chip ADC frames, cascade
  heatmaps, LiDAR scans, each validated against the calibration (file size must equal the bytes
  the config implies; NaN/inf rejected; an empty LiDAR scan rejected) with
  :class:`radarpc.io.DataFileError` naming the file.
* :func:`pair_radar_lidar` -- nearest-timestamp pairing, pairs farther apart than ``max_dt``
  dropped (RaLD removes non-overlapping frames).
* :func:`lidar_to_radar` / :func:`frustum_mask` / :func:`crop_to_frustum` -- LiDAR into the
  single-chip frame, ``p_radar = T_base_radar^-1 T_base_lidar p_lidar`` (``base_to_X`` files hold
  translation then quaternion ``qx qy qz qw``, scalar last, mapping X-frame points to base),
  then the radar frustum (range, azimuth ``atan2(y, x)``, elevation ``asin(z / r)``).
* :meth:`ColoRadar.cube` -- a frame's RaLD radar cube, computed by
  :func:`radarpc.dsp.tdm.radar_cube` (the single-chip TDM processing lives in the DSP package).
* :func:`upsample_intensity` -- bilinear (``align_corners=True``) angle upsampling of the
  intensity to the model grid (128 x 64 x 32), as RaLD's dataset does.
* :func:`rald_intensity` -- the radar input of RaLD's networks: the intensity clipped to
  ``[0, 45]`` dB and divided by 45, then upsampled (RaLD's dataset, in that order).
* :class:`ColoRadar` -- torch ``Dataset`` of paired frames of a split; items are
  :class:`ColoRadarItem` (upsampled intensity, cropped LiDAR in the radar frame, metadata).

Splits (:func:`split_runs`): runs named in RaLD's published lists (``split_indoor_june.json``,
``split_outdoor_june.json``) take that split. Any other run (simulated data, runs RaLD did not
use) follows RaLD's rule per scene: runs sorted by their ``_run{k}`` index, the last one is
``test``, the one before ``val``, the rest ``train`` (a scene with two runs gives train/test,
with one run train only). Scene = run name without the ``_run{k}`` suffix.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from radarpc.data.coloradar_format import load_calib
from radarpc.dsp.tdm import RadarCube, radar_cube
from radarpc.io import DataFileError
from radarpc.sensors.coloradar import AWR1843_FOV, ColoRadarCalib, RadarFOV

__all__ = [
    "RALD_SPLITS",
    "DISJOINT_SPLITS",
    "SPLIT_CHOICES",
    "ColoRadarRun",
    "ColoRadarItem",
    "ColoRadar",
    "find_calib",
    "find_runs",
    "simulated_lidar_nbytes",
    "scene_of_run",
    "split_runs",
    "read_timestamps",
    "read_poses",
    "pair_radar_lidar",
    "lidar_to_radar",
    "frustum_mask",
    "crop_to_frustum",
    "upsample_intensity",
    "RALD_MAX_INTENSITY_DB",
    "rald_intensity",
    "collate_coloradar",
]

DISJOINT_SPLITS: tuple[str, ...] = ("train", "val", "test")
"""The three disjoint run-level splits."""
SPLIT_CHOICES: tuple[str, ...] = DISJOINT_SPLITS + ("all",)
"""What ``split`` arguments accept: a disjoint split or ``"all"`` runs."""

# RaLD's published run lists (resource/split_files.tar.gz of RoyAPTX4869/RaLD).
RALD_SPLITS: dict[str, tuple[str, ...]] = {
    "train": (
        "12_21_2020_ec_hallways_run0", "12_21_2020_ec_hallways_run1", "12_21_2020_ec_hallways_run2",
        "12_21_2020_arpg_lab_run0", "12_21_2020_arpg_lab_run1", "12_21_2020_arpg_lab_run2",
        *(f"2_24_2021_aspen_run{k}" for k in range(10)),
        *(f"2_23_2021_edgar_classroom_run{k}" for k in range(4)),
        *(f"2_23_2021_edgar_army_run{k}" for k in range(4)),
        *(f"2_28_2021_outdoors_run{k}" for k in range(8)),
        *(f"2_22_2021_longboard_run{k}" for k in range(6)),
    ),
    "val": ("12_21_2020_arpg_lab_run3", "12_21_2020_ec_hallways_run3", "2_24_2021_aspen_run10",
            "2_23_2021_edgar_classroom_run4", "2_23_2021_edgar_army_run4",
            "2_28_2021_outdoors_run8", "2_22_2021_longboard_run6"),
    "test": ("12_21_2020_arpg_lab_run4", "12_21_2020_ec_hallways_run4", "2_24_2021_aspen_run11",
             "2_23_2021_edgar_classroom_run5", "2_23_2021_edgar_army_run5",
             "2_28_2021_outdoors_run9", "2_22_2021_longboard_run7"),
}

_RUN_RE = re.compile(r"^(.*)_run(\d+)$")


def scene_of_run(name: str) -> str:
    """``'12_21_2020_ec_hallways_run3' -> '12_21_2020_ec_hallways'``; ``'lab_run0' -> 'lab'``."""
    m = _RUN_RE.match(name)
    return m.group(1) if m else name


def _run_index(name: str) -> int:
    m = _RUN_RE.match(name)
    return int(m.group(2)) if m else 0


def split_runs(names: Sequence[str], split: str) -> list[str]:
    """Runs of ``names`` that belong to ``split`` (``train``/``val``/``test``/``all``), see module doc."""
    if split not in SPLIT_CHOICES:
        raise ValueError(f"split must be one of {SPLIT_CHOICES}, got {split!r}")
    names = sorted(set(names))
    if split == "all":
        return names
    official = {n: s for s, runs in RALD_SPLITS.items() for n in runs}
    by_scene: dict[str, list[str]] = {}
    for n in names:
        if n not in official:
            by_scene.setdefault(scene_of_run(n), []).append(n)
    assign = dict((n, official[n]) for n in names if n in official)
    for runs in by_scene.values():
        runs = sorted(runs, key=_run_index)
        for i, n in enumerate(runs):
            last = len(runs) - 1
            assign[n] = "test" if (i == last and last >= 1) else "val" if (i == last - 1 and last >= 2) else "train"
    return [n for n in names if assign[n] == split]


def find_calib(root: str | os.PathLike) -> Path:
    """The ``calib`` folder of a dataset root: ``ROOT/calib`` (ColoRadar's own tools, RaLD, the
    simulator) or ``ROOT/../calib`` (coloradar-library's ``kitti/`` layout, calib beside the runs'
    folder). Raises :class:`DataFileError` naming ``ROOT/calib`` when neither exists."""
    root = Path(root)
    for cand in (root / "calib", root.parent / "calib"):
        if cand.is_dir():
            return cand
    if (root / "labels.csv").is_file():                                       # the other layout
        raise DataFileError(root, "this is a RADIal root (labels.csv, radar_FFT/); the ColoRadar reader and "
                                  "`radarpc baseline` / `evaluate-points` need a ColoRadar root (calib/ and "
                                  "run folders)")
    raise DataFileError(root / "calib", "calibration folder is missing (expected ROOT/calib/ or ROOT/../calib/)")


def find_runs(root: str | os.PathLike) -> list[str]:
    """Run folder names under a ColoRadar root (folders other than ``calib`` holding sensor data)."""
    root = Path(root)
    if not root.is_dir():
        raise DataFileError(root, "dataset root folder is missing")
    out = []
    for d in sorted(root.iterdir()):
        if d.is_dir() and d.name != "calib" and ((d / "lidar").is_dir() or (d / "single_chip").is_dir()):
            out.append(d.name)
    return out


# ------------------------------------------------------------------------------------------------
# text files
# ------------------------------------------------------------------------------------------------
def read_timestamps(path: str | os.PathLike) -> np.ndarray:
    """One float (s) per line -> ``(N,)`` float64; must be finite and non-decreasing."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "timestamps file is missing")
    try:
        vals = [float(ln.split()[0]) for ln in path.read_text().splitlines() if ln.strip()]
    except (ValueError, IndexError) as e:
        raise DataFileError(path, f"expected one number per line ({e})") from e
    t = np.asarray(vals, dtype=np.float64)
    if t.size == 0:
        raise DataFileError(path, "holds no timestamps")
    if not np.isfinite(t).all():
        raise DataFileError(path, "holds NaN or infinite timestamps")
    if (np.diff(t) < 0).any():
        raise DataFileError(path, f"timestamps decrease at line {int(np.argmax(np.diff(t) < 0)) + 2}")
    return t


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """``groundtruth_poses.txt`` -> ``(N, 7)`` float64 ``x y z qx qy qz qw`` (world <- base)."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "poses file is missing")
    rows = [ln.replace(",", " ").split() for ln in path.read_text().splitlines() if ln.strip()]
    if not rows or any(len(r) != 7 for r in rows):
        bad = next((i + 1 for i, r in enumerate(rows) if len(r) != 7), 1)
        raise DataFileError(path, f"expected 7 numbers 'x y z qx qy qz qw' per line (line {bad})")
    try:
        p = np.asarray(rows, dtype=np.float64)
    except ValueError as e:
        raise DataFileError(path, f"cannot parse poses ({e})") from e
    if not np.isfinite(p).all():
        raise DataFileError(path, "holds NaN or infinite values")
    return p


def simulated_lidar_nbytes(root: str | os.PathLike) -> int | None:
    """Bytes of every LiDAR scan of a simulated root, or None for a real dataset root.

    The simulator (:mod:`radarpc.sim.coloradar_writer`) records its LiDAR pattern in
    ``ROOT/simulation.json`` (``"lidar": {"beams": B, "azimuth_steps": S, ...}``) and writes one
    float32 ``(x, y, z, intensity)`` row per ray, rays without return as zeros, so each scan is
    exactly ``B * S * 16`` bytes. Real ColoRadar scans drop empty returns and vary in size.

    Raises
    ------
    DataFileError
        ``simulation.json`` exists but is not JSON or lacks positive integer ``lidar.beams`` /
        ``lidar.azimuth_steps``.
    """
    path = Path(root) / "simulation.json"
    if not path.is_file():
        return None
    import json
    try:
        meta = json.loads(path.read_text())
        beams, steps = meta["lidar"]["beams"], meta["lidar"]["azimuth_steps"]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DataFileError(path, f"expected simulator metadata with lidar.beams and lidar.azimuth_steps ({e})") from e
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (beams, steps)):
        raise DataFileError(path, f"lidar.beams={beams!r} and lidar.azimuth_steps={steps!r} must be positive integers")
    return beams * steps * 16


def _read_bin(path: Path, dtype, nbytes: int | None, what: str, *, multiple_of: int | None = None,
              source: str = "the calibration") -> np.ndarray:
    if not path.is_file():
        raise DataFileError(path, f"{what} file is missing")
    size = path.stat().st_size
    if nbytes is not None and size != nbytes:
        raise DataFileError(path, f"{what}: expected {nbytes} bytes from {source}, found {size} "
                                  f"({'truncated' if size < nbytes else 'too long'})")
    if multiple_of is not None and size % multiple_of:
        raise DataFileError(path, f"{what}: size {size} bytes is not a multiple of {multiple_of} (truncated?)")
    arr = np.fromfile(path, dtype=dtype)
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise DataFileError(path, f"{what} contains NaN or infinite values")
    return arr


# ------------------------------------------------------------------------------------------------
class ColoRadarRun:
    """One ColoRadar run folder, read lazily and validated.

    Parameters
    ----------
    path : path-like
        The run folder (``.../12_21_2020_ec_hallways_run0`` or ``.../lab_run0``).
    calib : ColoRadarCalib, optional
        Defaults to the ``calib/`` found by :func:`find_calib` from the run's parent folder.
    lidar_nbytes : int or "auto" or None
        Exact size every LiDAR scan must have; ``"auto"`` (default) takes it from the parent
        root's ``simulation.json`` (:func:`simulated_lidar_nbytes`; None for real data, whose
        scans vary and are only checked to hold whole 16-byte points).
    """

    def __init__(self, path: str | os.PathLike, calib: ColoRadarCalib | None = None, *,
                 lidar_nbytes: int | str | None = "auto"):
        self.path = Path(path)
        if not self.path.is_dir():
            raise DataFileError(self.path, "run folder is missing")
        self.calib = calib if calib is not None else load_calib(find_calib(self.path.parent))
        if lidar_nbytes == "auto":
            lidar_nbytes = simulated_lidar_nbytes(self.path.parent)
        elif lidar_nbytes is not None and (int(lidar_nbytes) != lidar_nbytes or lidar_nbytes <= 0
                                           or lidar_nbytes % 16):
            raise ValueError(f"lidar_nbytes must be 'auto', None or a positive multiple of 16, got {lidar_nbytes!r}")
        self.lidar_nbytes = lidar_nbytes
        self.name = self.path.name
        self.scene = scene_of_run(self.name)
        self._ts: dict[str, np.ndarray] = {}

    # -- timestamps and poses ---------------------------------------------------------------------
    def _timestamps(self, key: str, rel: str) -> np.ndarray:
        if key not in self._ts:
            self._ts[key] = read_timestamps(self.path / rel)
        return self._ts[key]

    @property
    def radar_timestamps(self) -> np.ndarray:
        """Single-chip ADC frame times ``(F,)``."""
        return self._timestamps("radar", "single_chip/adc_samples/timestamps.txt")

    @property
    def heatmap_timestamps(self) -> np.ndarray:
        """Cascade heatmap times."""
        return self._timestamps("heatmap", "cascade/heatmaps/timestamps.txt")

    @property
    def lidar_timestamps(self) -> np.ndarray:
        return self._timestamps("lidar", "lidar/timestamps.txt")

    @property
    def pose_timestamps(self) -> np.ndarray:
        return self._timestamps("pose", "groundtruth/timestamps.txt")

    @property
    def poses(self) -> np.ndarray:
        """``(P, 7)`` world <- base poses ``x y z qx qy qz qw``; count checked against timestamps."""
        p = read_poses(self.path / "groundtruth" / "groundtruth_poses.txt")
        if len(p) != len(self.pose_timestamps):
            raise DataFileError(self.path / "groundtruth" / "groundtruth_poses.txt",
                                f"{len(p)} poses but {len(self.pose_timestamps)} timestamps")
        return p

    # timestamps file, data folder, data file name (index as group 1), what the files are
    _STREAMS = {
        "radar": ("single_chip/adc_samples/timestamps.txt", "single_chip/adc_samples/data",
                  re.compile(r"^frame_(\d+)\.bin$"), "single-chip ADC frame files"),
        "heatmap": ("cascade/heatmaps/timestamps.txt", "cascade/heatmaps/data",
                    re.compile(r"^heatmap_(\d+)\.bin$"), "cascade heatmap files"),
        "lidar": ("lidar/timestamps.txt", "lidar/pointclouds",
                  re.compile(r"^lidar_pointcloud_(\d+)\.bin$"), "LiDAR scan files"),
    }

    def count_problems(self) -> list[DataFileError]:
        """One error per stream whose ``timestamps.txt`` does not have one line per data file.

        A frame file without a timestamp line can never be paired (and one with a line but no
        file fails when read), so a short ``lidar/timestamps.txt`` would silently drop frames.
        Each line names the timestamps file, its line count and the file count, e.g.
        ``.../lidar/timestamps.txt: 4 timestamp lines but 6 LiDAR scan files in lidar/pointclouds/``.
        """
        out = []
        for key, (rel, folder, pattern, what) in self._STREAMS.items():
            ts_path = self.path / rel
            if key == "radar" and not self.has_adc or key == "heatmap" and not self.has_heatmaps:
                continue
            n_lines = len(self._timestamps(key, rel))
            data = self.path / folder
            n_files = sum(1 for f in data.iterdir() if pattern.match(f.name)) if data.is_dir() else 0
            if n_lines != n_files:
                why = ("the files without a line are never paired" if n_lines < n_files
                       else "the lines without a file cannot be read")
                out.append(DataFileError(ts_path, f"{n_lines} timestamp lines but {n_files} {what} in "
                                                  f"{folder}/ ({why})"))
        return out

    def check_counts(self) -> None:
        """Raise the first error of :meth:`count_problems`: a stream's timestamp lines and data
        files differ in number."""
        problems = self.count_problems()
        if problems:
            raise problems[0]

    def check_poses(self) -> None:
        """Parse and validate the ground-truth poses (NaN/inf, malformed lines, count against the
        timestamps): :class:`DataFileError` naming ``groundtruth_poses.txt`` otherwise."""
        self.poses

    @property
    def has_adc(self) -> bool:
        return (self.path / "single_chip" / "adc_samples" / "timestamps.txt").is_file()

    @property
    def has_heatmaps(self) -> bool:
        return (self.path / "cascade" / "heatmaps" / "timestamps.txt").is_file()

    @property
    def num_radar_frames(self) -> int:
        return len(self.radar_timestamps)

    @property
    def num_lidar_frames(self) -> int:
        return len(self.lidar_timestamps)

    # -- frames -----------------------------------------------------------------------------------
    def adc_path(self, i: int) -> Path:
        return self.path / "single_chip" / "adc_samples" / "data" / f"frame_{i}.bin"

    def heatmap_path(self, i: int) -> Path:
        return self.path / "cascade" / "heatmaps" / "data" / f"heatmap_{i}.bin"

    def lidar_path(self, i: int) -> Path:
        return self.path / "lidar" / "pointclouds" / f"lidar_pointcloud_{i}.bin"

    def adc(self, i: int) -> np.ndarray:
        """Single-chip frame ``i`` as complex64 ``(tx, rx, chirps, samples)`` (I + jQ)."""
        chip = self.calib.single_chip
        raw = _read_bin(self.adc_path(i), np.int16, chip.adc_nbytes, "single-chip ADC frame")
        raw = raw.reshape(chip.adc_shape).astype(np.float32)
        return (raw[..., 0] + 1j * raw[..., 1]).astype(np.complex64)

    def heatmap(self, i: int) -> np.ndarray:
        """Cascade heatmap ``i``: float32 ``(elevation, azimuth, range, 2)`` (intensity, Doppler)."""
        if self.calib.cascade is None:
            raise DataFileError(self.path.parent / "calib" / "cascade", "cascade calibration is missing")
        hm = self.calib.cascade.heatmap
        arr = _read_bin(self.heatmap_path(i), np.float32, self.calib.cascade.heatmap_nbytes, "cascade heatmap")
        return arr.reshape(hm.shape)

    def lidar(self, i: int, *, drop_zeros: bool = True) -> np.ndarray:
        """LiDAR scan ``i``: float32 ``(N, 4)`` x y z intensity in the LiDAR frame.

        All-zero points (no return) are dropped unless ``drop_zeros=False``. An empty scan, a
        size that is not whole points, or (simulated roots) a size other than the recorded
        pattern's raises :class:`DataFileError`.
        """
        path = self.lidar_path(i)
        arr = _read_bin(path, np.float32, self.lidar_nbytes, "LiDAR scan", multiple_of=16,
                        source="the simulator's LiDAR pattern (simulation.json: beams x azimuth steps x 16)"
                        ).reshape(-1, 4)
        if drop_zeros:
            arr = arr[np.any(arr[:, :3] != 0, axis=1)]
        if arr.shape[0] == 0:
            raise DataFileError(path, "LiDAR scan is empty (no point with a return)")
        return arr

    def __repr__(self) -> str:
        return f"ColoRadarRun({str(self.path)!r})"


# ------------------------------------------------------------------------------------------------
def pair_radar_lidar(run: ColoRadarRun, *, max_dt: float | None = None, radar: str = "adc") -> np.ndarray:
    """Nearest-timestamp pairs ``(P, 2)`` int64 ``(radar_index, lidar_index)``.

    Parameters
    ----------
    run : ColoRadarRun
    max_dt : float, optional
        Drop pairs further apart (s). Default: half the median LiDAR period.
    radar : {"adc", "heatmap"}
        Which radar stream to pair (single-chip ADC or cascade heatmaps).
    """
    if radar not in ("adc", "heatmap"):
        raise ValueError(f"radar must be 'adc' or 'heatmap', got {radar!r}")
    tr = run.radar_timestamps if radar == "adc" else run.heatmap_timestamps
    tl = run.lidar_timestamps
    if max_dt is None:
        max_dt = 0.5 * float(np.median(np.diff(tl))) if len(tl) > 1 else 0.05
    if not max_dt > 0:
        raise ValueError(f"max_dt must be > 0, got {max_dt}")
    j = np.clip(np.searchsorted(tl, tr), 1, max(len(tl) - 1, 1)) if len(tl) > 1 else np.zeros(len(tr), int)
    if len(tl) > 1:
        j = np.where(np.abs(tl[j - 1] - tr) <= np.abs(tl[j] - tr), j - 1, j)
    ok = np.abs(tl[j] - tr) <= max_dt
    return np.stack([np.nonzero(ok)[0], j[ok]], 1).astype(np.int64)


def lidar_to_radar(points: np.ndarray, calib: ColoRadarCalib) -> np.ndarray:
    """``(N, >=3)`` LiDAR-frame points -> single-chip frame ``p_radar = T_base_radar^-1 T_base_lidar p``.

    Extra columns (intensity) are carried along unchanged.
    """
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"points must be (N, 3+), got shape {p.shape}")
    out = p.copy()
    out[:, :3] = calib.lidar_to_single_chip().apply(p[:, :3].astype(np.float64)).astype(p.dtype)
    return out


def frustum_mask(points, fov: RadarFOV = AWR1843_FOV):
    """Boolean mask of points (``(N, >=3)`` NumPy or torch) inside the radar frustum (closed bounds)."""
    is_t = isinstance(points, torch.Tensor)
    p = points if is_t else np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"points must be (N, 3+), got shape {tuple(p.shape)}")
    lib = torch if is_t else np
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = lib.sqrt(x * x + y * y + z * z)
    az = lib.arctan2(y, x) if not is_t else torch.atan2(y, x)
    el = (torch.asin if is_t else np.arcsin)((z / lib.where(r > 0, r, lib.ones_like(r))).clip(-1, 1))
    a0, a1 = (math.radians(v) for v in fov.azimuth_deg)
    e0, e1 = (math.radians(v) for v in fov.elevation_deg)
    return (r > fov.min_range_m) & (r <= fov.max_range_m) & (az >= a0) & (az <= a1) & (el >= e0) & (el <= e1)


def crop_to_frustum(points, fov: RadarFOV = AWR1843_FOV):
    """Points inside the radar frustum (same type as the input)."""
    return points[frustum_mask(points, fov)]


# ------------------------------------------------------------------------------------------------
def upsample_intensity(intensity: "torch.Tensor | RadarCube", size: tuple[int, int, int] = (128, 64, 32)) -> torch.Tensor:
    """Resize ``(..., R, A, E)`` intensity (or a :class:`RadarCube`'s) to ``size``
    (trilinear, ``align_corners=True``; RaLD: 128 x 64 x 32).

    With equal range sizes this is RaLD's bilinear upsampling of the two angle axes.
    """
    x = intensity.intensity_db if isinstance(intensity, RadarCube) else torch.as_tensor(intensity)
    if x.ndim < 3:
        raise ValueError(f"intensity must be (..., R, A, E), got shape {tuple(x.shape)}")
    if len(size) != 3 or min(size) < 1:
        raise ValueError(f"size must be 3 positive ints, got {size}")
    lead = x.shape[:-3]
    y = x.reshape(-1, 1, *x.shape[-3:]).to(torch.float32)
    y = F.interpolate(y, size=tuple(int(s) for s in size), mode="trilinear", align_corners=True)
    return y.reshape(*lead, *size)


RALD_MAX_INTENSITY_DB = 45.0
"""RaLD's intensity normalisation: dB values clipped to ``[0, 45]`` and divided by 45."""


def rald_intensity(intensity: "torch.Tensor | RadarCube", size: tuple[int, int, int] = (128, 64, 32), *,
                   max_db: float = RALD_MAX_INTENSITY_DB) -> torch.Tensor:
    """RaLD's network input from a radar cube's intensity ``(..., R, A, E)`` in dB.

    As RaLD's ColoRadar dataset (``process_radar_data``: ``norm_intensity``, then ``upsample``)::

        x = clip(I_dB, 0, max_db) / max_db            # on the raw 128 x 8 x 2 cube
        x = upsample_intensity(x, size)               # then the angles, bilinear, align_corners

    The clipping comes first: upsampling the dB values and clipping afterwards differs wherever
    neighbouring bins straddle 0 or ``max_db``. Every value is in ``[0, 1]`` (interpolation is a
    convex combination).

    Parameters
    ----------
    intensity : torch.Tensor or RadarCube
        Intensity in dB (:attr:`RadarCube.intensity_db`).
    size : (int, int, int)
        The model's cube (RaLD: 128 x 64 x 32); the range size normally equals the input's.
    max_db : float
        The clipping ceiling and divisor (RaLD: 45 dB).
    """
    if not (math.isfinite(max_db) and max_db > 0):
        raise ValueError(f"max_db must be a finite number > 0, got {max_db}")
    x = intensity.intensity_db if isinstance(intensity, RadarCube) else torch.as_tensor(intensity)
    x = x.to(torch.float32).clamp(0.0, max_db) / max_db
    return upsample_intensity(x, size)


# ------------------------------------------------------------------------------------------------
@dataclass
class ColoRadarItem:
    """One paired frame of :class:`ColoRadar`."""

    intensity: torch.Tensor   # (R, A, E) float32 radar cube intensity (dB), upsampled to cube_size
    points: torch.Tensor      # (N, 3) float32 LiDAR points in the radar frame, inside the frustum
    run: str
    scene: str
    radar_index: int
    lidar_index: int
    radar_time: float
    lidar_time: float


class ColoRadar(torch.utils.data.Dataset):
    """Paired (radar cube, cropped LiDAR) frames of a ColoRadar root (real or simulated).

    Parameters
    ----------
    root : path-like
        Folder holding ``calib/`` and the run folders.
    split : {"train", "val", "test", "all"}
        Run-level split (see :func:`split_runs`).
    runs : sequence of str, optional
        Restrict to these runs (after the split).
    scenes : sequence of str, optional
        Restrict to the runs of these scenes (:func:`scene_of_run`: ``lab`` for ``lab_run3``), after
        the split: training on some scene types and scoring the others held out.
    cube_size : (int, int, int) or None
        Upsampled intensity size (RaLD: 128 x 64 x 32); None keeps the raw 128 x 8 x 2 cube.
    fov : RadarFOV
        Frustum for the LiDAR crop.
    max_dt : float, optional
        Pairing tolerance (default half the LiDAR period).
    every : int
        Keep every ``every``-th paired frame of each run (its 1st, ``every + 1``-th, ...): an
        evenly spread subset of a split for jobs too slow to run on every frame (1: all frames).

    Raises
    ------
    DataFileError
        Missing or malformed calibration, timestamps or ground-truth poses (every run's poses are
        parsed up front, so a NaN pose fails here, naming the file), or a ``timestamps.txt`` whose
        line count differs from its stream's data files (:meth:`ColoRadarRun.count_problems`);
        frames are checked when read.
    """

    def __init__(self, root: str | os.PathLike, split: str = "train", *, runs: Sequence[str] | None = None,
                 cube_size: tuple[int, int, int] | None = (128, 64, 32), fov: RadarFOV = AWR1843_FOV,
                 max_dt: float | None = None, every: int = 1, scenes: Sequence[str] | None = None):
        if isinstance(every, bool) or int(every) != every or every < 1:
            raise ValueError(f"every must be a positive integer (1 keeps every frame), got {every!r}")
        if isinstance(scenes, str):
            raise ValueError(f"scenes must be a sequence of scene names, got the string {scenes!r}")
        self.root = Path(root)
        self.calib = load_calib(find_calib(self.root))
        names = split_runs(find_runs(self.root), split)
        if runs is not None:
            missing = sorted(set(runs) - set(names))
            if missing:
                raise ValueError(f"runs {missing} are not in split {split!r} of {self.root}")
            names = [n for n in names if n in set(runs)]
        if scenes is not None:
            have = sorted({scene_of_run(n) for n in names})
            missing = sorted(set(scenes) - set(have))
            if missing or not scenes:
                raise ValueError(f"scenes {sorted(set(scenes))} of {self.root}: "
                                 + (f"{missing} have no run in split {split!r}" if missing else "give at least one")
                                 + f" (its scenes: {', '.join(have) or 'none'})")
            names = [n for n in names if scene_of_run(n) in set(scenes)]
        self.scenes = None if scenes is None else tuple(scenes)
        self.split = split
        self.cube_size = cube_size
        self.fov = fov
        self.every = int(every)
        self.runs = [ColoRadarRun(self.root / n, self.calib) for n in names]
        for run in self.runs:
            run.check_poses()
            run.check_counts()
        index = []
        for k, run in enumerate(self.runs):
            for ri, li in pair_radar_lidar(run, max_dt=max_dt)[::self.every]:
                index.append((k, int(ri), int(li)))
        self.index = index

    def __len__(self) -> int:
        return len(self.index)

    def lidar_points(self, i: int) -> np.ndarray:
        """Cropped LiDAR (N, 3) float32 in the radar frame of item ``i``."""
        k, _, li = self.index[i]
        run = self.runs[k]
        pts = lidar_to_radar(run.lidar(li), self.calib)[:, :3]
        pts = crop_to_frustum(pts, self.fov)
        if pts.shape[0] == 0:
            raise DataFileError(run.lidar_path(li), "no LiDAR point inside the radar frustum")
        return pts.astype(np.float32)

    def cube(self, i: int) -> RadarCube:
        k, ri, _ = self.index[i]
        return radar_cube(self.runs[k].adc(ri), self.calib.single_chip)

    def __getitem__(self, i: int) -> ColoRadarItem:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} items")
        i = i % len(self)
        k, ri, li = self.index[i]
        run = self.runs[k]
        inten = self.cube(i).intensity_db
        if self.cube_size is not None:
            inten = upsample_intensity(inten, self.cube_size)
        return ColoRadarItem(inten, torch.from_numpy(self.lidar_points(i)), run.name, run.scene, ri, li,
                             float(run.radar_timestamps[ri]), float(run.lidar_timestamps[li]))


def collate_coloradar(items: Sequence[ColoRadarItem]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[ColoRadarItem]]:
    """Batch items: ``(B, R, A, E)`` intensities, concatenated ``(sum N, 3)`` points, ``(B,)``
    cumulative ``offset`` (Pointcept style), and the items (metadata)."""
    inten = torch.stack([it.intensity for it in items])
    pts = torch.cat([it.points for it in items])
    offset = torch.cumsum(torch.tensor([it.points.shape[0] for it in items]), 0)
    return inten, pts, offset, list(items)
