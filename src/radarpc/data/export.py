"""Per-frame point-cloud files for neighbouring tools: OpenPCDet/KITTI ``.npy`` and ``.bin``, and PLY.

One file per frame holds the frame's points as an ``(N, C)`` float32 table, one row per point,
the columns in a stated order (:data:`DEFAULT_COLUMNS` unless chosen). Formats:

* ``npy`` -- a NumPy ``.npy`` array of dtype ``<f4`` and shape ``(N, C)``, as OpenPCDet's custom
  dataset reads ``points/{sample_id}.npy`` (``np.load``; ``x, y, z, intensity`` first, then extra
  features, named in the dataset config's ``POINT_FEATURE_ENCODING.src_feature_list``);
* ``bin`` -- the same table as a raw little-endian float32 buffer without header, row-major, like
  KITTI's ``velodyne/*.bin``: read it with ``np.fromfile(path, "<f4").reshape(-1, C)``;
* ``ply`` -- binary little-endian PLY 1.0: an ASCII header (``element vertex N``, one
  ``property float NAME`` per column, in order) followed by the same row-major float32 table.

Every file is written atomically (:func:`radarpc.io.atomic_write`). A frame without points gives a
valid empty file: a ``(0, C)`` array, a 0-byte ``.bin``, a PLY with ``element vertex 0``.

Default columns, in order (:data:`DEFAULT_COLUMNS`)::

    0 x              m      Cartesian, radar frame: x forward
    1 y              m      y left
    2 z              m      z up
    3 amplitude      linear Ae = |s_j[k_j]|, the beamformed amplitude: OpenPCDet's "intensity"
                            slot (not normalised to [0, 1]; scale it in the dataset config if a
                            KITTI-trained model expects that)
    4 velocity_mps   m/s    radial velocity (Doppler), the feature radar detectors use most
    5 snr            linear CFAR signal-to-noise ratio, the detection confidence
    6 range_m        m      polar position, for range-dependent processing
    7 azimuth_deg    deg    positive to the left
    8 elevation_deg  deg    positive up

Why this order: position and an intensity first is the layout every OpenPCDet/KITTI consumer
slices (``points[:, :4]``); velocity and SNR are the radar-specific features; the polar
coordinates follow last because they repeat the position in the sensor's own terms. Other
point-store columns can be chosen (:data:`EXPORTABLE_COLUMNS`); the integer bins and the
``is_neighbour`` flag are written as float32 (exact: the bins are far below 2**24).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from radarpc.io import atomic_write
from radarpc.points import BOOL_FIELDS, FLOAT_FIELDS, INT_FIELDS

__all__ = [
    "FORMATS",
    "DEFAULT_COLUMNS",
    "EXPORTABLE_COLUMNS",
    "COLUMN_DOCS",
    "check_format",
    "check_columns",
    "frame_file_name",
    "frame_points",
    "ply_header",
    "write_ply",
    "write_frame",
    "columns_text",
]

FORMATS: tuple[str, ...] = ("npy", "bin", "ply")
"""Per-frame file formats (the file extension)."""

DEFAULT_COLUMNS: tuple[str, ...] = (
    "x", "y", "z", "amplitude", "velocity_mps", "snr", "range_m", "azimuth_deg", "elevation_deg")
"""Exported columns unless chosen: position, intensity, then the radar features (module docstring)."""

EXPORTABLE_COLUMNS: tuple[str, ...] = FLOAT_FIELDS + INT_FIELDS + BOOL_FIELDS
"""Point-store columns that can be exported (the per-point scalars)."""

COLUMN_DOCS: dict[str, tuple[str, str]] = {
    "x": ("m", "Cartesian position, x forward (radar frame: x forward, y left, z up)"),
    "y": ("m", "Cartesian position, y left"),
    "z": ("m", "Cartesian position, z up"),
    "amplitude": ("linear", "beamformed amplitude Ae = |s_j[k_j]| (the intensity channel; not normalised)"),
    "velocity_mps": ("m/s", "radial velocity"),
    "snr": ("linear", "CFAR signal-to-noise ratio"),
    "range_m": ("m", "range"),
    "azimuth_deg": ("deg", "azimuth, positive to the left"),
    "elevation_deg": ("deg", "elevation, positive up"),
    "doppler_bin": ("bin", "consolidated Doppler index (integer, as float32)"),
    "range_bin": ("bin", "range bin (integer, as float32)"),
    "doppler_full": ("bin", "resolved full-axis Doppler bin (integer, as float32)"),
    "is_neighbour": ("0/1", "1 for a point added by the RD-neighbourhood enrichment, 0 for a CFAR peak"),
}
"""``{column: (unit, meaning)}``, written into each export folder's ``columns.txt``."""


def check_format(fmt: str) -> str:
    """``fmt`` if it is one of :data:`FORMATS`, else a ``ValueError`` naming the choices."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    return fmt


def check_columns(columns: Sequence[str]) -> tuple[str, ...]:
    """Validate an export column list: known store columns, no repeats, starting with x, y, z.

    Raises
    ------
    ValueError
        Naming the bad column and the choices.
    """
    cols = tuple(str(c).strip() for c in columns)
    if not cols:
        raise ValueError("no columns to export; give at least x,y,z")
    unknown = [c for c in cols if c not in EXPORTABLE_COLUMNS]
    if unknown:
        raise ValueError(f"unknown point column(s) {', '.join(map(repr, unknown))}; exportable columns are "
                         f"{', '.join(EXPORTABLE_COLUMNS)}")
    repeated = sorted({c for c in cols if cols.count(c) > 1})
    if repeated:
        raise ValueError(f"column(s) {', '.join(repeated)} given more than once")
    if cols[:3] != ("x", "y", "z"):
        raise ValueError(f"the columns must start with x,y,z (the OpenPCDet/KITTI layout), got {','.join(cols)}")
    return cols


def frame_file_name(sample_id: int | str, fmt: str) -> str:
    """``{sample_id:06d}.{fmt}``: OpenPCDet's custom-dataset file name of a frame."""
    return f"{int(sample_id):06d}.{check_format(fmt)}"


