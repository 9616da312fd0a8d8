"""A point store's spectral point clouds written into its RADIal root as ``radar_PCL/``.

RADIal's ready-to-use release holds one radar point cloud per frame, read by its
``loader/dataset.py`` as ``radar_PCL/pcl_{numSample:06d}.npy``, a ``(9, N)`` array whose rows are
:data:`radarpc.data.radial_format.RADAR_PCL_ROWS` (range, azimuth, elevation, power, doppler,
x, y, z, v). :func:`write_radial_pcl` writes those files from a point store made from the root
(``radarpc pointcloud ROOT --split all --out store.parquet``), so that the official loader reads
a simulated root::

    range      range_m                    m
    azimuth    -azimuth_deg               deg, positive to the right (see RADAR_PCL_ROWS)
    elevation  elevation_deg              deg
    power      20 log10(amplitude)        dB of the beamformed amplitude
    doppler    doppler_full               Doppler bin after DDMA unfolding
    x, y, z    x, -y, z                   m, y positive to the right
    v          velocity_mps               m/s, receding positive

The root's lock is held while writing (the simulator's writer is refused meanwhile); each file is
written atomically; a rerun rewrites every frame of the store. ``radar_PCL/`` is one of the
simulator's outputs (a rerun with ``overwrite`` deletes it with the cubes it came from).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarpc.data.point_dataset import check_store_root
from radarpc.data.radial import read_labels
from radarpc.data.pointstore import PointStore
from radarpc.data.radial_format import RADAR_PCL_ROWS, radar_pcl_path
from radarpc.io import save_npy_atomic
from radarpc.runs import locked_output

__all__ = ["RadialPclRun", "radar_pcl_rows", "write_radial_pcl"]

_SOURCE = ("range_m", "azimuth_deg", "elevation_deg", "amplitude", "doppler_full", "x", "y", "z", "velocity_mps")


@dataclass(frozen=True)
class RadialPclRun:
    """What :func:`write_radial_pcl` wrote."""

    root: Path
    n_frames: int
    n_points: int


def radar_pcl_rows(columns: dict[str, np.ndarray]) -> np.ndarray:
    """RADIal's ``(9, N)`` float32 radar point array from radarpc point fields (module docstring).

    Parameters
    ----------
    columns : dict of str to ndarray
        ``range_m, azimuth_deg, elevation_deg, amplitude, doppler_full, x, y, z, velocity_mps``,
        each ``(N,)``.
    """
    missing = [c for c in _SOURCE if c not in columns]
    if missing:
        raise ValueError(f"radar_pcl_rows needs the point fields {list(_SOURCE)}; missing {missing}")
    c = {k: np.asarray(columns[k], dtype=np.float64) for k in _SOURCE}
    with np.errstate(divide="ignore", invalid="ignore"):      # amplitude 0 -> -inf dB (a negative one: NaN)
        power = 20.0 * np.log10(c["amplitude"])
    rows = {"range": c["range_m"], "azimuth": -c["azimuth_deg"], "elevation": c["elevation_deg"],
            "power": power, "doppler": c["doppler_full"], "x": c["x"], "y": -c["y"], "z": c["z"],
            "v": c["velocity_mps"]}
    return np.stack([rows[r] for r in RADAR_PCL_ROWS]).astype(np.float32)


def write_radial_pcl(store: str | os.PathLike | PointStore, root: str | os.PathLike | None = None, *,
                     progress: bool = True) -> RadialPclRun:
    """Write ``ROOT/radar_PCL/pcl_{frame:06d}.npy`` for every frame of a point store.

    Parameters
    ----------
    store : path-like or PointStore
        A store made from ``root``.
    root : path-like, optional
        The RADIal root; default the store's ``source_root``.
    progress : bool
        A tqdm bar over frames.

    Raises
    ------
    radarpc.io.DataFileError
        ``store`` is missing or not a point store.
    ValueError
        ``root`` is not a RADIal root (no ``labels.csv``), or the store was made from another root
        (:func:`~radarpc.data.point_dataset.check_store_root`), or holds frames ``root`` does not list.
    radarpc.runs.OutputBusyError
        Another process writes ``root``.
    """
    from tqdm import tqdm

    store = store if isinstance(store, PointStore) else PointStore(store)
    root = Path(root) if root is not None else Path(store.metadata.source_root)
    if not (root / "labels.csv").is_file():
        raise ValueError(f"{root} is not a RADIal root (no labels.csv): radar_PCL/ goes into the root "
                         f"the store {store.path} was made from")
    check_store_root(store, root)
    # a root that was moved passes the path check: its frames must still be the store's
    listed = set(read_labels(root / "labels.csv").num_sample.tolist())
    foreign = [int(f) for f in store.frames if int(f) not in listed]
    if foreign:
        raise ValueError(f"the point store {store.path} holds frames that {root}/labels.csv does not list "
                         f"({len(foreign)} of {len(store)}, e.g. numSample {foreign[0]}): it was made from another root")
    n_points = 0
    with locked_output(root, "dataset root"):
        for i in tqdm(range(len(store)), desc="radar_PCL", unit="frame", disable=not progress):
            table = store.frame_rows(i)
            arr = radar_pcl_rows({k: table.column(k).to_numpy() for k in _SOURCE})
            save_npy_atomic(radar_pcl_path(root, store.frames[i]), arr)
            n_points += arr.shape[1]
    return RadialPclRun(root, len(store), n_points)
