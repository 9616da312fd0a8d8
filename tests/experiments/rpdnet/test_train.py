"""The occupancy baseline end to end on the session's simulated hallway: `radarpc train` (run folder,
loader, resume), `radarpc generate` (RaLD's prediction-folder layout, the cells above the threshold
as points) and `radarpc evaluate-points` beside OS-CFAR."""
from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from radarpc.cli import main
from radarpc.data.coloradar import ColoRadar, rald_intensity
from radarpc.experiments.rpdnet.config import load_experiment
from radarpc.experiments.rpdnet.runs import is_occupancy_run, load_occupancy_run, run_key
from radarpc.io import DataFileError
from radarpc.models.rpdnet import RPDNet
from radarpc.pipelines.occupancy_clouds import occupancy_points
from radarpc.rald.frustum import cartesian_to_polar
from radarpc.training.checkpoint import load_weights
from radarpc.training.loop import BEST_WEIGHTS

YAML = Path(__file__).parent / "configs" / "rpdnet-tiny.yaml"


def _quiet(*argv) -> int:
    with contextlib.redirect_stdout(io.StringIO()):
        return main([*map(str, argv)])


@pytest.fixture(scope="module")
def run(colo_hallway_root, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rpdnet") / "run"
    assert _quiet("train", YAML, "--data", colo_hallway_root, "--out", out, "--no-progress") == 0
    return out


def test_run_folder_loader_and_resume(run, colo_hallway_root):
    for name in ("config.yaml", "run.json", BEST_WEIGHTS, "checkpoints/last.safetensors", "log.csv"):
        assert (run / name).is_file(), name
    cfg = load_experiment(YAML)
    key = json.loads((run / "run.json").read_text())
    assert {k: v for k, v in key.items() if k != "software"} == run_key(cfg, colo_hallway_root)
    assert load_experiment(run / "config.yaml") == cfg and is_occupancy_run(run)
    header = (run / "log.csv").read_text().splitlines()[0].split(",")
    assert {"val_loss", "val_iou", "val_precision", "val_recall", "val_f1", "train_loss"} <= set(header)
    loaded = load_occupancy_run(run)
    assert isinstance(loaded.model, RPDNet) and not loaded.model.training and loaded.finished is True
    assert loaded.grid.shape == (32, 16, 8)
    state, _ = load_weights(run / BEST_WEIGHTS)
    for k, v in loaded.model.state_dict().items():
        torch.testing.assert_close(v, state[k], rtol=0, atol=0)
    # the same command again: the finished run is kept as it is
    before = (run / BEST_WEIGHTS).read_bytes()
    assert _quiet("train", YAML, "--data", colo_hallway_root, "--out", run, "--no-progress") == 0
    assert (run / BEST_WEIGHTS).read_bytes() == before


def test_loader_refuses_other_runs(run, tmp_path):
    other = tmp_path / "ae"
    other.mkdir()
    (other / "run.json").write_text(json.dumps({"experiment": {"name": "x", "stage": "autoencoder"}, "data": None}))
    assert not is_occupancy_run(other) and not is_occupancy_run(tmp_path)
    with pytest.raises(DataFileError, match="not a run of the occupancy baseline"):
        load_occupancy_run(other)
    with pytest.raises(FileNotFoundError, match="no training run here"):
        load_occupancy_run(tmp_path)


def test_generate_writes_the_cells_above_the_threshold_and_evaluate_points_scores_them(
        run, colo_hallway_root, tmp_path, capsys):
    preds, oscfar, cmp = tmp_path / "rpdnet", tmp_path / "oscfar", tmp_path / "cmp"
    assert main(["generate", str(run), "--out", str(preds), "--split", "test", "--no-progress"]) == 0
    assert "wrote 2 new point clouds (2 frames)" in capsys.readouterr().out
    index = json.loads((preds / "index.json").read_text())
    assert index["method"] == "rpdnet" and index["split"] == "test" and index["cloud"]["threshold"] == 0.5
    assert index["grid"]["cell"] == [0.5, 11.25, 5.0] and index["root"] == str(colo_hallway_root.resolve())
    assert {"prediction.json", "prediction.csv", "index.json"} <= {p.name for p in preds.iterdir()}
    # each cloud: the centres of the cells whose probability exceeds 0.5, the network run here again
    loaded = load_occupancy_run(run)
    ds = ColoRadar(colo_hallway_root, "test", cube_size=None)
    for i, entry in enumerate(index["frames"]):
        cloud = np.load(preds / entry["file"])
        assert cloud.dtype == np.float32 and cloud.ndim == 2 and cloud.shape[1] == 3
        with torch.no_grad():
            prob = torch.sigmoid(loaded.model(rald_intensity(ds.cube(i), (32, 16, 8))[None])[0])
        n_above = int((prob > 0.5).sum())
        assert 0 < len(cloud) == entry["n_points"] == n_above
        rae = cartesian_to_polar(torch.from_numpy(cloud).double())
        lo, cell = torch.tensor(loaded.grid.lo, dtype=torch.float64), torch.tensor(loaded.grid.cell, dtype=torch.float64)
        frac = (rae - lo) / cell % 1.0                                      # where in its cell each point lies
        torch.testing.assert_close(frac, torch.full_like(frac, 0.5), rtol=0, atol=1e-4)
    # the same command again keeps every cloud; other settings into the same folder are refused
    assert main(["generate", str(run), "--out", str(preds), "--split", "test", "--no-progress"]) == 0
    assert "wrote 0 new point clouds (2 frames)" in capsys.readouterr().out
    moved = tmp_path / "moved"                         # the run elsewhere: the same weights, kept clouds
    shutil.copytree(run, moved)
    assert main(["generate", str(moved), "--out", str(preds), "--split", "test", "--no-progress"]) == 0
    assert "wrote 0 new point clouds (2 frames)" in capsys.readouterr().out
    assert json.loads((preds / "prediction.json").read_text())["model"]["run"] == str(moved.resolve())
    assert main(["generate", str(run), "--out", str(preds), "--split", "test", "--threshold", "0.4",
                 "--no-progress"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    # jittered: other points, each inside a cell above the threshold, the same again with the same seed
    jit, jit2 = tmp_path / "jit", tmp_path / "jit2"
    for out in (jit, jit2):
        assert main(["generate", str(run), "--out", str(out), "--jitter", "--seed", "3", "--threshold", "0.5",
                     "--no-progress"]) == 0
    first = index["frames"][0]["file"]
    a, b = np.load(jit / first), np.load(jit2 / first)
    np.testing.assert_array_equal(a, b)
    with torch.no_grad():
        prob = torch.sigmoid(loaded.model(rald_intensity(ds.cube(0), (32, 16, 8))[None])[0])
    above = prob > 0.5
    assert 0 < len(a) == int(above.sum()) < above.numel()
    ijk = ((cartesian_to_polar(torch.from_numpy(a).double()) - lo) / cell).floor().long()
    hit = torch.zeros_like(above)
    hit[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    assert torch.equal(hit, above)                                          # one point in each cell above 0.5
    assert not np.allclose(a, np.load(preds / first))                        # not the centres
    assert json.loads((jit / "index.json").read_text())["cloud"] == {"threshold": 0.5, "jitter": True, "seed": 3}
    # beside OS-CFAR, scored by evaluate-points
    assert _quiet("baseline", "os-cfar", colo_hallway_root, "--split", "test", "--out", oscfar, "--quick-tune") == 0
    capsys.readouterr()
    assert main(["evaluate-points", str(preds), str(oscfar), "--data", str(colo_hallway_root), "--split", "test",
                 "--emd-points", "64", "--out", str(cmp)]) == 0
    summary = json.loads((cmp / "comparison.json").read_text())
    assert [m["name"] for m in summary["methods"]] == ["rpdnet", "os-cfar"]
    assert all(m["overall"]["n_frames"] == 2 for m in summary["methods"])
    metrics = json.loads((preds / "metrics.json").read_text())
    assert metrics["overall"]["chamfer_mean"] > 0


def test_generate_options_and_errors(run, tmp_path, capsys):
    for argv, message in (
            (["--steps", "3"], "is a radar-to-occupancy run (stage: occupancy): --steps belong to RaLD's generation"),
            (["--guide", "none"], "--guide belong to RaLD's generation"),
            (["--threshold", "1.5"], "threshold must be a probability in [0, 1), got 1.5")):
        assert main(["generate", str(run), "--out", str(tmp_path / "p"), *argv, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert main(["generate", str(tmp_path), "--out", str(tmp_path / "p"), "--jitter", "--no-progress"]) == 2
    assert "--threshold and --jitter read a radar-to-occupancy run's cells" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_occupancy_points_refuses_another_grid(run):
    grid = load_occupancy_run(run).grid
    with pytest.raises(ValueError, match=r"probabilities of shape \(16, 8, 4\) for a grid of \(32, 16, 8\)"):
        occupancy_points(grid, torch.zeros(16, 8, 4))
