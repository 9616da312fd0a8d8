"""Reader for RADIal-layout roots (the real dataset or the simulator's output): a torch Dataset.

One frame ``numSample`` of a root (layout in :mod:`radarpc.data.radial_format`) gives

* ``rd``        complex64 ``(n_range, n_doppler, n_rx)``, from ``radar_FFT/fft_{:06d}.npy`` (or ``.npz``);
* ``labels``    float32 ``(n_vehicles, 14)``, columns :data:`LABEL_TENSOR_COLUMNS` (``(0, 14)`` if none);
* ``freespace`` bool ``(256, 224)``, the 512 x 900 PNG centre-cropped to 512 x 448 and resized
  (nearest) to 256 x 224 exactly as RADIal's own loader does (:func:`freespace_to_model`).

Splits are by sequence (the ``dataset`` column): RADIal's official validation/test sequences for
real ``RECORD@...`` names, :func:`radarpc.data.radial_format.simulated_split` for simulated
``SIM@s{seed}_q{idx}`` names, or a frame-level random split with a seed. Every file opened is
validated; :func:`check_root` scans a whole root and lists each bad or missing file, and
``skip=`` leaves listed frames out.

Examples
--------
>>> from radarpc.data.radial import RADIal                    # doctest: +SKIP
>>> ds = RADIal("data/sim_radial", split="train")             # doctest: +SKIP
>>> rd, labels, freespace = ds[0]                             # doctest: +SKIP
"""
from __future__ import annotations

import abc
import csv
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch
from PIL import Image

from radarpc.data.radial_format import (
    FREESPACE_CROP,
    FREESPACE_OUT,
    FREESPACE_SHAPE,
    LABEL_COLUMNS,
    LABEL_TENSOR_COLUMNS,
    OFFICIAL_SPLITS,
    fft_path,
    freespace_path,
    load_calibration,
    simulated_split,
    stored_fft_path,
)
from radarpc.io import DataFileError, atomic_write, load_array
from radarpc.sensors.radial import RADIAL, Calibration, DDMARadarConfig

__all__ = [
    "SPLIT_CHOICES",
    "SIMULATED_META_KEYS",
    "LabelTable",
    "label_problems",
    "label_reach_m",
    "SimulatedMeta",
    "FileProblem",
    "CheckReport",
    "FrameSelection",
    "RadialFrames",
    "RADIal",
    "read_labels",
    "read_sensor_json",
    "root_sensor",
    "read_skip_file",
    "write_skip_file",
    "find_fft_file",
    "load_rd",
    "load_freespace",
    "freespace_to_model",
    "split_of_sequence",
    "random_split_indices",
    "select_frames",
    "check_cube",
    "check_root",
    "radial_collate",
]

SPLIT_CHOICES: tuple[str, ...] = ("train", "val", "test", "all")
"""Values accepted by ``RADIal(split=...)``."""

SIMULATED_META_KEYS: tuple[str, ...] = ("seed", "n_sequences", "frames_per_sequence", "radarpc_version")
"""Keys of a simulated root's ``sensor.json`` that describe the run rather than the sensor."""

_INT_COLUMNS: tuple[str, ...] = ("numSample", "dataset_index", "Difficult")
_STR_COLUMNS: tuple[str, ...] = ("dataset",)
_FLOAT_COLUMNS: tuple[str, ...] = tuple(c for c in LABEL_COLUMNS if c not in _INT_COLUMNS + _STR_COLUMNS)
# Columns that are all -1 on the row RADIal writes for a frame without any vehicle. (Camera pixel
# columns are left out: a vehicle outside the camera's view has -1 there too.)
_EMPTY_MARKER_COLUMNS: tuple[str, ...] = (
    "laser_X_m", "laser_Y_m", "laser_Z_m",
    "radar_X_m", "radar_Y_m", "radar_R_m", "radar_A_deg", "radar_D", "radar_P_db",
)
_SIM_NAME = re.compile(r"^SIM@s(-?\d+)_q(\d+)$")


