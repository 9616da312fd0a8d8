"""The per-frame detections an evaluation writes, and their conversions to other formats.

``radarpc evaluate`` writes, beside ``eval_{split}[...].json``, the file
``eval_{split}[...]_detections.csv``: one row per decoded detection, columns
:data:`DETECTION_COLUMNS`, frames in the split's order; a frame without detections has no row.
The frames scored (those too) are listed in the ``frames`` entry of the ``.json`` of the same
stem, so a reader knows every frame of the split (:func:`read_detections`).

``radarpc export eval_test_detections.csv --out FILE`` converts the pair into

* ``.npz`` -- offset-batched arrays (no pickled objects): ``root`` (F,) str and ``numSample`` (F,)
  int64 of every frame, ``offset`` (F,) int64 the cumulative detection counts (frame ``f`` owns
  rows ``offset[f-1]:offset[f]``), ``detections`` (D, 3) float64 columns ``range_m, azimuth_deg,
  score``: per frame, the ``(N, 3)`` (range, azimuth, confidence) array RADIal's
  ``GetFullMetrics`` takes as one frame's predictions
  (``np.split(detections, offset[:-1])``);
* ``.jsonl`` -- one JSON object per frame, frames without detections included: ``root``,
  ``numSample`` and ``detections``, each ``{"score", "range_m", "azimuth_deg", "x_m", "y_m",
  "box_xy_m"}`` with the reference point ``x_m = R sin A`` (lateral, positive to the left as the azimuth),
  ``y_m = R cos A`` (forward) and RADIal's evaluation box (:func:`radarpc.boxes.ra_to_box_xy`) as
  its four corners in metres.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from radarpc.boxes import BOX_LENGTH_M, BOX_WIDTH_M
from radarpc.io import DataFileError, atomic_write

__all__ = ["DETECTION_COLUMNS", "DETECTION_FORMATS", "DetectionTable", "write_detections", "read_detections",
           "write_detections_as"]

DETECTION_COLUMNS = ("root", "numSample", "score", "range_m", "azimuth_deg")
"""Columns of ``eval_{split}..._detections.csv``: one row per decoded detection (RADIal's decoding
at confidence 0.05 and NMS; the metrics then keep those whose box's near edge lies within
:data:`~radarpc.eval.detection.RANGE_GATE_M`, as RADIal does), frames in the split's order;
``root`` the dataset root's folder name, ``numSample`` RADIal's frame number, ``range_m`` /
``azimuth_deg`` the box reference point (azimuth positive to the left). A frame without
detections has no row."""

DETECTION_FORMATS = ("npz", "jsonl")
"""What :func:`write_detections_as` writes (the output file's suffix)."""


@dataclass(frozen=True)
class DetectionTable:
    """Every frame of an evaluated split and its detections, offset-batched.

    Attributes
    ----------
    root, num_sample : tuple
        ``(F,)`` the dataset root's folder name and RADIal's frame number of each frame, in order.
    offset : numpy.ndarray
        ``(F,)`` int64 cumulative detection counts: frame ``f`` owns rows ``offset[f-1]:offset[f]``.
    rows : numpy.ndarray
        ``(D, 3)`` float64 columns ``score, range_m, azimuth_deg``.
    """

    root: tuple[str, ...]
    num_sample: tuple[int, ...]
    offset: np.ndarray
    rows: np.ndarray

    def frame_rows(self, f: int) -> np.ndarray:
        start = 0 if f == 0 else int(self.offset[f - 1])
        return self.rows[start:int(self.offset[f])]


def write_detections(path: str | os.PathLike, frames: Sequence[tuple[str, int]],
                     per_frame: Sequence[np.ndarray]) -> None:
    """Write the detections CSV atomically: ``frames`` the (root folder name, numSample) of every
    frame, ``per_frame`` their ``(K, 3)`` (score, range_m, azimuth_deg) rows."""
    if len(per_frame) != len(frames):
        raise ValueError(f"{len(per_frame)} frames of detections for {len(frames)} frames")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(DETECTION_COLUMNS)
    for (root, num), rows in zip(frames, per_frame):
        for score, r, a in np.asarray(rows, dtype=np.float64).reshape(-1, 3).tolist():
            w.writerow([root, int(num), repr(score), repr(r), repr(a)])
    with atomic_write(path, "w") as f:
        f.write(buf.getvalue())


def _frames_of(json_path: Path) -> tuple[list[str], list[int]]:
    """The ``frames`` entry of an evaluation's ``.json``: ``{"root": [...], "numSample": [...]}``."""
    if not json_path.is_file():
        raise DataFileError(json_path, "the evaluation's summary beside its detections file is missing: it lists "
                                       "the frames scored (frames without detections have no CSV row); "
                                       "run `radarpc evaluate` again")
    try:
        frames = json.loads(json_path.read_text())["frames"]
        roots, nums = frames["root"], frames["numSample"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise DataFileError(json_path, "expected an evaluation summary with a 'frames' entry "
                                       "{'root': [...], 'numSample': [...]} (evaluations written before it existed have "
                                       f"none: run `radarpc evaluate` again); found {type(e).__name__}: {e}") from e
    if (not isinstance(roots, list) or not isinstance(nums, list) or len(roots) != len(nums)
            or not all(isinstance(r, str) for r in roots)
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in nums)):
        raise DataFileError(json_path, "expected 'frames' to hold equally long lists of root names (strings) "
                                       "and numSample frame numbers (integers)")
    return roots, nums


def read_detections(path: str | os.PathLike) -> DetectionTable:
    """Read ``eval_..._detections.csv`` and the frame list of the ``.json`` of the same stem.

    Raises
    ------
    radarpc.io.DataFileError
        Either file is missing or malformed: another header, a field that is not a finite number,
        a row naming a frame the evaluation did not score, rows of one frame not together.
    """
    path = Path(path)
    if not path.name.endswith("_detections.csv"):
        raise DataFileError(path, "expected an evaluation's detections file, eval_{split}..._detections.csv "
                                  "(written by `radarpc evaluate`)")
    roots, nums = _frames_of(path.with_name(path.name[:-len("_detections.csv")] + ".json"))
    position = {(r, n): f for f, (r, n) in enumerate(zip(roots, nums))}
    if len(position) != len(roots):
        raise DataFileError(path, "its evaluation lists a frame twice")
    counts = np.zeros(len(roots), dtype=np.int64)
    rows: list[tuple[float, float, float]] = []
    last = -1
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if tuple(header or ()) != DETECTION_COLUMNS:
                raise DataFileError(path, f"expected the header {','.join(DETECTION_COLUMNS)}; found "
                                          f"{','.join(header) if header else 'nothing'}")
            for line, rec in enumerate(reader, start=2):
                if len(rec) != len(DETECTION_COLUMNS):
                    raise DataFileError(path, f"line {line}: expected {len(DETECTION_COLUMNS)} fields, found {len(rec)}")
                try:
                    num = int(rec[1])
                    values = tuple(float(v) for v in rec[2:])
                except ValueError as e:
                    raise DataFileError(path, f"line {line}: expected an integer numSample and numbers, found "
                                              f"{rec[1:]}") from e
                if not all(math.isfinite(v) for v in values):
                    raise DataFileError(path, f"line {line}: a detection value is not finite: {rec[2:]}")
                f_idx = position.get((rec[0], num))
                if f_idx is None:
                    raise DataFileError(path, f"line {line}: frame {rec[0]} {num} is not among the evaluation's "
                                              "frames (the .json beside it belongs to another evaluation)")
                if f_idx < last:
                    raise DataFileError(path, f"line {line}: frames are out of the evaluation's order")
                last = f_idx
                counts[f_idx] += 1
                rows.append(values)
    except UnicodeDecodeError as e:
        raise DataFileError(path, f"expected a UTF-8 CSV file ({e})") from e
    table = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    return DetectionTable(tuple(roots), tuple(nums), np.cumsum(counts), table)


def _box_corners(range_m: float, azimuth_deg: float) -> tuple[float, float, list[list[float]]]:
    """RADIal's evaluation box (radarpc.boxes.ra_to_box_xy): near-edge centre and corners."""
    a = math.radians(azimuth_deg)
    x, y = range_m * math.sin(a), range_m * math.cos(a)
    w = BOX_WIDTH_M / 2
    return x, y, [[x - w, y], [x + w, y], [x + w, y + BOX_LENGTH_M], [x - w, y + BOX_LENGTH_M]]


def write_detections_as(table: DetectionTable, out: str | os.PathLike) -> str:
    """Write ``table`` as ``out`` in the format its suffix names (:data:`DETECTION_FORMATS`,
    module docstring), atomically; returns the format."""
    out = Path(out)
    fmt = out.suffix.lstrip(".").lower()
    if fmt not in DETECTION_FORMATS:
        raise ValueError(f"--out {out}: detections export to {' or '.join('.' + f for f in DETECTION_FORMATS)} "
                         f"(the suffix names the format), not {out.suffix or 'a name without suffix'}")
    if fmt == "npz":
        buf = io.BytesIO()
        np.savez(buf, root=np.asarray(table.root, dtype=str), numSample=np.asarray(table.num_sample, dtype=np.int64),
                 offset=table.offset.astype(np.int64), detections=table.rows[:, [1, 2, 0]])
        with atomic_write(out, "wb") as f:
            f.write(buf.getvalue())
        return fmt
    lines = []
    for f, (root, num) in enumerate(zip(table.root, table.num_sample)):
        dets = []
        for score, r, a in table.frame_rows(f).tolist():
            x, y, corners = _box_corners(r, a)
            dets.append({"score": score, "range_m": r, "azimuth_deg": a, "x_m": x, "y_m": y, "box_xy_m": corners})
        lines.append(json.dumps({"root": root, "numSample": num, "detections": dets}))
    with atomic_write(out, "w") as fh:
        fh.write("\n".join(lines) + ("\n" if lines else ""))
    return fmt
