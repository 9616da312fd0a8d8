"""Telling a RADIal root from a ColoRadar root."""
from __future__ import annotations

import pytest

from radarpc.data.layout import root_layout
from radarpc.io import DataFileError


def test_root_layout(tmp_path):
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "labels.csv").write_text("numSample\n")
    (tmp_path / "c" / "calib").mkdir(parents=True)
    (tmp_path / "x").mkdir()
    assert root_layout(tmp_path / "r") == "radial" and root_layout(tmp_path / "c") == "coloradar"
    with pytest.raises(DataFileError, match=r"x: is neither a RADIal root \(labels.csv.*ColoRadar root \(calib/"):
        root_layout(tmp_path / "x")
    with pytest.raises(DataFileError, match="dataset root folder is missing"):
        root_layout(tmp_path / "missing")