# ---- labels.csv ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class LabelTable:
    """The rows of a ``labels.csv``, column-wise (one row per vehicle, or a -1 row per empty frame).

    Attributes
    ----------
    path : Path
        The file the rows were read from.
    num_sample : ndarray, int64, ``(n,)``
        ``numSample`` (frame id) of each row.
    values : ndarray, float64, ``(n, len(FLOAT_COLUMNS))``
        The numeric columns :attr:`FLOAT_COLUMNS` (pixels, laser and radar coordinates).
    dataset : tuple of str, ``(n,)``
        Sequence name of each row.
    dataset_index : ndarray, int64, ``(n,)``
        Index of the frame in its sequence.
    difficult : ndarray, int64, ``(n,)``
        RADIal's ``Difficult`` flag (1 = hard to see; -1 on an empty frame's row).
    """

    FLOAT_COLUMNS = _FLOAT_COLUMNS

    path: Path
    num_sample: np.ndarray
    values: np.ndarray
    dataset: tuple[str, ...]
    dataset_index: np.ndarray
    difficult: np.ndarray

    def __len__(self) -> int:
        return int(self.num_sample.shape[0])

    @classmethod
    def from_rows(cls, rows: Sequence[Sequence], path: str | os.PathLike = "<rows>") -> "LabelTable":
        """The table of ``labels.csv`` rows given in memory (tuples in :data:`LABEL_COLUMNS` order).

        Values are converted as :func:`read_labels` converts the text the simulator writes
        (``repr`` of a float parses back to the same float64), so a table built from the rows
        equals the one read back from the written file.
        """
        pos = {c: i for i, c in enumerate(LABEL_COLUMNS)}
        for k, r in enumerate(rows):
            if len(r) != len(LABEL_COLUMNS):
                raise ValueError(f"label row {k} has {len(r)} fields, expected {len(LABEL_COLUMNS)}")
        n = len(rows)
        vals = np.asarray([[float(r[pos[c]]) for c in _FLOAT_COLUMNS] for r in rows],
                          dtype=np.float64).reshape(n, len(_FLOAT_COLUMNS))
        if not np.isfinite(vals).all():
            raise ValueError("label rows contain NaN or infinite values")
        ints = np.asarray([[int(r[pos[c]]) for c in _INT_COLUMNS] for r in rows],
                          dtype=np.int64).reshape(n, len(_INT_COLUMNS))
        return cls(path=Path(path), num_sample=ints[:, 0].copy(), values=vals,
                   dataset=tuple(str(r[pos["dataset"]]) for r in rows),
                   dataset_index=ints[:, 1].copy(), difficult=ints[:, 2].copy())

    def column(self, name: str) -> np.ndarray:
        """Column ``name`` (any of :data:`LABEL_COLUMNS`) as an array of length ``len(self)``."""
        if name == "numSample":
            return self.num_sample
        if name == "dataset_index":
            return self.dataset_index
        if name == "Difficult":
            return self.difficult
        if name == "dataset":
            return np.asarray(self.dataset, dtype=object)
        if name not in _FLOAT_COLUMNS:
            raise ValueError(f"unknown label column {name!r}; expected one of {list(LABEL_COLUMNS)}")
        return self.values[:, _FLOAT_COLUMNS.index(name)]

    @property
    def has_vehicle(self) -> np.ndarray:
        """``(n,)`` bool: False on the -1 row of a frame without vehicles."""
        idx = [_FLOAT_COLUMNS.index(c) for c in _EMPTY_MARKER_COLUMNS]
        return ~np.all(self.values[:, idx] == -1.0, axis=1)

    def row(self, k: int) -> dict[str, int | float | str]:
        """Row ``k`` as ``{column: value}`` over all :data:`LABEL_COLUMNS`, in file order."""
        out: dict[str, int | float | str] = {}
        for c in LABEL_COLUMNS:
            if c in _STR_COLUMNS:
                out[c] = self.dataset[k]
            elif c in _INT_COLUMNS:
                out[c] = int(self.column(c)[k])
            else:
                out[c] = float(self.values[k, _FLOAT_COLUMNS.index(c)])
        return out

    def tensor_rows(self, rows: Sequence[int] | np.ndarray) -> np.ndarray:
        """Rows ``rows`` as float32 ``(len(rows), 14)`` in :data:`LABEL_TENSOR_COLUMNS` order."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1)
        out = np.empty((rows.shape[0], len(LABEL_TENSOR_COLUMNS)), dtype=np.float32)
        for j, c in enumerate(LABEL_TENSOR_COLUMNS):
            out[:, j] = self.column(c)[rows]
        return out


def label_reach_m(sensor: DDMARadarConfig) -> float:
    """How far the labels of a RADIal-layout root may reach: the larger of the sensor's
    instrumented range and RADIal's (103 m, the reach of the format's detection map). A small
    simulated sensor sees less far than the scene it labels."""
    return max(sensor.max_range_m, RADIAL.max_range_m)


def label_problems(labels: LabelTable, max_range_m: float | None = None) -> list[str]:
    """What in ``labels`` no radar could have measured, one line per bad value (empty: none).

    A vehicle row must have a range ``radar_R_m`` in [0, ``max_range_m``] (without it, any range
    >= 0), an azimuth ``radar_A_deg`` within +-90 deg (in front of the array) and ``Difficult`` 0
    or 1. A frame's empty marker row (-1 in the position columns) is left alone.
    :func:`label_reach_m` gives the range a root's labels may reach.
    """
    out = []
    r = labels.column("radar_R_m")
    a = labels.column("radar_A_deg")
    vehicle = labels.has_vehicle
    for k in np.flatnonzero(vehicle).tolist():
        where = f"row {k + 1} (numSample {int(labels.num_sample[k])})"
        if not 0.0 <= r[k] <= (math.inf if max_range_m is None else max_range_m):
            span = "" if max_range_m is None else f" .. {max_range_m:.1f}"
            out.append(f"{where}: radar_R_m {r[k]:g} is outside 0{span} m")
        if not -90.0 <= a[k] <= 90.0:
            out.append(f"{where}: radar_A_deg {a[k]:g} is outside -90 .. 90 deg")
        if int(labels.difficult[k]) not in (0, 1):
            out.append(f"{where}: Difficult {int(labels.difficult[k])} is neither 0 nor 1")
    return out


def _parse_number(text: str, column: str, path: Path, line: int, integer: bool) -> float | int:
    try:
        v = float(text)
    except ValueError:
        raise DataFileError(path, f"line {line}: column {column!r} holds {text!r}, expected a number") from None
    if not math.isfinite(v):
        raise DataFileError(path, f"line {line}: column {column!r} holds {text!r}, expected a finite number")
    if integer:
        if v != int(v):
            raise DataFileError(path, f"line {line}: column {column!r} holds {text!r}, expected an integer")
        return int(v)
    return v


def read_labels(path: str | os.PathLike) -> LabelTable:
    """Parse a RADIal ``labels.csv``.

    Parameters
    ----------
    path : path-like
        The CSV file; its header must be exactly :data:`LABEL_COLUMNS`, in order.

    Returns
    -------
    LabelTable

    Raises
    ------
    DataFileError
        Missing file, wrong header (listing missing and extra columns), a row of the wrong length
        or a value that is not a number, naming the file and the line.
    """
    path = Path(path)
    if not path.is_file():
        if (path.parent / "calib").is_dir() and path.name == "labels.csv":     # the other layout
            raise DataFileError(path.parent, "this is a ColoRadar root (calib/ and run folders, no labels.csv); "
                                             "the RADIal reader and `radarpc pointcloud` / `show` need a RADIal "
                                             "root (labels.csv, radar_FFT/, radar_Freespace/)")
        raise DataFileError(path, f"labels file is missing (expected a CSV with columns {', '.join(LABEL_COLUMNS)})")
    n_int, n_float = len(_INT_COLUMNS), len(_FLOAT_COLUMNS)
    nums: list[int] = []
    vals: list[list[float]] = []
    names: list[str] = []
    ints: list[list[int]] = []
    pos = {c: i for i, c in enumerate(LABEL_COLUMNS)}
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise DataFileError(path, f"is empty; expected the header {','.join(LABEL_COLUMNS)}")
            header = [h.strip() for h in header]
            if tuple(header) != LABEL_COLUMNS:
                missing = [c for c in LABEL_COLUMNS if c not in header]
                extra = [c for c in header if c not in LABEL_COLUMNS]
                detail = f"missing columns {missing}, extra columns {extra}" if (missing or extra) else \
                    f"columns in the wrong order: {header}"
                raise DataFileError(path, f"header is not RADIal's labels header ({detail}); expected "
                                          f"{','.join(LABEL_COLUMNS)}")
            for rec in reader:
                line = reader.line_num
                if not rec or all(not x.strip() for x in rec):
                    continue
                if len(rec) != len(LABEL_COLUMNS):
                    raise DataFileError(path, f"line {line}: {len(rec)} fields, expected {len(LABEL_COLUMNS)}")
                nums.append(int(_parse_number(rec[0], "numSample", path, line, True)))
                vals.append([float(_parse_number(rec[pos[c]], c, path, line, False)) for c in _FLOAT_COLUMNS])
                names.append(rec[pos["dataset"]].strip())
                ints.append([int(_parse_number(rec[pos[c]], c, path, line, True)) for c in _INT_COLUMNS[1:]])
    except DataFileError:
        raise
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataFileError(path, f"cannot be read as a CSV file ({e})") from e
    ints_a = np.asarray(ints, dtype=np.int64).reshape(-1, n_int - 1)
    return LabelTable(
        path=path,
        num_sample=np.asarray(nums, dtype=np.int64),
        values=np.asarray(vals, dtype=np.float64).reshape(-1, n_float),
        dataset=tuple(names),
        dataset_index=ints_a[:, 0].copy(),
        difficult=ints_a[:, 1].copy(),
    )


# ---- sensor.json --------------------------------------------------------------------------------
@dataclass(frozen=True)
class SimulatedMeta:
    """Run description stored beside the sensor in a simulated root's ``sensor.json``."""

    seed: int | None = None                 # simulator seed
    n_sequences: int | None = None          # sequences written
    frames_per_sequence: int | None = None  # frames per sequence
    radarpc_version: str | None = None      # package version that wrote the root


