"""The RADIal on-disk layout: file names, ``labels.csv`` columns, freespace geometry, splits.

One place for the format, shared by the simulator's writer and the reader::

    ROOT/
      labels.csv                         one row per vehicle; a row of -1 for a frame without any
      calibration.npz                    Signal, H, Azimuth_table, Elevation_table (radarpc; plain npz;
                                         RADIal ships it pickled as CalibrationTable.npy):
                                         :func:`load_calibration` / :func:`save_calibration`
      sensor.json                        the DDMARadarConfig + seed and sizes (radarpc; absent on the real dataset)
      scene.json                         the RoadSceneConfig of a simulated root (radarpc; absent on the real dataset)
      radar_FFT/fft_{numSample:06d}.npy  complex RD cube (n_range, n_doppler, n_rx); or .npz holding one
                                         array (``arr_0``), compressed in radarpc's sparse-RD roots
                                         (:func:`save_fft_npz`); the .npy wins if both exist
      radar_Freespace/freespace_{numSample:06d}.png   uint8 512 x 900, 255 = free, 0 = not free
      camera/image_{numSample:06d}.jpg   RGB camera view, 960 x 540 (half of the 1920 x 1080 frames whose
                                         pixels ``x1_pix .. y2_pix`` use, as in RADIal's ready-to-use release)
      laser_PCL/pcl_{numSample:06d}.npy  LiDAR points (N, 8) float32: :data:`LASER_PCL_COLUMNS`
      radar_PCL/pcl_{numSample:06d}.npy  radar points (9, N) float32, one row per :data:`RADAR_PCL_ROWS`
                                         (written from a point store by :mod:`radarpc.pipelines.radial_pcl`)

The last three follow RADIal's ready-to-use release as its ``loader/dataset.py`` reads it; the
simulator writes ``camera/`` and ``laser_PCL/`` unless told not to.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from radarpc.io import DataFileError, atomic_write, save_npz_atomic
from radarpc.sensors.radial import Calibration

__all__ = [
    "LABEL_COLUMNS",
    "LABEL_TENSOR_COLUMNS",
    "FREESPACE_SHAPE",
    "FREESPACE_FOV_DEG",
    "FREESPACE_CROP",
    "FREESPACE_OUT",
    "SPARSE_RD_MANIFEST",
    "OFFICIAL_SPLITS",
    "FFT_SUFFIXES",
    "fft_path",
    "stored_fft_path",
    "save_fft_npz",
    "freespace_path",
    "camera_path",
    "laser_pcl_path",
    "radar_pcl_path",
    "LASER_PCL_COLUMNS",
    "RADAR_PCL_ROWS",
    "freespace_azimuth_deg",
    "simulated_sequence_name",
    "simulated_split",
    "save_calibration",
    "load_calibration",
]

LABEL_COLUMNS: tuple[str, ...] = (
    "numSample", "x1_pix", "y1_pix", "x2_pix", "y2_pix",
    "laser_X_m", "laser_Y_m", "laser_Z_m",
    "radar_X_m", "radar_Y_m", "radar_R_m", "radar_A_deg", "radar_D", "radar_P_db",
    "dataset", "dataset_index", "Difficult",
)
"""Exactly RADIal's ``labels.csv`` header, in order."""

LABEL_TENSOR_COLUMNS: tuple[str, ...] = (
    "radar_R_m", "radar_A_deg", "radar_D", "radar_X_m", "radar_Y_m", "radar_P_db",
    "laser_X_m", "laser_Y_m", "laser_Z_m", "x1_pix", "y1_pix", "x2_pix", "y2_pix", "Difficult",
)
"""Columns, in order, of the per-frame ``labels`` float tensor ``(n_vehicles, 14)`` that the
readers return (``(0, 14)`` for a frame without vehicles)."""

FREESPACE_SHAPE: tuple[int, int] = (512, 900)
"""Freespace PNG: 512 range rows (row 0 = range 0, row pitch = sensor max range / 512) by 900
azimuth columns over 180 degrees (0.2 deg per column)."""
FREESPACE_FOV_DEG: float = 180.0
FREESPACE_CROP: tuple[int, int] = (512, 448)
"""RADIal's reader centre-crops the PNG to 512 x 448 (+-89.6 deg) ..."""
FREESPACE_OUT: tuple[int, int] = (256, 224)
"""... and resizes it (nearest) to 256 x 224."""

SPARSE_RD_MANIFEST: str = "sparse_rd.json"
"""In the top folder of a sparse-RD root (``radarpc pointcloud --sparse-rd-out``): its settings,
tau and per-frame records. Its presence marks the cubes as masked to a CFAR-detected set."""

