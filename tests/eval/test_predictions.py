"""Tests for radarpc.eval.predictions: the prediction-folder layout and its index check."""
from __future__ import annotations

import json

import numpy as np
import pytest

from radarpc.eval.predictions import check_index, index_frames, load_prediction, prediction_path, write_index
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
    assert load_prediction(tmp_path, "r_run0", 3, allow_empty=True).shape == (0, 3)
    np.save(path, np.arange(6, dtype=np.float32).reshape(2, 3))
    np.testing.assert_array_equal(load_prediction(tmp_path, "r_run0", 3), [[0, 1, 2], [3, 4, 5]])


def test_index_frames_lists_the_frames_and_names_bad_entries(tmp_path):
    write_index(tmp_path, "m", tmp_path, "test", [{"run": "b_run1", "frame": 9, "empty": True}, {"run": "a_run0", "frame": 2}])
    assert index_frames(tmp_path) == [("b_run1", 9), ("a_run0", 2)]                    # the index's order
    for frames, match in (([{"run": "a", "frame": 1}, {"run": "a", "frame": 1}], "lists run 'a' frame 1 twice"),
                          ([{"run": "a", "frame": "1"}], r"frames\[0\] must hold a string 'run' and an integer"),
                          ([{"frame": 1}], r"frames\[0\]"), ({"a": 1}, "'frames' must be a list")):
        write_index(tmp_path, "m", tmp_path, "test", [])
        doc = json.loads((tmp_path / "index.json").read_text())
        doc["frames"] = frames
        (tmp_path / "index.json").write_text(json.dumps(doc))
        with pytest.raises(DataFileError, match=match):
            index_frames(tmp_path)
    (tmp_path / "index.json").write_text("{}")
    with pytest.raises(DataFileError, match="'frames' list"):
        index_frames(tmp_path)
    with pytest.raises(DataFileError, match="missing"):
        index_frames(tmp_path / "none")