def read_sensor_json(path: str | os.PathLike) -> tuple[DDMARadarConfig, SimulatedMeta]:
    """Read a simulated root's ``sensor.json``: ``DDMARadarConfig.to_dict()`` plus run keys.

    Raises
    ------
    DataFileError
        Missing or unreadable file, or keys that do not build a :class:`DDMARadarConfig`.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "sensor description is missing")
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataFileError(path, f"is not readable JSON ({e})") from e
    if not isinstance(d, dict):
        raise DataFileError(path, f"expected a JSON object, found {type(d).__name__}")
    meta_d = {k: d.pop(k) for k in SIMULATED_META_KEYS if k in d}
    try:
        sensor = DDMARadarConfig.from_dict(d)
    except (TypeError, ValueError) as e:
        raise DataFileError(path, f"does not describe a DDMARadarConfig ({e})") from e
    def opt_int(k: str) -> int | None:
        v = meta_d.get(k)
        return None if v is None else int(v)
    meta = SimulatedMeta(seed=opt_int("seed"), n_sequences=opt_int("n_sequences"),
                         frames_per_sequence=opt_int("frames_per_sequence"),
                         radarpc_version=None if meta_d.get("radarpc_version") is None
                         else str(meta_d["radarpc_version"]))
    return sensor, meta


def root_sensor(root: str | os.PathLike, sensor: DDMARadarConfig | None = None
                ) -> tuple[DDMARadarConfig, SimulatedMeta | None]:
    """The sensor of a RADIal root: ``sensor.json`` if present (simulated), else :data:`RADIAL`.

    An explicit ``sensor`` wins, but must have the cube shape that ``sensor.json`` states.
    """
    path = Path(root) / "sensor.json"
    if not path.is_file():
        return (sensor if sensor is not None else RADIAL), None
    stored, meta = read_sensor_json(path)
    if sensor is None:
        return stored, meta
    if sensor.rd_shape != stored.rd_shape:
        raise ValueError(f"sensor {sensor.name!r} has RD shape {sensor.rd_shape} but {path} describes "
                         f"{stored.name!r} with {stored.rd_shape}")
    return sensor, meta


# ---- skip lists ---------------------------------------------------------------------------------
def read_skip_file(path: str | os.PathLike) -> list[int]:
    """numSample values listed in a text file, one per line (blank lines and ``#`` comments ignored)."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, "skip list is missing (expected one numSample per line)")
    out: list[int] = []
    for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        try:
            out.append(int(s))
        except ValueError:
            raise DataFileError(path, f"line {k}: {s!r} is not an integer numSample") from None
    return out


def write_skip_file(path: str | os.PathLike, num_samples: Iterable[int]) -> None:
    """Write ``num_samples`` (sorted, unique), one per line, atomically."""
    with atomic_write(path, "w") as f:
        for n in sorted({int(x) for x in num_samples}):
            f.write(f"{n}\n")


def _skip_set(skip: Iterable[int] | str | os.PathLike | None) -> set[int]:
    if skip is None:
        return set()
    if isinstance(skip, (str, os.PathLike)):
        return set(read_skip_file(skip))
    return {int(x) for x in skip}


# ---- files --------------------------------------------------------------------------------------
def find_fft_file(root: str | os.PathLike, num_sample: int) -> Path:
    """``radar_FFT/fft_{:06d}.npy``, else the ``.npz`` (the newer public release; radarpc's
    compressed sparse-RD roots).

    Raises
    ------
    DataFileError
        If neither exists (naming the ``.npy``).
    """
    found = stored_fft_path(root, num_sample)
    if found is None:
        raise DataFileError(fft_path(root, num_sample, ".npy"),
                            f"RD cube of frame {int(num_sample)} is missing (no .npy nor .npz)")
    return found


def load_rd(path: str | os.PathLike, sensor: DDMARadarConfig, *, validate: bool = True) -> np.ndarray:
    """Load one RD cube as complex64 ``(n_range, n_doppler, n_rx)``.

    Parameters
    ----------
    path : path-like
        ``.npy``, or ``.npz`` (compressed or not) holding a single array.
    sensor : DDMARadarConfig
        Gives the expected shape ``sensor.rd_shape``.
    validate : bool
        Check shape, complex dtype and finiteness (True), or only that the file loads.

    Raises
    ------
    DataFileError
        Missing, truncated, wrong-shape, real-valued or NaN-containing file, naming the file.
    """
    if validate:
        arr = load_array(path, sensor.rd_shape, complex_=True)
    else:
        arr = load_array(path, None, allow_nan=True)
    return np.asarray(arr, dtype=np.complex64)


def load_freespace(path: str | os.PathLike, *, validate: bool = True) -> np.ndarray:
    """Load a freespace PNG as uint8 ``FREESPACE_SHAPE`` (512 x 900; 255 = free, 0 = not free).

    Raises
    ------
    DataFileError
        Missing, truncated or unreadable PNG, more than one channel, wrong size, or (with
        ``validate``) values other than 0 and 255.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(path, f"freespace mask is missing (expected a {FREESPACE_SHAPE[0]} x "
                                  f"{FREESPACE_SHAPE[1]} PNG)")
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            arr = np.asarray(im)
    except (OSError, ValueError, SyntaxError) as e:
        raise DataFileError(path, f"is truncated or not a readable PNG ({e})") from e
    if arr.ndim != 2:
        raise DataFileError(path, f"expected a single-channel mask, found image mode {mode} with shape {arr.shape}")
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8) * 255
    if validate:
        if arr.shape != FREESPACE_SHAPE:
            raise DataFileError(path, f"expected a {FREESPACE_SHAPE[0]} x {FREESPACE_SHAPE[1]} mask, "
                                      f"found {arr.shape[0]} x {arr.shape[1]}")
        if not np.isin(arr, (0, 255)).all():
            bad = np.unique(arr[~np.isin(arr, (0, 255))])[:5].tolist()
            raise DataFileError(path, f"expected mask values 0 and 255, found also {bad}")
    return np.asarray(arr, dtype=np.uint8)


def _pil_nearest_index(n_in: int, n_out: int) -> np.ndarray:
    # PIL's NEAREST resize samples the source at the output pixel centre:
    # src = floor((dst + 1/2) * n_in / n_out)   (computed in exact integer arithmetic)
    dst = np.arange(n_out, dtype=np.int64)
    return ((2 * dst + 1) * n_in) // (2 * n_out)


def freespace_to_model(mask: np.ndarray) -> np.ndarray:
    """RADIal's freespace target: centre crop to :data:`FREESPACE_CROP`, nearest resize to
    :data:`FREESPACE_OUT`, ``== 255``.

    RADIal's loader applies torchvision ``CenterCrop((512, 448))`` then
    ``Resize((256, 224), NEAREST)`` to the PIL image, i.e. PIL's crop box
    ``left = round((900 - 448) / 2) = 226`` and PIL's nearest rule, which samples each output
    pixel at its centre: ``src = floor((dst + 0.5) * n_in / n_out)`` (rows 1, 3, ..., 511 and
    columns 227, 229, ..., 673 here). This is reproduced in numpy, index for index.

    Parameters
    ----------
    mask : ndarray, uint8 (255 = free) or bool, ``(512, 900)``

    Returns
    -------
    ndarray, bool, ``(256, 224)``
    """
    mask = np.asarray(mask)
    if mask.shape != FREESPACE_SHAPE:
        raise ValueError(f"freespace mask must be {FREESPACE_SHAPE}, got {mask.shape}")
    if mask.dtype != np.bool_ and mask.dtype != np.uint8:
        raise ValueError(f"freespace mask must be uint8 (255 = free) or bool, got dtype {mask.dtype}")
    (h, w), (ch, cw), (oh, ow) = FREESPACE_SHAPE, FREESPACE_CROP, FREESPACE_OUT
    top, left = int(round((h - ch) / 2.0)), int(round((w - cw) / 2.0))  # torchvision center_crop
    rows = top + _pil_nearest_index(ch, oh)                               # (256,)
    cols = left + _pil_nearest_index(cw, ow)                              # (224,)
    out = mask[np.ix_(rows, cols)]                                        # (256, 224)
    return out if out.dtype == np.bool_ else out == 255


# ---- splits -------------------------------------------------------------------------------------
def split_of_sequence(name: str, all_sequence_names: Iterable[str], *, n_sequences: int | None = None) -> str:
    """``"train"``, ``"val"`` or ``"test"`` for sequence ``name``.

    * Simulated names ``SIM@s{seed}_q{idx:03d}``: :func:`simulated_split` ``(idx, n)`` with ``n``
      = ``n_sequences`` if given (the count in ``sensor.json``), else one more than the largest
      index among ``all_sequence_names`` of the same seed.
    * Any other name (real RADIal ``RECORD@...``): RADIal's official lists
      :data:`OFFICIAL_SPLITS`; every sequence not listed is training data.
    """
    m = _SIM_NAME.match(name)
    if m is None:
        for split, names in OFFICIAL_SPLITS.items():
            if name in names:
                return split
        return "train"
    seed, idx = m.group(1), int(m.group(2))
    if n_sequences is None:
        same = [int(mm.group(2)) for mm in map(_SIM_NAME.match, all_sequence_names)
                if mm is not None and mm.group(1) == seed]
        n_sequences = max(same + [idx]) + 1
    return simulated_split(idx, n_sequences)


def random_split_indices(n: int, fractions: tuple[float, float, float], seed: int) -> dict[str, np.ndarray]:
    """Frame-level random train/val/test split, as FFTRadNet's ``random`` mode.

    ``n_train = int(f_train * n)``, ``n_val = int(f_val * n)``, test the rest, taken in that
    order from ``torch.randperm(n)`` under ``torch.Generator().manual_seed(seed)`` (what
    ``torch.utils.data.random_split`` does). Returns sorted positions in ``[0, n)`` per split.
    """
    f = tuple(float(x) for x in fractions)
    if len(f) != 3 or any(not math.isfinite(x) or x < 0 for x in f) or abs(sum(f) - 1.0) > 1e-6:
        raise ValueError(f"random_split must be three non-negative fractions summing to 1, got {fractions}")
    g = torch.Generator().manual_seed(int(seed))
    perm = torch.randperm(int(n), generator=g).numpy()
    n_train, n_val = int(f[0] * n), int(f[1] * n)
    parts = (perm[:n_train], perm[n_train:n_train + n_val], perm[n_train + n_val:])
    return {s: np.sort(p) for s, p in zip(("train", "val", "test"), parts)}


# ---- frame selection (shared by the on-disk and the on-the-fly datasets) -----------------------
_SIM_SPLIT_RULE = ("simulated sequences are assigned by radarpc.data.radial_format.simulated_split: "
                   "the last sequence is test and the one before it val when there are at least 3, "
                   "and with 6 or more every 6k+4 / 6k+5 pair is also val / test; write at least 3 "
                   "sequences, or use random_split")
_REAL_SPLIT_RULE = ("real sequences are assigned by RADIal's official lists OFFICIAL_SPLITS (every "
                    "sequence not listed is train)")


@dataclass(frozen=True)
class FrameSelection:
    """The frames of a split, as :func:`select_frames` chooses them.

    Attributes
    ----------
    frame_ids : list of int           numSample of each item, ascending
    sequences : list of str           sequence name (``dataset`` column) of each item
    all_rows : list of ndarray        indices into the label table of every row of the item
    vehicle_rows : list of ndarray    the rows returned as the item's ``labels`` tensor
    """

    frame_ids: list[int]
    sequences: list[str]
    all_rows: list[np.ndarray]
    vehicle_rows: list[np.ndarray]


def select_frames(labels: LabelTable, split: str, *, difficult: bool = True,
                  skip: Iterable[int] | str | os.PathLike | None = None,
                  random_split: tuple[float, float, float] | None = None, seed: int = 0,
                  n_sequences: int | None = None, source: str = "the dataset") -> FrameSelection:
    """Choose the frames of ``split`` from a label table: split, ``difficult`` and ``skip`` rules.

    The one implementation behind :class:`RADIal` and the on-the-fly
    :class:`radarpc.sim.radial_writer.SimulatedRADIal`.

    Parameters
    ----------
    labels : LabelTable
        Every row of the root (or of the simulated run).
    split : {"train", "val", "test", "all"}
    difficult, skip, random_split, seed :
        As for :class:`RADIal`.
    n_sequences : int, optional
        Number of simulated sequences of the run (``sensor.json``), for :func:`split_of_sequence`.
    source : str
        Named in error messages.

    Raises
    ------
    ValueError
        Unknown split, or a split without any frame (naming the split, the number of sequences
        and how splits are assigned).
    """
    if split not in SPLIT_CHOICES:
        raise ValueError(f"split must be one of {SPLIT_CHOICES}, got {split!r}")
    frames = _group_frames(labels, difficult=difficult)                 # [(numSample, seq, rows)]
    all_names = sorted({seq for _, seq, _ in frames})
    if random_split is not None:
        pos = random_split_indices(len(frames), random_split, seed)
        keep = set(range(len(frames))) if split == "all" else set(pos[split].tolist())
        rule = (f"random_split={tuple(random_split)} of {len(frames)} frames takes int(fraction * n) "
                "frames for train and val and the rest for test")
    else:
        split_of = {s: split_of_sequence(s, all_names, n_sequences=n_sequences) for s in all_names}
        keep = {k for k, (_, seq, _) in enumerate(frames) if split == "all" or split_of[seq] == split}
        simulated = any(_SIM_NAME.match(s) for s in all_names)
        rule = _SIM_SPLIT_RULE if simulated else _REAL_SPLIT_RULE
    if not keep:
        raise ValueError(f"split {split!r} of {source} is empty: {len(all_names)} sequence(s) with "
                         f"{len(frames)} frame(s), none in {split!r}; {rule}")
    skipped = _skip_set(skip)
    chosen = [frames[k] for k in sorted(keep) if frames[k][0] not in skipped]
    has_vehicle = labels.has_vehicle
    easy = labels.difficult != 1
    all_rows = [r for _, _, r in chosen]
    return FrameSelection(
        frame_ids=[n for n, _, _ in chosen],
        sequences=[s for _, s, _ in chosen],
        all_rows=all_rows,
        vehicle_rows=[r[has_vehicle[r] & (easy[r] | bool(difficult))] for r in all_rows],
    )


def check_cube(rd: torch.Tensor, sensor: DDMARadarConfig, what: str = "RD cube") -> torch.Tensor:
    """Validate an RD cube tensor: complex64 ``sensor.rd_shape``, finite. Returns it.

    Raises
    ------
    ValueError
        Naming ``what``, the bad shape / dtype, or the presence of NaN/inf.
    """
    if not isinstance(rd, torch.Tensor):
        raise ValueError(f"{what}: expected a torch.Tensor, got {type(rd).__name__}")
    if tuple(rd.shape) != tuple(sensor.rd_shape):
        raise ValueError(f"{what}: expected shape {sensor.rd_shape} (n_range, n_doppler, n_rx) of sensor "
                         f"{sensor.name!r}, got {tuple(rd.shape)}")
    if rd.dtype != torch.complex64:
        raise ValueError(f"{what}: expected complex64, got {rd.dtype}")
    if not bool(torch.isfinite(torch.view_as_real(rd)).all()):
        raise ValueError(f"{what}: contains NaN or infinite values")
    return rd


# ---- the Datasets -------------------------------------------------------------------------------
class RadialFrames(torch.utils.data.Dataset, abc.ABC):
    """Common interface of RADIal-format datasets, on disk (:class:`RADIal`) or generated on the
    fly (:class:`radarpc.sim.radial_writer.SimulatedRADIal`): code written against it runs on
    either.

    Subclasses set the attributes below and implement :meth:`cube` and :meth:`freespace_mask`.

    Attributes
    ----------
    sensor : DDMARadarConfig
    split : str
    difficult : bool
    device : torch.device
    labels : LabelTable
        Every label row of the root or run.
    frame_ids : list of int
        numSample of each item, ascending.
    sequences : list of str
        Sequence name of each item.
    """

    sensor: DDMARadarConfig
    split: str
    difficult: bool
    device: torch.device
    labels: LabelTable
    frame_ids: list[int]
    sequences: list[str]

    def _set_selection(self, sel: FrameSelection) -> None:
        self.frame_ids = sel.frame_ids
        self.sequences = sel.sequences
        self._all_rows = sel.all_rows
        self._vehicle_rows = sel.vehicle_rows

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= int(i) < n:
            raise IndexError(f"index {i} out of range for {type(self).__name__} split {self.split!r} of "
                             f"{n} frames")
        return int(i) % n

    @property
    @abc.abstractmethod
    def calibration(self) -> Calibration:
        """The sensor's calibration table (``calibration.npz`` content)."""

    @abc.abstractmethod
    def cube(self, i: int) -> torch.Tensor:
        """RD cube of item ``i``: validated complex64 ``(n_range, n_doppler, n_rx)`` on :attr:`device`."""

    @abc.abstractmethod
    def freespace_mask(self, i: int) -> np.ndarray:
        """Full freespace mask of item ``i``: uint8 ``FREESPACE_SHAPE`` (255 = free)."""

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(rd, labels, freespace)`` of item ``i``.

        Returns
        -------
        rd : complex64 ``(n_range, n_doppler, n_rx)``
        labels : float32 ``(n_vehicles, 14)``, columns ``LABEL_TENSOR_COLUMNS``
        freespace : bool ``(256, 224)``
        """
        i = self._index(i)
        return self.cube(i), self.label_tensor(i), self.freespace(i)

    def label_tensor(self, i: int) -> torch.Tensor:
        """The ``labels`` of item ``i`` (as :meth:`__getitem__`, without reading the cube):
        float32 ``(n_vehicles, 14)``, columns ``LABEL_TENSOR_COLUMNS``, on :attr:`device`."""
        lab = self.labels.tensor_rows(self._vehicle_rows[self._index(i)])
        return torch.from_numpy(lab).to(self.device)

    def freespace(self, i: int) -> torch.Tensor:
        """The ``freespace`` target of item ``i`` (as :meth:`__getitem__`, without reading the
        cube): bool ``FREESPACE_OUT`` (:func:`freespace_to_model` of :meth:`freespace_mask`)."""
        fs = freespace_to_model(self.freespace_mask(self._index(i)))
        return torch.from_numpy(np.ascontiguousarray(fs)).to(self.device)

    def frame_labels(self, i: int) -> list[dict[str, int | float | str]]:
        """The raw ``labels.csv`` rows (all :data:`LABEL_COLUMNS`) of item ``i``, -1 rows included."""
        return [self.labels.row(int(k)) for k in self._all_rows[self._index(i)]]

    def index_of(self, num_sample: int) -> int:
        """Position of frame ``num_sample`` in this split."""
        try:
            return self.frame_ids.index(int(num_sample))
        except ValueError:
            raise KeyError(f"frame {num_sample} is not in the {self.split!r} split of {self!r}") from None


class RADIal(RadialFrames):
    """Frames of a RADIal-layout root (real or simulated) as ``(rd, labels, freespace)`` tensors.

    Parameters
    ----------
    root : path-like
        Folder holding ``labels.csv``, ``radar_FFT/`` and ``radar_Freespace/``.
    split : {"train", "val", "test", "all"}
        Which frames: by sequence (see :func:`split_of_sequence`) unless ``random_split``. An
        empty split raises ``ValueError``.
    sensor : DDMARadarConfig, optional
        Defaults to the root's ``sensor.json`` (simulated data) or :data:`RADIAL` (real data).
    difficult : bool
        True keeps every label row. False follows RADIal's "easy" mode for vehicles: label rows
        with ``Difficult == 1`` are dropped, and so are frames all of whose vehicles are difficult.
        Frames without vehicles are kept (RADIal's loader drops those too, because their -1 row
        is not ``Difficult == 0``; radarpc keeps them as negative examples).
    skip : iterable of int, or path-like, optional
        numSample values to leave out, or a text file of them (one per line, as written by
        ``radarpc info --check --write-skip FILE``). Applied after the split, so that skipping
        frames never reshuffles a random split.
    random_split : (float, float, float), optional
        Train/val/test fractions of a frame-level random split (FFTRadNet's random mode; with
        ``difficult=True`` the same frames as FFTRadNet for the same seed).
    seed : int
        Seed of ``random_split``.
    validate : bool
        Validate every file opened (shape, complex dtype, NaN, mask values); False only checks
        that files load.
    device : torch.device or str, optional
        Where returned tensors live (default CPU).
    trust_pickle : bool
        Allow :attr:`calibration` to unpickle the official ``CalibrationTable.npy`` when no
        ``calibration.npz`` exists (unpickling runs code from the file).

    Attributes
    ----------
    root : Path
    meta : SimulatedMeta or None
        Run keys of ``sensor.json`` (None on a real root).
    and those of :class:`RadialFrames`.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str = "train",
        *,
        sensor: DDMARadarConfig | None = None,
        difficult: bool = True,
        skip: Iterable[int] | str | os.PathLike | None = None,
        random_split: tuple[float, float, float] | None = None,
        seed: int = 0,
        validate: bool = True,
        device: torch.device | str | None = None,
        trust_pickle: bool = False,
    ) -> None:
        if split not in SPLIT_CHOICES:
            raise ValueError(f"split must be one of {SPLIT_CHOICES}, got {split!r}")
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataFileError(self.root, "RADIal root folder is missing")
        self.split = split
        self.difficult = bool(difficult)
        self.validate = bool(validate)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.trust_pickle = bool(trust_pickle)
        self.sensor, self.meta = root_sensor(self.root, sensor)
        self.labels = read_labels(self.root / "labels.csv")
        self._calibration: Calibration | None = None
        n_seq = self.meta.n_sequences if self.meta is not None else None
        self._set_selection(select_frames(self.labels, split, difficult=self.difficult, skip=skip,
                                          random_split=random_split, seed=seed, n_sequences=n_seq,
                                          source=str(self.root)))

    def cube(self, i: int) -> torch.Tensor:
        """RD cube of item ``i`` from its file (validated unless ``validate=False``), on :attr:`device`."""
        num = self.frame_ids[self._index(i)]
        rd = load_rd(find_fft_file(self.root, num), self.sensor, validate=self.validate)
        return torch.from_numpy(rd).to(self.device)

    def freespace_mask(self, i: int) -> np.ndarray:
        """The item's ``radar_Freespace`` PNG as uint8 ``FREESPACE_SHAPE``."""
        num = self.frame_ids[self._index(i)]
        return load_freespace(freespace_path(self.root, num), validate=self.validate)

    @property
    def calibration(self) -> Calibration:
        """The root's calibration table, loaded on first use.

        ``calibration.npz``; else the official pickled ``CalibrationTable.npy`` only if the
        dataset was built with ``trust_pickle=True``.
        """
        if self._calibration is None:
            npz = self.root / "calibration.npz"
            npy = self.root / "CalibrationTable.npy"
            if npz.is_file() or not npy.is_file():
                calib = load_calibration(npz)
                src = npz
            else:
                calib = load_calibration(npy, trust_pickle=self.trust_pickle)
                src = npy
            calib.check_sensor(self.sensor, src)
            self._calibration = calib
        return self._calibration

    def __repr__(self) -> str:
        return (f"RADIal(root={str(self.root)!r}, split={self.split!r}, frames={len(self)}, "
                f"sequences={len(set(self.sequences))}, sensor={self.sensor.name!r})")


