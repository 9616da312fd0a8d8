"""The prediction-folder layout: where a method's point clouds for a ColoRadar split live.

::

    PRED_DIR/
      {run}/{frame:06d}.npy   float32 (N, 3) points in the single-chip radar frame, one per paired
                              radar frame of the split (frame = index of the ADC frame in its run)
      index.json              {"method", "root", "split", the method's settings (RaLD: "generation",
                              "guide", "grid", "mirror_azimuth", "model", "empty_frames"),
                              "frames": [one entry per frame]}
      config.yaml             the method's parameters (OS-CFAR: radarpc.rald.oscfar_baseline)
      tuning.json             the tuning search, when the parameters were tuned
      generation.json         RaLD: the generation's key (radarpc.pipelines.rald_generate; the
                              autoencoder's reconstruction, kind "reconstruction":
                              radarpc.pipelines.rald_reconstruct)
      generation.csv          RaLD: per frame, points, empty flag, query counts, seconds per stage
      metrics.json, metrics.md   written by ``radarpc evaluate-points``

Writers: :mod:`radarpc.pipelines.oscfar` and :mod:`radarpc.pipelines.rald_generate`, through the
shared loop :func:`radarpc.pipelines.predictions.fill_predictions`; reader: ``radarpc evaluate-points``
through :func:`prediction_pairs`, which refuses a folder whose ``index.json`` names another root
or split (:func:`check_index`). The frames a folder holds are those its index lists
(:func:`index_frames`): every paired frame of the split, or a subset of them (e.g. every K-th);
a cloud without a point is a frame whose prediction is empty (flagged ``empty`` in the index).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterator, Mapping, Sequence

from radarpc.io import DataFileError, atomic_write, load_array

__all__ = ["INDEX_FILE", "prediction_path", "write_index", "check_index", "index_frames", "load_prediction",
           "prediction_pairs"]

INDEX_FILE = "index.json"


def prediction_path(out: str | os.PathLike, run: str, frame: int) -> Path:
    """``out/{run}/{frame:06d}.npy``: where a method's cloud for a radar frame lives."""
    return Path(out) / run / f"{int(frame):06d}.npy"


def write_index(out: str | os.PathLike, method: str, root: str | os.PathLike, split: str,
                frames: Sequence[dict], extra: Mapping[str, object] | None = None) -> None:
    """Write ``out/index.json`` atomically; ``root`` is stored resolved (see :func:`check_index`).

    ``extra`` adds keys (a method's settings, e.g. RaLD's ``generation``) before ``frames``.
    """
    doc = {"method": method, "root": str(Path(root).resolve()), "split": split}
    clash = sorted(set(extra or {}) & {*doc, "frames"})
    if clash:
        raise ValueError(f"index.json extra keys {clash} would replace the layout's own")
    doc.update(dict(extra or {}))
    doc["frames"] = list(frames)
    with atomic_write(Path(out) / INDEX_FILE, "w") as f:
        json.dump(doc, f, indent=1)


def check_index(pred_dir: str | os.PathLike, data: str | os.PathLike, split: str) -> None:
    """Raise ``ValueError`` unless ``pred_dir/index.json`` names the dataset root ``data`` and ``split``.

    Roots are compared after ``Path.resolve()``; a missing or unreadable index is an error too
    (:class:`radarpc.io.DataFileError`).
    """
    path = Path(pred_dir) / INDEX_FILE
    if not path.is_file():
        raise DataFileError(path, "prediction index is missing: cannot check which dataset root and split the "
                                  "predictions were made on (pass --force to score them anyway)")
    try:
        idx = json.loads(path.read_text())
        root, sp = idx["root"], idx["split"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise DataFileError(path, f"expected a JSON object with 'root' and 'split' ({e})") from e
    if Path(root).resolve() != Path(data).resolve():
        raise ValueError(f"{path} says the predictions were made on root {root!r}, but --data is {str(data)!r} "
                         "(pass --force to score them anyway)")
    if sp != split:
        raise ValueError(f"{path} says the predictions were made on split {sp!r}, but --split is {split!r} "
                         "(pass --force to score them anyway)")


def index_frames(pred_dir: str | os.PathLike) -> list[tuple[str, int]]:
    """``(run, frame)`` of every frame ``pred_dir/index.json`` lists, in its order.

    Raises
    ------
    radarpc.io.DataFileError
        The index is missing or unreadable, has no ``frames`` list, an entry lacks a string
        ``run`` or an integer ``frame``, or lists a frame twice (the message names the file and
        the entry).
    """
    path = Path(pred_dir) / INDEX_FILE
    if not path.is_file():
        raise DataFileError(path, "prediction index is missing: cannot tell which frames the folder holds")
    try:
        frames = json.loads(path.read_text())["frames"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DataFileError(path, f"expected a JSON object with a 'frames' list ({e})") from e
    if not isinstance(frames, list):
        raise DataFileError(path, f"'frames' must be a list, found {type(frames).__name__}")
    keys: list[tuple[str, int]] = []
    for k, e in enumerate(frames):
        run = e.get("run") if isinstance(e, dict) else None
        frame = e.get("frame") if isinstance(e, dict) else None
        if not isinstance(run, str) or isinstance(frame, bool) or not isinstance(frame, int):
            raise DataFileError(path, f"frames[{k}] must hold a string 'run' and an integer 'frame', found {e!r}")
        keys.append((run, frame))
    seen: set[tuple[str, int]] = set()
    for run, frame in keys:
        if (run, frame) in seen:
            raise DataFileError(path, f"lists run {run!r} frame {frame} twice")
        seen.add((run, frame))
    return keys


def load_prediction(pred_dir: str | os.PathLike, run: str, frame: int, *, allow_empty: bool = False):
    """The ``(N, 3)`` float cloud of ``run``'s radar frame ``frame``; a missing or malformed file is a
    :class:`radarpc.io.DataFileError` naming the file, and so is an empty one unless ``allow_empty``
    (then it is returned as a ``(0, 3)`` array)."""
    path = prediction_path(pred_dir, run, frame)
    if not path.is_file():
        raise DataFileError(path, f"prediction for run {run!r} frame {frame} is missing "
                                  f"(expected float32 (N, 3) points, one file per frame of the split)")
    pred = load_array(path, shape=(None, 3), complex_=False)
    if pred.shape[0] == 0 and not allow_empty:
        raise DataFileError(path, "prediction is empty: Chamfer distance and EMD need at least one point")
    return pred


def prediction_pairs(ds, pred_dir: str | os.PathLike, items: Sequence[int] | None = None, *,
                     allow_empty: bool = False) -> Iterator:
    """``CloudPair(run, frame, prediction, cropped LiDAR)`` for the items ``items`` (default all,
    in order) of a :class:`radarpc.data.coloradar.ColoRadar` dataset (for
    :func:`radarpc.eval.pointsets.evaluate_clouds`); ``allow_empty`` passes empty clouds on (they
    are counted, not scored) instead of refusing them."""
    from radarpc.eval.pointsets import CloudPair

    for i in range(len(ds)) if items is None else items:
        k, ri, _ = ds.index[i]
        run = ds.runs[k]
        yield CloudPair(run.name, int(ri), load_prediction(pred_dir, run.name, ri, allow_empty=allow_empty),
                        ds.lidar_points(i))
