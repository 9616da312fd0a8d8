"""An evaluation's detections file and its conversions: hand-made cases, independent readers, bad input."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from radarpc.cli import main
from radarpc.eval.detection_files import DETECTION_COLUMNS, read_detections, write_detections
from radarpc.io import DataFileError

FRAMES = [("sim_a", 7), ("sim_a", 9), ("sim_b", 2)]                 # frame 9 has no detection
ROWS = [np.array([[0.9, 10.0, 30.0], [0.25, 40.5, -12.0]]), np.zeros((0, 3)), np.array([[0.5, 20.0, 0.0]])]


def _evaluation(folder, frames=FRAMES, rows=ROWS, stem="eval_test"):
    """A detections file and its evaluation summary, as radarpc evaluate writes them."""
    write_detections(folder / f"{stem}_detections.csv", frames, rows)
    (folder / f"{stem}.json").write_text(json.dumps({"split": "test", "frames": {
        "root": [r for r, _ in frames], "numSample": [n for _, n in frames]}}))
    return folder / f"{stem}_detections.csv"


def test_csv_has_one_row_per_detection_and_reads_back_with_every_frame(tmp_path):
    path = _evaluation(tmp_path)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(DETECTION_COLUMNS) and len(lines) == 1 + 3
    assert lines[1] == "sim_a,7,0.9,10.0,30.0"
    t = read_detections(path)
    assert t.root == ("sim_a", "sim_a", "sim_b") and t.num_sample == (7, 9, 2)
    assert t.offset.tolist() == [2, 2, 3]
    for f, rows in enumerate(ROWS):
        np.testing.assert_array_equal(t.frame_rows(f), rows.reshape(-1, 3))


def test_npz_holds_radial_metric_arrays_per_frame(tmp_path, capsys):
    src = _evaluation(tmp_path)
    assert main(["export", str(src), "--out", str(tmp_path / "dets.npz")]) == 0
    assert "wrote 3 detections of 3 frames" in capsys.readouterr().out
    with np.load(tmp_path / "dets.npz", allow_pickle=False) as z:               # nothing pickled
        assert z["root"].tolist() == ["sim_a", "sim_a", "sim_b"] and z["numSample"].tolist() == [7, 9, 2]
        per_frame = np.split(z["detections"], z["offset"][:-1])
    assert [len(p) for p in per_frame] == [2, 0, 1]
    np.testing.assert_array_equal(per_frame[0], [[10.0, 30.0, 0.9], [40.5, -12.0, 0.25]])   # (R, A, C)
    np.testing.assert_array_equal(per_frame[2], [[20.0, 0.0, 0.5]])


def test_jsonl_lists_every_frame_with_radial_boxes_in_metres(tmp_path):
    src = _evaluation(tmp_path)
    assert main(["export", str(src), "--out", str(tmp_path / "dets.jsonl"), "--format", "jsonl"]) == 0
    frames = [json.loads(line) for line in (tmp_path / "dets.jsonl").read_text().splitlines()]
    assert [(f["root"], f["numSample"], len(f["detections"])) for f in frames] == [("sim_a", 7, 2), ("sim_a", 9, 0),
                                                                                   ("sim_b", 2, 1)]
    d = frames[0]["detections"][0]
    # 10 m at 30 deg left: x = 10 sin 30 = 5 (lateral), y = 10 cos 30 = 8.66 (forward); the 1.8 m x 4 m
    # box has its near edge centred there
    assert d["score"] == 0.9 and math.isclose(d["x_m"], 5.0, rel_tol=1e-12)
    assert math.isclose(d["y_m"], 5 * math.sqrt(3), rel_tol=1e-12)
    np.testing.assert_allclose(d["box_xy_m"], [[4.1, 5 * 3 ** .5], [5.9, 5 * 3 ** .5], [5.9, 5 * 3 ** .5 + 4],
                                               [4.1, 5 * 3 ** .5 + 4]], rtol=1e-12)


def test_export_refuses_to_replace_or_misname(tmp_path, capsys):
    src = _evaluation(tmp_path)
    out = tmp_path / "dets.npz"
    out.write_text("mine")
    assert main(["export", str(src), "--out", str(out)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err and out.read_text() == "mine"
    assert main(["export", str(src), "--out", str(out), "--overwrite"]) == 0
    assert main(["export", str(src), "--out", str(tmp_path / "dets.txt")]) == 2
    assert "to .npz or .jsonl (the suffix names the format), not .txt" in capsys.readouterr().err
    assert main(["export", str(src), "--out", str(tmp_path / "d.npz"), "--format", "jsonl"]) == 2
    assert "--format jsonl but --out" in capsys.readouterr().err
    assert main(["export", str(src), "--out", str(tmp_path / "d.npz"), "--columns", "x,y,z"]) == 2
    assert "takes no --columns" in capsys.readouterr().err


@pytest.mark.parametrize("case, message", [
    ("no_json", "the frames scored"),
    ("old_json", "expected an evaluation summary with a 'frames' entry"),
    ("header", "expected the header root,numSample,score,range_m,azimuth_deg"),
    ("nan", "line 2: a detection value is not finite"),
    ("text", "line 2: expected an integer numSample and numbers"),
    ("foreign", "line 2: frame sim_c 7 is not among the evaluation's frames"),
    ("order", "line 3: frames are out of the evaluation's order"),
    ("name", "expected an evaluation's detections file"),
])
def test_bad_detection_files_name_the_file_and_the_problem(tmp_path, case, message):
    path = _evaluation(tmp_path)
    body = path.read_text().splitlines()
    if case == "no_json":
        (tmp_path / "eval_test.json").unlink()
    elif case == "old_json":
        (tmp_path / "eval_test.json").write_text(json.dumps({"split": "test"}))
    elif case == "header":
        path.write_text("\n".join(["root,frame,score,range_m,azimuth_deg"] + body[1:]))
    elif case == "nan":
        path.write_text("\n".join([body[0], "sim_a,7,nan,10.0,30.0"] + body[2:]))
    elif case == "text":
        path.write_text("\n".join([body[0], "sim_a,seven,0.9,10.0,30.0"] + body[2:]))
    elif case == "foreign":
        path.write_text("\n".join([body[0], "sim_c,7,0.9,10.0,30.0"] + body[2:]))
    elif case == "order":
        path.write_text("\n".join([body[0], body[3], body[1]]))
    elif case == "name":
        path = path.rename(tmp_path / "detections.csv")
    with pytest.raises(DataFileError, match=message) as e:
        read_detections(path)
    assert str(path if case not in ("no_json", "old_json") else tmp_path / "eval_test.json") in str(e.value)
