"""The detection task's frame choices, by hand."""
from __future__ import annotations

from radarpc.data.radial import LabelTable
from radarpc.data.radial_format import LABEL_COLUMNS
from radarpc.experiments.radial_detection.task import data_pairs, frames_without_vehicles


def _row(num, difficult, vehicle=True):
    row = {c: (0.0 if vehicle else -1) for c in LABEL_COLUMNS}
    row |= {"numSample": num, "dataset": "s", "dataset_index": num, "Difficult": difficult if vehicle else -1}
    if vehicle:
        row |= {"radar_R_m": 20.0, "radar_A_deg": 5.0}
    return tuple(row[c] for c in LABEL_COLUMNS)


def test_frames_without_vehicles_by_hand():
    table = LabelTable.from_rows([
        _row(0, 0),                    # a vehicle
        _row(1, 0, vehicle=False),     # RADIal's -1 row: no vehicle
        _row(2, 1),                    # only a difficult vehicle
        _row(3, 1), _row(3, 0),        # a difficult and a plain one
    ])
    assert frames_without_vehicles(table, difficult=True) == [1]
    assert frames_without_vehicles(table, difficult=False) == [1, 2]     # RADIal's easy mode drops frame 2 too


def test_the_same_root_twice_is_refused(tmp_path):
    import pytest

    (tmp_path / "a").mkdir()
    with pytest.raises(ValueError, match="the same dataset root is given twice"):
        data_pairs([tmp_path / "a", tmp_path / "b" / ".." / "a"])
    with pytest.raises(ValueError, match="the same point store is given twice"):
        data_pairs([tmp_path / "a", tmp_path / "c"], [tmp_path / "p.parquet", tmp_path / "p.parquet"])
    assert len(data_pairs([tmp_path / "a", tmp_path / "c"], [tmp_path / "p.parquet", tmp_path / "q.parquet"])) == 2
