"""Tests for radarpc.eval.predictions: the prediction-folder layout and its index check."""
from __future__ import annotations

import json

import numpy as np
import pytest

from radarpc.eval.predictions import check_index, load_prediction, prediction_path, write_index
from radarpc.io import DataFileError


def test_layout_and_index_round_trip(tmp_path):
    assert prediction_path(tmp_path, "lab_run2", 7) == tmp_path / "lab_run2" / "000007.npy"
    root = tmp_path / "data" / ".." / "data"
    write_index(tmp_path, "os-cfar", root, "test", [{"run": "lab_run2", "frame": 7}])
    idx = json.loads((tmp_path / "index.json").read_text())
    assert idx == {"method": "os-cfar", "root": str((tmp_path / "data").resolve()), "split": "test",
                   "frames": [{"run": "lab_run2", "frame": 7}]}
    check_index(tmp_path, tmp_path / "data", "test")                  # same root after resolve()
    with pytest.raises(ValueError, match="split 'test', but --split is 'val'"):
        check_index(tmp_path, tmp_path / "data", "val")
    with pytest.raises(ValueError, match="--data is"):
        check_index(tmp_path, tmp_path / "other", "test")
    (tmp_path / "index.json").write_text("[1, 2]")
    with pytest.raises(DataFileError, match="index.json.*'root' and 'split'"):
        check_index(tmp_path, tmp_path / "data", "test")
    with pytest.raises(DataFileError, match="index.json.*missing"):
        check_index(tmp_path / "none", tmp_path / "data", "test")


def test_load_prediction_names_bad_files(tmp_path):
    path = prediction_path(tmp_path, "r_run0", 3)
    with pytest.raises(DataFileError, match=r"000003\.npy.*missing"):
        load_prediction(tmp_path, "r_run0", 3)
    path.parent.mkdir()
    np.save(path, np.zeros((0, 3), np.float32))
    with pytest.raises(DataFileError, match="empty"):
        load_prediction(tmp_path, "r_run0", 3)
    np.save(path, np.arange(6, dtype=np.float32).reshape(2, 3))
    np.testing.assert_array_equal(load_prediction(tmp_path, "r_run0", 3), [[0, 1, 2], [3, 4, 5]])