def frame_points(store, i: int, columns: Sequence[str] = DEFAULT_COLUMNS) -> np.ndarray:
    """The points of item ``i`` of a :class:`radarpc.data.pointstore.PointStore` as ``(N, C)`` float32.

    Columns in the order of ``columns`` (validated by :func:`check_columns`); ``(0, C)`` for a frame
    without points.
    """
    cols = check_columns(columns)
    table = store.frame_rows(i)
    out = np.empty((table.num_rows, len(cols)), dtype="<f4")      # (N, C)
    for k, name in enumerate(cols):
        out[:, k] = table.column(name).to_numpy().astype(np.float32)
    return out


def _table(points: np.ndarray | Mapping[str, np.ndarray], names: Sequence[str] | None
           ) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(N, C)`` ``<f4`` table and its column names from a dict of columns or an array + names."""
    if isinstance(points, Mapping):
        names = tuple(points) if names is None else tuple(names)
        if not names:
            raise ValueError("no columns to write")
        cols = [np.asarray(points[n]).reshape(-1) for n in names]
        n = cols[0].shape[0]
        bad = [f"{nm} ({c.shape[0]})" for nm, c in zip(names, cols) if c.shape[0] != n]
        if bad:
            raise ValueError(f"columns differ in length: {names[0]} has {n} values, {', '.join(bad)}")
        arr = np.empty((n, len(cols)), dtype="<f4")
        for k, c in enumerate(cols):
            arr[:, k] = c
        return arr, names
    arr = np.asarray(points)
    if arr.ndim != 2:
        raise ValueError(f"points must be an (N, C) array, got shape {arr.shape}")
    if names is None or len(names) != arr.shape[1]:
        raise ValueError(f"{arr.shape[1]} columns need as many names, got {None if names is None else list(names)}")
    return np.ascontiguousarray(arr, dtype="<f4"), tuple(names)


def ply_header(names: Sequence[str], n_points: int, comments: Sequence[str] = ()) -> bytes:
    """The ASCII header of a binary little-endian PLY with ``n_points`` vertices of float properties."""
    for name in names:
        if not name or any(ch.isspace() for ch in name) or not name.isascii():
            raise ValueError(f"PLY property names must be ASCII words without spaces, got {name!r}")
    lines = ["ply", "format binary_little_endian 1.0"]
    for c in comments:
        if "\n" in c or "\r" in c:
            raise ValueError(f"a PLY comment must be one line, got {c!r}")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {int(n_points)}")
    lines += [f"property float {name}" for name in names]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(path: str | os.PathLike, points: np.ndarray | Mapping[str, np.ndarray],
              names: Sequence[str] | None = None, comments: Sequence[str] = ()) -> Path:
    """Write a binary little-endian PLY of float32 vertex properties, atomically.

    Parameters
    ----------
    path : path-like
        The ``.ply`` file (its folder is created).
    points : dict of str to array, or ndarray
        ``{name: (N,) values}`` in property order, or an ``(N, C)`` array with ``names``.
    names : sequence of str, optional
        Property names (the order of the columns); with a dict, a subset/order of its keys.
    comments : sequence of str
        ``comment`` lines of the header.

    Examples
    --------
    >>> write_ply("cloud.ply", {"x": x, "y": y, "z": z, "snr": snr})   # doctest: +SKIP
    """
    arr, names = _table(points, names)
    path = Path(path)
    with atomic_write(path, "wb") as f:
        f.write(ply_header(names, arr.shape[0], comments))
        f.write(arr.tobytes(order="C"))
    return path


def write_frame(path: str | os.PathLike, points: np.ndarray, fmt: str,
                names: Sequence[str] | None = None, comments: Sequence[str] = ()) -> Path:
    """Write one frame's ``(N, C)`` points as ``fmt`` (:data:`FORMATS`), atomically.

    ``names`` (the column names) is needed for ``ply`` only; ``comments`` goes into a PLY header.
    """
    check_format(fmt)
    path = Path(path)
    if fmt == "ply":
        return write_ply(path, points, names, comments)
    arr = np.asarray(points)
    if arr.ndim != 2:
        raise ValueError(f"points must be an (N, C) array, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype="<f4")
    with atomic_write(path, "wb") as f:
        if fmt == "npy":
            np.save(f, arr, allow_pickle=False)
        else:
            f.write(arr.tobytes(order="C"))
    return path


def columns_text(columns: Sequence[str], fmt: str, layout: str) -> str:
    """The ``columns.txt`` of an export folder: the column order, units and how to read a file."""
    c = len(columns)
    read = {"npy": "np.load(path)  # (N, {c}) float32",
            "bin": 'np.fromfile(path, dtype="<f4").reshape(-1, {c})',
            "ply": "binary little-endian PLY: header, then N rows of {c} float32 (property names = columns)",
            }[check_format(fmt)].format(c=c)
    lines = [f"# radarpc export: every {layout} file holds an (N, {c}) float32 little-endian table,",
             "# one row per point, columns in this order (index name unit meaning):",
             f"# read: {read}"]
    width = max(len(n) for n in columns)
    for k, name in enumerate(columns):
        unit, meaning = COLUMN_DOCS.get(name, ("", ""))
        lines.append(f"{k} {name:<{width}} {unit:<6} {meaning}".rstrip())
    return "\n".join(lines) + "\n"
