"""The shared frame loop of prediction folders (radarpc.pipelines.predictions)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from radarpc.data.coloradar import ColoRadar
from radarpc.io import DataFileError
from radarpc.pipelines.predictions import FramePrediction, fill_predictions, read_records


def _cloud(i: int) -> np.ndarray:
    return np.full((i + 1, 3), float(i), np.float32)


def test_fill_keeps_valid_clouds_and_redoes_damaged_ones(colo_root, tmp_path):
    ds = ColoRadar(colo_root, "test", cube_size=None)
    out = tmp_path / "pred"
    calls = []

    def predict(i):
        calls.append(i)
        return FramePrediction(_cloud(i), {"value": 10 * i}, warning="odd" if i == 1 else None)

    res = fill_predictions(out, ds, predict, keep=lambda i, p: True, method="m", root=colo_root, split="test",
                           records="rec.csv", index_extra={"setting": 3}, progress=False)
    assert (res.n_frames, res.n_new, calls) == (2, 2, [0, 1]) and res.warnings == ("run lab_run2 frame 1: odd",)
    index = json.loads((out / "index.json").read_text())
    assert index["setting"] == 3 and [e["n_points"] for e in index["frames"]] == [1, 2]
    rows = read_records(out / "rec.csv")
    assert [rows[("lab_run2", f)]["value"] for f in (0, 1)] == ["0", "10"]
    # a damaged cloud is predicted again, the valid one kept with its record
    (out / "lab_run2" / "000000.npy").write_bytes(b"\x93NUMPY truncated")
    calls.clear()
    res = fill_predictions(out, ds, predict, keep=lambda i, p: True, method="m", root=colo_root, split="test",
                           records="rec.csv", progress=False)
    assert calls == [0] and res.n_new == 1 and res.warnings == ()
    np.testing.assert_array_equal(np.load(out / "lab_run2" / "000000.npy"), _cloud(0))
    assert read_records(out / "rec.csv")[("lab_run2", 1)]["value"] == "10"
    # keep=False: everything again; a cloud of the wrong shape is refused, naming the frame
    with pytest.raises(ValueError, match=r"run lab_run2 frame 0: a cloud must be \(N, 3\)"):
        fill_predictions(out, ds, lambda i: np.zeros((2, 2)), keep=lambda i, p: False, method="m", root=colo_root,
                         split="test", progress=False)


def test_a_bad_record_file_is_named(tmp_path):
    path = tmp_path / "rec.csv"
    path.write_text("a,b\n1,2\n")
    with pytest.raises(DataFileError, match="rec.csv: expected a CSV with 'run' and 'frame' columns"):
        read_records(path)
    assert read_records(tmp_path / "none.csv") == {}
