"""``radarpc baseline os-cfar`` and ``radarpc evaluate-points`` end to end on a tiny simulated root."""
import json

import numpy as np
import pytest

from radarpc.cli import main
from radarpc.data.coloradar import ColoRadar
from radarpc.eval.pointsets import chamfer_distance, earth_movers_distance
from radarpc.rald.oscfar_baseline import load_config


@pytest.fixture
def root(colo_hallway_root):
    # the session's 3 runs of one scene: run0 train, run1 val, run2 test; a cheap radar and LiDAR, no cascade
    return colo_hallway_root


def test_baseline_then_evaluate(root, tmp_path, capsys):
    pred = tmp_path / "oscfar"
    assert main(["baseline", "os-cfar", str(root), "--split", "test", "--out", str(pred), "--quick-tune"]) == 0
    ds = ColoRadar(root, "test", cube_size=None)
    index = json.loads((pred / "index.json").read_text())
    assert len(index["frames"]) == len(ds) > 0
    cfg = load_config(pred / "config.yaml")
    tuning = json.loads((pred / "tuning.json").read_text())
    assert len(tuning["candidates"]) == 3 and tuning["best"] == cfg.to_dict()
    assert tuning["best_chamfer_m"] == min(c["chamfer_m"] for c in tuning["candidates"])
    for e in index["frames"]:
        pts = np.load(pred / e["file"], allow_pickle=False)
        assert pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == 3 and len(pts) == e["n_points"] >= 1
        assert e["run"] == "hallway_run2" and e["file"] == f"hallway_run2/{e['frame']:06d}.npy"

    capsys.readouterr()
    assert main(["evaluate-points", str(pred), "--data", str(root), "--split", "test", "--emd-points", "256"]) == 0
    printed = capsys.readouterr().out
    assert "| hallway |" in printed and "**all**" in printed and "Wasserstein-1" in printed
    metrics = json.loads((pred / "metrics.json").read_text())
    assert metrics["emd_points"] == 256 and (pred / "metrics.md").is_file()
    # the numbers are those of the metric functions on the files and the reader's LiDAR
    for i, f in enumerate(metrics["frames"]):
        k, ri, _ = ds.index[i]
        p = np.load(pred / f["run"] / f"{ri:06d}.npy")
        gt = ds.lidar_points(i)
        assert f["chamfer"] == pytest.approx(chamfer_distance(p, gt))
        assert f["emd"] == pytest.approx(earth_movers_distance(p, gt, n=256, seed=0))
    assert metrics["overall"]["chamfer_mean"] == pytest.approx(np.mean([f["chamfer"] for f in metrics["frames"]]))

    # the index must name the same root and split
    assert main(["evaluate-points", str(pred), "--data", str(root), "--split", "val"]) == 2
    assert "split 'test', but --split is 'val'" in capsys.readouterr().err
    other = tmp_path / "other_root"
    other.mkdir()
    assert main(["evaluate-points", str(pred), "--data", str(other), "--split", "test"]) == 2
    assert "--data is" in capsys.readouterr().err

    # resume: a rerun keeps config.yaml and the existing files
    before = {e["file"]: (pred / e["file"]).stat().st_mtime_ns for e in index["frames"]}
    assert main(["baseline", "os-cfar", str(root), "--split", "test", "--out", str(pred)]) == 0
    assert {f: (pred / f).stat().st_mtime_ns for f in before} == before


def test_evaluate_points_names_a_missing_or_bad_prediction(root, tmp_path, capsys):
    pred = tmp_path / "hand"
    ds = ColoRadar(root, "test", cube_size=None)
    frames = [ds.index[i][1] for i in range(len(ds))]
    (pred / "hallway_run2").mkdir(parents=True)
    np.save(pred / "hallway_run2" / f"{frames[0]:06d}.npy", np.ones((5, 3), np.float32))
    missing = pred / "hallway_run2" / f"{frames[1]:06d}.npy"
    # a hand-made folder has no index.json: refused unless --force
    assert main(["evaluate-points", str(pred), "--data", str(root), "--split", "test"]) == 2
    err = capsys.readouterr().err
    assert "index.json" in err and "--force" in err
    force = ["evaluate-points", str(pred), "--data", str(root), "--split", "test", "--force"]
    assert main(force) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "missing" in err
    np.save(missing, np.zeros((0, 3), np.float32))
    assert main(force) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "empty" in err
    np.save(missing, np.zeros((4, 2), np.float32))
    assert main(force) == 2
    assert "expected shape *x3" in capsys.readouterr().err
    assert not (pred / "metrics.json").exists()


