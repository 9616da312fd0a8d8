"""The simulator's ground-truth sidecars of a RADIal-layout root, and label statistics of any root.

A simulated root holds, beside RADIal's ``labels.csv``, two files that a real recording cannot
give from its labels alone:

* ``sim_frames.csv``: one row per frame, columns :data:`SIM_FRAME_COLUMNS`
  (``numSample, dataset, dataset_index, scene, ego_speed_mps``): the scene preset of the frame's
  sequence and the ego speed over the ground.
* ``sim_vehicles.csv``: one row per labelled vehicle, in the order of its ``labels.csv`` row,
  columns :data:`SIM_VEHICLE_COLUMNS` (``numSample, vehicle_id, kind, state, ground_speed_mps,
  radar_R_m, radar_A_deg``); ``kind`` is one of :data:`VEHICLE_KINDS`, ``state`` one of
  :data:`VEHICLE_STATES`.

:func:`label_statistics` computes what ``radarpc info`` prints to compare a simulated root with a
real one: vehicles per frame, the share of empty frames, the label distributions, and, where the
sidecars exist, the scene mix and the share of parked / stopped / queued vehicles.
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarpc.io import DataFileError

__all__ = [
    "SIM_FRAMES_FILE",
    "SIM_VEHICLES_FILE",
    "SIM_FRAME_COLUMNS",
    "SIM_VEHICLE_COLUMNS",
    "VEHICLE_KINDS",
    "VEHICLE_STATES",
    "SimFrames",
    "SimVehicles",
    "read_sim_frames",
    "read_sim_vehicles",
    "Quantiles",
    "LabelStatistics",
    "label_statistics",
]

SIM_FRAMES_FILE = "sim_frames.csv"
SIM_VEHICLES_FILE = "sim_vehicles.csv"
SIM_FRAME_COLUMNS: tuple[str, ...] = ("numSample", "dataset", "dataset_index", "scene", "ego_speed_mps")
SIM_VEHICLE_COLUMNS: tuple[str, ...] = ("numSample", "vehicle_id", "kind", "state", "ground_speed_mps",
                                        "radar_R_m", "radar_A_deg")
VEHICLE_KINDS: tuple[str, ...] = ("car", "truck")
VEHICLE_STATES: tuple[str, ...] = ("moving", "stopped", "queued", "parked")
QUANTILE_LEVELS: tuple[float, ...] = (0.05, 0.25, 0.5, 0.75, 0.95)


@dataclass(frozen=True)
class SimFrames:
    """``sim_frames.csv`` column-wise (``n`` frames)."""

    num_sample: np.ndarray          # int64 (n,)
    dataset: tuple[str, ...]
    dataset_index: np.ndarray       # int64 (n,)
    scene: tuple[str, ...]
    ego_speed_mps: np.ndarray       # float64 (n,)


@dataclass(frozen=True)
class SimVehicles:
    """``sim_vehicles.csv`` column-wise (``n`` labelled vehicles)."""

    num_sample: np.ndarray          # int64 (n,)
    vehicle_id: np.ndarray          # int64 (n,)
    kind: tuple[str, ...]
    state: tuple[str, ...]
    ground_speed_mps: np.ndarray    # float64 (n,)
    radar_R_m: np.ndarray           # float64 (n,)
    radar_A_deg: np.ndarray         # float64 (n,)


def _read_rows(path: Path, columns: tuple[str, ...]) -> list[dict[str, str]]:
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            header = tuple(reader.fieldnames or ())
            if header != columns:
                raise DataFileError(path, f"expected the header {','.join(columns)}, got "
                                    f"{','.join(header) or 'an empty file'}")
            return list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataFileError(path, f"cannot read ({e})") from e


def _column(rows: list[dict[str, str]], name: str, kind: type, path: Path) -> np.ndarray:
    try:
        vals = [kind(r[name]) for r in rows]
    except (TypeError, ValueError) as e:
        raise DataFileError(path, f"column {name!r} must hold {kind.__name__} values ({e})") from e
    out = np.asarray(vals, dtype=np.int64 if kind is int else np.float64).reshape(len(rows))
    if kind is float and not np.isfinite(out).all():
        raise DataFileError(path, f"column {name!r} contains NaN or infinite values")
    return out


def _check_choice(values: tuple[str, ...], allowed: tuple[str, ...], name: str, path: Path) -> None:
    bad = sorted(set(values) - set(allowed))
    if bad:
        raise DataFileError(path, f"column {name!r} holds {bad}; expected one of {list(allowed)}")


def read_sim_frames(path: str | os.PathLike) -> SimFrames:
    """Read a ``sim_frames.csv`` (see the module docstring); bad content raises ``DataFileError``."""
    path = Path(path)
    rows = _read_rows(path, SIM_FRAME_COLUMNS)
    return SimFrames(num_sample=_column(rows, "numSample", int, path),
                     dataset=tuple(r["dataset"] for r in rows),
                     dataset_index=_column(rows, "dataset_index", int, path),
                     scene=tuple(r["scene"] for r in rows),
                     ego_speed_mps=_column(rows, "ego_speed_mps", float, path))


def read_sim_vehicles(path: str | os.PathLike) -> SimVehicles:
    """Read a ``sim_vehicles.csv`` (see the module docstring); bad content raises ``DataFileError``."""
    path = Path(path)
    rows = _read_rows(path, SIM_VEHICLE_COLUMNS)
    out = SimVehicles(num_sample=_column(rows, "numSample", int, path),
                      vehicle_id=_column(rows, "vehicle_id", int, path),
                      kind=tuple(r["kind"] for r in rows), state=tuple(r["state"] for r in rows),
                      ground_speed_mps=_column(rows, "ground_speed_mps", float, path),
                      radar_R_m=_column(rows, "radar_R_m", float, path),
                      radar_A_deg=_column(rows, "radar_A_deg", float, path))
    _check_choice(out.kind, VEHICLE_KINDS, "kind", path)
    _check_choice(out.state, VEHICLE_STATES, "state", path)
    return out


@dataclass(frozen=True)
class Quantiles:
    """The 5, 25, 50, 75 and 95 % quantiles of a sample (linear interpolation), and its size."""

    values: tuple[float, ...]
    n: int

    @classmethod
    def of(cls, x: np.ndarray) -> "Quantiles | None":
        x = np.asarray(x, dtype=np.float64)
        if x.size == 0:
            return None
        return cls(tuple(float(q) for q in np.quantile(x, QUANTILE_LEVELS)), int(x.size))

    def format(self, unit: str) -> str:
        return "  ".join(f"{v:7.1f}" for v in self.values) + f"  {unit}"


@dataclass(frozen=True)
class LabelStatistics:
    """Label statistics of a root, for comparing a simulated root with a real one.

    Attributes
    ----------
    n_frames : int
    vehicles_per_frame : float
        Labelled vehicles (``Difficult`` ones included) over frames.
    max_vehicles_per_frame : int
    empty_share : float
        Share of frames without any vehicle.
    range_m, azimuth_deg, doppler_mps : Quantiles or None
        Distributions of ``radar_R_m``, ``radar_A_deg`` and ``radar_D`` of the vehicles.
    scene_share : dict or None
        Share of frames per scene preset (``sim_frames.csv``); None for a root without it.
    state_share : dict or None
        Share of labelled vehicles per state (``sim_vehicles.csv``); None without it.
    ego_speed_mps, ground_speed_mps : Quantiles or None
        Ego speed over frames and vehicles' ground speed, from the sidecars.
    """

    n_frames: int
    vehicles_per_frame: float
    max_vehicles_per_frame: int
    empty_share: float
    range_m: Quantiles | None
    azimuth_deg: Quantiles | None
    doppler_mps: Quantiles | None
    scene_share: dict[str, float] | None = None
    state_share: dict[str, float] | None = None
    ego_speed_mps: Quantiles | None = None
    ground_speed_mps: Quantiles | None = None

    @property
    def not_moving_share(self) -> float | None:
        """Share of labelled vehicles that are parked, stopped or queued (None without sidecar)."""
        if self.state_share is None:
            return None
        return sum(v for k, v in self.state_share.items() if k != "moving")

    def format(self) -> list[str]:
        """The lines ``radarpc info`` prints under "statistics"."""
        def share(d: dict[str, float] | None, names: tuple[str, ...]) -> str:
            if d is None:
                return "not recorded (no simulator sidecar)"
            return ", ".join(f"{k} {100 * d.get(k, 0.0):.1f} %" for k in names)

        q = "          " + "  ".join(f"{f'p{round(100 * lv)}':>7}" for lv in QUANTILE_LEVELS)
        lines = [
            f"per frame:   {self.vehicles_per_frame:.2f} vehicles (max {self.max_vehicles_per_frame}), "
            f"{100 * self.empty_share:.1f} % of frames empty",
            "scenes:      " + share(self.scene_share, ("city", "countryside", "highway")),
            "states:      " + share(self.state_share, VEHICLE_STATES),
            "quantiles:" + q[10:],
        ]
        for name, v, unit in (("range", self.range_m, "m"), ("azimuth", self.azimuth_deg, "deg"),
                              ("velocity", self.doppler_mps, "m/s (radar_D)"),
                              ("ego speed", self.ego_speed_mps, "m/s"),
                              ("veh. speed", self.ground_speed_mps, "m/s over ground")):
            if v is not None:
                lines.append(f"  {name:<10} {v.format(unit)}")
        return lines


def label_statistics(labels, root: str | os.PathLike | None = None) -> LabelStatistics:
    """Statistics of a root's labels, with the simulator sidecars of ``root`` when it has them.

    Parameters
    ----------
    labels : radarpc.data.radial.LabelTable
        The root's ``labels.csv``.
    root : path-like, optional
        Where to look for ``sim_frames.csv`` and ``sim_vehicles.csv``.

    Raises
    ------
    DataFileError
        A sidecar exists but is malformed, or does not match ``labels.csv`` (frame ids, vehicle
        count).
    """
    veh = labels.has_vehicle
    frames = np.unique(labels.num_sample)
    n_frames = int(frames.size)
    per_frame = np.bincount(np.searchsorted(frames, labels.num_sample[veh]), minlength=n_frames)
    stats = dict(
        n_frames=n_frames,
        vehicles_per_frame=float(per_frame.mean()) if n_frames else math.nan,
        max_vehicles_per_frame=int(per_frame.max()) if n_frames else 0,
        empty_share=float((per_frame == 0).mean()) if n_frames else math.nan,
        range_m=Quantiles.of(labels.column("radar_R_m")[veh]),
        azimuth_deg=Quantiles.of(labels.column("radar_A_deg")[veh]),
        doppler_mps=Quantiles.of(labels.column("radar_D")[veh]))
    if root is not None:
        root = Path(root)
        fpath, vpath = root / SIM_FRAMES_FILE, root / SIM_VEHICLES_FILE
        if fpath.is_file():
            sf = read_sim_frames(fpath)
            if not np.array_equal(np.sort(sf.num_sample), frames):
                raise DataFileError(fpath, f"its numSample values are not the frames of labels.csv "
                                    f"({sf.num_sample.size} rows for {n_frames} frames)")
            names, counts = np.unique(np.asarray(sf.scene, dtype=str), return_counts=True)
            stats["scene_share"] = {str(k): float(c) / sf.num_sample.size for k, c in zip(names, counts)}
            stats["ego_speed_mps"] = Quantiles.of(sf.ego_speed_mps)
        if vpath.is_file():
            sv = read_sim_vehicles(vpath)
            if not np.array_equal(sv.num_sample, labels.num_sample[veh]):
                raise DataFileError(vpath, f"expected one row per vehicle row of labels.csv in the same "
                                    f"order ({int(veh.sum())} rows), got {sv.num_sample.size}")
            n = max(len(sv.state), 1)
            stats["state_share"] = {s: sv.state.count(s) / n for s in VEHICLE_STATES}
            stats["ground_speed_mps"] = Quantiles.of(sv.ground_speed_mps)
    return LabelStatistics(**stats)