OFFICIAL_SPLITS: dict[str, tuple[str, ...]] = {
    "val": ("RECORD@2020-11-22_12.49.56", "RECORD@2020-11-22_12.11.49",
            "RECORD@2020-11-22_12.28.47", "RECORD@2020-11-21_14.25.06"),
    "test": ("RECORD@2020-11-22_12.45.05", "RECORD@2020-11-22_12.25.47",
             "RECORD@2020-11-22_12.03.47", "RECORD@2020-11-22_12.54.38"),
}
"""RADIal's official validation and test sequences (FFTRadNet's ``dataloader.py``); every other
sequence of the real dataset is training data."""


def fft_path(root: str | os.PathLike, num_sample: int, suffix: str = ".npy") -> Path:
    """``ROOT/radar_FFT/fft_{num_sample:06d}{suffix}``."""
    return Path(root) / "radar_FFT" / f"fft_{int(num_sample):06d}{suffix}"


FFT_SUFFIXES: tuple[str, ...] = (".npy", ".npz")
"""Suffixes an RD cube file may have, in the order a reader looks for them."""


def stored_fft_path(root: str | os.PathLike, num_sample: int) -> Path | None:
    """The RD cube file of frame ``num_sample`` that exists (``.npy``, else ``.npz``), or None."""
    for suffix in FFT_SUFFIXES:
        p = fft_path(root, num_sample, suffix)
        if p.is_file():
            return p
    return None


def save_fft_npz(root: str | os.PathLike, num_sample: int, cube: np.ndarray, *, compress: bool = True) -> Path:
    """Write frame ``num_sample``'s RD cube as an ``.npz`` (one array, ``arr_0``); atomic.

    Compressed by default: zlib stores a run of zero cells in a few bytes, so a masked (mostly
    zero) cube takes about as many bytes as its kept cells; a dense simulated cube does not
    shrink, and ``compress=False`` saves the time. A ``.npy`` of the same frame is removed first
    (a reader would prefer it); a kill in between leaves neither file, never a stale one.
    Returns the path.
    """
    path = fft_path(root, num_sample, ".npz")
    fft_path(root, num_sample, ".npy").unlink(missing_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, np.ascontiguousarray(cube))
    return path


def freespace_path(root: str | os.PathLike, num_sample: int) -> Path:
    """``ROOT/radar_Freespace/freespace_{num_sample:06d}.png``."""
    return Path(root) / "radar_Freespace" / f"freespace_{int(num_sample):06d}.png"


def camera_path(root: str | os.PathLike, num_sample: int) -> Path:
    """``ROOT/camera/image_{num_sample:06d}.jpg``."""
    return Path(root) / "camera" / f"image_{int(num_sample):06d}.jpg"


def laser_pcl_path(root: str | os.PathLike, num_sample: int) -> Path:
    """``ROOT/laser_PCL/pcl_{num_sample:06d}.npy``."""
    return Path(root) / "laser_PCL" / f"pcl_{int(num_sample):06d}.npy"


def radar_pcl_path(root: str | os.PathLike, num_sample: int) -> Path:
    """``ROOT/radar_PCL/pcl_{num_sample:06d}.npy``."""
    return Path(root) / "radar_PCL" / f"pcl_{int(num_sample):06d}.npy"


LASER_PCL_COLUMNS: tuple[str, ...] = (
    "x", "y", "z", "intensity", "radialDistance", "polAngle", "aziAngle", "layer_index")
"""Columns of a ``laser_PCL`` file, as RADIal's ``loader/dataset.py`` lists them: metres in the
LiDAR frame (x forward, y left, z up), intensity in [0, 1], range (m), elevation and azimuth
(radians, up and left positive), layer index 0 .. 15 (bottom to top)."""

RADAR_PCL_ROWS: tuple[str, ...] = (
    "range", "azimuth", "elevation", "power", "doppler", "x", "y", "z", "v")
"""Rows of a ``radar_PCL`` file (``(9, N)``), as RADIal's ``loader/dataset.py`` lists them: range (m),
azimuth and elevation (degrees), power (dB), Doppler bin (full, unfolded), x, y, z (m), radial
velocity v (m/s, receding positive). The file's y and azimuth are positive to the RIGHT: RADIal's
loader negates y on reading (``radar_pc[:, 1] *= -1``) to put the radar points in the left-positive
frame of its laser points, so radarpc writes ``y = -y_radarpc`` and ``azimuth = -azimuth_radarpc``."""


