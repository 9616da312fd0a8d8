"""``radarpc show`` on a ColoRadar root (radar cube, LiDAR, a prediction folder's cloud) and on an
OS-CFAR tuning file, on a tiny simulated root."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from PIL import Image

from radarpc import viz
from radarpc.cli import show
from radarpc.data.coloradar import ColoRadarRun, pair_radar_lidar
from radarpc.eval.predictions import prediction_path, write_index
from radarpc.io import DataFileError, save_npy_atomic

# the session's tiny simulated ColoRadar root (tests/conftest.py): 3 lab runs of 2 radar frames


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="radarpc")
    sub = parser.add_subparsers(dest="command", required=True)
    show.add_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture
def colo(colo_root):
    return colo_root


@pytest.fixture
def figures(monkeypatch):
    saved = []
    save = viz.save_figure

    def keep(fig, out, dpi):
        saved.append(fig)
        save(fig, out, dpi)

    monkeypatch.setattr(viz, "save_figure", keep)
    return saved


def _pred_folder(colo, tmp_path, frame: int, n: int = 25):
    pred = tmp_path / "preds"
    pts = np.random.default_rng(0).uniform(0.5, 5.0, (n, 3)).astype(np.float32)
    save_npy_atomic(prediction_path(pred, "lab_run0", frame), pts)
    write_index(pred, "os-cfar", colo, "all", [{"run": "lab_run0", "frame": frame}])
    return pred, pts


def test_show_coloradar_frame_with_prediction(colo, tmp_path, capsys, figures):
    run = ColoRadarRun(colo / "lab_run0")
    ri, li = (int(v) for v in pair_radar_lidar(run)[0])
    out = tmp_path / "c.png"
    assert run_cli(["show", str(colo), "--frame", str(ri), "--out", str(out)]) == 0
    msg = capsys.readouterr().out
    assert f"run lab_run0, radar frame {ri}, LiDAR scan {li}" in msg and "predicted" not in msg
    fig = figures[-1]
    assert len(fig.axes) == 4 and fig.axes[3].get_label() == "<colorbar>"      # cube + BEV + side + colour bar
    assert fig.axes[0].collections[0].get_array().size == 128 * 8                # range x azimuth, max over elevation
    with Image.open(out) as im:
        assert im.format == "PNG" and np.asarray(im.convert("L")).std() > 10
    pred, pts = _pred_folder(colo, tmp_path, ri)
    out2 = tmp_path / "p.png"
    assert run_cli(["show", str(colo), "--run", "lab_run0", "--frame", str(ri), "--pred", str(pred),
                    "--out", str(out2)]) == 0
    assert "25 predicted points (os-cfar (preds))" in capsys.readouterr().out
    bev = figures[-1].axes[1]
    drawn = [c for c in bev.collections if c.get_label().startswith("prediction (25)")]
    assert len(drawn) == 1
    np.testing.assert_allclose(drawn[0].get_offsets(), pts[:, [1, 0]], rtol=1e-6)   # (y, x) in the BEV


def test_show_coloradar_bad_input(colo, tmp_path):
    out = str(tmp_path / "f.png")
    with pytest.raises(ValueError, match="radar frame 9 is not in run lab_run0 \\(it has 2 single-chip frames"):
        run_cli(["show", str(colo), "--frame", "9", "--out", out])
    with pytest.raises(ValueError, match="run 'nope' is not in .* \\(runs: lab_run0, lab_run1, lab_run2\\)"):
        run_cli(["show", str(colo), "--frame", "0", "--run", "nope", "--out", out])
    with pytest.raises(ValueError, match="--density apply to RADIal roots; .* is a ColoRadar root"):
        run_cli(["show", str(colo), "--frame", "0", "--density", "0.1", "--out", out])
    with pytest.raises(DataFileError, match="prediction for run 'lab_run0' frame 1 is missing"):
        run_cli(["show", str(colo), "--frame", "1", "--pred", str(tmp_path / "nopreds"), "--out", out])
    with pytest.raises(ValueError, match="--frame is required"):
        run_cli(["show", str(colo), "--out", out])
    with pytest.raises(DataFileError, match="is neither a RADIal root"):
        run_cli(["show", str(tmp_path), "--frame", "0", "--out", out])
    # a suffix that names no figure format is refused before the frame is looked for
    with pytest.raises(ValueError, match=r"cannot write the figure .*f\.txt: its suffix '\.txt' names no figure "
                                         r"format; give a path ending in one of .*\.png"):
        run_cli(["show", str(colo), "--frame", "9", "--out", str(tmp_path / "f.txt")])
    assert not (tmp_path / "f.png").exists() and not (tmp_path / "f.txt").exists()


def test_show_tuning(tmp_path, capsys, figures):
    cands = [{"config": {"window": [9, 3, 3], "guard": [3, 1, 1], "rank": 0.75, "tau_db": t, "angle_bins": None},
              "chamfer_m": cd, "points_per_frame": n} for t, cd, n in ((4.0, 1.8, 95.0), (8.0, 1.5, 45.0),
                                                                     (12.0, 2.1, 12.0))]
    folder = tmp_path / "preds"
    folder.mkdir()
    (folder / "tuning.json").write_text(json.dumps({"split": "val", "frames": 2, "best": cands[1]["config"],
                                                    "best_chamfer_m": 1.5, "candidates": cands}))
    out = tmp_path / "tuning.png"
    assert run_cli(["show", "--tuning", str(folder), "--out", str(out)]) == 0
    assert ("3 OS-CFAR candidates on 2 val frames; best window 9x3x3, guard 3x1x1, rank 0.75, tau 8 dB: "
            "mean Chamfer 1.500 m, 45 points per frame") in capsys.readouterr().out
    assert out.is_file() and len(figures[-1].axes) == 3
    with pytest.raises(ValueError, match="--tuning draws the tuning search alone"):
        run_cli(["show", str(tmp_path), "--frame", "0", "--tuning", str(folder), "--out", str(out)])
    with pytest.raises(DataFileError, match="OS-CFAR tuning file is missing"):
        run_cli(["show", "--tuning", str(tmp_path / "none"), "--out", str(out)])
    # the suffix names the format: JPEG's and PDF's magic bytes; a suffix naming none is refused
    for name, magic in (("t.jpg", b"\xff\xd8\xff"), ("t.pdf", b"%PDF-")):
        assert run_cli(["show", "--tuning", str(folder), "--out", str(tmp_path / name)]) == 0
        assert (tmp_path / name).read_bytes().startswith(magic)
    with pytest.raises(ValueError, match="cannot write the figure .*t.doc: its suffix '.doc' names no figure format"):
        run_cli(["show", "--tuning", str(folder), "--out", str(tmp_path / "t.doc")])
    assert not (tmp_path / "t.doc").exists()
