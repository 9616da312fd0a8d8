"""``radarpc baseline os-cfar`` and ``radarpc evaluate-points`` end to end on a tiny simulated root."""
import json

import numpy as np
import pytest

from radarpc.cli import main
from radarpc.data.coloradar import ColoRadar
from radarpc.eval.pointsets import chamfer_distance, earth_movers_distance, earth_movers_distance_equal
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
    np.save(missing, np.zeros((4, 2), np.float32))
    assert main(force) == 2
    assert "expected shape *x3" in capsys.readouterr().err
    assert not (pred / "metrics.json").exists()
    # an empty cloud is counted, not scored
    np.save(missing, np.zeros((0, 3), np.float32))
    assert main(force + ["--emd-points", "16"]) == 0
    metrics = json.loads((pred / "metrics.json").read_text())
    assert metrics["overall"]["n_frames"] == 2 and metrics["overall"]["empty"] == 1
    assert [f["empty"] for f in metrics["frames"]] == [False, True] and metrics["frames"][1]["chamfer"] is None
    assert metrics["overall"]["chamfer_mean"] == metrics["frames"][0]["chamfer"]
    assert metrics["extra"]["frames_from"] == "split (no index, --force)"


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
    assert table in printed and "| scene | method | frames | empty | CD mean |" in table and "EMD_equal median" in table
    row = [ln for ln in table.splitlines() if ln.startswith("| hallway | lidar-shifted |")][0].strip("| ").split(" | ")
    s = b["scenes"][0]
    assert row[:4] == ["hallway", "lidar-shifted", str(len(ds)), "0"]
    assert row[4:] == [f"{s[k]:.3f}" for k in ("chamfer_mean", "chamfer_median", "emd_mean", "emd_median",
                                                 "emd_equal_mean", "emd_equal_median")]
    assert "| hallway | lidar | 2 | 0 | 0.000 |" in table
    # EMD_equal: the per-frame numbers are the metric function's on the files
    for i, f in enumerate(b["frames"]):
        gt = ds.lidar_points(i)
        assert f["emd_equal"] == pytest.approx(earth_movers_distance_equal(gt + np.float32([0.5, 0, 0]), gt, n=64))
    summary = json.loads((out / "comparison.json").read_text())
    assert [m["name"] for m in summary["methods"]] == ["lidar", "lidar-shifted"] and summary["split"] == "test"
    assert summary["n_frames"] == len(ds) and summary["common_scored"] is None
    with Image.open(out / "figures" / "hallway.png") as im:
        assert im.format == "PNG" and im.size == (int(4.2 * 4 * 100), 840)
    for name in ("cdf_chamfer.png", "cdf_emd.png", "cdf_emd_equal.png"):
        with Image.open(out / "figures" / name) as im:
            im.load()
            assert im.format == "PNG" and im.size == (int(6.4 * 110), int(4.8 * 110))    # one scene: one panel
        assert f"wrote {out / 'figures' / name}" in printed
    assert f"wrote {out / 'figures' / 'hallway.png'}" in printed
    # the same folder twice is refused
    assert main(["evaluate-points", str(exact), str(exact), "--data", str(root), "--split", "test"]) == 2
    assert "given twice" in capsys.readouterr().err


def _folder(folder, root, ds, method, items, *, shift=0.0, empty=()):
    """A prediction folder of the LiDAR truth (shifted in x) for the split's items ``items``, with an
    index listing exactly those; the items in ``empty`` get a cloud without a point."""
    from radarpc.eval.predictions import prediction_path, write_index

    frames = []
    for i in items:
        k, ri, _ = ds.index[i]
        path = prediction_path(folder, ds.runs[k].name, ri)
        path.parent.mkdir(parents=True, exist_ok=True)
        pts = np.zeros((0, 3), np.float32) if i in empty else ds.lidar_points(i) + np.float32([shift, 0, 0])
        np.save(path, pts)
        frames.append({"run": ds.runs[k].name, "frame": ri, "n_points": len(pts), "empty": len(pts) == 0})
    write_index(folder, method, root, "test", frames)
    return folder


