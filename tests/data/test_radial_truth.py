"""Tests of :mod:`radarpc.data.radial_truth`: the simulator sidecars and the label statistics,
on hand-written roots."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from radarpc.data.radial import LabelTable
from radarpc.data.radial_format import LABEL_COLUMNS
from radarpc.data.radial_truth import (
    SIM_FRAME_COLUMNS,
    SIM_FRAMES_FILE,
    SIM_VEHICLE_COLUMNS,
    SIM_VEHICLES_FILE,
    label_statistics,
    read_sim_vehicles,
)
from radarpc.io import DataFileError


def _row(num: int, r: float, a: float, d: float, seq: str = "SIM@s0_q0") -> list:
    x, y = r * np.cos(np.radians(a)), r * np.sin(np.radians(a))
    return [num, -1, -1, -1, -1, x, y, 0.0, x, y, r, a, d, 40.0, seq, num, 0]


def _empty(num: int, seq: str = "SIM@s0_q0") -> list:
    return [num] + [-1] * 13 + [seq, num, -1]


# 4 frames: frame 0 has 2 vehicles, frame 1 none, frame 2 has 3, frame 3 none
ROWS = [_row(0, 10.0, 0.0, 1.0), _row(0, 20.0, 10.0, -1.0), _empty(1),
        _row(2, 30.0, -10.0, 0.0), _row(2, 40.0, 5.0, 2.0), _row(2, 50.0, 20.0, 3.0), _empty(3)]


def _write(path: Path, header, rows) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def test_statistics_from_labels_alone():
    s = label_statistics(LabelTable.from_rows(ROWS))
    assert s.n_frames == 4
    assert s.vehicles_per_frame == pytest.approx(5 / 4) and s.max_vehicles_per_frame == 3
    assert s.empty_share == pytest.approx(0.5)
    # quantiles with linear interpolation over the 5 ranges 10..50: p25 = 20, p50 = 30, p5 = 12
    assert s.range_m.values[1:4] == pytest.approx((20.0, 30.0, 40.0)) and s.range_m.values[0] == pytest.approx(12.0)
    assert s.range_m.n == 5
    assert s.scene_share is None and s.state_share is None and s.not_moving_share is None
    text = "\n".join(s.format())
    assert "1.25 vehicles (max 3), 50.0 % of frames empty" in text and "not recorded" in text


def test_statistics_with_sidecars(tmp_path):
    _write(tmp_path / SIM_FRAMES_FILE, SIM_FRAME_COLUMNS,
           [[n, "SIM@s0_q0", n, sc, v] for n, sc, v in ((0, "city", 5.0), (1, "city", 6.0),
                                                      (2, "highway", 25.0), (3, "countryside", 15.0))])
    _write(tmp_path / SIM_VEHICLES_FILE, SIM_VEHICLE_COLUMNS,
           [[0, 1, "car", "parked", 0.0, 10.0, 0.0], [0, 2, "car", "queued", 0.5, 20.0, 10.0],
            [2, 3, "truck", "moving", 22.0, 30.0, -10.0], [2, 4, "car", "moving", 30.0, 40.0, 5.0],
            [2, 5, "car", "stopped", 0.0, 50.0, 20.0]])
    s = label_statistics(LabelTable.from_rows(ROWS), tmp_path)
    assert s.scene_share == pytest.approx({"city": 0.5, "highway": 0.25, "countryside": 0.25})
    assert s.state_share == pytest.approx({"moving": 0.4, "stopped": 0.2, "queued": 0.2, "parked": 0.2})
    assert s.not_moving_share == pytest.approx(0.6)
    assert s.ego_speed_mps.values[2] == pytest.approx(10.5)          # median of 5, 6, 15, 25
    text = "\n".join(s.format())
    assert "city 50.0 %, countryside 25.0 %, highway 25.0 %" in text
    assert "moving 40.0 %, stopped 20.0 %, queued 20.0 %, parked 20.0 %" in text


def test_sidecar_errors_name_the_file(tmp_path):
    labels = LabelTable.from_rows(ROWS)
    path = tmp_path / SIM_VEHICLES_FILE
    _write(path, SIM_VEHICLE_COLUMNS, [[0, 1, "car", "flying", 0.0, 10.0, 0.0]])
    with pytest.raises(DataFileError, match=r"sim_vehicles\.csv: column 'state' holds \['flying'\]"):
        read_sim_vehicles(path)
    _write(path, SIM_VEHICLE_COLUMNS, [[0, 1, "car", "moving", 0.0, 10.0, 0.0]])
    with pytest.raises(DataFileError, match=r"one row per vehicle row of labels\.csv .*\(5 rows\), got 1"):
        label_statistics(labels, tmp_path)
    _write(path, ("numSample", "kind"), [[0, "car"]])
    with pytest.raises(DataFileError, match="expected the header numSample,vehicle_id"):
        label_statistics(labels, tmp_path)
    path.unlink()
    _write(tmp_path / SIM_FRAMES_FILE, SIM_FRAME_COLUMNS, [[0, "SIM@s0_q0", 0, "city", "fast"]])
    with pytest.raises(DataFileError, match="column 'ego_speed_mps' must hold float"):
        label_statistics(labels, tmp_path)
    _write(tmp_path / SIM_FRAMES_FILE, SIM_FRAME_COLUMNS, [[0, "SIM@s0_q0", 0, "city", 1.0]])
    with pytest.raises(DataFileError, match="not the frames of labels.csv"):
        label_statistics(labels, tmp_path)


def test_label_columns_unchanged():
    # the hand rows above follow RADIal's column order
    assert len(LABEL_COLUMNS) == len(ROWS[0])
