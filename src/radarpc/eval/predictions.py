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
or split (:func:`check_index`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterator, Mapping, Sequence

from radarpc.io import DataFileError, atomic_write, load_array

__all__ = ["INDEX_FILE", "prediction_path", "write_index", "check_index", "load_prediction", "prediction_pairs"]

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


def load_prediction(pred_dir: str | os.PathLike, run: str, frame: int):
    """The ``(N, 3)`` float cloud of ``run``'s radar frame ``frame``; missing or empty files are a
    :class:`radarpc.io.DataFileError` naming the file."""
    path = prediction_path(pred_dir, run, frame)
    if not path.is_file():
        raise DataFileError(path, f"prediction for run {run!r} frame {frame} is missing "
                                  f"(expected float32 (N, 3) points, one file per frame of the split)")
    pred = load_array(path, shape=(None, 3), complex_=False)
    if pred.shape[0] == 0:
        raise DataFileError(path, "prediction is empty: Chamfer distance and EMD need at least one point")
    return pred


def prediction_pairs(ds, pred_dir: str | os.PathLike) -> Iterator:
    """``CloudPair(run, frame, prediction, cropped LiDAR)`` for every item of a
    :class:`radarpc.data.coloradar.ColoRadar` dataset, in order (for
    :func:`radarpc.eval.pointsets.evaluate_clouds`)."""
    from radarpc.eval.pointsets import CloudPair

    for i in range(len(ds)):
        k, ri, _ = ds.index[i]
        run = ds.runs[k]
        yield CloudPair(run.name, int(ri), load_prediction(pred_dir, run.name, ri), ds.lidar_points(i))