def test_evaluate_points_scores_the_listed_frames_and_compares_common_ones(root, tmp_path, capsys):
    ds = ColoRadar(root, "test", cube_size=None)
    assert len(ds) == 2
    full = _folder(tmp_path / "full", root, ds, "every", [0, 1], shift=0.2)
    sub = _folder(tmp_path / "sub", root, ds, "every-2nd", [1], shift=0.4)
    base = ["--data", str(root), "--split", "test", "--emd-points", "16"]
    # a subset folder alone: exactly its listed frame (no file of the other frame is needed)
    assert main(["evaluate-points", str(sub), *base]) == 0
    m = json.loads((sub / "metrics.json").read_text())
    assert [(f["run"], f["frame"]) for f in m["frames"]] == [(ds.runs[0].name, ds.index[1][1])]
    # different frame sets: refused before any scoring, with how they differ
    (sub / "metrics.json").unlink()
    capsys.readouterr()
    assert main(["evaluate-points", str(full), str(sub), *base, "--out", str(tmp_path / "cmp")]) == 2
    err = capsys.readouterr().err
    assert "list different frames (every lists 2, every-2nd lists 1, 1 in common; e.g. run" in err
    assert f"frame {ds.index[0][1]} only by every" in err and "--common-frames" in err
    assert not (full / "metrics.json").exists() and not (sub / "metrics.json").exists()
    # --common-frames: compared over the common frame; each metrics.json covers its own frames
    assert main(["evaluate-points", str(full), str(sub), *base, "--out", str(tmp_path / "cmp"), "--common-frames"]) == 0
    out = capsys.readouterr().out
    assert "## side by side (1 frame)" in out
    assert len(json.loads((full / "metrics.json").read_text())["frames"]) == 2
    cmp = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert cmp["n_frames"] == 1 and cmp["frames"].startswith("common") and cmp["methods"][0]["overall"]["n_frames"] == 1
    full_frame = json.loads((full / "metrics.json").read_text())["frames"][1]
    assert cmp["methods"][0]["overall"]["chamfer_mean"] == full_frame["chamfer"]
    assert (tmp_path / "cmp" / "comparison.md").read_text().startswith("Compared over the 1 frame every folder lists")
    first = _folder(tmp_path / "first", root, ds, "first", [0])
    assert main(["evaluate-points", str(first), str(sub), *base, "--common-frames"]) == 2
    assert "have no frame in common: first lists 1, every-2nd lists 1" in capsys.readouterr().err
    # an index listing a frame the split lacks
    bad = _folder(tmp_path / "bad", root, ds, "bad", [0])
    doc = json.loads((bad / "index.json").read_text())
    doc["frames"].append({"run": "hallway_run0", "frame": 0})
    (bad / "index.json").write_text(json.dumps(doc))
    assert main(["evaluate-points", str(bad), *base]) == 2
    assert "lists run 'hallway_run0' frame 0, which is not a paired radar/LiDAR frame of split 'test'" in \
        capsys.readouterr().err
    assert main(["evaluate-points", str(bad), *base, "--force"]) == 0                  # --force: the split's frames
    assert [f["frame"] for f in json.loads((bad / "metrics.json").read_text())["frames"]] == [ds.index[0][1]]


