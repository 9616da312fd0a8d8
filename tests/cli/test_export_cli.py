"""``radarpc export``: files a neighbouring tool reads, clear one-line errors, the column order in --help."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from radarpc.cli import main
from radarpc.data.export import DEFAULT_COLUMNS


def _load(name, rel):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / rel)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


H = _load("_export_helpers_cli", "data/test_export.py")             # independent readers, tiny store
P = _load("_export_pipeline_cli", "pipelines/test_export.py")       # a tiny prediction folder


@pytest.fixture
def store(tmp_path):
    return H.make_store(tmp_path / "pc.parquet")


def test_export_bin_with_columns_then_resume(store, tmp_path, capsys):
    out = tmp_path / "kitti"
    argv = ["export", str(store.path), "--out", str(out), "--format", "bin", "--columns", "x,y,z,amplitude,velocity_mps"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert f"wrote 4 bin files (4 frames, 1 without points) to {out}" in text
    assert "columns (float32, in order): x y z amplitude velocity_mps" in text
    got = H.read_bin(out / "points" / "000012.bin", 5)
    np.testing.assert_array_equal(got, H.expected(store, 2, ("x", "y", "z", "amplitude", "velocity_mps")))
    assert (out / "points" / "000011.bin").stat().st_size == 0          # the empty frame
    assert main(argv) == 0
    assert "wrote 0 bin files (4 frames, 1 without points, kept 4 from an earlier run)" in capsys.readouterr().out


def test_export_default_is_openpcdet_npy(store, tmp_path, capsys):
    out = tmp_path / "custom"
    assert main(["export", str(store.path), "--out", str(out)]) == 0
    assert sorted(p.name for p in (out / "points").iterdir()) == ["000010.npy", "000011.npy", "000012.npy",
                                                                  "1234567.npy"]
    np.testing.assert_array_equal(H.read_npy(out / "points" / "000010.npy"), H.expected(store, 0, DEFAULT_COLUMNS))


def test_export_predictions_as_ply(tmp_path, capsys):
    pred = tmp_path / "pred"
    clouds = P.make_predictions(pred)
    assert main(["export", str(pred), "--out", str(tmp_path / "ply")]) == 0
    assert "wrote 3 ply files (3 frames, 1 without points)" in capsys.readouterr().out
    names, got = H.read_ply(tmp_path / "ply" / "run1" / "000007.ply")
    assert names == ["x", "y", "z"]
    np.testing.assert_array_equal(got, clouds[("run1", 7)])


def test_errors_are_one_line(store, tmp_path, capsys):
    (tmp_path / "bad.parquet").write_text("nope")
    assert main(["export", str(tmp_path / "bad.parquet"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("radarpc export: error: ") and "is not a readable Parquet file" in err
    assert "Traceback" not in err

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "other.txt").write_text("x")
    assert main(["export", str(store.path), "--out", str(busy)]) == 2
    err = capsys.readouterr().err
    assert "is not empty and does not hold a run with these settings" in err and "--overwrite" in err
    assert main(["export", str(store.path), "--out", str(busy), "--overwrite"]) == 0
    capsys.readouterr()

    assert main(["export", str(store.path), "--out", str(tmp_path / "o"), "--columns", "x,y,z,rcs"]) == 2
    assert "unknown point column(s) 'rcs'" in capsys.readouterr().err

    with pytest.raises(SystemExit) as e:
        main(["export", str(store.path), "--out", str(tmp_path / "o"), "--format", "las"])
    assert e.value.code == 2
    assert "invalid choice: 'las'" in capsys.readouterr().err


def test_help_states_the_column_order(capsys):
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = capsys.readouterr().out
    assert " ".join(DEFAULT_COLUMNS) in text
    assert 'np.fromfile(path, dtype="<f4").reshape(-1, C)' in text
    assert "``" not in text


def test_radial_pcl_into_a_root(store, tmp_path, capsys):
    from radarpc.data.radial_format import radar_pcl_path

    root = tmp_path / "root"
    root.mkdir()
    argv = ["export", str(store.path), "--radial-pcl", "--root", str(root), "--no-progress"]
    assert main(argv) == 2
    assert "is not a RADIal root (no labels.csv)" in capsys.readouterr().err
    from radarpc.data.radial_format import LABEL_COLUMNS

    # a root that lists the store's frames (one empty-frame row each); the store's recorded root,
    # /data/root, does not exist here (a moved root), so the frames decide
    rows = [",".join(LABEL_COLUMNS)] + [",".join(str(n) if c == "numSample" else "A" if c == "dataset" else "-1"
                                                 for c in LABEL_COLUMNS) for n in (10, 11, 12)]
    (root / "labels.csv").write_text("\n".join(rows) + "\n")
    assert main(argv) == 2                                            # frame 1234567 is not this root's
    assert "(1 of 4, e.g. numSample 1234567)" in capsys.readouterr().err
    (root / "labels.csv").write_text("\n".join(rows + [rows[-1].replace("12,", "1234567,", 1)]) + "\n")
    assert main(argv) == 0
    assert f"wrote radar_PCL for 4 frames" in capsys.readouterr().out
    pcl = np.load(radar_pcl_path(root, 12))
    want = H.expected(store, 2, ("range_m",))[:, 0]
    assert pcl.shape == (9, len(want)) and pcl.dtype == np.float32
    np.testing.assert_array_equal(pcl[0], want)                      # row 0: range, as RADIal's loader reads it
    assert main(argv + ["--out", str(tmp_path / "x")]) == 2
    assert "takes no --out" in capsys.readouterr().err
    assert main(["export", str(store.path)]) == 2
    assert "--out is required" in capsys.readouterr().err