def _group_frames(labels: LabelTable, *, difficult: bool) -> list[tuple[int, str, np.ndarray]]:
    """``[(numSample, sequence, row indices)]`` sorted by numSample; with ``difficult=False``
    frames whose vehicle rows are all ``Difficult == 1`` are left out."""
    if len(labels) == 0:
        return []
    order = np.argsort(labels.num_sample, kind="stable")
    ids, starts = np.unique(labels.num_sample[order], return_index=True)
    groups = np.split(order, starts[1:])
    has_vehicle = labels.has_vehicle
    out = []
    for num, rows in zip(ids.tolist(), groups):
        veh = rows[has_vehicle[rows]]
        if not difficult and veh.size and np.all(labels.difficult[veh] == 1):
            continue
        out.append((int(num), labels.dataset[int(rows[0])], rows))
    return out


def radial_collate(batch: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
                   ) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """DataLoader ``collate_fn``: ``(rd (B, R, D, Rx), [labels_b (n_b, 14)], freespace (B, 256, 224))``."""
    rd = torch.stack([b[0] for b in batch])
    fs = torch.stack([b[2] for b in batch])
    return rd, [b[1] for b in batch], fs


# ---- whole-root check ---------------------------------------------------------------------------
@dataclass(frozen=True)
class FileProblem:
    """One bad or missing file of a root."""

    path: Path              # the file
    reason: str             # what is wrong, and what was expected
    num_sample: int | None  # the frame it belongs to (None for root-level files)