def freespace_azimuth_deg(col) -> np.ndarray:
    """Azimuth (deg, left positive) of the centre of freespace PNG column ``col``.

    Column 0 is at -90 deg + half a column, column 899 at +90 deg - half a column: azimuth grows
    with the column index, as in the range-azimuth maps of the models.
    """
    step = FREESPACE_FOV_DEG / FREESPACE_SHAPE[1]
    return -FREESPACE_FOV_DEG / 2 + (np.asarray(col, dtype=np.float64) + 0.5) * step


def simulated_sequence_name(seed: int, sequence: int) -> str:
    """Sequence name of simulated data, written to the ``dataset`` column: ``SIM@s{seed}_q{seq:03d}``."""
    return f"SIM@s{int(seed)}_q{int(sequence):03d}"


def simulated_split(sequence_index: int, n_sequences: int) -> str:
    """Deterministic split of simulated sequence ``sequence_index`` out of ``n_sequences``.

    The last sequence is ``test``, the one before it ``val`` (when there are at least 3), every
    other one ``train``; with 6 or more sequences, every 6th pair (indices 6k+4, 6k+5) is also held
    out, keeping roughly 2/3 train, 1/6 val, 1/6 test.
    """
    i, n = int(sequence_index), int(n_sequences)
    if not 0 <= i < n:
        raise ValueError(f"sequence index {i} outside [0, {n})")
    if n < 3:
        return "train"
    if i == n - 1:
        return "test"
    if i == n - 2:
        return "val"
    if n >= 6 and i % 6 in (4, 5):
        return "val" if i % 6 == 4 else "test"
    return "train"


def save_calibration(path: str | os.PathLike, calib: Calibration) -> None:
    """Write ``calib`` as a plain ``.npz`` with RADIal's keys (``Signal``, ``H``, tables); atomic."""
    save_npz_atomic(path, Signal=calib.signal, H=calib.window[None, :],
                    Azimuth_table=calib.azimuth_deg, Elevation_table=calib.elevation_deg)


def load_calibration(path: str | os.PathLike, *, trust_pickle: bool = False) -> Calibration:
    """Read a calibration table.

    Parameters
    ----------
    path : path-like
        ``calibration.npz`` (radarpc's format, also what real RADIal tables convert to), or the
        official pickled ``CalibrationTable.npy``.
    trust_pickle : bool
        The official RADIal table is a pickled dict; unpickling runs code from the file, so it
        is refused unless you pass ``trust_pickle=True`` for a file you obtained from RADIal
        yourself. Convert it once with :func:`save_calibration` and use the ``.npz`` after.

    Raises
    ------
    DataFileError
        Missing file, missing keys, or inconsistent shapes, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "calibration table is missing (expected calibration.npz with keys "
                                  "Signal, H, Azimuth_table, Elevation_table)")
    try:
        if path.suffix == ".npy":
            if not trust_pickle:
                raise DataFileError(path, "is a pickled .npy calibration table; loading it runs code from "
                                          "the file. If it is the official RADIal CalibrationTable.npy you "
                                          "downloaded yourself, convert it once to calibration.npz beside it, "
                                          "which every command reads: python -c \"from radarpc.data.radial_format "
                                          "import load_calibration, save_calibration; save_calibration("
                                          "'calibration.npz', load_calibration('CalibrationTable.npy', "
                                          "trust_pickle=True))\" (in Python: RADIal(..., trust_pickle=True))")
            d = np.load(path, allow_pickle=True).item()  # explicit user opt-in, see docstring
        else:
            with np.load(path, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
    except DataFileError:
        raise
    except Exception as e:  # noqa: BLE001 - any decoding failure is a bad file
        raise DataFileError(path, f"is not a readable calibration table ({e})") from e
    missing = {"Signal", "H", "Azimuth_table", "Elevation_table"} - set(d)
    if missing:
        raise DataFileError(path, f"calibration table lacks keys {sorted(missing)}")
    signal = np.asarray(d["Signal"])
    h = np.asarray(d["H"], dtype=np.float32)
    h = h.reshape(-1, h.shape[-1])[0] if h.ndim > 1 else h
    try:
        calib = Calibration(signal=signal.astype(np.complex64), window=h,
                            azimuth_deg=np.asarray(d["Azimuth_table"], dtype=np.float32).reshape(-1),
                            elevation_deg=np.asarray(d["Elevation_table"], dtype=np.float32).reshape(-1))
    except ValueError as e:
        raise DataFileError(path, str(e)) from e
    if not np.isfinite(calib.signal).all():
        raise DataFileError(path, "calibration Signal contains NaN or infinite values")
    return calib
