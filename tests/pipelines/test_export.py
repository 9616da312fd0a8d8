"""Export jobs (radarpc.pipelines.export): layout, exact values, resume, refusal, predictions."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from radarpc.data.export import DEFAULT_COLUMNS
from radarpc.io import DataFileError
from radarpc.pipelines.export import export, export_predictions, export_store
from radarpc.runs import OutputBusyError, OutputLock, RunMismatchError


def _load(name):
    spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "data" / "test_export.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


H = _load("_export_helpers")        # the independent readers and the tiny store of tests/data/test_export.py


@pytest.fixture
def store(tmp_path):
    return H.make_store(tmp_path / "pc.parquet")


@pytest.mark.parametrize("fmt", ["npy", "bin", "ply"])
def test_store_export_layout_and_exact_values(store, tmp_path, fmt):
    out = tmp_path / "export"
    res = export_store(store.path, out, fmt, progress=False)
    assert (res.n_frames, res.n_new, res.n_reused, res.n_empty) == (4, 4, 0, 1)
    assert res.n_points == int(store.frame_table.n_points.sum())
    names = sorted(p.name for p in (out / "points").iterdir())
    assert names == sorted(f"{s}.{fmt}" for s in ("000010", "000011", "000012", "1234567"))
    assert (out / "ImageSets" / "test.txt").read_text() == "000010\n000011\n000012\n1234567\n"
    for i, frame in enumerate(store.frames):
        path = out / "points" / f"{frame:06d}.{fmt}"
        if fmt == "npy":
            got = H.read_npy(path)
        elif fmt == "bin":
            got = H.read_bin(path, len(DEFAULT_COLUMNS))
        else:
            cols, got = H.read_ply(path)
            assert cols == list(DEFAULT_COLUMNS)
        np.testing.assert_array_equal(got, H.expected(store, i, DEFAULT_COLUMNS))
    meta = json.loads((out / "export.json").read_text())
    assert meta["columns"] == list(DEFAULT_COLUMNS) and meta["format"] == fmt
    assert meta["store"]["split"] == "test" and meta["store"]["tau"] == 10.0
    assert meta["openpcdet"]["NUM_POINT_FEATURES"] == 9
    rows = [ln.split()[1] for ln in (out / "columns.txt").read_text().splitlines() if not ln.startswith("#")]
    assert rows == list(DEFAULT_COLUMNS)
    assert not list(out.rglob(".*.tmp")) and not (tmp_path / ".export.lock").exists()


def test_rerun_resumes_and_keeps_finished_frames(store, tmp_path):
    out = tmp_path / "export"
    export_store(store.path, out, "bin", progress=False)
    before = {p.name: p.read_bytes() for p in (out / "points").iterdir()}
    (out / "points" / "000012.bin").unlink()                     # as if killed before this frame
    (out / "points" / "000010.bin").write_bytes(b"kept")        # proves a finished frame is not rewritten
    res = export_store(store.path, out, "bin", progress=False)
    assert (res.n_new, res.n_reused) == (1, 3)
    assert (out / "points" / "000012.bin").read_bytes() == before["000012.bin"]
    assert (out / "points" / "000010.bin").read_bytes() == b"kept"


def test_other_settings_are_refused_unless_overwrite(store, tmp_path):
    out = tmp_path / "export"
    export_store(store.path, out, "npy", progress=False)
    with pytest.raises(RunMismatchError, match=r"differs in export.json:.*format.*pass --overwrite"):
        export_store(store.path, out, "bin", progress=False)
    with pytest.raises(RunMismatchError, match="columns"):
        export_store(store.path, out, "npy", ("x", "y", "z"), progress=False)
    res = export_store(store.path, out, "bin", ("x", "y", "z"), overwrite=True, progress=False)
    assert res.n_new == 4
    assert sorted(p.suffix for p in (out / "points").iterdir()) == [".bin"] * 4
    np.testing.assert_array_equal(H.read_bin(out / "points" / "000012.bin", 3), H.expected(store, 2, "xyz"))


def test_a_foreign_folder_is_refused_and_overwrite_keeps_foreign_files(store, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(RunMismatchError, match="is not empty"):
        export_store(store.path, out, progress=False)
    export_store(store.path, out, overwrite=True, progress=False)
    assert (out / "notes.txt").read_text() == "mine"             # only the export's own entries are removed


def test_a_second_writer_is_refused(store, tmp_path):
    out = tmp_path / "export"
    with OutputLock(out, "export folder"):
        with pytest.raises(OutputBusyError, match="another radarpc process"):
            export_store(store.path, out, progress=False)


def test_bad_sources(tmp_path):
    (tmp_path / "x.parquet").write_text("not parquet")
    with pytest.raises(DataFileError, match="x.parquet: is not a readable Parquet file"):
        export(tmp_path / "x.parquet", tmp_path / "o", progress=False)
    with pytest.raises(FileNotFoundError, match="missing.parquet does not exist: expected a point store"):
        export(tmp_path / "missing.parquet", tmp_path / "o", progress=False)
    with pytest.raises(ValueError, match="unknown export format 'las'"):
        export(tmp_path / "x.parquet", tmp_path / "o", "las", progress=False)
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(ValueError, match="is not a prediction folder"):
        export(tmp_path / "empty_dir", tmp_path / "o", progress=False)
    assert not (tmp_path / "o").exists()


def test_unknown_column_is_refused_before_anything_is_written(store, tmp_path):
    with pytest.raises(ValueError, match="unknown point column"):
        export_store(store.path, tmp_path / "o", "npy", ("x", "y", "z", "rcs"), progress=False)
    assert not (tmp_path / "o").exists()


# ---- predictions ------------------------------------------------------------------------------------
def make_predictions(folder):
    rng = np.random.default_rng(0)
    clouds = {("run0", 0): rng.normal(size=(5, 3)).astype(np.float32),
              ("run0", 1): np.zeros((0, 3), np.float32),
              ("run1", 7): rng.normal(size=(2, 3)).astype(np.float32)}
    for (run, frame), pts in clouds.items():
        (folder / run).mkdir(parents=True, exist_ok=True)
        np.save(folder / run / f"{frame:06d}.npy", pts)
    (folder / "index.json").write_text(json.dumps({"method": "os-cfar", "root": "/r", "split": "test", "frames": []}))
    (folder / "config.yaml").write_text("tau_db: 8\n")
    return clouds


def test_predictions_as_ply(tmp_path):
    pred, out = tmp_path / "pred", tmp_path / "ply"
    clouds = make_predictions(pred)
    res = export(pred, out, progress=False)
    assert (res.fmt, res.n_frames, res.n_new, res.n_empty) == ("ply", 3, 3, 1)
    for (run, frame), pts in clouds.items():
        names, got = H.read_ply(out / run / f"{frame:06d}.ply")
        assert names == ["x", "y", "z"]
        np.testing.assert_array_equal(got, pts)
    meta = json.loads((out / "export.json").read_text())
    assert meta["method"] == "os-cfar" and meta["split"] == "test"
    again = export_predictions(pred, out, progress=False)
    assert (again.n_new, again.n_reused, again.n_empty) == (0, 3, 1)
    (pred / "config.yaml").write_text("tau_db: 12\n")            # predictions made again: not the same export
    with pytest.raises(RunMismatchError, match="source_digest"):
        export_predictions(pred, out, progress=False)



def test_moved_sources_resume_their_export(store, tmp_path):
    import shutil

    # a point store moved: the same content (its metadata), so the export resumes
    out = tmp_path / "export"
    export_store(store.path, out, "bin", progress=False)
    moved = tmp_path / "elsewhere" / "pc.parquet"
    moved.parent.mkdir()
    shutil.move(store.path, moved)
    res = export_store(moved, out, "bin", progress=False)
    assert res.n_new == 0 and json.loads((out / "export.json").read_text())["source"] == str(moved.resolve())
    # predictions whose model's run folder moved (the generation records its new place, model.run):
    # the same clouds, the same export; other weights are another export
    pred, ply = tmp_path / "pred", tmp_path / "ply"
    make_predictions(pred)
    index = {"method": "rald", "root": "/r", "split": "test", "frames": [],
             "model": {"run": "/runs/a", "weights": {"best.safetensors": "f00"}}}
    (pred / "index.json").write_text(json.dumps(index))
    export_predictions(pred, ply, progress=False)
    (pred / "index.json").write_text(json.dumps({**index, "model": {**index["model"], "run": "/moved/a"}}))
    shutil.move(pred, tmp_path / "pred2")
    assert export_predictions(tmp_path / "pred2", ply, progress=False).n_new == 0
    (tmp_path / "pred2" / "index.json").write_text(
        json.dumps({**index, "model": {"run": "/moved/a", "weights": {"best.safetensors": "ba5"}}}))
    with pytest.raises(RunMismatchError, match="source_digest"):
        export_predictions(tmp_path / "pred2", ply, progress=False)

def test_prediction_export_errors(tmp_path):
    pred = tmp_path / "pred"
    make_predictions(pred)
    with pytest.raises(ValueError, match="exported as ply only, not npy"):
        export(pred, tmp_path / "o", "npy", progress=False)
    with pytest.raises(ValueError, match="drop --columns"):
        export(pred, tmp_path / "o", columns=["x", "y", "z"], progress=False)
    with pytest.raises(ValueError, match="overlaps the source"):
        export(pred, pred / "ply", progress=False)
    np.save(pred / "run1" / "000008.npy", np.zeros((4, 2), np.float32))
    with pytest.raises(DataFileError, match=r"000008.npy: expected shape \*x3, found 4x2"):
        export(pred, tmp_path / "o", progress=False)