@dataclass
class CheckReport:
    """Result of :func:`check_root`: every bad or missing file, with the frames they break."""

    root: Path
    sensor: DDMARadarConfig | None
    n_frames: int = 0
    problems: list[FileProblem] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def bad_frames(self) -> list[int]:
        """numSample of every frame with a bad or missing file, ascending (a skip list)."""
        return sorted({p.num_sample for p in self.problems if p.num_sample is not None})

    def add(self, err: DataFileError, num_sample: int | None = None) -> None:
        self.problems.append(FileProblem(path=err.path, reason=err.problem, num_sample=num_sample))

    def format(self) -> str:
        """Human-readable listing, one problem per line."""
        lines = [f"{self.root}: {self.n_frames} frames checked, {len(self.problems)} problem(s), "
                 f"{len(self.bad_frames)} bad frame(s)"]
        for p in self.problems:
            tag = f"frame {p.num_sample}: " if p.num_sample is not None else ""
            lines.append(f"  {tag}{p.path}: {p.reason}")
        return "\n".join(lines)


def check_root(root: str | os.PathLike, sensor: DDMARadarConfig | None = None, *,
               progress: bool = False) -> CheckReport:
    """Open and validate every file a RADIal root's ``labels.csv`` references.

    Checks ``sensor.json`` (if present), ``labels.csv``, ``calibration.npz`` (required when the
    root is simulated, checked when present), and for every frame its RD cube (missing,
    truncated, wrong shape, not complex, NaN/inf) and freespace PNG (missing, truncated, wrong
    size, values other than 0/255). On a simulated root ``labels.csv`` must list
    ``n_sequences * frames_per_sequence`` frames of ``sensor.json`` (a truncated ``labels.csv``
    is listed). Never raises for a bad file or a mismatching ``sensor``: each
    problem is listed.

    Parameters
    ----------
    root : path-like
    sensor : DDMARadarConfig, optional
        As for :class:`RADIal`.
    progress : bool
        Show a tqdm progress bar over frames.

    Returns
    -------
    CheckReport
    """
    root = Path(root)
    report = CheckReport(root=root, sensor=None)
    if not root.is_dir():
        report.add(DataFileError(root, "RADIal root folder is missing"))
        return report
    meta: SimulatedMeta | None = None
    sensor_json = root / "sensor.json"
    try:
        sensor, meta = root_sensor(root, sensor)
    except DataFileError as e:  # unreadable sensor.json: still check that cubes load as 3-D complex
        report.add(e)
        sensor = None
    except ValueError as e:     # explicit sensor of the wrong shape: report, check with the stored one
        report.add(DataFileError(sensor_json, str(e)))
        sensor, meta = read_sensor_json(sensor_json)
    report.sensor = sensor
    # calibration: required on a simulated root (sensor.json present, even if unreadable)
    npz = root / "calibration.npz"
    if npz.is_file() or sensor_json.exists():
        try:
            calib = load_calibration(npz)
            if sensor is not None:
                calib.check_sensor(sensor, npz)
        except DataFileError as e:
            report.add(e)
        except ValueError as e:
            report.add(DataFileError(npz, str(e)))
    try:
        labels = read_labels(root / "labels.csv")
    except DataFileError as e:
        report.add(e)
        return report
    for problem in label_problems(labels, None if sensor is None else label_reach_m(sensor)):
        report.add(DataFileError(labels.path, problem))
    ids = np.unique(labels.num_sample).tolist()
    report.n_frames = len(ids)
    if meta is not None and meta.n_sequences is not None and meta.frames_per_sequence is not None:
        want = meta.n_sequences * meta.frames_per_sequence
        if len(ids) != want:
            report.add(DataFileError(labels.path, (
                f"lists {len(ids)} frames, but sensor.json describes n_sequences * frames_per_sequence = "
                f"{meta.n_sequences} x {meta.frames_per_sequence} = {want} frames (truncated labels.csv?)")))
    it: Iterable[int] = ids
    if progress:
        from tqdm import tqdm

        it = tqdm(ids, desc=f"check {root.name}", unit="frame")
    for num in it:
        try:
            path = find_fft_file(root, num)
            if sensor is not None:
                load_rd(path, sensor)
            else:
                load_array(path, (None, None, None), complex_=True)
        except DataFileError as e:
            report.add(e, num)
        try:
            load_freespace(freespace_path(root, num))
        except DataFileError as e:
            report.add(e, num)
    return report