def test_evaluate_points_counts_empty_predictions_and_compares_over_frames_all_scored(root, tmp_path, capsys):
    ds = ColoRadar(root, "test", cube_size=None)
    good = _folder(tmp_path / "good", root, ds, "good", [0, 1], shift=0.3)
    fails = _folder(tmp_path / "fails", root, ds, "fails", [0, 1], shift=0.1, empty={0})
    capsys.readouterr()
    assert main(["evaluate-points", str(good), str(fails), "--data", str(root), "--split", "test",
                 "--emd-points", "16", "--out", str(tmp_path / "cmp")]) == 0
    f = json.loads((fails / "metrics.json").read_text())
    g = json.loads((good / "metrics.json").read_text())
    assert f["overall"]["empty"] == 1 and f["overall"]["n_frames"] == 2 and g["overall"]["empty"] == 0
    assert f["overall"]["chamfer_mean"] == f["frames"][1]["chamfer"]                     # over the scored frame
    table = (tmp_path / "cmp" / "comparison.md").read_text()
    assert "| hallway | fails | 2 | 1 |" in table and "Over the 1 frame every method scored:" in table
    cmp = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    common = cmp["common_scored"]
    assert common["n_frames"] == 1 and common["frames"] == [{"run": ds.runs[0].name, "frame": ds.index[1][1]}]
    assert common["methods"][0]["overall"]["chamfer_mean"] == g["frames"][1]["chamfer"]
    assert common["methods"][1]["overall"]["chamfer_mean"] == f["frames"][1]["chamfer"]


def test_evaluate_points_scores_a_folder_once(root, tmp_path, capsys, monkeypatch):
    import os

    import radarpc.pipelines.point_eval as point_eval

    ds = ColoRadar(root, "test", cube_size=None)
    pred = _folder(tmp_path / "shifted", root, ds, "shifted", [0, 1], shift=0.3)
    args = ["--data", str(root), "--split", "test", "--emd-points", "16"]
    capsys.readouterr()
    assert main(["evaluate-points", str(pred), *args]) == 0
    first = capsys.readouterr().out
    stored = json.loads((pred / "metrics.json").read_text())
    assert f"wrote {pred / 'metrics.json'}" in first and stored["extra"]["scores"]["version"] == point_eval.SCORING_VERSION

    def scored(*a, **k):
        raise AssertionError("scored again")

    # the same clouds, truth and settings, from a moved folder: the stored scores, the same table
    moved = tmp_path / "moved"
    pred.rename(moved)
    with monkeypatch.context() as m:
        m.setattr(point_eval, "evaluate_clouds", scored)
        assert main(["evaluate-points", str(moved), *args]) == 0
    again = capsys.readouterr().out
    assert f"reused {moved / 'metrics.json'}" in again and "--rescore" in again
    table = first.split("wrote")[0]
    assert table.strip() and table in again
    # scored again: another EMD size, --rescore, a changed cloud, a changed LiDAR scan
    calls = []
    real = point_eval.evaluate_clouds

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(point_eval, "evaluate_clouds", counting)
    assert main(["evaluate-points", str(moved), *args[:-1], "17"]) == 0 and len(calls) == 1
    assert main(["evaluate-points", str(moved), *args[:-1], "16"]) == 0 and len(calls) == 2
    assert main(["evaluate-points", str(moved), *args]) == 0 and len(calls) == 2          # reused
    assert main(["evaluate-points", str(moved), *args, "--rescore"]) == 0 and len(calls) == 3
    k, ri, li = ds.index[0]
    cloud = moved / ds.runs[k].name / f"{ri:06d}.npy"
    np.save(cloud, np.load(cloud) + np.float32([0.3, 0, 0]))
    assert main(["evaluate-points", str(moved), *args]) == 0 and len(calls) == 4
    changed = json.loads((moved / "metrics.json").read_text())["frames"][0]["chamfer"]
    assert changed != stored["frames"][0]["chamfer"]
    assert changed == pytest.approx(chamfer_distance(np.load(cloud), ds.lidar_points(0)))    # the new cloud's
    scan = ds.runs[k].lidar_path(li)
    st = scan.stat()
    try:
        os.utime(scan, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        assert main(["evaluate-points", str(moved), *args]) == 0 and len(calls) == 5
    finally:
        os.utime(scan, ns=(st.st_atime_ns, st.st_mtime_ns))
