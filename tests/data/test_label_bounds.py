"""Labels no radar could have measured: listed by ``radarpc info --check``, refused by training."""
from __future__ import annotations

import csv
import shutil

import pytest

from radarpc.cli import main
from radarpc.data.radial import LabelTable, label_problems, label_reach_m, read_labels
from radarpc.data.radial_format import LABEL_COLUMNS
from radarpc.sensors.radial import RADIAL_S
from radarpc.sim.radial_writer import write_radial_dataset
from radarpc.sim.scenes import scene_mix


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    return write_radial_dataset(tmp_path_factory.mktemp("lb") / "r", RADIAL_S, 3, 1, seed=3, progress=False,
                                scenes=scene_mix("city"))


def _row(**values):
    row = {c: 0 for c in LABEL_COLUMNS} | {"dataset": "s", "radar_R_m": 20.0, "radar_A_deg": 10.0, "Difficult": 0}
    row |= values
    return tuple(row[c] for c in LABEL_COLUMNS)


def test_the_labels_reach_radials_range_at_least():
    from radarpc.sensors.radial import RADIAL, TINY

    assert label_reach_m(RADIAL) == label_reach_m(RADIAL_S) == RADIAL.max_range_m == 103.0
    assert TINY.max_range_m < 103.0 and label_reach_m(TINY) == 103.0   # a small sensor labels a whole scene


def test_label_problems_by_hand():
    table = LabelTable.from_rows([
        _row(),                                        # fine
        _row(numSample=1, radar_R_m=1e6),              # beyond the sensor
        _row(numSample=2, radar_R_m=-20.0),            # behind it
        _row(numSample=3, radar_A_deg=400.0),
        _row(numSample=4, Difficult=7),
        _row(numSample=5, radar_R_m=103.0),            # the edge itself is measurable
    ])
    assert label_problems(table, 103.0) == [
        "row 2 (numSample 1): radar_R_m 1e+06 is outside 0 .. 103.0 m",
        "row 3 (numSample 2): radar_R_m -20 is outside 0 .. 103.0 m",
        "row 4 (numSample 3): radar_A_deg 400 is outside -90 .. 90 deg",
        "row 5 (numSample 4): Difficult 7 is neither 0 nor 1",
    ]
    # without a sensor only a negative range is impossible
    assert label_problems(table) == ["row 3 (numSample 2): radar_R_m -20 is outside 0 m"] + label_problems(table, 103.0)[2:]
    # a frame without vehicles has one marker row of -1s, Difficult -1 included: not a problem
    empty = {c: -1 for c in LABEL_COLUMNS} | {"numSample": 9, "dataset": "s", "dataset_index": 0}
    assert label_problems(LabelTable.from_rows([tuple(empty[c] for c in LABEL_COLUMNS)]), 103.0) == []


def _corrupt(root, tmp_path, **values):
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    with open(bad / "labels.csv", newline="") as f:
        rows = list(csv.reader(f))
    header = rows[0]
    k = next(i for i, r in enumerate(rows[1:], 1) if float(r[header.index("radar_R_m")]) > 0)
    for c, v in values.items():
        rows[k][header.index(c)] = str(v)
    with open(bad / "labels.csv", "w", newline="") as f:
        csv.writer(f).writerows(rows)
    return bad


def test_info_check_lists_and_training_refuses_implausible_labels(tiny_root, tmp_path, capsys):
    bad = _corrupt(tiny_root, tmp_path, radar_R_m=1e6, Difficult=7)
    assert main(["info", str(bad), "--check", "--no-plot"]) != 0  # no plot in the working directory
    out = capsys.readouterr().out
    assert "radar_R_m 1e+06 is outside 0 .. " in out and "Difficult 7 is neither 0 nor 1" in out
    assert not label_problems(read_labels(tiny_root / "labels.csv"), label_reach_m(RADIAL_S))   # the simulator's are fine
    (tmp_path / "fft.yaml").write_text("name: f\nmodel: {variant: fftradnet-tiny}\ntrain: {epochs: 1}\n")
    code = main(["train", str(tmp_path / "fft.yaml"), "--data", str(bad), "--out", str(tmp_path / "run"),
                 "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "labels no radar could have measured" in err and "radar_R_m 1e+06" in err
    assert "Traceback" not in err and not (tmp_path / "run").exists()