def test_baseline_with_given_config_and_bad_split(root, tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("oscfar: {window: [9, 3, 3], guard: [3, 1, 1], rank: 0.5, tau_db: 6.0}\n")
    pred = tmp_path / "given"
    assert main(["baseline", "os-cfar", str(root), "--split", "val", "--out", str(pred), "--config", str(cfg)]) == 0
    assert load_config(pred / "config.yaml").tau_db == 6.0 and not (pred / "tuning.json").exists()
    cfg.write_text("oscfar: {window: [8, 3, 3]}\n")
    assert main(["baseline", "os-cfar", str(root), "--out", str(tmp_path / "x"), "--config", str(cfg)]) == 2
    assert "cfg.yaml" in capsys.readouterr().err


def test_baseline_owns_its_prediction_folder(root, tmp_path, capsys):
    from radarpc.runs import OutputLock

    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("oscfar: {window: [9, 3, 3], guard: [3, 1, 1], rank: 0.5, tau_db: 6.0}\n")
    pred = tmp_path / "owned"
    args = ["baseline", "os-cfar", str(root), "--split", "val", "--out", str(pred), "--config", str(cfg)]
    with OutputLock(pred, "prediction folder"):                      # another writer holds the folder
        assert main(args) == 2
        assert "another radarpc process" in capsys.readouterr().err and not pred.exists()
    assert main(args) == 0
    # a killed job's temp file is removed by the next one, the kept frames are untouched
    leftover = pred / "hallway_run1" / ".000000.npy.1234.tmp"
    leftover.write_bytes(b"partial")
    files = sorted(pred.glob("hallway_run1/*.npy"))
    before = {f: f.read_bytes() for f in files}
    assert main(args) == 0 and not leftover.exists()
    assert {f: f.read_bytes() for f in files} == before
    assert "wrote 0 new point clouds" in capsys.readouterr().out


def test_baseline_never_mixes_roots_or_splits_in_one_folder(root, tmp_path, capsys):
    import shutil

    other = tmp_path / "other"
    shutil.copytree(root, other)
    pred = tmp_path / "oscfar"
    argv = ["baseline", "os-cfar", str(root), "--split", "test", "--out", str(pred), "--quick-tune",
            "--max-tune-frames", "1"]
    assert main(argv) == 0
    first = {p.name: p.read_bytes() for p in (pred / "hallway_run2").iterdir()}
    capsys.readouterr()
    # another root, or another split, into the same folder: refused before any work, nothing changed
    for args in (["baseline", "os-cfar", str(other), "--split", "test"], ["baseline", "os-cfar", str(root), "--split", "val"]):
        assert main(args + ["--out", str(pred), "--quick-tune", "--max-tune-frames", "1"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "holds predictions of" in err and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in (pred / "hallway_run2").iterdir()} == first
    assert json.loads((pred / "index.json").read_text())["root"] == str(root.resolve())
    # --overwrite replaces them: only the new split's clouds are left
    assert main(["baseline", "os-cfar", str(root), "--split", "val", "--out", str(pred), "--quick-tune",
                 "--max-tune-frames", "1", "--overwrite"]) == 0
    assert sorted(p.name for p in pred.iterdir() if p.is_dir()) == ["hallway_run1"]
    # a non-empty folder that is not a prediction folder, and a file in place of the folder
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["baseline", "os-cfar", str(root), "--out", str(busy), "--quick-tune"]) == 2
    assert "is not empty and is not a prediction folder" in capsys.readouterr().err
    afile = tmp_path / "afile.txt"
    afile.write_text("hi")
    assert main(["baseline", "os-cfar", str(root), "--out", str(afile), "--quick-tune"]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err


def test_evaluate_points_side_by_side_with_figures(root, tmp_path, capsys):
    from PIL import Image

    from radarpc.eval.predictions import prediction_path, write_index

    ds = ColoRadar(root, "test", cube_size=None)
    exact, shifted = tmp_path / "exact", tmp_path / "shifted"
    for folder, method, shift in ((exact, "lidar", 0.0), (shifted, "lidar-shifted", 0.5)):
        frames = []
        for i in range(len(ds)):
            k, ri, _ = ds.index[i]
            path = prediction_path(folder, ds.runs[k].name, ri)
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, ds.lidar_points(i) + np.float32([shift, 0, 0]))
            frames.append({"run": ds.runs[k].name, "frame": ri})
        write_index(folder, method, root, "test", frames)
    out = tmp_path / "cmp"
    capsys.readouterr()
    assert main(["evaluate-points", str(exact), str(shifted), "--data", str(root), "--split", "test",
                 "--emd-points", "64", "--figures", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    a = json.loads((exact / "metrics.json").read_text())
    b = json.loads((shifted / "metrics.json").read_text())
    assert a["overall"]["chamfer_mean"] == 0.0 and b["overall"]["chamfer_mean"] > 0.1      # the truth scores 0
    table = (out / "comparison.md").read_text()
    assert table in printed and "lidar: CD mean" in table and "lidar-shifted: EMD median" in table
    row = [ln for ln in table.splitlines() if ln.startswith("| hallway |")][0].strip("| ").split(" | ")
    s = b["scenes"][0]
    assert row[:3] == ["hallway", str(len(ds)), "0.000"]
    assert row[6:] == [f"{s['chamfer_mean']:.3f}", f"{s['chamfer_median']:.3f}", f"{s['emd_mean']:.3f}",
                         f"{s['emd_median']:.3f}"]
    summary = json.loads((out / "comparison.json").read_text())
    assert [m["name"] for m in summary["methods"]] == ["lidar", "lidar-shifted"] and summary["split"] == "test"
    with Image.open(out / "figures" / "hallway.png") as im:
        assert im.format == "PNG" and im.size == (int(4.2 * 4 * 100), 840)
    assert f"wrote {out / 'figures' / 'hallway.png'}" in printed
    # the same folder twice is refused
    assert main(["evaluate-points", str(exact), str(exact), "--data", str(root), "--split", "test"]) == 2
    assert "given twice" in capsys.readouterr().err
